/* Register overlays for the few STM32F405 / Cortex-M4 peripherals this target uses.
 * Written from the reference manual (RM0090) and the ARMv7-M ARM; only what the drivers touch.
 * Every struct mirrors the register block's layout exactly, so offsets are checked by the
 * _Static_asserts at the bottom rather than trusted. */
#ifndef DS_STM32F405_H
#define DS_STM32F405_H

#include <stdint.h>

#define REG volatile uint32_t

/* ---- Cortex-M4 core peripherals ---- */
typedef struct {
    REG CTRL, LOAD, VAL, CALIB;
} systick_t;
#define SYSTICK ((systick_t *)0xE000E010u)
#define SYSTICK_CTRL_ENABLE (1u << 0)
#define SYSTICK_CTRL_TICKINT (1u << 1)
#define SYSTICK_CTRL_CLKSOURCE (1u << 2) /* 1 = processor clock (HCLK) */

typedef struct {
    REG CPUID, ICSR, VTOR, AIRCR, SCR, CCR;
    volatile uint8_t SHPR[12]; /* system handler priorities, handlers 4..15 */
    REG SHCSR, CFSR, HFSR, DFSR, MMFAR, BFAR, AFSR;
} scb_t;
#define SCB ((scb_t *)0xE000ED00u)
#define SCB_ICSR_PENDSTSET (1u << 26)
#define SCB_SHCSR_ALLFAULTS ((1u << 16) | (1u << 17) | (1u << 18)) /* MEM, BUS, USG enable */
#define SCB_CCR_DIV_0_TRP (1u << 4)
#define CPACR (*(REG *)0xE000ED88u)

typedef struct {
    REG ISER[8];
    uint32_t rsv0[24];
    REG ICER[8];
    uint32_t rsv1[24];
    REG ISPR[8];
    uint32_t rsv2[24];
    REG ICPR[8];
    uint32_t rsv3[24];
    REG IABR[8];
    uint32_t rsv4[56];
    volatile uint8_t IP[240];
} nvic_t;
#define NVIC ((nvic_t *)0xE000E100u)

static inline void nvic_enable(unsigned irq, uint8_t prio)
{
    /* The F4 implements the top 4 priority bits. */
    NVIC->IP[irq] = (uint8_t)(prio << 4);
    NVIC->ISER[irq >> 5] = 1u << (irq & 31u);
}

static inline void irq_disable(void) { __asm volatile("cpsid i" ::: "memory"); }
static inline void irq_enable(void) { __asm volatile("cpsie i" ::: "memory"); }
static inline uint32_t irq_save(void)
{
    uint32_t primask;
    __asm volatile("mrs %0, primask\n cpsid i" : "=r"(primask)::"memory");
    return primask;
}
static inline void irq_restore(uint32_t primask)
{
    __asm volatile("msr primask, %0" ::"r"(primask) : "memory");
}
static inline void wfi(void) { __asm volatile("wfi" ::: "memory"); }
static inline void dsb(void) { __asm volatile("dsb 0xF" ::: "memory"); }
static inline void isb(void) { __asm volatile("isb 0xF" ::: "memory"); }

/* IRQ numbers (RM0090 table 61) */
#define IRQ_EXTI0 6u
#define IRQ_EXTI1 7u
#define IRQ_EXTI2 8u
#define IRQ_EXTI3 9u
#define IRQ_USART1 37u
#define N_IRQS 82u

/* ---- RCC / FLASH ---- */
typedef struct {
    REG CR, PLLCFGR, CFGR, CIR, AHB1RSTR, AHB2RSTR, AHB3RSTR;
    uint32_t rsv0;
    REG APB1RSTR, APB2RSTR;
    uint32_t rsv1[2];
    REG AHB1ENR, AHB2ENR, AHB3ENR;
    uint32_t rsv2;
    REG APB1ENR, APB2ENR;
} rcc_t;
#define RCC ((rcc_t *)0x40023800u)
#define RCC_CR_HSION (1u << 0)
#define RCC_CR_HSIRDY (1u << 1)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_PLLCFGR_SRC_HSE (1u << 22)
#define RCC_CFGR_SW_MASK 3u
#define RCC_CFGR_SW_PLL 2u
#define RCC_CFGR_SWS_MASK (3u << 2)
#define RCC_CFGR_SWS_PLL (2u << 2)
#define RCC_AHB1ENR_GPIOA (1u << 0)
#define RCC_AHB1ENR_GPIOB (1u << 1)
#define RCC_AHB1ENR_GPIOC (1u << 2)
#define RCC_APB1ENR_TIM3 (1u << 1)
#define RCC_APB2ENR_USART1 (1u << 4)
#define RCC_APB2ENR_SPI1 (1u << 12)
#define RCC_APB2ENR_SYSCFG (1u << 14)

typedef struct {
    REG ACR, KEYR, OPTKEYR, SR, CR, OPTCR;
} flash_t;
#define FLASH ((flash_t *)0x40023C00u)
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_ACR_DCEN (1u << 10)

