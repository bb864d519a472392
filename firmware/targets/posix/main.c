/* dualscale-sim: the portable firmware core run as a host process behind a pseudo-terminal.
 *
 * The Modbus side is the real core talking over a pty, so any Modbus RTU master (the host
 * library, mbpoll, pymodbus) talks to it exactly as to the board. The "hardware" (lights,
 * analyzer servo, trigger lines, camera-edge inputs) is published on an optional Unix-socket side
 * channel as newline-delimited JSON, and camera edges can be injected through it.
 *
 * Device time: see sim.h. The invariant the loop keeps is that the core only ever sees
 * non-decreasing times, every deadline is handed to ds_core_poll() at exactly the deadline (so
 * sequencer events land on schedule at any speed), and input (bytes, edges) is handed at the
 * current device time after every deadline that precedes it. */
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <sys/stat.h>
#include <termios.h>
#include <unistd.h>

#include "ds_core.h"
#include "sim.h"

#define SIM_TARGET_NAME "posix"
/* In virtual-time modes, a frame whose bytes the pty happens to deliver in pieces must not be
 * cut by virtual time racing past t3.5: device time is held just short of a partial frame's
 * t3.5 until this much *real* silence has passed on the line. */
#define SIM_HOLD_REAL_US 2000u
/* FIFO headroom in virtual-time modes. A real-time rig makes events at 1x: a host that frees
 * events (EVT_ACK, CLEAR_EVENTS) and then reads nothing for P seconds finds the events of P
 * device-seconds added to what it left. An accelerated simulator would add S x P seconds' worth,
 * and lose events a real rig keeps. So, while SIM_FIFO_HIGH or more events are pending, device
 * time may run no further past the device time of the host's last ack than the real time since:
 *     device now <= v(last ack) + (real now - real(last ack)).
 * Below the mark the clock runs free (speed S, or jumps at speed 0); a host that keeps reading
 * (EVT_WINDOW, 20 events, at a time) never notices. The backlog so exceeds a real-time rig's by
 * at most SIM_FIFO_HIGH: a pause that a real-time rig survives with SIM_FIFO_HIGH events to spare
 * loses nothing here, and a host that stays away longer than the FIFO lasts at 1x still sees
 * EVT_DROPPED count what a real rig would lose. A host slower than the events throttles device
 * time to 1x, where a real rig would be. */
#define SIM_FIFO_HIGH (DS_FIFO_DEPTH / 8u)

/* ---- simulated hardware ------------------------------------------------------------------- */

typedef struct {
    uint16_t live[DS_N_SOURCES];    /* what the lights show */
    uint16_t next[DS_N_SOURCES];    /* what the driver chain holds (preload), latched by latch */
    uint16_t polarizer_cdeg;
    uint8_t triggers;
    uint64_t now;                   /* device time of the core call in progress */
} sim_hw_t;

static ds_core_t core;
static sim_hw_t hw;
static int pty_master = -1;
static int pty_slave = -1;          /* kept open for the whole run (see open_pty) */
static volatile sig_atomic_t stop_signal;

/* Flat index of a light source, same order as ds_core's lights[]: LEDs, back lights, diffuse. */
static int source_slot(uint8_t kind, uint8_t index)
{
    switch (kind) {
    case DS_SRC_LED:
        return index < DS_N_LEDS ? (int)index : -1;
    case DS_SRC_BACKLIGHT:
        return index < DS_N_BACKLIGHTS ? (int)(DS_N_LEDS + index) : -1;
    case DS_SRC_DIFFUSE:
        return index < DS_N_DIFFUSE ? (int)(DS_N_LEDS + DS_N_BACKLIGHTS + index) : -1;
    default:
        return -1;
    }
}

static void slot_source(int slot, uint8_t *kind, uint8_t *index)
{
    if (slot < (int)DS_N_LEDS) {
        *kind = DS_SRC_LED;
        *index = (uint8_t)slot;
    } else if (slot < (int)(DS_N_LEDS + DS_N_BACKLIGHTS)) {
        *kind = DS_SRC_BACKLIGHT;
        *index = (uint8_t)(slot - (int)DS_N_LEDS);
    } else {
        *kind = DS_SRC_DIFFUSE;
        *index = (uint8_t)(slot - (int)(DS_N_LEDS + DS_N_BACKLIGHTS));
    }
}

