/* Forno et al. 2020 pipeline, block 5: the yaw mounting-angle alignment (iotnav.techniques.mount)
 * in C99, the form the iotnav pipeline runs (method "lsq").
 *
 * The paper (Sec. III-A5) buffers the accelerometer and the GPS course while moving and, on a
 * straight (var(alpha) < theta_alpha), takes [a_x a_y a_z]^T = R_b^n mean(y_b) - g_n (Eq. 2) and
 * eps_alpha = arctan(a_y / a_x) (Eq. 3). iotnav's robust form keeps Eq. 2's levelled, gravity-free
 * acceleration a_s (levelled against the aligner's own gravity reference f_ref_b, not the tilt
 * filter) and replaces Eq. 3 by the least-squares rotation between a_s and the vehicle-frame
 * acceleration a_v = [dv/dt, v r] from GPS and the gyroscope, over buffers of GPS intervals:
 *
 *     mount_yaw = atan2(sum (a_s x a_v)_z, sum a_s . a_v)
 *
 * with matched triangular smoothing of the rows, forgetting, the NIS-like buffer gate, the levelled
 * and demeaned forms with their Birge ratio (auto_demean), the settled and provisional acceptance:
 * the rules of the Python module docstring, here operation for operation. The paper form (method
 * "paper") is refused at pl_mount_init (PL_MOUNT_ERR_UNSUPPORTED), never silently different.
 *
 * No dynamic memory, no global state (one pl_mount_state per device), nothing from libc but
 * <math.h> (sqrt, sin, cos, atan2, hypot, pow, floor, isfinite). */
#ifndef IOTNAV_PIPELINE_MOUNT_H
#define IOTNAV_PIPELINE_MOUNT_H

#include "pipeline_nav_config.h"

#define PL_MOUNT_OK 0
#define PL_MOUNT_ERR_UNSUPPORTED (-1)
/* columns of a buffer row (mount.AS_X, AS_Y, DV, DT, AV_Y: the ones the lsq form reads) */
#define PL_MOUNT_COLS 5

/* Exponentially forgotten lsq sums of one form of the buffers (mount._Fusion). */
typedef struct {
    IOTNAV_REAL acc[4]; /* sum cross, sum dot, sum |a_v|^2, sum |a_s|^2 (lsq_sums) */
    IOTNAV_REAL n;      /* forgetting-weighted row count */
    IOTNAV_REAL w2;     /* sum of the squared forgetting weights */
    IOTNAV_REAL z2;     /* forgetting-weighted sum of squared normalised buffer innovations */
    IOTNAV_REAL nz;     /* their forgetting-weighted count */
    int32_t demean;
} pl_mount_fusion;

/* What an evaluated buffer gave (the mount_estimate event of MountAligner.add_gnss). */
typedef struct {
    int32_t accepted, applied, provisional, settled, buffer_outlier, demeaned;
    IOTNAV_REAL mount_yaw_rad;   /* the angle in use after this buffer, rad */
    IOTNAV_REAL candidate_rad;   /* the fused estimate, rad */
    IOTNAV_REAL std_rad;         /* its standard deviation (consistency-scaled with auto_demean), rad */
    IOTNAV_REAL coherence;
    IOTNAV_REAL excitation_mps2;
    IOTNAV_REAL consistency;     /* Birge ratio (NaN without auto_demean) */
    IOTNAV_REAL buffer_mount_yaw_rad, buffer_coherence, buffer_std_rad, buffer_excitation_mps2;
} pl_mount_event;

