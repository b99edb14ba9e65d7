/* The Forno et al. 2020 pipeline (Fig. 1, blocks 1-6) wired as ONE engine in C99: the step of
 * iotnav.engines.pipeline.Pipeline (its IMU kernel pipeline_imu_kernel and its _gnss), chaining
 * the blocks of pipeline_lastpos.h (1), pipeline_cascade.h (2), pipeline_static.h (3),
 * pipeline_lowpass3.h (4), pipeline_mount.h (5) and pipeline_fusion.h (6) in the same order of
 * operations, with the same events (as flags, PL_EV_*) and the same output row.
 *
 *   pl_init        Pipeline.__init__ (stored = None); pl_set_stored: a stored last position
 *   pl_step_imu    Pipeline.step(ImuSample): InputGuard, then pipeline_imu_kernel on one sample
 *   pl_step_gnss   Pipeline.step(GnssSample): InputGuard, then Pipeline._gnss
 *   pl_step_mag    Pipeline.step(MagSample): the yaw filter's magnetometer aid when yaw.use_mag
 *   pl_output      the Output row of the latest IMU sample
 *
 * Refused at pl_init (PL_ERR_UNSUPPORTED), never silently different: fusion.smoothing (the RTS
 * smoother's log is not in C), mount.method = "paper", sizes beyond the blocks' fixed maxima
 * (PL_STATIC_SPEED_WINDOW_MAX, PL_LOWPASS3_N_MAX, PL_MOUNT_*_MAX), and a yaw or fusion
 * gate_probability > 0 without its chi-square quantile in yaw_gate_nis / fusion_gate_nis (the
 * generated PL_PIPELINE_CONFIG_DEFAULTS carry them; <math.h> cannot compute them).
 *
 * Coordinates and times as in anchor.h: latitude / longitude as integer 1e-7 deg plus a fraction
 * (the tangent plane anchored at a fix in those units, re-anchored beyond
 * PL_REANCHOR_DISTANCE_M as TangentPlane.follow), times as whole seconds plus a fraction.
 *
 * No dynamic memory, no global state (one pl_state per device), nothing from libc but <math.h>. */
#ifndef IOTNAV_PIPELINE_H
#define IOTNAV_PIPELINE_H

#include "pipeline_cascade.h"
#include "pipeline_engine_config.h"
#include "pipeline_fusion.h"
#include "pipeline_lastpos.h"
#include "pipeline_lowpass3.h"
#include "pipeline_mount.h"
#include "pipeline_static.h"

/* Events of a step (bits of the return value; Pipeline.events' types). */
#define PL_EV_FIX_REJECTED 0x001    /* "fix_rejected": reason in st->fix_reason (PL_FIX_*, PL_FIX_NIS) */
#define PL_EV_MOVED_WHILE_OFF 0x002 /* "moved_while_off": distance in st->moved_distance_m */
#define PL_EV_FIRST_FIX 0x004       /* "first_fix" */
#define PL_EV_VERTICAL_RESET 0x008  /* "vertical_reset": st->vertical_jump_m */
#define PL_EV_MOUNT 0x010           /* "mount_estimate": st->mount_event */
#define PL_EV_SAVE 0x020            /* a save is due (store.save): st->save */
#define PL_EV_STATIC_START 0x040    /* "static_start" */
#define PL_EV_STATIC_END 0x080      /* "static_end" */
#define PL_EV_BOOT_MOVE 0x100       /* "boot_movement_before_fix" */
#define PL_EV_SKIPPED 0x200         /* InputGuard refused the sample (reason in st->skip_reason) */
#define PL_EV_IMU_GAP 0x400         /* InputGuard's "imu_gap" (the sample is used) */
#define PL_EV_COURSE_REPAIRED 0x800 /* "gnss_course_nonfinite": course_valid taken as 0 */
#define PL_EV_NUMERIC 0x1000        /* a fusion update's S was not positive definite (skipped) */