static void publish(int fd, const char *fmt_line, int n)
{
    if (n > 0) {
        sidechan_send(fd, fmt_line, (size_t)n);
    }
}

static void publish_light(int fd, uint64_t t, int slot, uint16_t intensity)
{
    if (!sidechan_enabled()) {
        return;
    }
    uint8_t kind, index;
    slot_source(slot, &kind, &index);
    char line[160];
    int n = snprintf(line, sizeof line,
                     "{\"t_us\":%llu,\"ev\":\"light\",\"kind\":%u,\"index\":%u,\"intensity\":%u}",
                     (unsigned long long)t, kind, index, intensity);
    publish(fd, line, n);
}

static void set_live(int slot, uint16_t intensity)
{
    if (hw.live[slot] != intensity) {
        hw.live[slot] = intensity;
        publish_light(-1, hw.now, slot, intensity);
    }
}

static void hal_uart_write(void *ctx, const uint8_t *buf, uint16_t len)
{
    (void)ctx;
    size_t off = 0;
    while (off < len) {
        ssize_t n = write(pty_master, buf + off, len - off);
        if (n > 0) {
            off += (size_t)n;
        } else if (n < 0 && errno == EINTR) {
            continue;
        } else if (n < 0 && errno == EAGAIN) {
            /* Nobody drains the pty: wait a little, then drop the rest like a disconnected line. */
            struct pollfd p = {.fd = pty_master, .events = POLLOUT, .revents = 0};
            if (poll(&p, 1, 1000) <= 0) {
                return;
            }
        } else {
            return;
        }
    }
}

/* The serial-line format on the pty, as on a real port: CS8, PARENB (+ PARODD), CSTOPB. A pty
 * moves bytes whatever these say, but they are visible to (and shared with) the host's
 * tcgetattr() on the same terminal, so they follow SERIAL_PARITY / SERIAL_STOP_BITS. Linux ptys
 * keep PARODD and CSTOPB but force CS8 and clear PARENB (drivers/tty/pty.c), so the side
 * channel's hello line states the whole format. */
static void set_line_format(int fd, uint8_t parity, uint8_t stop_bits)
{
    struct termios tio;
    if (fd < 0 || tcgetattr(fd, &tio) != 0) {
        return;
    }
    tio.c_cflag &= ~(tcflag_t)(CSIZE | PARENB | PARODD | CSTOPB);
    tio.c_cflag |= CS8 | CREAD | CLOCAL;
    if (parity != DS_PARITY_NONE) {
        tio.c_cflag |= PARENB;
        if (parity == DS_PARITY_ODD) {
            tio.c_cflag |= PARODD;
        }
    }
    if (stop_bits == 2u) {
        tio.c_cflag |= CSTOPB;
    }
    (void)tcsetattr(fd, TCSANOW, &tio);
}

static void hal_uart_format(void *ctx, uint8_t parity, uint8_t stop_bits)
{
    (void)ctx;
    set_line_format(pty_slave, parity, stop_bits);
}

static void hal_light_set(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    (void)ctx;
    int slot = source_slot(kind, index);
    if (slot < 0) {
        return;
    }
    /* A direct set also rewrites that channel of the driver chain's pending frame, as the
     * STM32 target does: a later latch cannot bring back a light the core switched off. */
    hw.next[slot] = intensity;
    set_live(slot, intensity);
}

static void hal_light_preload(void *ctx, uint8_t kind, uint8_t index, uint16_t intensity)
{
    (void)ctx;
    int slot = source_slot(kind, index);
    if (slot < 0) {
        return;
    }
    hw.next[slot] = intensity;
    if (sidechan_enabled()) {
        char line[160];
        int n = snprintf(line, sizeof line,
                         "{\"t_us\":%llu,\"ev\":\"preload\",\"kind\":%u,\"index\":%u,\"intensity\":%u}",
                         (unsigned long long)hw.now, kind, index, intensity);
        publish(-1, line, n);
    }
}

