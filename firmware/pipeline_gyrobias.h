/* Forno et al. 2020 pipeline, block 2's gyroscope-bias Kalman filter
 * (iotnav.techniques.gyro_bias_kf) in C99. The bias b_g (rad/s, sensor frame) is a random walk
 * (F = I, Q = q_b dt I, q_b = bias_rw_rad_s2_rthz^2), observed directly by the raw gyroscope
 * while the device is static (H = I, R = gyro_noise_rad_s^2 I), unless a component exceeds
 * max_rate_rad_s; the corrected rate is omega_b = omega_meas_b - b_g.
 *
 * pl_gyrobias_predict mirrors gyro_bias_predict, pl_gyrobias_update gyro_bias_update (the
 * Cholesky / Joseph-form update of iotnav.techniques.kf3.update3 without its gate, which the
 * bias filter does not use). No dynamic memory, no global state (one pl_gyrobias_state per
 * device), nothing from libc but <math.h> (sqrt, fabs). */
#ifndef IOTNAV_PIPELINE_GYROBIAS_H
#define IOTNAV_PIPELINE_GYROBIAS_H

#include "pipeline_config.h"

#ifndef PL_OK
#define PL_OK 0
#define PL_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */
#endif

typedef struct {
    pl_gyrobias_config cfg;
    IOTNAV_REAL x[3];  /* the bias in b, rad/s */
    IOTNAV_REAL P[9];  /* its covariance, row-major, rad^2/s^2 */
    IOTNAV_REAL q_b;   /* bias_rw_rad_s2_rthz^2, rad^2/s^3 */
    IOTNAV_REAL r;     /* gyro_noise_rad_s^2, rad^2/s^2 */
} pl_gyrobias_state;

/* Set up `st`: x = b0 (rad/s; NULL: zero), P = init_std_rad_s^2 I. Returns PL_OK (0). */
int pl_gyrobias_init(pl_gyrobias_state *st, const pl_gyrobias_config *cfg, const IOTNAV_REAL *b0);
/* Random-walk propagation over dt s (nothing when dt <= 0): P += q_b dt I. */
void pl_gyrobias_predict(pl_gyrobias_state *st, IOTNAV_REAL dt);
/* Static update with the raw rate (rad/s, b). Returns 1 when used, 0 when a component's
 * magnitude exceeds max_rate_rad_s (or is NaN: refused; state unchanged). */
int pl_gyrobias_update(pl_gyrobias_state *st, IOTNAV_REAL gx, IOTNAV_REAL gy, IOTNAV_REAL gz);

/* sizeof(pl_gyrobias_state), for bindings that check their layout. */
int32_t pl_gyrobias_sizeof(void);

#endif
