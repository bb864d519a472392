/* USART1 (PA9 TX, PA10 RX): the Modbus line.
 *
 * RX: the RXNE interrupt only moves the byte into a ring; framing (t3.5) is the core's job, done
 * from the main loop with the µs clock. The ring holds several maximal frames, so a busy main
 * loop (an LED-chain shift, a long Modbus write) never drops bytes.
 * TX: ds_core hands a complete response; it is copied into a ring that the TXE interrupt drains,
 * so the main loop never waits ~22 ms for a 256-byte frame to leave at 115200 baud while a
 * sequence deadline is due. uart_tx_pump() also drains it from the main loop, which keeps TX
 * going on emulators that do not raise the TXE interrupt.
 * Errors: a character received with a parity, framing or noise error, or after an overrun (of
 * the USART or of the ring), is queued with its DS_UART_ERR_* flags; uart_read() stops there and
 * hands them over, and the core drops the frame (PROTOCOL.md §1).
 * Format: 8 data bits, parity and stop bits from the register map (uart_cfg.h); a new format
 * waits until the response in the TX ring has completely left the line (SR.TC). */
#include "board.h"
#include "ds_core.h"
#include "stm32f405.h"
#include "uart_cfg.h"

#define RX_RING 1024u /* power of two */
#define TX_RING 1024u

static volatile uint16_t rx_buf[RX_RING];  /* byte | DS_UART_ERR_* << 8 */
static volatile uint32_t rx_head, rx_tail; /* head: ISR writes; tail: main loop */
static volatile uint8_t rx_lost;           /* the ring was full: characters were dropped */

static uint32_t line_baud;
static volatile uint8_t fmt_pending;       /* a new format waits for the TX line to drain */
static uint8_t fmt_parity = DS_DEFAULT_PARITY, fmt_stop = DS_DEFAULT_STOP_BITS;

static volatile uint8_t tx_buf[TX_RING];
static volatile uint32_t tx_head, tx_tail; /* head: main loop; tail: ISR / pump */

void USART1_IRQHandler(void);
void USART1_IRQHandler(void)
{
    uint32_t sr = USART1->SR;
    if (sr & (USART_SR_RXNE | USART_SR_ORE)) {
        /* Reading DR after SR clears PE, FE, NF and ORE. With PCE, bit 8 of DR is the parity. */
        uint16_t e = (uint16_t)((uint16_t)(USART1->DR & 0xFFu) | (uint16_t)(uart_sr_errors(sr) << 8));
        uint32_t h = rx_head;
        if (h - rx_tail < RX_RING) {
            rx_buf[h & (RX_RING - 1u)] = e;
            rx_head = h + 1u;
        } else {
            rx_lost = 1u; /* reported as an overrun once the ring has been read */
        }
    }
    if ((USART1->CR1 & USART_CR1_TXEIE) && (sr & USART_SR_TXE)) {
        uint32_t t = tx_tail;
        if (t != tx_head) {
            USART1->DR = tx_buf[t & (TX_RING - 1u)];
            tx_tail = t + 1u;
        } else {
            USART1->CR1 &= ~USART_CR1_TXEIE; /* nothing left: stop the TXE interrupt */
        }
    }
}

void uart_init(uint32_t baud)
{
    RCC->AHB1ENR |= RCC_AHB1ENR_GPIOA;
    RCC->APB2ENR |= RCC_APB2ENR_USART1;
    (void)RCC->APB2ENR; /* RM0090: wait for the clock enable to take effect */
    gpio_config(GPIOA, 9, GPIO_MODE_AF, 7, 0);
    gpio_config(GPIOA, 10, GPIO_MODE_AF, 7, 1); /* pull-up: an unplugged RX idles high */

    line_baud = baud;
    uart_cfg_t r = uart_cfg(g_clock.pclk2_hz, baud, fmt_parity, fmt_stop);
    USART1->CR1 = 0;
    USART1->BRR = r.brr;
    USART1->CR2 = r.cr2;
    USART1->CR3 = 0;
    USART1->CR1 = r.cr1;
    /* Below the camera edges and SysTick: a byte waits at most one character time anyway. */
    nvic_enable(IRQ_USART1, 2);
}

size_t uart_read(uint8_t *buf, size_t max, uint8_t *errors)
{
    size_t n = 0;
    uint32_t t = rx_tail;
    uint32_t h = rx_head;
    *errors = 0u;
    while (t != h && n < max) {
        uint16_t e = rx_buf[t & (RX_RING - 1u)];
        t++;
        if (e >> 8) {
            *errors = (uint8_t)(e >> 8); /* this character ends the read; its value is void */
            break;
        }
        buf[n++] = (uint8_t)e;
    }
    rx_tail = t;
    if (t == h && *errors == 0u && rx_lost) {
        uint32_t pm = irq_save();
        rx_lost = 0u;
        irq_restore(pm);
        *errors = DS_UART_ERR_OVERRUN;
    }
    return n;
}

void uart_set_format(uint8_t parity, uint8_t stop_bits)
{
    fmt_parity = parity;
    fmt_stop = stop_bits;
    fmt_pending = 1u;
    uart_tx_pump(); /* applies it at once if the line is idle */
}

/* The new format, once the TX ring is empty and the last stop bit has left (TC). Changing M
 * during a transfer is not allowed (RM0090 §30.6.4), so the USART is briefly disabled. */
static void apply_format(void)
{
    if (!fmt_pending || tx_head != tx_tail || !(USART1->SR & USART_SR_TC)) {
        return;
    }
    fmt_pending = 0u;
    uart_cfg_t r = uart_cfg(g_clock.pclk2_hz, line_baud, fmt_parity, fmt_stop);
    USART1->CR1 = 0;
    USART1->BRR = r.brr;
    USART1->CR2 = r.cr2;
    USART1->CR1 = r.cr1;
}

int uart_rx_pending(void)
{
    return rx_head != rx_tail || rx_lost;
}

void uart_write(const uint8_t *buf, size_t len)
{
    for (size_t i = 0; i < len; i++) {
        /* The ring holds four maximal frames; a full ring means the previous response is still
         * leaving, so give it the time, bounded, pumping by hand in case TXE never interrupts. */
        for (uint32_t spin = 0; tx_head - tx_tail >= TX_RING && spin < 10000000u; spin++) {
            uart_tx_pump();
        }
        if (tx_head - tx_tail >= TX_RING) {
            return; /* line stuck: drop the rest rather than hang the sequencer */
        }
        tx_buf[tx_head & (TX_RING - 1u)] = buf[i];
        tx_head = tx_head + 1u;
    }
    USART1->CR1 |= USART_CR1_TXEIE;
}

void uart_tx_pump(void)
{
    uint32_t pm = irq_save();
    if (tx_tail != tx_head && (USART1->SR & USART_SR_TXE)) {
        uint32_t t = tx_tail;
        USART1->DR = tx_buf[t & (TX_RING - 1u)];
        tx_tail = t + 1u;
    }
    apply_format();
    irq_restore(pm);
}

int uart_tx_pending(void)
{
    return tx_head != tx_tail || fmt_pending;
}
