/* The POSIX simulator's own modules: a virtual device clock and the hardware side channel.
 * The core itself is the unmodified portable core (ds_core.h); this target only supplies the
 * "hardware" behind ds_hal_t and a main loop that feeds it bytes, edges and deadlines. */
#ifndef DS_SIM_H
#define DS_SIM_H

#include <stddef.h>
#include <stdint.h>
#include <sys/select.h>

/* ---- device clock ----------------------------------------------------------------------------
 * Device time (µs) = v_base + (real − r_base) · rate, where real is CLOCK_MONOTONIC in µs.
 * rate = speed for speed > 0, and 1 for speed 0 ("as fast as possible"), which additionally
 * jumps v_base forward to the core's next deadline whenever nothing else is pending. */
typedef struct {
    double speed;     /* 0 = as fast as possible, 1 = real time, otherwise accelerated */
    double rate;      /* device µs per real µs between jumps */
    uint64_t v_base;  /* device time at r_base */
    uint64_t r_base;  /* real time of the last rebase */
} sim_clock_t;

uint64_t sim_real_us(void);
void sim_clock_init(sim_clock_t *k, double speed);
/* Device time that corresponds to real time `real` (no jumps, no holds). */
uint64_t sim_clock_at(const sim_clock_t *k, uint64_t real);
/* Real µs until device time reaches `v` (0 if already there), rounded up. */
uint64_t sim_clock_real_until(const sim_clock_t *k, uint64_t now_real, uint64_t v);
/* Jump: make device time `v` correspond to real time `real` from now on. */
void sim_clock_jump(sim_clock_t *k, uint64_t real, uint64_t v);

/* ---- hardware side channel -------------------------------------------------------------------
 * A Unix stream socket; every client receives one JSON object per line for each hardware
 * change, and may send {"ev":"edge","camera":C} lines, which come back through on_edge. */
#define SIDECHAN_MAX_CLIENTS 16

typedef void (*sidechan_edge_fn)(void *ctx, uint8_t camera);
typedef void (*sidechan_hello_fn)(void *ctx, int client_fd);

int sidechan_open(const char *path);  /* 0 on success, -1 with errno/perror */
void sidechan_close(void);
int sidechan_enabled(void);
/* File descriptors to watch for reading (listen socket + clients); returns the highest fd. */
int sidechan_fill_fds(fd_set *readfds);
/* Handle whatever is readable in readfds: accept clients, parse their lines. */
void sidechan_service(const fd_set *readfds, sidechan_edge_fn on_edge, sidechan_hello_fn on_hello,
                      void *ctx);
/* Send one line (a '\n' is appended) to every client, or to one fd if fd >= 0. */
void sidechan_send(int fd, const char *line, size_t len);

#endif /* DS_SIM_H */