static void hal_light_latch(void *ctx)
{
    (void)ctx;
    if (sidechan_enabled()) {
        char line[64];
        int n = snprintf(line, sizeof line, "{\"t_us\":%llu,\"ev\":\"latch\"}",
                         (unsigned long long)hw.now);
        publish(-1, line, n);
    }
    for (int s = 0; s < (int)DS_N_SOURCES; s++) {
        set_live(s, hw.next[s]);
    }
}

static void hal_polarizer_set(void *ctx, uint16_t cdeg)
{
    (void)ctx;
    hw.polarizer_cdeg = cdeg;
    if (sidechan_enabled()) {
        char line[80];
        int n = snprintf(line, sizeof line, "{\"t_us\":%llu,\"ev\":\"polarizer\",\"cdeg\":%u}",
                         (unsigned long long)hw.now, cdeg);
        publish(-1, line, n);
    }
}

static void publish_triggers(int fd, uint64_t t)
{
    if (sidechan_enabled()) {
        char line[80];
        int n = snprintf(line, sizeof line, "{\"t_us\":%llu,\"ev\":\"triggers\",\"mask\":%u}",
                         (unsigned long long)t, hw.triggers);
        publish(fd, line, n);
    }
}

static void hal_triggers_write(void *ctx, uint8_t mask)
{
    (void)ctx;
    mask &= (uint8_t)((1u << DS_N_TRIGGERS) - 1u);
    if (mask != hw.triggers) { /* the side channel reports edges, not repeated levels */
        hw.triggers = mask;
        publish_triggers(-1, hw.now);
    }
}

static uint16_t evt_next_seq; /* SEQ after the last stored event (see note_acks) */

static void hal_on_event(void *ctx, const ds_event_t *e)
{
    (void)ctx;
    evt_next_seq = (uint16_t)(e->seq + 1u);
    if (!sidechan_enabled()) {
        return;
    }
    char line[160];
    int n = snprintf(line, sizeof line,
                     "{\"t_us\":%llu,\"ev\":\"event\",\"kind\":%u,\"arg\":%u,\"step\":%u,\"seq\":%u}",
                     (unsigned long long)e->ts_us, e->kind_arg & 0xFFu, e->kind_arg >> 8, e->step, e->seq);
    publish(-1, line, n);
}

static const ds_hal_t sim_hal = {
    .ctx = NULL,
    .uart_write = hal_uart_write,
    .light_set = hal_light_set,
    .light_preload = hal_light_preload,
    .light_latch = hal_light_latch,
    .polarizer_set = hal_polarizer_set,
    .triggers_write = hal_triggers_write,
    .uart_format = hal_uart_format,
    .on_event = hal_on_event,
};

/* ---- time and the main loop --------------------------------------------------------------- */

typedef struct {
    sim_clock_t clk;
    uint64_t last;        /* latest device time handed to the core */
    uint64_t t35;         /* frame-end silence, µs of device time */
    int rx_pending;       /* bytes handed whose t3.5 has not yet passed */
    uint64_t rx_v;        /* device time of the last bytes */
    uint64_t rx_real;     /* real time of the last bytes */
    uint16_t first_seq;   /* SEQ of the oldest pending event (or the next one) when last seen */
    uint64_t ack_v;       /* device time of the host's last ack, see SIM_FIFO_HIGH */
    uint64_t ack_real;    /* real time of the host's last ack */
    uint64_t host_v;      /* device time of the host's last bytes (speed 0 watchdog rule) */
    uint64_t host_real;   /* real time of the host's last bytes */
} sim_loop_t;

static sim_loop_t L;

static int hold_active(uint64_t real)
{
    return L.clk.speed != 1.0 && L.rx_pending && real - L.rx_real < SIM_HOLD_REAL_US;
}

/* After every call into the core at device time v: did the host free events? Pushes leave the
 * oldest pending SEQ (next SEQ - pending) as it was; only an ack or a clear moves it. */