/* The NIS gate's reason (Python "nis"), after block 1's PL_FIX_* */
#define PL_FIX_NIS 7

/* InputGuard's reasons (st->skip_reason, st->n_skipped[]) */
#define PL_SKIP_IMU_NONFINITE 0
#define PL_SKIP_IMU_TIME_BACKWARDS 1
#define PL_SKIP_IMU_GAP 2
#define PL_SKIP_GNSS_NONFINITE 3
#define PL_SKIP_GNSS_TIME_BACKWARDS 4
#define PL_SKIP_GNSS_COURSE_NONFINITE 5
#define PL_SKIP_MAG_NONFINITE 6
#define PL_SKIP_MAG_TIME_BACKWARDS 7
#define PL_N_SKIP 8

/* Output sources (iotnav.engines.base SRC_*) */
#define PL_SRC_NONE 0
#define PL_SRC_FIX 1
#define PL_SRC_DR 2
#define PL_SRC_LOWPASS 3
#define PL_SRC_LAST_POSITION 4

/* One IMU sample: device time, specific force and angular rate in the sensor frame. */
typedef struct {
    iotnav_time t;       /* s */
    IOTNAV_REAL f_b[3];  /* m/s^2 */
    IOTNAV_REAL w_b[3];  /* rad/s */
} pl_imu_in;

/* One GNSS epoch. Missing figures are NaN; no position: lat_frac_e7 / lon_frac_e7 NaN. */
typedef struct {
    iotnav_time t;                        /* device time, s */
    int32_t valid;                        /* the receiver declares a fix */
    int32_t num_sv;                       /* satellites used */
    int32_t lat_e7, lon_e7;               /* geodetic latitude / longitude, 1e-7 deg ... */
    IOTNAV_REAL lat_frac_e7, lon_frac_e7; /* ... plus these fractions of 1e-7 deg */
    IOTNAV_REAL height_m;                 /* ellipsoidal height, m (NaN: 2D fix) */
    IOTNAV_REAL h_acc_m, v_acc_m, s_acc_mps, pdop, hdop;
    IOTNAV_REAL speed_mps, course_rad;    /* ground speed, m/s; course over ground, rad */
    int32_t course_valid;
    IOTNAV_REAL vn, ve, vd;               /* NED velocity, m/s */
} pl_gnss_in;

/* A geodetic point: 1e-7 deg plus fraction, height m. */
typedef struct {
    int32_t lat_e7, lon_e7;
    IOTNAV_REAL lat_frac_e7, lon_frac_e7;
    IOTNAV_REAL height_m;
} pl_geo;

/* The output row of the latest IMU sample (Output of Pipeline.step). */
typedef struct {
    iotnav_time t;
    int32_t source;           /* PL_SRC_* */
    int32_t is_static;        /* block 3 */
    int32_t has_position;     /* 0: NaN position (source none) */
    IOTNAV_REAL r_n[3];       /* NED about the origin, m */
    IOTNAV_REAL v_n[3];       /* NED velocity, m/s */
    IOTNAV_REAL std_north, std_east; /* 1-sigma, m */
    pl_geo geo;               /* geodetic position (meaningful with has_position) */
    IOTNAV_REAL roll, pitch, yaw; /* vehicle attitude once the mount is known, else the sensor's, rad */
} pl_output_t;

/* The tangent plane (iotnav.engines.tangent_plane.TangentPlane), anchored at a fix: north =
 * n_a + (lat - lat_a) k_n, east = e_a + (lon - lon_a) k_e (1e-7 deg), down = h0 - h. */
typedef struct {
    int32_t lat_a_e7, lon_a_e7;
    IOTNAV_REAL lat_a_frac_e7, lon_a_frac_e7;
    IOTNAV_REAL n_a, e_a, h0_m;
    IOTNAV_REAL k_n, k_e, inv_k_n, inv_k_e; /* m per 1e-7 deg and inverses */
    int32_t n_anchors;
} pl_plane;

