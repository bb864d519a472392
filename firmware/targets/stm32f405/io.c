/* Analyzer servo (TIM3 PWM), trigger outputs (GPIO) and camera-edge inputs (EXTI).
 *
 * Camera edges are time-stamped inside the EXTI interrupt (highest priority) and queued; the
 * main loop hands them to the core with that timestamp. So an edge's recorded time does not
 * depend on what the main loop was doing, only the latch that follows it does. */
#include "board.h"
#include "ds_core.h"
#include "stm32f405.h"

#define SERVO_PERIOD_US 20000u /* 50 Hz */
#define TRIG_PORT GPIOC        /* PC0..PC3 */
#define CAM_PORT_INDEX 1u      /* EXTICR port code for GPIOB: PB0..PB3 */
#define EDGE_RING 32u          /* power of two */
#define TRIG_PINS ((1u << DS_N_TRIGGERS) - 1u) /* PC0.. one pin per trigger output */
#define CAM_PINS ((1u << DS_N_CAMERAS) - 1u)   /* PB0.. / EXTI0.. one line per camera input */

_Static_assert(DS_N_TRIGGERS == 4 && DS_N_CAMERAS == 4, "pin map is for 4 triggers/cameras");

typedef struct {
    uint64_t t_us;
    uint8_t camera;
} edge_t;
static volatile edge_t edges[EDGE_RING];
static volatile uint32_t edge_head, edge_tail;
static volatile uint32_t edges_dropped;

void io_init(void)
{
    RCC->AHB1ENR |= RCC_AHB1ENR_GPIOB | RCC_AHB1ENR_GPIOC;
    RCC->APB1ENR |= RCC_APB1ENR_TIM3;
    RCC->APB2ENR |= RCC_APB2ENR_SYSCFG;
    (void)RCC->APB2ENR;

    /* Trigger outputs low before they become outputs: no glitch at boot. */
    TRIG_PORT->BSRR = TRIG_PINS << 16;
    for (unsigned pin = 0; pin < DS_N_TRIGGERS; pin++) {
        gpio_config(TRIG_PORT, pin, GPIO_MODE_OUT, 0, 0);
    }

    /* Servo: TIM3_CH1 on PC6, 1 MHz counter, 20 ms period. CCR1 = pulse width in µs. It is 0
     * (no pulses: the servo holds still, unpowered) until the core commands an angle, which
     * ds_core_init() does at once so that POLARIZER_NOW and the servo agree from boot. */
    gpio_config(GPIOC, 6, GPIO_MODE_AF, 2, 0);
    TIM3->CR1 = 0;
    TIM3->PSC = g_clock.tim_apb1_hz / 1000000u - 1u;
    TIM3->ARR = SERVO_PERIOD_US - 1u;
    TIM3->CCR1 = 0;
    TIM3->CCMR1 = TIM_CCMR1_OC1M_PWM1 | TIM_CCMR1_OC1PE;
    TIM3->CCER = TIM_CCER_CC1E;
    TIM3->EGR = TIM_EGR_UG;
    TIM3->CR1 = TIM_CR1_ARPE | TIM_CR1_CEN;

    /* Camera inputs: PB0..PB3, pulled down (an unplugged camera reads low), rising edge. */
    for (unsigned pin = 0; pin < DS_N_CAMERAS; pin++) {
        gpio_config(GPIOB, pin, GPIO_MODE_IN, 0, 2);
    }
    SYSCFG->EXTICR[0] = (CAM_PORT_INDEX << 0) | (CAM_PORT_INDEX << 4) | (CAM_PORT_INDEX << 8) |
                        (CAM_PORT_INDEX << 12);
    EXTI->RTSR |= CAM_PINS;
    EXTI->FTSR &= ~CAM_PINS;
    EXTI->PR = CAM_PINS;
    EXTI->IMR |= CAM_PINS;
    nvic_enable(IRQ_EXTI0, 0);
    nvic_enable(IRQ_EXTI1, 0);
    nvic_enable(IRQ_EXTI2, 0);
    nvic_enable(IRQ_EXTI3, 0);
}

void servo_set_cdeg(uint16_t cdeg)
{
    if (cdeg > DS_POL_MAX_CDEG) {
        cdeg = (uint16_t)DS_POL_MAX_CDEG;
    }
    uint32_t span = DS_POL_SERVO_PULSE_MAX_US - DS_POL_SERVO_PULSE_MIN_US;
    uint32_t pulse = DS_POL_SERVO_PULSE_MIN_US + (cdeg * span + DS_POL_MAX_CDEG / 2u) / DS_POL_MAX_CDEG;
    TIM3->CCR1 = pulse; /* preloaded: takes effect at the next period, never a runt pulse */
}

void triggers_write(uint8_t mask)
{
    /* One BSRR write sets and clears all four lines in the same bus cycle: triggers that rise
     * together are simultaneous. */
    uint32_t set = mask & TRIG_PINS;
    TRIG_PORT->BSRR = set | ((~set & TRIG_PINS) << 16);
}

void triggers_emergency_low(void)
{
    RCC->AHB1ENR |= RCC_AHB1ENR_GPIOC;
    (void)RCC->AHB1ENR;
    TRIG_PORT->BSRR = TRIG_PINS << 16;
}

static void edge_isr(uint8_t camera)
{
    uint64_t t = clock_now_us();
    EXTI->PR = 1u << camera; /* write-1-to-clear */
    uint32_t h = edge_head;
    if (h - edge_tail < EDGE_RING) {
        edges[h & (EDGE_RING - 1u)].t_us = t;
        edges[h & (EDGE_RING - 1u)].camera = camera;
        edge_head = h + 1u;
    } else {
        edges_dropped++;
    }
}

void EXTI0_IRQHandler(void);
void EXTI1_IRQHandler(void);
void EXTI2_IRQHandler(void);
void EXTI3_IRQHandler(void);
void EXTI0_IRQHandler(void) { edge_isr(0); }
void EXTI1_IRQHandler(void) { edge_isr(1); }
void EXTI2_IRQHandler(void) { edge_isr(2); }
void EXTI3_IRQHandler(void) { edge_isr(3); }

int camera_edge_pop(uint8_t *camera, uint64_t *t_us)
{
    uint32_t t = edge_tail;
    if (t == edge_head) {
        return 0;
    }
    *camera = edges[t & (EDGE_RING - 1u)].camera;
    *t_us = edges[t & (EDGE_RING - 1u)].t_us;
    edge_tail = t + 1u;
    return 1;
}

int camera_edge_pending(void)
{
    return edge_head != edge_tail;
}