static void note_acks(uint64_t real, uint64_t v)
{
    uint16_t first = (uint16_t)(evt_next_seq - ds_core_events_pending(&core));
    if (first != L.first_seq) {
        L.first_seq = first;
        L.ack_v = v;
        L.ack_real = real;
    }
}

/* The latest device time a real-time rig could have reached by real time `real`, by the rule at
 * SIM_FIFO_HIGH; UINT64_MAX (no limit) at speed 1 or while fewer events are pending. */
static uint64_t congestion_cap(uint64_t real)
{
    if (L.clk.speed == 1.0 || ds_core_events_pending(&core) < SIM_FIFO_HIGH) {
        return UINT64_MAX;
    }
    return L.ack_v + (real > L.ack_real ? real - L.ack_real : 0u);
}

/* The cap never holds back the host's own frame: while a request is arriving, device time may
 * always reach its t3.5 (the frame's end), so the reply -- and with it the host's next ack, the
 * only thing that lifts the cap -- is never delayed by the cap. Without this, a clock that had
 * jumped past the cap (speed 0 jumps freely while few events are pending) kept every reply
 * waiting until real time caught up, the host timed out, never acked, and the link died. */
static uint64_t effective_cap(uint64_t real)
{
    uint64_t cap = congestion_cap(real);
    /* Speed 0 and the host watchdog: jumps from deadline to deadline would carry device time
     * past any WATCHDOG_MS between two frames of a host that polls without pause, and trip it.
     * So, with the watchdog on, device time runs at most half its period past the host's last
     * bytes, then at 1x real time: a host that keeps talking never trips it, a host that stops
     * (killed) trips it after about the period of real time, as on a real-time rig. */
    uint32_t wd_ms = core.hr[DS_HR_WATCHDOG_MS];
    if (L.clk.speed == 0.0 && wd_ms != 0u) {
        uint64_t lim = L.host_v + (uint64_t)wd_ms * 500u + (real > L.host_real ? real - L.host_real : 0u);
        if (lim < cap) {
            cap = lim;
        }
    }
    if (L.rx_pending && cap != UINT64_MAX && L.rx_v + L.t35 > cap) {
        cap = L.rx_v + L.t35;
    }
    return cap;
}

static uint64_t device_now(uint64_t real)
{
    uint64_t v = sim_clock_at(&L.clk, real);
    uint64_t cap = effective_cap(real);
    if (v > cap) {
        /* held back: rebase, so the clock goes on from here (at its own rate) once the host
         * has caught up, instead of leaping over the time it was held */
        v = cap < L.last ? L.last : cap;
        sim_clock_jump(&L.clk, real, v);
    }
    if (hold_active(real) && v > L.rx_v + L.t35 - 1u) {
        v = L.rx_v + L.t35 - 1u;
    }
    return v < L.last ? L.last : v;
}

static void note_time(uint64_t t)
{
    if (t > L.last) {
        L.last = t;
    }
    if (L.rx_pending && t >= L.rx_v + L.t35) {
        L.rx_pending = 0;
    }
}

/* Hand every deadline up to v to the core, each at exactly its own time. If the FIFO passes
 * its mark meanwhile (virtual modes), stop at the first deadline a real-time rig could not have
 * reached yet; the caller's next device_now() holds the clock there. */
static void run_due(uint64_t v)
{
    uint64_t real = sim_real_us();
    for (unsigned guard = 0; guard < 1000000u; guard++) {
        uint64_t d = ds_core_next_deadline(&core);
        if (d == DS_NO_DEADLINE || d > v) {
            break;
        }
        if (d > effective_cap(real)) {
            return;
        }
        uint64_t t = d < L.last ? L.last : d;
        hw.now = t;
        ds_core_poll(&core, t);
        note_time(t);
        note_acks(real, t);
    }
    note_time(v);
}

static void on_edge(void *ctx, uint8_t camera)
{
    (void)ctx;
    uint64_t real = sim_real_us();
    run_due(device_now(real));
    uint64_t v = device_now(real); /* again: run_due may have stopped at the FIFO's limit */
    hw.now = v;
    ds_core_camera_edge(&core, camera, v);
    note_time(v);
}

