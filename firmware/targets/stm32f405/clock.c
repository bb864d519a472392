/* System clock (168 MHz from an 8 MHz crystal) and the µs device clock on SysTick.
 *
 * Every wait on a hardware ready bit is bounded. Real silicon answers within microseconds; a
 * missing crystal must not hang the board (it falls back to the internal oscillator), and QEMU
 * does not model the RCC at all (every read is 0, the ready bits never come). The emulated
 * case is recognised up front: on silicon HSION/HSIRDY read 1 out of reset, since the chip is
 * running on HSI at that moment; an RCC that reads CR == 0 is therefore not real, and QEMU's
 * netduinoplus2 clocks the CPU (and SysTick) at a fixed 168 MHz.
 *
 * SysTick rather than a TIMx is the time base because it is also what QEMU models correctly
 * (its TIM2-5 run on a wrong clock). */
#include "board.h"
#include "stm32f405.h"

#define HSE_HZ 8000000u
#define HSI_HZ 16000000u
#define TARGET_SYSCLK_HZ 168000000u
#define READY_SPINS 200000u /* >10 ms at 16 MHz; HSE starts in ~2 ms, the PLL in ~0.1 ms */

clock_info_t g_clock;

static int wait_set(volatile uint32_t *reg, uint32_t mask, uint32_t want)
{
    for (uint32_t i = 0; i < READY_SPINS; i++) {
        if ((*reg & mask) == want) {
            return 1;
        }
    }
    return 0;
}

static void use_fixed(uint32_t sysclk, uint32_t pclk1, uint32_t pclk2, uint8_t src)
{
    g_clock.sysclk_hz = sysclk;
    g_clock.pclk1_hz = pclk1;
    g_clock.pclk2_hz = pclk2;
    /* Timers on an APB bus with a prescaler > 1 run at twice the bus clock (RM0090 §6.2). */
    g_clock.tim_apb1_hz = pclk1 == sysclk ? pclk1 : 2u * pclk1;
    g_clock.source = src;
}

void clock_init(void)
{
    if ((RCC->CR & (RCC_CR_HSION | RCC_CR_HSIRDY)) == 0) {
        use_fixed(TARGET_SYSCLK_HZ, TARGET_SYSCLK_HZ / 4u, TARGET_SYSCLK_HZ / 2u, CLOCK_SRC_EMULATED);
        return;
    }

    /* 5 wait states + caches before raising the clock (RM0090 table 10, 2.7-3.6 V). */
    FLASH->ACR = FLASH_ACR_PRFTEN | FLASH_ACR_ICEN | FLASH_ACR_DCEN | 5u;

    RCC->CR |= RCC_CR_HSEON;
    int hse = wait_set(&RCC->CR, RCC_CR_HSERDY, RCC_CR_HSERDY);
    uint32_t pllm = hse ? HSE_HZ / 1000000u : HSI_HZ / 1000000u; /* 1 MHz PLL input */
    if (!hse) {
        RCC->CR &= ~RCC_CR_HSEON;
    }

    /* VCO = 1 MHz * 336 = 336 MHz; SYSCLK = VCO / 2 = 168 MHz; 48 MHz domain = VCO / 7. */
    RCC->CR &= ~RCC_CR_PLLON;
    (void)wait_set(&RCC->CR, RCC_CR_PLLRDY, 0);
    RCC->PLLCFGR = pllm | (336u << 6) | (0u << 16) /* P = 2 */ | (hse ? RCC_PLLCFGR_SRC_HSE : 0u) |
                   (7u << 24);
    /* AHB /1, APB1 /4 (42 MHz, its maximum), APB2 /2 (84 MHz, its maximum). */
    RCC->CFGR = (RCC->CFGR & ~((0xFu << 4) | (7u << 10) | (7u << 13))) | (5u << 10) | (4u << 13);
    RCC->CR |= RCC_CR_PLLON;
    if (!wait_set(&RCC->CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY)) {
        /* Stay on HSI with the prescalers at /1 so every derived rate is simply 16 MHz. */
        RCC->CFGR &= ~((7u << 10) | (7u << 13));
        use_fixed(HSI_HZ, HSI_HZ, HSI_HZ, CLOCK_SRC_HSI);
        return;
    }
    RCC->CFGR = (RCC->CFGR & ~RCC_CFGR_SW_MASK) | RCC_CFGR_SW_PLL;
    if (!wait_set(&RCC->CFGR, RCC_CFGR_SWS_MASK, RCC_CFGR_SWS_PLL)) {
        RCC->CFGR &= ~(RCC_CFGR_SW_MASK | (7u << 10) | (7u << 13));
        use_fixed(HSI_HZ, HSI_HZ, HSI_HZ, CLOCK_SRC_HSI);
        return;
    }
    use_fixed(TARGET_SYSCLK_HZ, TARGET_SYSCLK_HZ / 4u, TARGET_SYSCLK_HZ / 2u,
              hse ? CLOCK_SRC_HSE_PLL : CLOCK_SRC_HSI_PLL);
}

/* ---- µs clock ----
 * ms_count counts SysTick interrupts (1 kHz); the current µs inside the millisecond comes from
 * SysTick->VAL, which counts down from LOAD. 64 bits: never wraps in the rig's lifetime. */
static volatile uint64_t ms_count;
static uint32_t ticks_per_us;

void SysTick_Handler(void);
void SysTick_Handler(void)
{
    ms_count++;
}

void systick_init(void)
{
    ticks_per_us = g_clock.sysclk_hz / 1000000u;
    SYSTICK->CTRL = 0;
    SYSTICK->LOAD = g_clock.sysclk_hz / 1000u - 1u;
    SYSTICK->VAL = 0;
    /* Priority 1 (just below the camera-edge EXTIs at 0): the tick must not be held off by the
     * UART for long, and clock_now_us() copes with a tick that is pending. */
    SCB->SHPR[15 - 4] = 1u << 4;
    SYSTICK->CTRL = SYSTICK_CTRL_CLKSOURCE | SYSTICK_CTRL_TICKINT | SYSTICK_CTRL_ENABLE;
}

uint64_t clock_now_us(void)
{
    /* Callable from any context, interrupts included. With interrupts masked, the counter may
     * have wrapped without ms_count being incremented yet: the pending SysTick bit says so,
     * and VAL is read again so that it belongs to the new millisecond. */
    uint32_t pm = irq_save();
    uint64_t ms = ms_count;
    uint32_t val = SYSTICK->VAL;
    if (SCB->ICSR & SCB_ICSR_PENDSTSET) {
        val = SYSTICK->VAL;
        ms++;
    }
    uint32_t load = SYSTICK->LOAD;
    irq_restore(pm);
    uint32_t in_ms = (load - val) / ticks_per_us;
    if (in_ms > 999u) {
        in_ms = 999u; /* VAL == LOAD + rounding: never report the next millisecond early */
    }
    return ms * 1000u + in_ms;
}