/* What a save (PL_EV_SAVE) stores: StoredPosition */
typedef struct {
    pl_geo pos;
    iotnav_time t;
    IOTNAV_REAL mount_yaw_rad; /* NaN: none (unknown or provisional) */
} pl_save;

/* The engine: one per device, fixed size. */
typedef struct {
    pl_pipeline_config cfg;
    pl_cascade_state att;     /* block 2 */
    pl_static_state det;      /* block 3 */
    pl_lowpass3_state lp;     /* block 4 */
    pl_lastpos_state boot;    /* block 1 */
    pl_mount_state mount;     /* block 5 */
    pl_fusion_state fus;      /* block 6 */
    pl_plane plane;
    int32_t have_frame, origin_2d, has_stored;
    /* the kernel's scalars (Pipeline._st) */
    iotnav_time t_prev;       /* ST_T_PREV (has_t_prev) */
    int32_t has_t_prev, is_static;
    IOTNAV_REAL a_long, v_gnss, g;
    iotnav_time t_speed;      /* frac -INFINITY: none */
    iotnav_time t_fix;        /* has_t_fix: -inf otherwise */
    iotnav_time t_boot_move;  /* has_boot_move */
    iotnav_time t_gnss;       /* the latest accepted fix (has_t_gnss) */
    int32_t has_t_fix, has_boot_move, has_t_gnss;
    /* InputGuard */
    iotnav_time guard_t[3];   /* IMU, GNSS, magnetometer (guard_has[]) */
    int32_t guard_has[3];
    uint32_t n_skipped[PL_N_SKIP]; /* per reason (unsigned: wraps, never undefined) */
    /* the latest step's event values */
    int32_t fix_reason, skip_reason;
    IOTNAV_REAL moved_distance_m, vertical_jump_m, nis;
    pl_mount_event mount_event;
    pl_save save;
    /* the latest IMU sample's row, as computed then (pl_output converts it) */
    iotnav_time row_t;
    int32_t row_source, row_static, row_has_position, row_mount_known;
    IOTNAV_REAL row_r[3], row_v[3], row_std_n, row_std_e, row_C[9], row_mu;
    /* cos and sin of the known mount angle cs_mu (for pl_output), formed only when it changes */
    IOTNAV_REAL cs_mu, row_cos_mu, row_sin_mu;
    pl_plane row_plane;
} pl_state;

/* Set up `st` (Pipeline(config) without a stored position). PL_OK, or PL_ERR_UNSUPPORTED for a
 * configuration this library does not implement (the state is then unusable). */
int pl_init(pl_state *st, const pl_pipeline_config *cfg);
/* A stored last position at boot (Pipeline(stored=...)): call once after pl_init, before any
 * sample. mount_yaw_rad NaN: no stored mount calibration. */
void pl_set_stored(pl_state *st, const pl_geo *pos, IOTNAV_REAL mount_yaw_rad);
/* One IMU sample. Returns its PL_EV_* flags (PL_EV_SKIPPED: refused, no new row). */
int pl_step_imu(pl_state *st, const pl_imu_in *in);
/* One GNSS epoch. Returns its PL_EV_* flags. */
int pl_step_gnss(pl_state *st, const pl_gnss_in *in);
/* One magnetometer sample (any unit, sensor frame). Returns PL_EV_* flags (0 or PL_EV_SKIPPED). */
int pl_step_mag(pl_state *st, iotnav_time t, const IOTNAV_REAL m_b[3]);
/* The row of the latest IMU sample (all NaN / source none before any). */
void pl_output(const pl_state *st, pl_output_t *out);

/* sizeof of the API structs (0 state, 1 config, 2 IMU input, 3 GNSS input, 4 output, 5 geo), for
 * bindings that check their layout; 0 for another `which`. */
int32_t pl_sizeof(int32_t which);

#endif