/* ---- GPIO ---- */
typedef struct {
    REG MODER, OTYPER, OSPEEDR, PUPDR, IDR, ODR, BSRR, LCKR;
    REG AFR[2];
} gpio_t;
#define GPIOA ((gpio_t *)0x40020000u)
#define GPIOB ((gpio_t *)0x40020400u)
#define GPIOC ((gpio_t *)0x40020800u)
#define GPIO_MODE_IN 0u
#define GPIO_MODE_OUT 1u
#define GPIO_MODE_AF 2u

/* Configure one pin: mode, alternate function (ignored unless AF), very-high speed, pull. */
static inline void gpio_config(gpio_t *g, unsigned pin, unsigned mode, unsigned af, unsigned pull)
{
    unsigned sh2 = pin * 2u;
    g->MODER = (g->MODER & ~(3u << sh2)) | (mode << sh2);
    g->OSPEEDR |= 3u << sh2;
    g->PUPDR = (g->PUPDR & ~(3u << sh2)) | (pull << sh2);
    unsigned sh4 = (pin & 7u) * 4u;
    g->AFR[pin >> 3] = (g->AFR[pin >> 3] & ~(0xFu << sh4)) | (af << sh4);
}

/* ---- USART ---- */
typedef struct {
    REG SR, DR, BRR, CR1, CR2, CR3, GTPR;
} usart_t;
#define USART1 ((usart_t *)0x40011000u)
#define USART_SR_PE (1u << 0)   /* parity error */
#define USART_SR_FE (1u << 1)   /* framing error */
#define USART_SR_NF (1u << 2)   /* noise detected */
#define USART_SR_ORE (1u << 3)  /* overrun */
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TC (1u << 6)   /* transmission complete: the last stop bit has left */
#define USART_SR_TXE (1u << 7)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_PS (1u << 9)   /* parity selection: 1 = odd */
#define USART_CR1_PCE (1u << 10) /* parity control enable: the MSB of the word is the parity bit */
#define USART_CR1_M (1u << 12)   /* word length: 1 = 9 bits (8 data + parity when PCE) */
#define USART_CR1_UE (1u << 13)
#define USART_CR2_STOP_1 (0u << 12)
#define USART_CR2_STOP_2 (2u << 12)

/* ---- SPI ---- */
typedef struct {
    REG CR1, CR2, SR, DR, CRCPR, RXCRCR, TXCRCR, I2SCFGR, I2SPR;
} spi_t;
#define SPI1 ((spi_t *)0x40013000u)
#define SPI_CR1_MSTR (1u << 2)
#define SPI_CR1_BR_DIV4 (1u << 3)
#define SPI_CR1_SPE (1u << 6)
#define SPI_CR1_SSI (1u << 8)
#define SPI_CR1_SSM (1u << 9)
#define SPI_SR_TXE (1u << 1)
#define SPI_SR_BSY (1u << 7)

/* ---- general-purpose timer (TIM2..5 layout) ---- */
typedef struct {
    REG CR1, CR2, SMCR, DIER, SR, EGR, CCMR1, CCMR2, CCER, CNT, PSC, ARR, RCR;
    REG CCR1, CCR2, CCR3, CCR4, BDTR, DCR, DMAR;
} tim_t;
#define TIM3 ((tim_t *)0x40000400u)
#define TIM_CR1_CEN (1u << 0)
#define TIM_CR1_ARPE (1u << 7)
#define TIM_EGR_UG (1u << 0)
#define TIM_CCMR1_OC1PE (1u << 3)
#define TIM_CCMR1_OC1M_PWM1 (6u << 4)
#define TIM_CCER_CC1E (1u << 0)

/* ---- EXTI / SYSCFG ---- */
typedef struct {
    REG IMR, EMR, RTSR, FTSR, SWIER, PR;
} exti_t;
#define EXTI ((exti_t *)0x40013C00u)

typedef struct {
    REG MEMRMP, PMC;
    REG EXTICR[4];
} syscfg_t;
#define SYSCFG ((syscfg_t *)0x40013800u)

_Static_assert(__builtin_offsetof(scb_t, SHCSR) == 0x24, "SCB layout");
_Static_assert(__builtin_offsetof(nvic_t, IP) == 0x300, "NVIC layout");
_Static_assert(__builtin_offsetof(rcc_t, AHB1ENR) == 0x30, "RCC layout");
_Static_assert(__builtin_offsetof(rcc_t, APB2ENR) == 0x44, "RCC layout");
_Static_assert(__builtin_offsetof(gpio_t, AFR) == 0x20, "GPIO layout");
_Static_assert(__builtin_offsetof(tim_t, CCR1) == 0x34, "TIM layout");
_Static_assert(__builtin_offsetof(syscfg_t, EXTICR) == 0x08, "SYSCFG layout");

#endif /* DS_STM32F405_H */
