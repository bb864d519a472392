/* The LED-driver chain: three TLC5955-class drivers (48 channels x 16-bit grayscale each) on
 * SPI1, daisy-chained MCU -> chip 0 -> chip 1 -> chip 2, with LAT on PA4.
 *
 * Channel numbering follows the coil map, so a channel number is also the light's coil
 * address: LED i -> channel i (0..126), back light j -> 128 + j, diffuse -> 136. Channel c is
 * output c % 48 of chip c / 48 (outputs in the chip's GS-latch order R0, G0, B0, R1, ...).
 *
 * Two frames are kept:
 *   live[] - what the lights show now (the last latched frame);
 *   next[] - the frame for the next latch (camera-master preloads).
 * A direct set changes both, so a later latch can never bring back a light the core switched
 * off. Shifting a frame takes ~110 us at 21 MHz, so the core's hooks only mark work and
 * leds_flush() (main loop, after each core call) shifts once per batch. A preloaded frame is
 * shifted in right away (without LAT), so that leds_latch() at a camera edge is just a LAT
 * pulse: the light changes exactly on the edge.
 *
 * Shift-register image of one chip: 1 select bit (0 = grayscale latch, 1 = control latch) and
 * 768 data bits, MSB first. Three chips = 2307 bits; 5 leading pad bits make 289 whole bytes and
 * simply fall off the far end of the chain. */
#include <string.h>

#include "board.h"
#include "ds_core.h"
#include "stm32f405.h"

#define FRAME_BITS (LEDS_N_CHIPS * 769u)
#define FRAME_BYTES ((FRAME_BITS + 7u) / 8u)
#define PAD_BITS (FRAME_BYTES * 8u - FRAME_BITS)
#define LAT_PIN 4u
#define SPI_SPINS 100000u

/* Control data (select bit 1, then 0x96 in bits 767..760): function bits, global brightness and
 * maximum current. Dot correction at its maximum (127) for every output; the per-LED balance
 * is the host's calibration business, not a firmware constant. */
#define TLC_FC_DSPRPT (1u << 0)  /* auto display repeat: the PWM keeps cycling */
#define TLC_FC_TMGRST (1u << 1)  /* a GS latch restarts the PWM period: on-time starts at LAT */
#define TLC_FC_ESPWM (1u << 3)   /* enhanced-spectrum PWM: on-time spread over 128 segments */
#define TLC_BC 127u              /* global brightness: 100 % */
#define TLC_MC 4u                /* max current code (board-specific: set for the LED type) */

static uint16_t live[LEDS_N_CHANNELS];
static uint16_t next[LEDS_N_CHANNELS];
static uint8_t frame[FRAME_BYTES];
static uint8_t need_latch;   /* live[] changed: shift it and latch */
static uint8_t sr_has_next;  /* the shift register currently holds next[] */

/* ---- bit packing ---- */
typedef struct {
    uint8_t *buf;
    uint32_t bit;
} bitw_t;

static void put_bits(bitw_t *w, uint32_t value, unsigned nbits)
{
    while (nbits-- > 0u) {
        uint32_t byte = w->bit >> 3;
        uint8_t mask = (uint8_t)(0x80u >> (w->bit & 7u));
        if ((value >> nbits) & 1u) {
            w->buf[byte] |= mask;
        } else {
            w->buf[byte] &= (uint8_t)~mask;
        }
        w->bit++;
    }
}

static void pack_gs(const uint16_t *gs)
{
    bitw_t w = {frame, 0};
    put_bits(&w, 0, PAD_BITS);
    for (int chip = (int)LEDS_N_CHIPS - 1; chip >= 0; chip--) { /* farthest chip first */
        put_bits(&w, 0, 1);                                        /* select: grayscale */
        for (int out = 47; out >= 0; out--) {
            put_bits(&w, gs[chip * 48 + out], 16);
        }
    }
}

