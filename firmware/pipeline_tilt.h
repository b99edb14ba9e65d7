/* Forno et al. 2020 pipeline, block 2's tilt Kalman filter (iotnav.techniques.tilt_kf) in C99:
 * the down axis of the navigation frame resolved in the sensor frame (third row of C_nb),
 * propagated with the bias-corrected gyroscope (F = I - dt [omega_b x],
 * Q = dt^2 (sigma_g^2 + sigma_b^2) (I - x x^T) + q_floor I) and corrected with the normalised
 * accelerometer (H = I, R = (sigma_a^2 + k_ext |a_ext|^2 + k_gnss max(|a_v| - a_0, 0)^2) / g^2 I;
 * samples with | |f_b| - g | > reject_mps2 not used; the first sample initialises x), x
 * renormalised after each step. The module docstring of iotnav.techniques.tilt_kf gives the model.
 *
 * pl_tilt_predict mirrors tilt_predict, pl_tilt_update tilt_update (kf3.update3 with R = r I and
 * no gate). No dynamic memory, no global state, nothing from libc but <math.h> (sqrt, fabs,
 * isfinite). */
#ifndef IOTNAV_PIPELINE_TILT_H
#define IOTNAV_PIPELINE_TILT_H

#include "pipeline_config.h"

#ifndef PL_OK
#define PL_OK 0
#define PL_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */
#endif

typedef struct {
    pl_tilt_config cfg;
    IOTNAV_REAL x[3];     /* the down axis in b (unit vector) */
    IOTNAV_REAL P[9];     /* its covariance, row-major */
    int32_t initialised;  /* the first accelerometer sample (or x0) set x */
    IOTNAV_REAL nis;      /* NIS of the latest accelerometer update (NaN before any) */
    IOTNAV_REAL gyro_var; /* gyro_noise_rad_s^2, rad^2/s^2 */
    IOTNAV_REAL acc_var;  /* acc_noise_mps2^2, m^2/s^4 */
} pl_tilt_state;

/* Set up `st`: x = x0 / |x0| (initialised) or [0, 0, 1] (x0 NULL: the first accelerometer
 * sample sets it), P = init_std^2 I. Returns PL_OK (0). */
int pl_tilt_init(pl_tilt_state *st, const pl_tilt_config *cfg, const IOTNAV_REAL *x0);
/* Propagate with the bias-corrected rate (rad/s, b) over dt s (nothing when dt <= 0); bias_var:
 * the gyro-bias variance, rad^2/s^2. */
void pl_tilt_predict(pl_tilt_state *st, IOTNAV_REAL wx, IOTNAV_REAL wy, IOTNAV_REAL wz, IOTNAV_REAL dt,
                     IOTNAV_REAL bias_var);
/* Accelerometer update with the specific force f_b (m/s^2, b), gravity g (m/s^2) and the
 * GNSS / gyro vehicle acceleration magnitude a_veh (m/s^2). Returns 1 when the sample was used. */
int pl_tilt_update(pl_tilt_state *st, IOTNAV_REAL fx, IOTNAV_REAL fy, IOTNAV_REAL fz, IOTNAV_REAL g,
                   IOTNAV_REAL a_veh);

/* sizeof(pl_tilt_state), for bindings that check their layout. */
int32_t pl_tilt_sizeof(void);

#endif