/* A new side-channel client gets the current hardware state, so it needs no history. */
static void on_hello(void *ctx, int fd)
{
    (void)ctx;
    uint64_t t = L.last;
    char line[160];
    int n = snprintf(line, sizeof line,
                     "{\"t_us\":%llu,\"ev\":\"hello\",\"target\":\"%s\",\"address\":%u,\"speed\":%g,"
                     "\"parity\":\"%c\",\"stop_bits\":%u}",
                     (unsigned long long)t, SIM_TARGET_NAME, core.address, L.clk.speed,
                     "NOE"[core.hr[DS_HR_SERIAL_PARITY] <= 2u ? core.hr[DS_HR_SERIAL_PARITY] : 0u],
                     core.hr[DS_HR_SERIAL_STOP_BITS]);
    publish(fd, line, n);
    n = snprintf(line, sizeof line, "{\"t_us\":%llu,\"ev\":\"polarizer\",\"cdeg\":%u}",
                 (unsigned long long)t, hw.polarizer_cdeg);
    publish(fd, line, n);
    publish_triggers(fd, t);
    for (int s = 0; s < (int)DS_N_SOURCES; s++) {
        if (hw.live[s] != 0) {
            publish_light(fd, t, s, hw.live[s]);
        }
    }
}

static void on_signal(int sig)
{
    stop_signal = sig;
}

static void usage(FILE *f)
{
    fprintf(f,
            "usage: dualscale-sim [--address N] [--parity E|O|N] [--stop-bits 1|2] [--speed S]\n"
            "                     [--link PATH] [--hw-socket PATH]\n"
            "  Runs the dualscale firmware core behind a pseudo-terminal; prints the pty path\n"
            "  as the first line on stdout. Stops on SIGINT/SIGTERM (lights off, exit 0).\n"
            "  --address N     Modbus server address, 1..247 (default %u)\n"
            "  --parity P      serial line parity at reset: E even (default), O odd, N none;\n"
            "                  8 data bits. SERIAL_PARITY reads it; set on the pty's termios\n"
            "  --stop-bits B   1 or 2 (default: 1 with parity, 2 without; none with 1 is refused,\n"
            "                  as Modbus over Serial Line v1.02 requires)\n"
            "  --speed S       1 = real time (default); S > 1 = device time runs S times faster;\n"
            "                  0 = as fast as possible (jump to each deadline when idle)\n"
            "  --link PATH     also make PATH a symlink to the pty (removed on exit)\n"
            "  --hw-socket P   publish the simulated hardware as JSON lines on Unix socket P\n"
            "                  and accept {\"ev\":\"edge\",\"camera\":C} camera edges\n",
            DS_DEFAULT_ADDRESS);
}

static int open_pty(int *slave_keep, char *name, size_t name_len)
{
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) != 0 || unlockpt(m) != 0) {
        perror("dualscale-sim: posix_openpt");
        return -1;
    }
    const char *sn = ptsname(m);
    if (sn == NULL || strlen(sn) >= name_len) {
        perror("dualscale-sim: ptsname");
        return -1;
    }
    strcpy(name, sn);
    /* Keep one slave descriptor open for the whole run: without it the master reports
     * EIO/hang-up whenever no host has the port open, and bytes written meanwhile are lost. */
    int s = open(name, O_RDWR | O_NOCTTY);
    if (s < 0) {
        perror("dualscale-sim: open pty slave");
        return -1;
    }
    /* Raw from the start: no echo back to the host, no CR/LF or XON/XOFF mangling of binary
     * frames; the line format (8E1 by default) is set by ds_core_init through hal.uart_format.
     * The host's own tcsetattr() later changes only what it cares about. */
    struct termios tio;
    if (tcgetattr(s, &tio) == 0) {
        cfmakeraw(&tio);
        cfsetispeed(&tio, B115200);
        cfsetospeed(&tio, B115200);
        (void)tcsetattr(s, TCSANOW, &tio);
    }
    int fl = fcntl(m, F_GETFL, 0);
    (void)fcntl(m, F_SETFL, fl | O_NONBLOCK);
    *slave_keep = s;
    return m;
}