static void pack_control(void)
{
    bitw_t w = {frame, 0};
    put_bits(&w, 0, PAD_BITS);
    for (unsigned chip = 0; chip < LEDS_N_CHIPS; chip++) {
        put_bits(&w, 1, 1);       /* select: control latch */
        put_bits(&w, 0x96u, 8);   /* bits 767..760: control-write key */
        put_bits(&w, 0, 389);     /* bits 759..371: unused */
        put_bits(&w, TLC_FC_DSPRPT | TLC_FC_TMGRST | TLC_FC_ESPWM, 5); /* 370..366 */
        put_bits(&w, TLC_BC, 7);  /* BC blue   365..359 */
        put_bits(&w, TLC_BC, 7);  /* BC green  358..352 */
        put_bits(&w, TLC_BC, 7);  /* BC red    351..345 */
        put_bits(&w, TLC_MC, 3);  /* MC blue   344..342 */
        put_bits(&w, TLC_MC, 3);  /* MC green  341..339 */
        put_bits(&w, TLC_MC, 3);  /* MC red    338..336 */
        for (unsigned out = 0; out < 48u; out++) {
            put_bits(&w, 127u, 7); /* DC 335..0 */
        }
    }
}

/* ---- SPI1 + LAT ---- */
static void spi_send_frame(void)
{
    for (uint32_t i = 0; i < FRAME_BYTES; i++) {
        for (uint32_t s = 0; !(SPI1->SR & SPI_SR_TXE) && s < SPI_SPINS; s++) {
        }
        *(volatile uint8_t *)&SPI1->DR = frame[i];
    }
    for (uint32_t s = 0; !(SPI1->SR & SPI_SR_TXE) && s < SPI_SPINS; s++) {
    }
    for (uint32_t s = 0; (SPI1->SR & SPI_SR_BSY) && s < SPI_SPINS; s++) {
    }
    (void)SPI1->DR; /* the received bytes are not used: clear RXNE/OVR */
    (void)SPI1->SR;
}

static void lat_pulse(void)
{
    GPIOA->BSRR = 1u << LAT_PIN;
    /* t_WH(LAT) is a few tens of ns; the bus round trip of the second write covers it. */
    (void)GPIOA->ODR;
    GPIOA->BSRR = 1u << (LAT_PIN + 16u);
}

void leds_init(void)
{
    RCC->AHB1ENR |= RCC_AHB1ENR_GPIOA;
    RCC->APB2ENR |= RCC_APB2ENR_SPI1;
    (void)RCC->APB2ENR;

    GPIOA->BSRR = 1u << (LAT_PIN + 16u);
    gpio_config(GPIOA, LAT_PIN, GPIO_MODE_OUT, 0, 0);
    gpio_config(GPIOA, 5, GPIO_MODE_AF, 5, 0); /* SCK */
    gpio_config(GPIOA, 6, GPIO_MODE_AF, 5, 1); /* MISO (SOUT), pulled up when unplugged */
    gpio_config(GPIOA, 7, GPIO_MODE_AF, 5, 0); /* MOSI */

    /* GSCLK on MCO1 (PA8): the crystal when it runs, else HSI; prescaler /1. */
    uint32_t mco1 = (g_clock.source == CLOCK_SRC_HSE_PLL) ? 2u : 0u;
    RCC->CFGR = (RCC->CFGR & ~((3u << 21) | (7u << 24))) | (mco1 << 21);
    gpio_config(GPIOA, 8, GPIO_MODE_AF, 0, 0);

    /* Master, mode 0 (the TLC5955 samples SIN on the rising SCLK edge), MSB first, 8-bit,
     * software NSS, fPCLK2/4 = 21 MHz (the driver's limit is 25 MHz). */
    SPI1->CR1 = 0;
    SPI1->CR2 = 0;
    SPI1->CR1 = SPI_CR1_MSTR | SPI_CR1_BR_DIV4 | SPI_CR1_SSM | SPI_CR1_SSI | SPI_CR1_SPE;

    /* Control data twice: the first write after power-up may meet a driver whose latch logic
     * is still settling; a second identical write costs 110 us once. */
    for (int k = 0; k < 2; k++) {
        pack_control();
        spi_send_frame();
        lat_pulse();
    }
    memset(live, 0, sizeof live);
    memset(next, 0, sizeof next);
    pack_gs(live);
    spi_send_frame();
    lat_pulse();
    need_latch = 0;
    sr_has_next = 1;
}

