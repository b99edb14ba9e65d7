/* The GNSS-only engine (iotnav.engines.fixes, issue 17) in C99: constant-velocity Kalman filter
 * per axis on the tangent plane of the first fix, the NIS gate with relocation, forced
 * re-initialisation and rollback of doubtful fixes, static detection (speed, motion and
 * ignition flags, the spread test, the accelerometer between fixes; the departure test while
 * parked) with the zero-velocity updates and the 3-level low-pass while static, the input checks and the settling gate of the
 * first fix. fixes_step_gnss mirrors FixesEngine.step() on a GNSS epoch (the compiled
 * iotnav.engines.fixes_kernel.fixes_kernel on one row, with the engine's boot decision),
 * fixes_step_imu its accumulation of |f_b| between fixes.
 *
 * Not in C (refused or left to the caller, never silently different): a stored last position at
 * boot and its saving (fixes_init starts without one: the engine's `stored=None`), the smoothing
 * records (FixesConfig.kf.smoothing: refused by the export), low-pass levels longer than
 * FIXES_LP_MAX (fixes_init returns FIXES_ERR_UNSUPPORTED).
 *
 * No dynamic memory, no global state (one fixes_state per device), no libc beyond <math.h>. */
#ifndef IOTNAV_FIXES_H
#define IOTNAV_FIXES_H

#include "fixes_config.h"

#define FIXES_OK 0
#define FIXES_ERR_UNSUPPORTED (-1)
/* fixes_step_imu */
#define FIXES_IMU_NONFINITE 1 /* imu_nonfinite: skipped */
#define FIXES_IMU_BACKWARDS 2 /* imu_time_backwards: skipped */
#define FIXES_IMU_GAP 3       /* imu_gap: counted, the sample used */

/* One GNSS epoch. Missing figures are NaN; lat/lon as integer 1e-7 deg plus a fraction of 1e-7
 * deg (u-blox style; NaN fraction: no coordinates); flags 1 / 0, -1 unknown. */
typedef struct {
    iotnav_time t;            /* device time, s (NaN fraction: not a time) */
    iotnav_time utc;          /* UTC, s since 1970, when has_utc */
    int32_t has_utc;
    int32_t valid;            /* receiver's validity flag */
    int32_t num_sv;           /* satellites used, -1 unknown */
    int32_t course_valid;
    int32_t motion, ignition; /* device flags: 1 moving / on, 0 still / off, -1 unknown */
    int32_t lat_e7, lon_e7;
    IOTNAV_REAL lat_frac_e7, lon_frac_e7;
    IOTNAV_REAL height_m;     /* ellipsoidal height, m (NaN: 2D fix) */
    IOTNAV_REAL h_acc_m, v_acc_m, hdop, pdop;
    IOTNAV_REAL speed_mps, course_rad; /* ground speed, m/s; course over ground, rad */
    IOTNAV_REAL vn, ve, vd;   /* NED velocity, m/s */
    IOTNAV_REAL s_acc_mps;    /* speed accuracy, m/s */
} fixes_gnss_in;

/* The row of a processed epoch (FixesEngine.step's Output), and the epoch's events. */
typedef struct {
    int32_t events;           /* FIXES_EV_* bits of this epoch (also of a skipped one) */
    IOTNAV_REAL event_value;  /* the kernel's evv: NIS, jump (m), offset change (s); NaN without */
    int32_t source;           /* FIXES_SRC_* */
    int32_t is_static;
    int32_t has_down;         /* 0: no height yet (height, down and vd are NaN in Python) */
    IOTNAV_REAL r_n[3];       /* north, east, down in the tangent plane of the first fix, m */
    IOTNAV_REAL v_n[3];       /* NED velocity, m/s */
    IOTNAV_REAL std_north, std_east; /* 1-sigma, m */
    int32_t lat_e7, lon_e7;   /* geodetic position, 1e-7 deg ... */
    IOTNAV_REAL lat_frac_e7, lon_frac_e7; /* ... plus these fractions of 1e-7 deg */
    IOTNAV_REAL height_m;     /* ellipsoidal height, m */
} fixes_output_t;

/* One axis of the filter: [p, v, P_pp, P_pv, P_vv] (m, m/s, m^2, m^2/s, m^2/s^2). */
typedef struct {
    IOTNAV_REAL p, v, pp, pv, vv;
} fixes_axis;