static void all_off(void)
{
    hw.now = L.last;
    for (int s = 0; s < (int)DS_N_SOURCES; s++) {
        hw.next[s] = 0;
        set_live(s, 0);
    }
    hal_triggers_write(NULL, 0);
}

int main(int argc, char **argv)
{
    unsigned long address = DS_DEFAULT_ADDRESS;
    int parity = DS_DEFAULT_PARITY;
    int stop_bits = -1; /* default: 1 with parity, 2 without */
    double speed = 1.0;
    const char *link_path = NULL;
    const char *hw_socket = NULL;

    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *val = (i + 1 < argc) ? argv[i + 1] : NULL;
        char *end = NULL;
        if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) {
            usage(stdout);
            return 0;
        } else if (strcmp(a, "--address") == 0 && val != NULL) {
            address = strtoul(val, &end, 0);
            if (*end != '\0' || address < 1 || address > 247) {
                fprintf(stderr, "dualscale-sim: --address must be 1..247\n");
                return 2;
            }
            i++;
        } else if (strcmp(a, "--parity") == 0 && val != NULL) {
            if (strcmp(val, "E") == 0 || strcmp(val, "e") == 0) {
                parity = DS_PARITY_EVEN;
            } else if (strcmp(val, "O") == 0 || strcmp(val, "o") == 0) {
                parity = DS_PARITY_ODD;
            } else if (strcmp(val, "N") == 0 || strcmp(val, "n") == 0) {
                parity = DS_PARITY_NONE;
            } else {
                fprintf(stderr, "dualscale-sim: --parity must be E, O or N\n");
                return 2;
            }
            i++;
        } else if (strcmp(a, "--stop-bits") == 0 && val != NULL) {
            stop_bits = (int)strtol(val, &end, 10);
            if (*end != '\0' || (stop_bits != 1 && stop_bits != 2)) {
                fprintf(stderr, "dualscale-sim: --stop-bits must be 1 or 2\n");
                return 2;
            }
            i++;
        } else if (strcmp(a, "--speed") == 0 && val != NULL) {
            speed = strtod(val, &end);
            if (*end != '\0' || !(speed >= 0.0) || speed > 1e6) {
                fprintf(stderr, "dualscale-sim: --speed must be 0 or a positive factor\n");
                return 2;
            }
            i++;
        } else if (strcmp(a, "--link") == 0 && val != NULL) {
            link_path = val;
            i++;
        } else if (strcmp(a, "--hw-socket") == 0 && val != NULL) {
            hw_socket = val;
            i++;
        } else {
            fprintf(stderr, "dualscale-sim: bad argument '%s'\n", a);
            usage(stderr);
            return 2;
        }
    }

    /* Signals: blocked except while waiting in pselect(), so a stop request is never lost
     * between the check of stop_signal and the wait. SIGPIPE: side-channel clients may vanish. */
    sigset_t block, orig;
    sigemptyset(&block);
    sigaddset(&block, SIGINT);
    sigaddset(&block, SIGTERM);
    sigprocmask(SIG_BLOCK, &block, &orig);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    if (stop_bits < 0) {
        stop_bits = parity == DS_PARITY_NONE ? 2 : 1;
    }
    if (parity == DS_PARITY_NONE && stop_bits != 2) {
        fprintf(stderr, "dualscale-sim: no parity needs --stop-bits 2 (Modbus over Serial Line "
                        "v1.02, 2.5.1); 8N1 is not a Modbus serial-line format\n");
        return 2;
    }

    char pty_name[128];
    int slave_keep = -1;
    pty_master = open_pty(&slave_keep, pty_name, sizeof pty_name);
    if (pty_master < 0) {
        return 1;
    }
    pty_slave = slave_keep;
    if (link_path != NULL) {
        struct stat st;
        if (lstat(link_path, &st) == 0 && S_ISLNK(st.st_mode)) {
            (void)unlink(link_path); /* a stale link from a killed run */
        }
        if (symlink(pty_name, link_path) != 0) {
            perror("dualscale-sim: --link");
            return 1;
        }
    }
    if (hw_socket != NULL && sidechan_open(hw_socket) != 0) {
        if (link_path != NULL) {
            (void)unlink(link_path);
        }
        return 1;
    }

    sim_clock_init(&L.clk, speed);
    L.t35 = ds_rtu_t35_us(DS_DEFAULT_BAUD);
    L.last = 0;
    L.ack_real = sim_real_us(); /* as if the host had just read: the FIFO is empty */
    hw.now = 0;
    ds_core_init(&core, &sim_hal, (uint8_t)address, 0);
    ds_core_set_target(&core, SIM_TARGET_NAME);
    (void)ds_core_set_line_format(&core, (uint8_t)parity, (uint8_t)stop_bits); /* checked above */

    printf("%s\n", pty_name);
    fflush(stdout);

    while (!stop_signal) {
        uint64_t real = sim_real_us();
        run_due(device_now(real));

        uint64_t d = ds_core_next_deadline(&core);
        uint64_t wait_us = 1000000u;   /* nothing due: wake up once a second anyway */
        int may_jump = 0;
        uint64_t cap = effective_cap(real);
        uint64_t target = d;           /* where a speed-0 jump goes: the deadline, or the cap */
        if (d != DS_NO_DEADLINE) {
            if (d > cap && L.clk.speed == 0.0 && !hold_active(real) && cap > device_now(real)) {
                /* as fast as possible, but only as far as the cap allows */
                wait_us = 0;
                may_jump = 1;
                target = cap;
            } else if (d > cap) {
                /* held back by the FIFO: the limit moves at 1x real time, or sooner with an ack */
                uint64_t w = d - cap;
                wait_us = w < wait_us ? w : wait_us;
            } else if (L.clk.speed == 0.0 && !hold_active(real)) {
                wait_us = 0;   /* only check for input, then jump */
                may_jump = 1;
            } else {
                uint64_t w = sim_clock_real_until(&L.clk, real, d);
                wait_us = w < wait_us ? w : wait_us;
            }
        }
        if (hold_active(real)) {
            uint64_t w = L.rx_real + SIM_HOLD_REAL_US - real;
            wait_us = w < wait_us ? w : wait_us;
        }

        fd_set rfds;
        FD_ZERO(&rfds);
        FD_SET(pty_master, &rfds);
        int maxfd = pty_master;
        int sfd = sidechan_fill_fds(&rfds);
        if (sfd > maxfd) {
            maxfd = sfd;
        }
        struct timespec ts = {.tv_sec = (time_t)(wait_us / 1000000u),
                              .tv_nsec = (long)(wait_us % 1000000u) * 1000L};
        int n = pselect(maxfd + 1, &rfds, NULL, NULL, &ts, &orig);
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            perror("dualscale-sim: pselect");
            break;
        }
        if (n == 0) {
            if (may_jump) {
                real = sim_real_us();
                uint64_t v = device_now(real);
                if (target > v) {
                    sim_clock_jump(&L.clk, real, target);
                }
            }
            continue;
        }

        real = sim_real_us();
        run_due(device_now(real)); /* deadlines that precede the input come first */
        uint64_t v = device_now(real); /* again: run_due may have stopped at the FIFO's limit */
        if (FD_ISSET(pty_master, &rfds)) {
            uint8_t buf[512];
            ssize_t r = read(pty_master, buf, sizeof buf);
            if (r > 0) {
                hw.now = v;
                ds_core_rx(&core, buf, (size_t)r, v);
                note_acks(real, v);
                note_time(v);
                L.rx_pending = 1;
                L.rx_v = v;
                L.rx_real = real;
                L.host_v = v;
                L.host_real = real;
            } else if (r < 0 && errno != EAGAIN && errno != EINTR && errno != EIO) {
                perror("dualscale-sim: read pty");
                break;
            }
        }
        sidechan_service(&rfds, on_edge, on_hello, NULL);
    }

    all_off();
    sidechan_close();
    if (link_path != NULL) {
        (void)unlink(link_path);
    }
    close(slave_keep);
    close(pty_master);
    return 0;
}
