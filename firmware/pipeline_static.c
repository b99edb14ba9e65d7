/* Forno pipeline block 3 in C99 (see pipeline_static.h and iotnav.techniques.static). */
#include <math.h>

#include "iotnav_common.h"
#include "pipeline_static.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define HYPOT hypot
#define EXP exp
#else
#define HYPOT hypotf
#define EXP expf
#endif

int pl_static_init(pl_static_state *st, const pl_static_config *cfg)
{
    int i;
    int32_t ring = cfg->speed_window > 1 ? cfg->speed_window : 1; /* max(1, speed_window) */
    if (ring > PL_STATIC_SPEED_WINDOW_MAX) return PL_ERR_UNSUPPORTED;
    st->cfg = *cfg;
    st->ring = ring;
    for (i = 0; i < PL_STATIC_SPEED_WINDOW_MAX; ++i) st->speeds[i] = (IOTNAV_REAL)NAN;
    st->n_speeds = 0;
    st->speed_avg = (IOTNAV_REAL)NAN;
    st->t_speed.s = st->t_prev.s = 0;
    st->t_speed.frac = st->t_prev.frac = R(0.0);
    st->acc_h = (IOTNAV_REAL)NAN;
    st->is_static = 0;
    /* precomputed: exp(-dt tau^-1) instead of exp(-dt / tau) (one division fewer per IMU sample:
     * the float64 build still equals Python to 1e-9), exit_factor theta_A (the same value) */
    st->inv_tau = cfg->acc_tau_s <= R(0.0) ? R(0.0) : R(1.0) / cfg->acc_tau_s; /* a NaN tau: NaN, as Python */
    st->exit_acc = cfg->exit_factor * cfg->theta_a_mps2;
    st->decay_dt = st->decay = (IOTNAV_REAL)NAN;
    return PL_OK;
}

/* StaticDetector.update_speed; and smoothed_speed (the ring summed in index order, as Python
 * does), computed here once instead of at every IMU sample: it changes only here */
void pl_static_update_speed(pl_static_state *st, iotnav_time t, IOTNAV_REAL speed_mps)
{
    int32_t k, i;
    IOTNAV_REAL total = R(0.0);
    if (!isfinite(speed_mps)) return;
    st->speeds[st->n_speeds % st->ring] = speed_mps;
    st->n_speeds += 1;
    st->t_speed = t;
    k = st->n_speeds < st->ring ? st->n_speeds : st->ring;
    for (i = 0; i < k; ++i) total += st->speeds[i];
    st->speed_avg = total / (IOTNAV_REAL)k;
}

/* smoothed_speed */
IOTNAV_REAL pl_static_speed(const pl_static_state *st) { return st->speed_avg; }

/* static_step */
int pl_static_step(pl_static_state *st, iotnav_time t, IOTNAV_REAL acc_north, IOTNAV_REAL acc_east,
                   IOTNAV_REAL fallback_speed_mps)
{
    const pl_static_config *p = &st->cfg;
    IOTNAV_REAL a_h = HYPOT(acc_north, acc_east), tau = p->acc_tau_s, thr;
    int was = st->is_static != 0, speed_ok = 1, quiet;
    if (!isfinite(st->acc_h) || tau <= R(0.0)) {
        st->acc_h = a_h;
    } else {
        IOTNAV_REAL dt = iotnav_time_diff(t, st->t_prev);
        if (R(0.0) > dt) dt = R(0.0); /* Python's max(dt, 0.0) (a NaN stays NaN) */
        if (!(dt == st->decay_dt)) { /* a new step (a NaN one always recomputed): the same value */
            st->decay_dt = dt;
            st->decay = R(1.0) - EXP(-dt * st->inv_tau);
        }
        st->acc_h += st->decay * (a_h - st->acc_h);
    }
    st->t_prev = t;
    thr = was && p->exit_speed_mps > p->speed_threshold_mps ? p->exit_speed_mps : p->speed_threshold_mps;
    /* Python: t - t_speed <= timeout, with t_speed = -inf before any GPS speed */
    if (st->n_speeds > 0 && iotnav_time_diff(t, st->t_speed) <= p->speed_timeout_s) {
        speed_ok = st->speed_avg < thr;
    } else {
        if (st->n_speeds > 0) speed_ok = st->speed_avg < thr; /* stale: slow at the last fix */
        if (isfinite(fallback_speed_mps)) speed_ok = speed_ok && fallback_speed_mps < thr;
    }
    quiet = st->acc_h < p->theta_a_mps2 && a_h < st->exit_acc;
    st->is_static = speed_ok && quiet;
    return st->is_static;
}

/* sizeof(pl_static_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_static_sizeof(void) { return (int32_t)sizeof(pl_static_state); }
