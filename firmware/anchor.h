/* Anchor-node Kalman filter (iotnav.engines.anchor) in C99: the paper's [p_n v_n] KF with the
 * IMU acceleration as control input, GNSS position and velocity updates.
 *
 * Reference: "Real time IoT mobile anchor nodes outdoor localization mechanism", Int. J. Smart
 * Sensing and Intelligent Systems 15(1), 2022 (Fig. 5). The equations are those of the Python
 * module's docstring; this file mirrors AnchorEngine.step(): anchor_step_imu for an IMU
 * sample, anchor_step_gnss for a GNSS epoch, anchor_output for the row Python outputs.
 *
 * Scope: the attitude C_nb is an input (the paper: "the IMU provides orientation"); in iotnav it
 * comes from the tilt / yaw / gyro-bias cascade, which this library does not contain, together
 * with the traces of its tilt and yaw covariances (the attitude term of Q). What the library
 * does not implement it refuses with ANCHOR_ERR_UNSUPPORTED (never a silent difference):
 * smoothing, the NIS gate (gate_probability > 0), fixes without height.
 *
 * No dynamic memory, no global state, no libc beyond <math.h>. */
#ifndef IOTNAV_ANCHOR_H
#define IOTNAV_ANCHOR_H

#include "anchor_config.h"

/* Return codes: >= 0 a decision, < 0 an error (state unchanged). */
#define ANCHOR_OK 0                   /* sample used (a fix: accepted) */
#define ANCHOR_REJECT_INVALID 1       /* fix not valid */
#define ANCHOR_REJECT_NUM_SV_UNKNOWN 2 /* satellite count unknown, accept_unknown_num_sv == 0 */
#define ANCHOR_REJECT_NUM_SV 3        /* fewer than min_satellites */
#define ANCHOR_ERR_UNSUPPORTED (-1)   /* configuration or input this library does not implement */
#define ANCHOR_ERR_NUMERIC (-2)       /* innovation covariance not positive definite */

/* Output source (iotnav.engines.base SRC_NONE, SRC_FIX, SRC_DR). */
#define ANCHOR_SRC_NONE 0
#define ANCHOR_SRC_FIX 1
#define ANCHOR_SRC_DR 2

/* One IMU sample. */
typedef struct {
    iotnav_time t;            /* device time, s */
    IOTNAV_REAL f_b[3];       /* specific force, sensor frame b, m/s^2 */
    IOTNAV_REAL C_nb[9];      /* attitude after this sample, row-major, maps b to n (NED) */
    IOTNAV_REAL tilt_p_trace; /* trace of the tilt filter's covariance of the down row, rad^2 */
    IOTNAV_REAL yaw_p_trace;  /* trace of the yaw filter's covariance, rad^2 */
} anchor_imu_in;

/* One GNSS epoch. Missing figures are NaN (h_acc_m, v_acc_m, hdop, pdop, s_acc_mps, vn, ve,
 * vd, speed_mps); lat/lon as u-blox gives them: integer 1e-7 deg plus a fraction of 1e-7 deg
 * (0 for UBX; the rest of an NMEA value), so float32 keeps centimetres. */
typedef struct {
    iotnav_time t;            /* device time, s */
    int32_t valid;            /* 1: a position fix */
    int32_t num_sv;           /* satellites used, -1 unknown */
    int32_t lat_e7, lon_e7;   /* geodetic latitude / longitude, 1e-7 deg */
    IOTNAV_REAL lat_frac_e7, lon_frac_e7; /* remainders, 1e-7 deg */
    IOTNAV_REAL height_m;     /* ellipsoidal height, m (NaN: 2D fix, refused) */
    IOTNAV_REAL h_acc_m, v_acc_m, hdop, pdop;
    IOTNAV_REAL vn, ve, vd;   /* NED velocity, m/s */
    IOTNAV_REAL speed_mps, course_rad; /* ground speed, m/s; course over ground, rad */
    int32_t course_valid;
    IOTNAV_REAL s_acc_mps;    /* speed accuracy, m/s */
} anchor_gnss_in;

/* The output row of an IMU step (AnchorEngine.step's Output, position part). */
typedef struct {
    int32_t has_position;     /* 0 before the first fix */
    int32_t source;           /* ANCHOR_SRC_* */
    IOTNAV_REAL r_n[3];       /* north, east, down in the tangent plane of the first fix, m */
    IOTNAV_REAL v_n[3];       /* NED velocity, m/s */
    IOTNAV_REAL std_north, std_east; /* 1-sigma, m */
    int32_t lat_e7, lon_e7;   /* geodetic position, 1e-7 deg ... */
    IOTNAV_REAL lat_frac_e7, lon_frac_e7; /* ... plus these fractions of 1e-7 deg */
    IOTNAV_REAL height_m;     /* ellipsoidal height, m */
} anchor_output_t;

/* Filter state: fixed size, one per device. */
typedef struct {
    anchor_config cfg;
    IOTNAV_REAL x[ANCHOR_N_STATES];
    IOTNAV_REAL P[ANCHOR_N_STATES * ANCHOR_N_STATES];
    IOTNAV_REAL a_n[3];       /* control input of the latest IMU sample, m/s^2 */
    IOTNAV_REAL sigma_a2;     /* its attitude-induced error variance per axis, m^2/s^4 */
    IOTNAV_REAL g, half_g2;   /* gravity magnitude, m/s^2; g^2 / 2 */
    iotnav_time t_x, t_fix, t_last; /* time of the state, of the last accepted fix, of the last output */
    int32_t has_t_x, initialised, n_fixes, n_rejected;
    /* Tangent plane (iotnav.engines.tangent_plane.TangentPlane): north = n_a + (lat - lat_a) k_n,
     * east = e_a + (lon - lon_a) k_e, down = h0 - h, linearised at the anchor (lat_a, lon_a),
     * first the first fix (n_a = e_a = 0), then a fix farther than ANCHOR_REANCHOR_DISTANCE_M */
    int32_t lat_a_e7, lon_a_e7; /* anchor, 1e-7 deg ... */
    IOTNAV_REAL lat_a_frac_e7, lon_a_frac_e7; /* ... plus these fractions of 1e-7 deg */
    IOTNAV_REAL n_a, e_a;     /* the anchor's north / east, m */
    IOTNAV_REAL h0_m;         /* ellipsoidal height of the origin (the first fix), m */
    IOTNAV_REAL k_n, k_e;     /* metres per 1e-7 deg of latitude / longitude at the anchor */
    IOTNAV_REAL inv_k_n, inv_k_e; /* their reciprocals */
    int32_t n_anchors;        /* linearisations so far (1 after the first fix) */
} anchor_state;

/* Set up `st` for `cfg`; ANCHOR_ERR_UNSUPPORTED for smoothing or a NIS gate. */
int anchor_init(anchor_state *st, const anchor_config *cfg);
/* One IMU sample: predict to its time with the previous control input, then take its own. */
int anchor_step_imu(anchor_state *st, const anchor_imu_in *in);
/* One GNSS epoch: gates, first-fix initialisation, position then velocity update. */
int anchor_step_gnss(anchor_state *st, const anchor_gnss_in *in);
/* The output row for the latest IMU sample. */
void anchor_output(const anchor_state *st, anchor_output_t *out);
/* sizeof of the API structs (0 state, 1 config, 2 IMU input, 3 GNSS input, 4 output). */
int32_t anchor_sizeof(int32_t which);

#endif
