/* Forno et al. 2020 pipeline, block 2's yaw Kalman filter (iotnav.techniques.yaw_kf) in C99: the
 * North axis of the navigation frame resolved in the sensor frame (first row of C_nb),
 * propagated with the bias-corrected gyroscope (F = I - dt [omega_b x],
 * Q = dt^2 (sigma_g^2 + sigma_b^2) (I - x x^T) + q_floor I, no renormalisation) and aided by a
 * sensor heading psi_b (GPS course + the mount angle of block 5: z = r1(roll, pitch, psi_b),
 * H = I, R = sigma^2 J J^T + (0.02 sigma)^2 I, J = d r1 / d psi, the optional chi-square NIS
 * gate) or by the magnetometer (the horizontal field rotated by the declination, R = sigma_m^2 I).
 * After each accepted update x is Gram-Schmidt orthogonalised to the tilt estimate x3 and made
 * unit length (pl_dcm_rows: C_nb = [x1; x3 x x1; x3]). The module docstring of
 * iotnav.techniques.yaw_kf gives the model.
 *
 * pl_yaw_predict mirrors yaw_predict, pl_yaw_update_heading YawKF.update_heading (kf3.update3 with
 * the full R and the gate), pl_yaw_reset_heading YawKF.reset_heading, pl_yaw_update_mag
 * YawKF.update_mag, pl_dcm_rows dcm_rows_into. No dynamic memory, no global state, nothing from
 * libc but <math.h> (sqrt, sin, cos, asin, atan2, fabs, isfinite, isnan). */
#ifndef IOTNAV_PIPELINE_YAW_H
#define IOTNAV_PIPELINE_YAW_H

#include "pipeline_config.h"

#ifndef PL_OK
#define PL_OK 0
#define PL_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */
#endif

typedef struct {
    pl_yaw_config cfg;
    IOTNAV_REAL x[3];      /* the North axis in b (unit vector) */
    IOTNAV_REAL P[9];      /* its covariance, row-major */
    int32_t initialised;   /* a heading (course or magnetometer) measurement set x */
    IOTNAV_REAL nis;       /* NIS of the latest update (NaN before any) */
    int32_t gated;         /* 1: the heading updates are NIS-gated at `gate` */
    IOTNAV_REAL gate;      /* chi-square threshold (3 dof) of gate_probability */
    IOTNAV_REAL gyro_var;  /* gyro_noise_rad_s^2, rad^2/s^2 */
    IOTNAV_REAL mag_var;   /* mag_noise^2 */
    IOTNAV_REAL cos_decl;  /* cos(declination_rad) */
    IOTNAV_REAL sin_decl;  /* sin(declination_rad) */
} pl_yaw_state;

/* Set up `st`: x = [1, 0, 0], P = I, not initialised. gate_nis: the chi-square quantile of
 * cfg->gate_probability for 3 degrees of freedom (math.h has no inverse chi-square: the
 * generator writes it as PL_YAW_GATE_NIS; iotnav.firmware.pipeline.yaw_gate), used only when
 * gate_probability > 0. Returns PL_OK, or PL_ERR_UNSUPPORTED for a gate that is not positive. */
int pl_yaw_init(pl_yaw_state *st, const pl_yaw_config *cfg, IOTNAV_REAL gate_nis);
/* Propagate with the bias-corrected rate (rad/s, b) over dt s (nothing when dt <= 0); bias_var:
 * the gyro-bias variance, rad^2/s^2. */
void pl_yaw_predict(pl_yaw_state *st, IOTNAV_REAL wx, IOTNAV_REAL wy, IOTNAV_REAL wz, IOTNAV_REAL dt,
                    IOTNAV_REAL bias_var);
/* Set x to the sensor yaw psi_b (rad) at the tilt x3 (down axis in b), P to its R (sigma rad;
 * NaN: course_noise_rad). */
void pl_yaw_reset_heading(pl_yaw_state *st, IOTNAV_REAL psi_b, const IOTNAV_REAL *x3, IOTNAV_REAL sigma);
/* Correct with a sensor yaw psi_b (rad; course + mount angle) at the tilt x3 (sigma rad; NaN:
 * course_noise_rad); the first one resets. Returns 1 when applied, 0 when gated out. */
int pl_yaw_update_heading(pl_yaw_state *st, IOTNAV_REAL psi_b, const IOTNAV_REAL *x3, IOTNAV_REAL sigma);
/* Correct with a magnetometer sample m_b (any unit, b) at the tilt x3. Returns 0 when its
 * horizontal part is zero or not finite (nothing done), else 1. */
int pl_yaw_update_mag(pl_yaw_state *st, IOTNAV_REAL mx, IOTNAV_REAL my, IOTNAV_REAL mz, const IOTNAV_REAL *x3);
/* C_nb (row-major, 9) from the North row x1 and the down row x3 (both in b): x3 normalised and
 * kept, x1 orthogonalised to it and normalised, East = x3 x x1. C may alias x1. */
void pl_dcm_rows(const IOTNAV_REAL *x1, const IOTNAV_REAL *x3, IOTNAV_REAL *C);

/* sizeof(pl_yaw_state), for bindings that check their layout. */
int32_t pl_yaw_sizeof(void);

#endif
