/* Virtual device clock of the simulator (see sim.h). Pure arithmetic on CLOCK_MONOTONIC, so the
 * same binary serves real time (speed 1), accelerated time and as-fast-as-possible runs. */
#include <time.h>

#include "sim.h"

uint64_t sim_real_us(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

void sim_clock_init(sim_clock_t *k, double speed)
{
    k->speed = speed;
    /* Speed 0 still lets time flow at 1x between jumps, so UPTIME keeps moving for a host that
     * polls it and t3.5 of a partial frame is reached in a bounded time. */
    k->rate = speed > 0.0 ? speed : 1.0;
    k->v_base = 0;
    k->r_base = sim_real_us();
}

uint64_t sim_clock_at(const sim_clock_t *k, uint64_t real)
{
    if (real <= k->r_base) {
        return k->v_base;
    }
    double dv = (double)(real - k->r_base) * k->rate;
    return k->v_base + (uint64_t)dv;
}

uint64_t sim_clock_real_until(const sim_clock_t *k, uint64_t now_real, uint64_t v)
{
    uint64_t now_v = sim_clock_at(k, now_real);
    if (v <= now_v) {
        return 0;
    }
    double dr = (double)(v - now_v) / k->rate;
    /* Cap far-away deadlines: the loop wakes up, finds nothing due and sleeps again. */
    if (dr > 1e9) {
        return 1000000000u;
    }
    uint64_t r = (uint64_t)dr;
    return (double)r < dr ? r + 1 : r; /* round up: never wake before the deadline */
}

void sim_clock_jump(sim_clock_t *k, uint64_t real, uint64_t v)
{
    k->v_base = v;
    k->r_base = real;
}

