/* Forno et al. 2020 pipeline, block 6: the fusion Kalman filter (iotnav.techniques.fusion_kf) in
 * C99. The 9-state linear GPS/INS integration of Table I ([n, m, p] = [9, 5, 3], the linear filter
 * of Zihajehzadeh et al. 2015, the paper's ref. [5]):
 *
 *     x = [r_n (3, m), v_n (3, m/s), b_a (3, m/s^2)],   u = C_nb f_b + g_n (m/s^2)
 *     F = [[I, dt I, -dt^2/2 C_nb], [0, I, -dt C_nb], [0, 0, I]],  B = [[dt^2/2 I], [dt I], [0]]
 *     Q = q_a [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]] (+) q_b dt I
 *
 * with the accelerometer bias in the sensor frame (so F depends on C_nb), the GNSS position
 * (H = [I 0 0], NIS-gated with forced re-convergence after max_rejections refusals or an outage)
 * and the velocity (horizontal [v_N, v_E] from speed and course, or the receiver's NED
 * velocity) as sequential updates with the Joseph form, as iotnav.kalman.update_selected.
 *
 * pl_fusion_predict mirrors fusion_predict (F and Q written out per 3 x 3 block, F's identity
 * and zero blocks skipped, the symmetric P- once per pair: no 9 x 9 products; float64 within
 * 1e-9 of Python); pl_fusion_update_* FusionKF.update_position / update_velocity / update_velocity_ned.
 * R is diagonal (gnss_noise's and the velocity's): three variances. No dynamic memory, no global
 * state (one pl_fusion_state per device), nothing from libc but <math.h> (sqrt). */
#ifndef IOTNAV_PIPELINE_FUSION_H
#define IOTNAV_PIPELINE_FUSION_H

#include "pipeline_nav_config.h"

#define PL_FUSION_N 9
#define PL_FUSION_OK 0
#define PL_FUSION_REJECTED 1          /* NIS above the gate: state unchanged */
#define PL_FUSION_ERR_NUMERIC (-2)    /* S not positive definite: state unchanged (Python: NaN) */
#define PL_FUSION_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */

typedef struct {
    pl_fusion_config cfg;
    IOTNAV_REAL x[PL_FUSION_N];                /* [r_n, v_n, b_a] (F_X) */
    IOTNAV_REAL P[PL_FUSION_N * PL_FUSION_N];  /* covariance, row-major (F_P) */
    int32_t initialised;                       /* F_INIT */
    int32_t n_rejected;                        /* consecutive gated fixes (FusionKF.n_rejected) */
    IOTNAV_REAL gate;                          /* position NIS gate (3 dof), 0: none */
    IOTNAV_REAL nis;                           /* NIS of the latest update */
} pl_fusion_state;

/* Set up `st` (not yet initialised: predictions do nothing). gate_nis: the chi-square quantile
 * (3 dof) of cfg->gate_probability (iotnav.kalman.gate_threshold; 0: no gate).
 * PL_FUSION_ERR_UNSUPPORTED for smoothing = 1 (the RTS smoother's log is not in C). */
int pl_fusion_init(pl_fusion_state *st, const pl_fusion_config *cfg, IOTNAV_REAL gate_nis);
/* FusionKF.initialise: position r_n (m) with the variances r_var (m^2, R's diagonal) and the
 * velocity v_n (m/s; NULL: zero). */
void pl_fusion_initialise(pl_fusion_state *st, const IOTNAV_REAL r_n[3], const IOTNAV_REAL r_var[3],
                          const IOTNAV_REAL *v_n);
/* fusion_predict with u = (a0, a1, a2) = C_nb f_b + g_n (NED, m/s^2), C_nb row-major, dt (s) and
 * the acceleration PSD q_a (m^2/s^3: cfg.acc_psd_m2_s3, or the pipeline's widened one while the
 * heading is unresolved); nothing for dt <= 0 or before initialisation. */
void pl_fusion_predict(pl_fusion_state *st, IOTNAV_REAL a0, IOTNAV_REAL a1, IOTNAV_REAL a2,
                       const IOTNAV_REAL C[9], IOTNAV_REAL dt, IOTNAV_REAL q_a);
/* FusionKF.update_position: fix r_n (NED, m), R's diagonal r_var (m^2); stale: the first fix
 * after an outage (taken at once, as a forced one). PL_FUSION_OK, PL_FUSION_REJECTED or
 * PL_FUSION_ERR_NUMERIC. */
int pl_fusion_update_position(pl_fusion_state *st, const IOTNAV_REAL r_n[3], const IOTNAV_REAL r_var[3],
                              int stale);
/* FusionKF.update_velocity ([v_N, v_E], m/s) and update_velocity_ned ([v_N, v_E, v_D]), 1-sigma
 * sigma_mps per component (m/s): PL_FUSION_OK or PL_FUSION_ERR_NUMERIC. */
int pl_fusion_update_velocity(pl_fusion_state *st, IOTNAV_REAL v_n, IOTNAV_REAL v_e, IOTNAV_REAL sigma_mps);
int pl_fusion_update_velocity_ned(pl_fusion_state *st, const IOTNAV_REAL v[3], IOTNAV_REAL sigma_mps);

/* sizeof(pl_fusion_state), for bindings that check their layout. */
int32_t pl_fusion_sizeof(void);

#endif