int leds_channel(uint8_t kind, uint8_t index)
{
    switch (kind) {
    case DS_SRC_LED:
        return index < DS_N_LEDS ? (int)(DS_COIL_LED + index) : -1;
    case DS_SRC_BACKLIGHT:
        return index < DS_N_BACKLIGHTS ? (int)(DS_COIL_BACKLIGHT + index) : -1;
    case DS_SRC_DIFFUSE:
        return index < DS_N_DIFFUSE ? (int)(DS_COIL_DIFFUSE + index) : -1;
    default:
        return -1;
    }
}
_Static_assert(DS_COIL_DIFFUSE + DS_N_DIFFUSE <= LEDS_N_CHANNELS, "coil map exceeds the chain");

void leds_set(int ch, uint16_t intensity)
{
    if (ch < 0 || ch >= (int)LEDS_N_CHANNELS) {
        return;
    }
    if (live[ch] != intensity || next[ch] != intensity) {
        live[ch] = intensity;
        next[ch] = intensity;
        need_latch = 1;
        sr_has_next = 0;
    }
}

void leds_preload(int ch, uint16_t intensity)
{
    if (ch < 0 || ch >= (int)LEDS_N_CHANNELS) {
        return;
    }
    if (next[ch] != intensity) {
        next[ch] = intensity;
        sr_has_next = 0;
    }
}

void leds_latch(void)
{
    if (need_latch) {
        /* Direct sets are pending too: they are already part of next[] (leds_set writes
         * both), so latching next[] applies them as well. */
        need_latch = 0;
        sr_has_next = 0;
    }
    if (!sr_has_next) {
        pack_gs(next);
        spi_send_frame();
        sr_has_next = 1;
    }
    lat_pulse();
    memcpy(live, next, sizeof live);
}

void leds_flush(void)
{
    if (need_latch) {
        pack_gs(live);
        spi_send_frame();
        lat_pulse();
        need_latch = 0;
        sr_has_next = memcmp(live, next, sizeof live) == 0;
    }
    if (!sr_has_next) {
        pack_gs(next); /* preload: data ready in the shift register, LAT at the edge */
        spi_send_frame();
        sr_has_next = 1;
    }
}

void leds_emergency_off(void)
{
    /* Called from fault handlers: re-establish the peripheral from scratch (it may never have
     * been initialised, or be mid-transfer), shift an all-zero grayscale frame and latch it.
     * Only registers and the stack are used. Zero GS data keeps every output off whatever the
     * select/control state, since with GS = 0 the PWM never turns an output on. */
    RCC->AHB1ENR |= RCC_AHB1ENR_GPIOA;
    RCC->APB2ENR |= RCC_APB2ENR_SPI1;
    (void)RCC->APB2ENR;
    gpio_config(GPIOA, LAT_PIN, GPIO_MODE_OUT, 0, 0);
    gpio_config(GPIOA, 5, GPIO_MODE_AF, 5, 0);
    gpio_config(GPIOA, 7, GPIO_MODE_AF, 5, 0);
    SPI1->CR1 = 0;
    SPI1->CR1 = SPI_CR1_MSTR | SPI_CR1_BR_DIV4 | SPI_CR1_SSM | SPI_CR1_SSI | SPI_CR1_SPE;
    for (uint32_t i = 0; i < FRAME_BYTES + 8u; i++) { /* extra zeros: any partial shift flushed */
        for (uint32_t s = 0; !(SPI1->SR & SPI_SR_TXE) && s < SPI_SPINS; s++) {
        }
        *(volatile uint8_t *)&SPI1->DR = 0;
    }
    for (uint32_t s = 0; (SPI1->SR & SPI_SR_BSY) && s < SPI_SPINS; s++) {
    }
    lat_pulse();
}
