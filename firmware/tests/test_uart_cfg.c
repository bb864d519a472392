/* The STM32F405 USART register values for each serial-line format (targets/stm32f405/uart_cfg.h,
 * what uart.c writes), checked against numbers worked out by hand from RM0090 §30.6:
 *   CR1: RE bit 2, TE bit 3, RXNEIE bit 5, PS bit 9 (odd), PCE bit 10, M bit 12 (9-bit word), UE 13
 *   CR2: STOP bits 13:12, 00 = 1 stop bit, 10 = 2 stop bits
 *   BRR (16x oversampling): fck / baud rounded, i.e. mantissa << 4 | fraction/16
 *   SR: PE bit 0, FE bit 1, NF bit 2, ORE bit 3 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>

#include <cmocka.h>

#include "uart_cfg.h"

#define BASE 0x202Cu /* UE | RXNEIE | TE | RE */

static void test_8e1_is_a_9_bit_word_with_even_parity(void **state)
{
    (void)state;
    uart_cfg_t r = uart_cfg(84000000u, 115200u, DS_PARITY_EVEN, 1u);
    assert_int_equal(r.cr1, BASE | 0x1000u | 0x0400u); /* M, PCE; PS = 0: even */
    assert_int_equal(r.cr1, 0x342Cu);
    assert_int_equal(r.cr2, 0x0000u);
    /* 84 MHz / 115200 = 729.17: USARTDIV 45.5625 = mantissa 45 (0x2D), fraction 9 */
    assert_int_equal(r.brr, 0x2D9u);
}

static void test_8o1_sets_ps(void **state)
{
    (void)state;
    uart_cfg_t r = uart_cfg(84000000u, 115200u, DS_PARITY_ODD, 1u);
    assert_int_equal(r.cr1, 0x362Cu);
    assert_int_equal(r.cr2, 0x0000u);
}

static void test_8n2_is_an_8_bit_word_with_two_stop_bits(void **state)
{
    (void)state;
    uart_cfg_t r = uart_cfg(84000000u, 115200u, DS_PARITY_NONE, 2u);
    assert_int_equal(r.cr1, BASE);
    assert_int_equal(r.cr2, 0x2000u);
    r = uart_cfg(84000000u, 115200u, DS_PARITY_EVEN, 2u); /* 8E2 is a valid format too */
    assert_int_equal(r.cr1, 0x342Cu);
    assert_int_equal(r.cr2, 0x2000u);
}

static void test_reset_format_is_8e1(void **state)
{
    (void)state;
    /* what uart_init writes before ds_core_init confirms it through hal.uart_format */
    uart_cfg_t r = uart_cfg(84000000u, DS_DEFAULT_BAUD, DS_DEFAULT_PARITY, DS_DEFAULT_STOP_BITS);
    assert_int_equal(r.cr1, 0x342Cu);
    assert_int_equal(r.cr2, 0x0000u);
}

static void test_brr_rounds_to_nearest(void **state)
{
    (void)state;
    assert_int_equal(uart_cfg(16000000u, 115200u, DS_PARITY_EVEN, 1u).brr, 139u); /* 138.89 */
    assert_int_equal(uart_cfg(84000000u, 9600u, DS_PARITY_EVEN, 1u).brr, 8750u);  /* exact */
    assert_int_equal(uart_cfg(84000000u, 19200u, DS_PARITY_EVEN, 1u).brr, 4375u); /* exact */
}

static void test_status_errors_map_to_the_core_kinds(void **state)
{
    (void)state;
    assert_int_equal(uart_sr_errors(0x20u), 0u); /* RXNE alone: a good character */
    assert_int_equal(uart_sr_errors(0x21u), DS_UART_ERR_PARITY);
    assert_int_equal(uart_sr_errors(0x22u), DS_UART_ERR_FRAMING);
    assert_int_equal(uart_sr_errors(0x24u), DS_UART_ERR_NOISE);
    assert_int_equal(uart_sr_errors(0x28u), DS_UART_ERR_OVERRUN);
    assert_int_equal(uart_sr_errors(0xEFu), DS_UART_ERR_PARITY | DS_UART_ERR_FRAMING |
                                                DS_UART_ERR_NOISE | DS_UART_ERR_OVERRUN);
    assert_int_equal(uart_sr_errors(0xC0u), 0u); /* TXE, TC */
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_8e1_is_a_9_bit_word_with_even_parity),
        cmocka_unit_test(test_8o1_sets_ps),
        cmocka_unit_test(test_8n2_is_an_8_bit_word_with_two_stop_bits),
        cmocka_unit_test(test_reset_format_is_8e1),
        cmocka_unit_test(test_brr_rounds_to_nearest),
        cmocka_unit_test(test_status_errors_map_to_the_core_kinds),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
