/* USART register values for a line format, kept free of hardware access so that the host unit
 * tests (firmware/tests/test_uart_cfg.c) check exactly what uart.c writes.
 *
 * RM0090 §30.6: the word length M counts the parity bit, so 8 data bits with parity need M = 1
 * (9-bit word) and PCE = 1, PS selecting odd; 8 data bits without parity are M = 0, PCE = 0.
 * CR2 STOP = 00 is 1 stop bit, 10 is 2. BRR at 16x oversampling is fck / baud in 12.4 fixed
 * point, rounded to nearest. Parity values are the register map's (DS_PARITY_NONE/ODD/EVEN). */
#ifndef DS_UART_CFG_H
#define DS_UART_CFG_H

#include <stdint.h>

#include "ds_core.h"
#include "stm32f405.h"

typedef struct {
    uint32_t cr1, cr2, brr;
} uart_cfg_t;

/* Receiver and transmitter on, RXNE interrupt on (it also fires on ORE; PE, FE and NF come with
 * RXNE and are read from SR in the interrupt). TXEIE is the driver's business, not the format's. */
static inline uart_cfg_t uart_cfg(uint32_t pclk_hz, uint32_t baud, uint8_t parity, uint8_t stop_bits)
{
    uart_cfg_t r;
    r.cr1 = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    if (parity == DS_PARITY_EVEN || parity == DS_PARITY_ODD) {
        r.cr1 |= USART_CR1_M | USART_CR1_PCE;
        if (parity == DS_PARITY_ODD) {
            r.cr1 |= USART_CR1_PS;
        }
    }
    r.cr2 = stop_bits == 2u ? USART_CR2_STOP_2 : USART_CR2_STOP_1;
    r.brr = baud ? (pclk_hz + baud / 2u) / baud : 0u;
    return r;
}

/* The receive errors SR reports with a character, as the core's DS_UART_ERR_* mask. */
static inline uint8_t uart_sr_errors(uint32_t sr)
{
    uint8_t e = 0u;
    if (sr & USART_SR_PE) {
        e |= DS_UART_ERR_PARITY;
    }
    if (sr & USART_SR_FE) {
        e |= DS_UART_ERR_FRAMING;
    }
    if (sr & USART_SR_NF) {
        e |= DS_UART_ERR_NOISE;
    }
    if (sr & USART_SR_ORE) {
        e |= DS_UART_ERR_OVERRUN;
    }
    return e;
}

#endif /* DS_UART_CFG_H */
