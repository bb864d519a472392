/* dualscale controller board: pin assignment and the interfaces between this target's drivers.
 *
 *   USART1 TX/RX       PA9 / PA10 (AF7)    Modbus RTU to the host (USB-serial bridge), 8E1 at reset
 *   SPI1 SCK/MOSI      PA5 / PA7 (AF5)     TLC5955 chain SCLK / SIN (3 drivers, 144 channels)
 *   SPI1 MISO          PA6 (AF5)           TLC5955 SOUT (reserved: LED-open read-back)
 *   LAT                PA4 (output)        TLC5955 LAT, rising edge latches the shift register
 *   GSCLK              PA8 (MCO1, AF0)     TLC5955 grayscale clock: the 8 MHz crystal (HSI 16 MHz
 *                                          if the crystal failed)
 *   SERVO              PC6 (TIM3_CH1, AF2) analyzer servo, 50 Hz, 1.0-2.0 ms
 *   TRIG0..3           PC0..PC3 (output)   camera trigger outputs (micro, mid, polar0, polar1)
 *   CAM0..3            PB0..PB3 (EXTI0..3) camera exposure-active inputs, rising edge
 *   SWDIO/SWCLK        PA13 / PA14         debug and flashing (ST-LINK)
 */
#ifndef DS_BOARD_H
#define DS_BOARD_H

#include <stddef.h>
#include <stdint.h>

/* ---- clock.c ---- */
typedef struct {
    uint32_t sysclk_hz, pclk1_hz, pclk2_hz, tim_apb1_hz;
    uint8_t source; /* CLOCK_SRC_* actually in use */
} clock_info_t;
enum { CLOCK_SRC_HSE_PLL = 1, CLOCK_SRC_HSI_PLL = 2, CLOCK_SRC_HSI = 3, CLOCK_SRC_EMULATED = 4 };
extern clock_info_t g_clock;
void clock_init(void);
void systick_init(void);
uint64_t clock_now_us(void);

/* ---- uart.c ---- */
void uart_init(uint32_t baud);
/* Drains the RX ring, never blocks. Stops after a character received with errors: its
 * DS_UART_ERR_* flags go to *errors (0 if none) and its value is not stored. */
size_t uart_read(uint8_t *buf, size_t max, uint8_t *errors);
int uart_rx_pending(void);
/* 8 data bits, DS_PARITY_* parity, 1 or 2 stop bits: applied once the TX line is idle. */
void uart_set_format(uint8_t parity, uint8_t stop_bits);
void uart_write(const uint8_t *buf, size_t len);
void uart_tx_pump(void);
int uart_tx_pending(void);

/* ---- leds.c (TLC5955 chain) ---- */
#define LEDS_N_CHIPS 3u
#define LEDS_N_CHANNELS (LEDS_N_CHIPS * 48u)
void leds_init(void);
int leds_channel(uint8_t kind, uint8_t index);  /* -1 if no such source */
void leds_set(int channel, uint16_t intensity); /* takes effect at leds_flush() */
void leds_preload(int channel, uint16_t intensity);
void leds_latch(void);
void leds_flush(void);
void leds_emergency_off(void); /* from fault handlers: no state, no interrupts */

/* ---- io.c ---- */
void io_init(void);
void servo_set_cdeg(uint16_t cdeg);
void triggers_write(uint8_t mask);
void triggers_emergency_low(void);
/* Camera edges time-stamped by the EXTI interrupts, oldest first. */
int camera_edge_pop(uint8_t *camera, uint64_t *t_us);
int camera_edge_pending(void);

#endif /* DS_BOARD_H */
