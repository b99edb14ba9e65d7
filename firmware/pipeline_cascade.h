/* Forno et al. 2020 pipeline, block 2: the cascaded Kalman filter (iotnav.techniques.cascade) in
 * C99, the wiring of the gyro-bias, tilt and yaw KFs (pipeline_gyrobias.h, pipeline_tilt.h,
 * pipeline_yaw.h). Per IMU sample (pl_cascade_step, cascade_step): the bias KF predicted and,
 * while block 3 says static, updated with the raw rate; omega_b = raw - bias; the tilt KF
 * predicted with omega_b and the bias variance (mean of the bias covariance's diagonal) and
 * updated with the accelerometer; the yaw KF predicted the same way; C_nb = [x1; x3 x x1; x3]
 * (pl_dcm_rows) and the yaw state set to its orthonormalised first row. At the GNSS rate the
 * course aid (pl_cascade_aid_heading, CascadeKF.aid_heading), the magnetometer aid
 * (pl_cascade_aid_mag) and the heading rotation when the mount estimate changes
 * (pl_cascade_rotate_heading). pl_front_end_step (front_end_step) runs blocks 2 and 3 for one
 * IMU sample as the pipeline and the anchor engine do. No dynamic memory, no global state, nothing from libc but
 * <math.h>. */
#ifndef IOTNAV_PIPELINE_CASCADE_H
#define IOTNAV_PIPELINE_CASCADE_H

#include "pipeline_gyrobias.h"
#include "pipeline_static.h"
#include "pipeline_tilt.h"
#include "pipeline_yaw.h"

typedef struct {
    pl_gyrobias_state bias;
    pl_tilt_state tilt;
    pl_yaw_state yaw;
    IOTNAV_REAL C[9];     /* C_nb (b -> NED), row-major */
    IOTNAV_REAL omega[3]; /* the latest bias-corrected rate in b, rad/s */
} pl_cascade_state;

/* The three filters' init (no initial bias, tilt from the first accelerometer sample, heading
 * from the first aid), C_nb = I, omega = 0. gate_nis: the yaw gate (pl_yaw_init). Returns PL_OK
 * or the first filter's error. */
int pl_cascade_init(pl_cascade_state *st, const pl_gyrobias_config *bias, const pl_tilt_config *tilt,
                    const pl_yaw_config *yaw, IOTNAV_REAL gate_nis);
/* One IMU sample: specific force f (m/s^2, b), raw rate w (rad/s, b), dt s (0 for the first),
 * block 3's decision, gravity g (m/s^2), vehicle acceleration a_veh (m/s^2). C_nb in st->C. */
void pl_cascade_step(pl_cascade_state *st, IOTNAV_REAL ax, IOTNAV_REAL ay, IOTNAV_REAL az, IOTNAV_REAL gx,
                     IOTNAV_REAL gy, IOTNAV_REAL gz, IOTNAV_REAL dt, int is_static, IOTNAV_REAL g,
                     IOTNAV_REAL a_veh);
/* Course aid: sensor yaw psi_b = course + mount angle (rad), sigma rad (NaN: the configured one).
 * Returns 1 when applied, 0 when gated out; C_nb rebuilt either way. */
int pl_cascade_aid_heading(pl_cascade_state *st, IOTNAV_REAL psi_b, IOTNAV_REAL sigma);
/* Magnetometer aid (any unit, b). Returns pl_yaw_update_mag's result; C_nb rebuilt either way. */
int pl_cascade_aid_mag(pl_cascade_state *st, IOTNAV_REAL mx, IOTNAV_REAL my, IOTNAV_REAL mz);
/* Add delta_rad to the sensor yaw (once the heading is initialised): the yaw KF reset to
 * atan2(C[3], C[0]) + delta with sigma = sqrt(trace P_yaw), C_nb rebuilt. */
void pl_cascade_rotate_heading(pl_cascade_state *st, IOTNAV_REAL delta_rad);

/* Blocks 2 and 3 for one IMU sample (front_end_step): the vehicle acceleration that de-weights
 * the tilt KF is hypot(a_long, v_gnss r) with the previous sample's yaw rate r while the GNSS
 * speed is at most 2.5 s old (t_speed: its time; frac -INFINITY: none yet), |v_dr r| with the
 * filter's horizontal speed v_dr (m/s) when older, else 0; then pl_cascade_step with block 3's
 * previous decision is_static, y_n = C_nb f_b (m/s^2, NED) into y_n[3], and pl_static_step on
 * its North / East with v_dr as the fallback speed. Returns block 3's new decision. */
int pl_front_end_step(pl_cascade_state *st, pl_static_state *det, iotnav_time t, IOTNAV_REAL ax, IOTNAV_REAL ay,
                      IOTNAV_REAL az, IOTNAV_REAL gx, IOTNAV_REAL gy, IOTNAV_REAL gz, IOTNAV_REAL dt, int is_static,
                      IOTNAV_REAL g, IOTNAV_REAL a_long, IOTNAV_REAL v_gnss, iotnav_time t_speed, IOTNAV_REAL v_dr,
                      IOTNAV_REAL *y_n);

/* sizeof(pl_cascade_state), for bindings that check their layout. */
int32_t pl_cascade_sizeof(void);

#endif
