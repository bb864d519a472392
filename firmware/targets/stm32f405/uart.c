/* USART1 (PA9 TX, PA10 RX): the Modbus line.
 *
 * RX: the RXNE interrupt only moves the byte into a ring; framing (t3.5) is the core's job, done
 * from the main loop with the µs clock. The ring holds several maximal frames, so a busy main
 * loop (an LED-chain shift, a long Modbus write) never drops bytes.
 * TX: ds_core hands a complete response; it is copied into a ring that the TXE interrupt drains,
 * so the main loop never waits ~22 ms for a 256-byte frame to leave at 115200 baud while a
 * sequence deadline is due. uart_tx_pump() also drains it from the main loop, which keeps TX
 * going on emulators that do not raise the TXE interrupt. */
#include "board.h"
#include "stm32f405.h"

#define RX_RING 1024u /* power of two */
#define TX_RING 1024u

static volatile uint8_t rx_buf[RX_RING];
static volatile uint32_t rx_head, rx_tail; /* head: ISR writes; tail: main loop */
static volatile uint32_t rx_overruns;

static volatile uint8_t tx_buf[TX_RING];
static volatile uint32_t tx_head, tx_tail; /* head: main loop; tail: ISR / pump */

void USART1_IRQHandler(void);
void USART1_IRQHandler(void)
{
    uint32_t sr = USART1->SR;
    if (sr & (USART_SR_RXNE | USART_SR_ORE)) {
        /* Reading DR after SR also clears ORE. */
        uint8_t b = (uint8_t)USART1->DR;
        uint32_t h = rx_head;
        if (h - rx_tail < RX_RING) {
            rx_buf[h & (RX_RING - 1u)] = b;
            rx_head = h + 1u;
        } else {
            rx_overruns++; /* the frame is broken anyway; its CRC will fail */
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

    USART1->CR1 = 0;
    /* 16x oversampling: BRR = fck / baud, mantissa.fraction in 12.4 fixed point, rounded. */
    USART1->BRR = (g_clock.pclk2_hz + baud / 2u) / baud;
    USART1->CR2 = 0; /* 1 stop bit */
    USART1->CR3 = 0;
    USART1->CR1 = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    /* Below the camera edges and SysTick: a byte waits at most one character time anyway. */
    nvic_enable(IRQ_USART1, 2);
}

size_t uart_read(uint8_t *buf, size_t max)
{
    size_t n = 0;
    uint32_t t = rx_tail;
    uint32_t h = rx_head;
    while (t != h && n < max) {
        buf[n++] = rx_buf[t & (RX_RING - 1u)];
        t++;
    }
    rx_tail = t;
    return n;
}

int uart_rx_pending(void)
{
    return rx_head != rx_tail;
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
    irq_restore(pm);
}

int uart_tx_pending(void)
{
    return tx_head != tx_tail;
}
