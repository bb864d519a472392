/* Reset handler, vector table and fault handlers for the STM32F405 (no vendor startup code).
 *
 * The image is linked with -nostartfiles: this file is the whole C runtime start-up. It enables
 * the FPU before any C code could touch a floating-point register (the build is hard-float),
 * copies .data from flash, zeroes .bss and calls main(). */
#include <stdint.h>

#include "board.h"
#include "stm32f405.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern void __libc_init_array(void);
int main(void);

void Reset_Handler(void);
void Default_Handler(void);
void Fault_Handler(void);
void SysTick_Handler(void);
void USART1_IRQHandler(void);
void EXTI0_IRQHandler(void);
void EXTI1_IRQHandler(void);
void EXTI2_IRQHandler(void);
void EXTI3_IRQHandler(void);

__attribute__((noreturn, used)) void Reset_Handler(void)
{
    /* CP10/CP11 full access; must precede any FP instruction (the compiler may use FP
     * registers even in integer code, e.g. for block copies). */
    CPACR |= 0xFu << 20;
    dsb();
    isb();

    uint32_t *src = &_sidata;
    for (uint32_t *dst = &_sdata; dst < &_edata;) {
        *dst++ = *src++;
    }
    for (uint32_t *dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0;
    }
    /* The table may be reached through the 0x00000000 alias; say where it really is so a
     * bootloader that jumps here leaves the vectors right. */
    SCB->VTOR = 0x08000000u;
    /* Separate MemManage/BusFault/UsageFault handlers (all end in Fault_Handler) and a trap on
     * integer division by zero rather than a silent 0. */
    SCB->SHCSR |= SCB_SHCSR_ALLFAULTS;
    SCB->CCR |= SCB_CCR_DIV_0_TRP;

    (void)main();
    for (;;) {
        Fault_Handler(); /* main() never returns; if it does, treat it as a fault */
    }
}

/* Any fault: lights off and trigger lines low first, with no reliance on RAM state, the core
 * or interrupts, then stop. A debugger can still inspect the stacked frame; the host sees the
 * device go silent and its watchdog/timeout logic takes over. */
__attribute__((noreturn)) void Fault_Handler(void)
{
    irq_disable();
    triggers_emergency_low();
    leds_emergency_off();
    for (;;) {
        wfi();
    }
}

void Default_Handler(void)
{
    /* An interrupt enabled without a handler is a firmware bug: fail safe. */
    Fault_Handler();
}

#define WEAK_ALIAS(name) void name(void) __attribute__((weak, alias("Default_Handler")))
WEAK_ALIAS(NMI_Handler);
WEAK_ALIAS(SVC_Handler);
WEAK_ALIAS(DebugMon_Handler);
WEAK_ALIAS(PendSV_Handler);

typedef void (*vector_t)(void);

/* Cortex-M4 system vectors followed by the F405's 82 peripheral interrupts. */
__attribute__((section(".isr_vector"), used)) const vector_t vector_table[16 + N_IRQS] = {
    [0] = (vector_t)(uintptr_t)&_estack,
    [1] = Reset_Handler,
    [2] = NMI_Handler,
    [3] = Fault_Handler,  /* HardFault */
    [4] = Fault_Handler,  /* MemManage */
    [5] = Fault_Handler,  /* BusFault */
    [6] = Fault_Handler,  /* UsageFault */
    [11] = SVC_Handler,
    [12] = DebugMon_Handler,
    [14] = PendSV_Handler,
    [15] = SysTick_Handler,
    [16 + IRQ_EXTI0] = EXTI0_IRQHandler,
    [16 + IRQ_EXTI1] = EXTI1_IRQHandler,
    [16 + IRQ_EXTI2] = EXTI2_IRQHandler,
    [16 + IRQ_EXTI3] = EXTI3_IRQHandler,
    [16 + IRQ_USART1] = USART1_IRQHandler,
};
