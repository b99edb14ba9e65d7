/* Forno et al. 2020 pipeline, block 3: the static case determination (iotnav.techniques.static)
 * in C99. The device is static when the (moving-average) GPS speed is below a threshold and the
 * low-passed norm of the horizontal specific force y_n = C_nb y_b (North, East) is below
 * theta_A; the module docstring of iotnav.techniques.static gives the rules (hysteresis, the
 * immediate exit on one large sample, stale GPS speed and the fallback speed).
 *
 * pl_static_update_speed mirrors StaticDetector.update_speed, pl_static_step static_step (one
 * IMU sample), pl_static_speed smoothed_speed. No dynamic memory, no global state (one
 * pl_static_state per device), nothing from libc but <math.h> (hypot, exp, isfinite). */
#ifndef IOTNAV_PIPELINE_STATIC_H
#define IOTNAV_PIPELINE_STATIC_H

#include "pipeline_config.h"

#define PL_OK 0
#define PL_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */

typedef struct {
    pl_static_config cfg;
    IOTNAV_REAL speeds[PL_STATIC_SPEED_WINDOW_MAX]; /* ring of the latest GPS speeds, m/s */
    int32_t ring;             /* its length: max(1, speed_window) */
    int32_t n_speeds;         /* GPS speeds received (S_N_SPEEDS) */
    IOTNAV_REAL speed_avg;    /* their moving average, m/s (smoothed_speed, kept since it changes only with them) */
    iotnav_time t_speed;      /* time of the latest, s (S_T_SPEED; meaningful when n_speeds > 0) */
    iotnav_time t_prev;       /* time of the latest IMU sample, s (S_T_PREV) */
    IOTNAV_REAL acc_h;        /* low-passed horizontal specific force, m/s^2 (S_ACC_H; NaN before any) */
    int32_t is_static;        /* the latest decision (S_STATIC) */
    IOTNAV_REAL inv_tau;      /* 1 / acc_tau_s (0 when acc_tau_s <= 0: not used), 1/s */
    IOTNAV_REAL exit_acc;     /* exit_factor theta_a_mps2, m/s^2 */
    IOTNAV_REAL decay_dt;     /* the step (s) of the latest low-pass factor (NaN: none yet) */
    IOTNAV_REAL decay;        /* its 1 - exp(-dt / acc_tau_s): reused while the IMU rate is steady */
} pl_static_state;

/* Set up `st`; PL_ERR_UNSUPPORTED when speed_window exceeds PL_STATIC_SPEED_WINDOW_MAX. */
int pl_static_init(pl_static_state *st, const pl_static_config *cfg);
/* A GPS speed over ground (m/s) at device time t; a non-finite speed is ignored. */
void pl_static_update_speed(pl_static_state *st, iotnav_time t, IOTNAV_REAL speed_mps);
/* One IMU sample: acc_north, acc_east of y_n (m/s^2), the speed used when the GPS speed is
 * stale (m/s, NaN: none). Returns 1 when static, else 0. */
int pl_static_step(pl_static_state *st, iotnav_time t, IOTNAV_REAL acc_north, IOTNAV_REAL acc_east,
                   IOTNAV_REAL fallback_speed_mps);
/* Moving average of the latest GPS speeds, m/s (NaN before any). */
IOTNAV_REAL pl_static_speed(const pl_static_state *st);

/* sizeof(pl_static_state), for bindings that check their layout. */
int32_t pl_static_sizeof(void);

#endif