typedef struct {
    pl_mount_config cfg;
    IOTNAV_REAL mount_yaw_rad;                       /* the angle in use, rad */
    int32_t known, provisional, accepted_once, done;
    IOTNAV_REAL buf[PL_MOUNT_BUF_MAX][PL_MOUNT_COLS]; /* the buffer of rows */
    int32_t n_buf, k;                                /* its length max(2, buffer_epochs), rows in it */
    pl_mount_fusion fu[2];                           /* the configured form; the demeaned one */
    /* the (t, fused angle) history of settle_s, a ring (Python keeps a list; beyond
     * PL_MOUNT_HIST_MAX entries C drops the oldest and counts it) */
    iotnav_time hist_t[PL_MOUNT_HIST_MAX];
    IOTNAV_REAL hist_mu[PL_MOUNT_HIST_MAX];
    int32_t hist_first, hist_n, n_hist_dropped;
    /* IMU sums of the current interval (IMU_*): levelled a_s x, y, rate r, |a_s|^2, count, f_b */
    IOTNAV_REAL sx, sy, sr, ssq;
    int32_t n_imu, body;
    IOTNAV_REAL fb[3];
    iotnav_time t_prev;                              /* latest GPS epoch (valid when have_prev) */
    int32_t have_prev;
    IOTNAV_REAL v_prev;                              /* its speed, m/s (NaN: none) */
    /* gravity reference of body-frame input: per interval f_b mean (3), n, dv, dt, v r */
    IOTNAV_REAL ring[PL_MOUNT_REF_MAX][7];
    int32_t ring_ok[PL_MOUNT_REF_MAX];
    int32_t n_ring, i_ring, ring_full;
    IOTNAV_REAL f_ref[3];                            /* m/s^2 (NaN: none yet) */
    iotnav_time t_ref;                               /* valid when have_ref */
    int32_t have_ref;
    /* matched smoothing: the last 2M - 1 contiguous good rows and the weights */
    IOTNAV_REAL sm[PL_MOUNT_SMOOTH_ROWS_MAX][PL_MOUNT_COLS];
    IOTNAV_REAL smooth_w[PL_MOUNT_SMOOTH_ROWS_MAX];
    int32_t n_sm, k_sm;
    IOTNAV_REAL sw, overlap;
} pl_mount_state;

/* Set up `st`; PL_MOUNT_ERR_UNSUPPORTED for method != 0 (lsq), or sizes beyond
 * PL_MOUNT_BUF_MAX / PL_MOUNT_REF_MAX / PL_MOUNT_SMOOTH_ROWS_MAX. */
int pl_mount_init(pl_mount_state *st, const pl_mount_config *cfg);
/* A stored (accepted) calibration at boot, rad: known, and done when one_off (Pipeline.__init__). */
void pl_mount_set_stored(pl_mount_state *st, IOTNAV_REAL mount_yaw_rad);
/* One IMU sample, levelled input: a_s (m/s^2), yaw rate r (rad/s) (MountAligner.add_imu). */
void pl_mount_add_imu(pl_mount_state *st, IOTNAV_REAL a_x, IOTNAV_REAL a_y, IOTNAV_REAL r);
/* One IMU sample in the sensor frame: f_b (m/s^2), yaw rate r (rad/s) (add_imu_body). */
void pl_mount_add_imu_body(pl_mount_state *st, IOTNAV_REAL fx, IOTNAV_REAL fy, IOTNAV_REAL fz, IOTNAV_REAL r);
/* set_gravity_reference: mean f_b (m/s^2) while unaccelerated, measured up to t. */
void pl_mount_set_gravity_reference(pl_mount_state *st, const IOTNAV_REAL f_b[3], iotnav_time t);
/* MountAligner.add_gnss: close the GPS interval ending at t (speed m/s, course rad, its validity,
 * block 3's decision). Returns 1 and fills *ev when a buffer was evaluated, else 0. */
int pl_mount_add_gnss(pl_mount_state *st, iotnav_time t, IOTNAV_REAL speed_mps, IOTNAV_REAL course_rad,
                      int course_valid, int is_static, pl_mount_event *ev);
/* mount.wrap: an angle (rad) to (-pi, pi]. */
IOTNAV_REAL pl_mount_wrap(IOTNAV_REAL a);

/* sizeof(pl_mount_state), for bindings that check their layout. */
int32_t pl_mount_sizeof(void);

#endif