typedef struct {
    iotnav_time t;
    IOTNAV_REAL n, e, d, s2; /* s2: the fix's horizontal variance per axis, m^2 */
} fixes_fix;

/* Filter state: fixed size, one per device. */
typedef struct {
    fixes_config cfg;
    fixes_axis kf[3], snap_x[3];      /* North, East, Down; the rollback snapshot */
    int32_t init, have_frame, have_d, is_static, have_t_last, have_off, snap, have_lp;
    iotnav_time t_last, t_x, t_fix, snap_t;
    int32_t lat_last_e7, lon_last_e7;
    IOTNAV_REAL lat_last_frac, lon_last_frac;
    iotnav_time off_ref, off_cand;    /* UTC - t: the reference, the candidate new one */
    int32_t off_n;
    IOTNAV_REAL n_rej, speed_run, n_used;
    /* departure test while parked: the run of displaced fixes, its first fix, the last fix
     * that was not displaced */
    IOTNAV_REAL dep_n, dep_vmax, dep_pn, dep_pe, dep_d0, lp_var; /* lp_var: the low-pass output's variance */
    /* floor of the rows' variance, north and east, m^2: the last accepted fix's own, grown by
     * each prediction as P_pp is (fixes_kernel S_FLOOR_N / S_FLOOR_E) */
    IOTNAV_REAL floor_v[2];
    iotnav_time dep_t, t_still;
    /* the departure test's jump tracking (fixes_kernel S_GOOD_*, S_JUMP_*, S_IN_JUMP): the last
     * fix that was no jump, the latest jump fix, whether the fixes are in a jump now */
    IOTNAV_REAL good_n, good_e, jump_n, jump_e;
    iotnav_time good_t, jump_t;
    int32_t in_jump;
    /* the tangent plane: north = (lat - lat0) k_n, east = (lon - lon0) k_e, down = h0 - h */
    int32_t lat0_e7, lon0_e7;
    IOTNAV_REAL lat0_frac, lon0_frac, h0, k_n, k_e, inv_k_n, inv_k_e;
    IOTNAV_REAL hold[3], lp_out[3];
    int32_t lp_k1, lp_k2, lp_k3, lp_since2;
    IOTNAV_REAL lp1[FIXES_LP_MAX][3], lp2[FIXES_LP_MAX][3], lp3[FIXES_LP_MAX][3];
    int32_t cand_n, ring_n;
    fixes_fix cand[FIXES_CAND_MAX];
    fixes_fix ring[FIXES_RING_MAX];   /* d unused */
    IOTNAV_REAL work_n[FIXES_RING_MAX], work_e[FIXES_RING_MAX]; /* spread test scratch */
    /* accelerometer between fixes: count, sums of |f| - 9.80665 and of its square */
    int32_t acc_n, have_t_imu;
    IOTNAV_REAL acc_s1, acc_s2;
    iotnav_time t_imu;
    /* settling gate of the first fix (LastPositionLogic.check_fix): valid fixes' (t, PDOP) */
    int32_t first_fix_seen, settle_n, settle_dropped;
    iotnav_time settle_t[FIXES_SETTLE_MAX];
    IOTNAV_REAL settle_pdop[FIXES_SETTLE_MAX];
} fixes_state;

/* Set up `st` for `cfg`; FIXES_ERR_UNSUPPORTED for low-pass levels beyond FIXES_LP_MAX. */
int fixes_init(fixes_state *st, const fixes_config *cfg);
/* One IMU sample (time s, specific force m/s^2, rate rad/s: checked for finite values only). */
int fixes_step_imu(fixes_state *st, iotnav_time t, const IOTNAV_REAL f_b[3], const IOTNAV_REAL w_b[3]);
/* One GNSS epoch: FIXES_R_OK and the row in `out`, or the reason it was skipped (FIXES_R_*);
 * out->events / out->event_value in both cases. */
int fixes_step_gnss(fixes_state *st, const fixes_gnss_in *in, fixes_output_t *out);
/* sizeof of the API structs (0 state, 1 config, 2 GNSS input, 3 output). */
int32_t fixes_sizeof(int32_t which);

#endif
