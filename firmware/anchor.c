/* Anchor-node Kalman filter in C99 (see anchor.h and iotnav.engines.anchor). */
#include <math.h>

#include "anchor.h"
#include "iotnav_common.h"

#define N ANCHOR_N_STATES
#ifdef IOTNAV_REAL_DOUBLE
#define FABS fabs
#else
#define FABS fabsf
#endif
#define R IOTNAV_R

#define DEG_E7_TO_RAD (3.14159265358979323846 / 180.0 * 1e-7)
/* iotnav.gnss_accuracy.VDOP_PER_HDOP, and 1 / hypot(1, VDOP_PER_HDOP) */
#define VDOP_PER_HDOP 1.5
#define INV_HYPOT_1_VDOP_PER_HDOP 0.55470019622522912

int anchor_init(anchor_state *st, const anchor_config *cfg)
{
    int i;
    if (cfg->smoothing != 0 || cfg->gate_probability > R(0.0)) {
        return ANCHOR_ERR_UNSUPPORTED;
    }
    st->cfg = *cfg;
    for (i = 0; i < N; ++i) st->x[i] = R(0.0);
    for (i = 0; i < N * N; ++i) st->P[i] = (i % (N + 1) == 0) ? R(1.0) : R(0.0);
    for (i = 0; i < 3; ++i) st->a_n[i] = R(0.0);
    st->sigma_a2 = R(0.0);
    st->g = cfg->gravity_mps2 > R(0.0) ? cfg->gravity_mps2 : R(9.80665);
    st->half_g2 = R(0.5) * st->g * st->g;
    st->t_x.s = st->t_fix.s = st->t_last.s = 0;
    st->t_x.frac = st->t_fix.frac = st->t_last.frac = R(0.0);
    st->has_t_x = st->initialised = st->n_fixes = st->n_rejected = 0;
    st->lat_a_e7 = st->lon_a_e7 = st->n_anchors = 0;
    st->lat_a_frac_e7 = st->lon_a_frac_e7 = st->n_a = st->e_a = R(0.0);
    st->h0_m = st->k_n = st->k_e = st->inv_k_n = st->inv_k_e = R(0.0);
    return ANCHOR_OK;
}

/* anchor_predict_to: x- = F x + B u, P- = sym(F P F^T + Q).
 *
 * F, Q and R are block-diagonal per axis and the initial P is too, so P never couples the
 * axes: its only non-zero entries are each axis' 2 x 2 block [[p_i p_i, p_i v_i], [v_i p_i,
 * v_i v_i]] (the paper writes one axis). The dense Python code adds exact zeros elsewhere;
 * computing only these blocks is the same arithmetic. P keeps the dense row-major layout and
 * is exactly symmetric (every write sets both off-diagonal entries), so symmetrising is exact:
 * sym of [[A, B], [B, D]] is itself.
 *
 * Cost on a microcontroller without an FPU (every float operation a library call): no
 * division or square root per sample, and the East block is the North one. The two are equal
 * by construction: the same initial P (identity, then the first fix's R, the same for north and
 * east), the same Q, the same position R and the same velocity R for both, and a velocity
 * update always measures both (velocity_measurement: 0, 2 or 3 components). So the North block
 * is computed and the East block takes its values: what Python computes twice from the same
 * numbers, the same bits. */
#define PP(i) st->P[(N + 1) * (ANCHOR_POS + (i))]
#define PV(i) st->P[N * (ANCHOR_POS + (i)) + ANCHOR_VEL + (i)]
#define VP(i) st->P[N * (ANCHOR_VEL + (i)) + ANCHOR_POS + (i)]
#define VV(i) st->P[(N + 1) * (ANCHOR_VEL + (i))]

static IOTNAV_REAL time_diff(iotnav_time a, iotnav_time b)
{
    /* iotnav_time_diff without the int -> float conversion and its addition within a second
     * (0 + d is d: the same value) */
    IOTNAV_REAL d = a.frac - b.frac;
    return a.s == b.s ? d : (IOTNAV_REAL)(a.s - b.s) + d;
}

static void predict_to(anchor_state *st, iotnav_time t)
{
    IOTNAV_REAL dt, half_dt, q_a, q3, q2, q1, dtd, bb, a, b, d;
    IOTNAV_REAL *x = st->x;
    int i;
    if (!st->initialised || !st->has_t_x) {
        st->t_x = t;
        st->has_t_x = 1;
        return;
    }
    dt = time_diff(t, st->t_x);
    if (dt <= R(0.0)) return;
    half_dt = R(0.5) * dt;
    q_a = st->cfg.acc_psd_m2_s3;
    if (st->cfg.attitude_in_q != 0) {
        IOTNAV_REAL since = time_diff(st->t_x, st->t_fix);
        IOTNAV_REAL s_f = (since > R(0.0) ? since : R(0.0)) + half_dt;
        q_a += R(3.0) * st->sigma_a2 * s_f;
    }
    /* Q per axis: q_a [[dt^3 / 3, dt^2 / 2], [dt^2 / 2, dt]] */
    q1 = q_a * dt;
    q2 = q1 * half_dt;
    q3 = q2 * (dt * R(2.0 / 3.0));
    for (i = 0; i < 3; ++i) {
        /* p += dt v + dt^2 / 2 u = dt / 2 (v + v'), v' = v + dt u */
        IOTNAV_REAL v = x[ANCHOR_VEL + i], v1 = v + dt * st->a_n[i];
        x[ANCHOR_POS + i] += half_dt * (v + v1);
        x[ANCHOR_VEL + i] = v1;
    }
    /* per block [[A, B], [B, D]] -> [[A + dt (B + B') + q3, B' + q2], [., D + q1]], B' = B + dt D
     * (A + dt (B + B^T) + dt^2 D, B + dt D: F P F^T): North, then Down; East is North */
    for (i = 0; i < 3; i += 2) {
        dtd = dt * VV(i);
        bb = PV(i) + dtd;
        a = PP(i) + dt * (PV(i) + bb) + q3;
        b = bb + q2;
        d = VV(i) + q1;
        PP(i) = a;
        PV(i) = VP(i) = b;
        VV(i) = d;
    }
    PP(1) = PP(0);
    PV(1) = VP(1) = PV(0);
    VV(1) = VV(0);
    st->t_x = t;
}

int anchor_step_imu(anchor_state *st, const anchor_imu_in *in)
{
    const IOTNAV_REAL *C = in->C_nb;
    IOTNAV_REAL f0, f1, f2;
    predict_to(st, in->t); /* with the previous sample's acceleration (mean over [t_k-1, t_k)) */
    f0 = C[0] * in->f_b[0] + C[1] * in->f_b[1] + C[2] * in->f_b[2];
    f1 = C[3] * in->f_b[0] + C[4] * in->f_b[1] + C[5] * in->f_b[2];
    f2 = C[6] * in->f_b[0] + C[7] * in->f_b[1] + C[8] * in->f_b[2];
    st->a_n[0] = f0;
    st->a_n[1] = f1;
    st->a_n[2] = f2 + st->g;
    /* g^2 / 2 tr(P_tilt) + |f_h|^2 tr(P_yaw) */
    st->sigma_a2 = st->half_g2 * in->tilt_p_trace + (f0 * f0 + f1 * f1) * in->yaw_p_trace;
    st->t_last = in->t;
    return ANCHOR_OK;
}

/* iotnav.kalman.update_selected on the decoupled axes (see predict_to): the measurement of state
 * m (0 position, 1 velocity; o the other one) of a 2 x 2 block [[P_mm, P_mo], [P_mo, P_oo]] with
 * variance r and S = P_mm + r > 0. K = P_:m / S (one reciprocal; Python: Cholesky l = sqrt(S),
 * K = (P_:m / l) / l) into k; and the simple form P' = (I - K e_m^T) P written out for the block
 * (1 - K_m = r / S, c = P_mo): P'_mm = r K_m, P'_mo = r K_o, P'_oo = P_oo - K_o c. Python's
 * Joseph form P' = A P A^T + K r K^T (A = I - K e_m^T) is the same matrix for this optimal gain
 * (the float64 build equals it to 1e-9; 3 multiplications instead of 12). */
static void block_update(IOTNAV_REAL *P, int mm, int mo, int oo, IOTNAV_REAL s, IOTNAV_REAL r, IOTNAV_REAL *k)
{
    IOTNAV_REAL inv = R(1.0) / s, c = P[mo];
    IOTNAV_REAL km = P[mm] * inv, ko = c * inv;
    k[0] = km;
    k[1] = ko;
    P[mm] = r * km;
    P[mo] = r * ko;
    P[oo] -= ko * c;
}

/* The measurement z of state m (0 position, 1 velocity) of the first n axes (2: North, East;
 * 3: and Down), variance r_h for North and East and r_d for Down. The innovation covariances are
 * checked before any is applied (state unchanged on error); the East block is the North one
 * (predict_to), with the same r_h; x += K (z - x_m) per axis. */
static int update_axes(anchor_state *st, int m, const IOTNAV_REAL *z, IOTNAV_REAL r_h, IOTNAV_REAL r_d, int n)
{
    IOTNAV_REAL *P = st->P, *x = st->x, k[2], s_n, s_d = R(1.0);
    const int xm = m == 0 ? ANCHOR_POS : ANCHOR_VEL, xo = m == 0 ? ANCHOR_VEL : ANCHOR_POS;
    int i;
    s_n = P[(N + 1) * xm] + r_h;
    if (!(s_n > R(0.0))) return ANCHOR_ERR_NUMERIC;
    if (n == 3) {
        s_d = P[(N + 1) * (xm + 2)] + r_d;
        if (!(s_d > R(0.0))) return ANCHOR_ERR_NUMERIC;
    }
    for (i = 0; i < n; i += 2) {
        int mm = (N + 1) * (xm + i), oo = (N + 1) * (xo + i);
        block_update(P, mm, N * (xm + i) + xo + i, oo, i == 0 ? s_n : s_d, i == 0 ? r_h : r_d, k);
        P[N * (xo + i) + xm + i] = P[N * (xm + i) + xo + i];
        if (i == 0) {
            IOTNAV_REAL y = z[1] - x[xm + 1];
            PP(1) = PP(0);
            PV(1) = VP(1) = PV(0);
            VV(1) = VV(0);
            x[xm + 1] += k[0] * y;
            x[xo + 1] += k[1] * y;
        }
        {
            IOTNAV_REAL y = z[i] - x[xm + i];
            x[xm + i] += k[0] * y;
            x[xo + i] += k[1] * y;
        }
    }
    return ANCHOR_OK;
}

/* gnss_velocity_measurement: number of components (0, 2 or 3) into z, sigma^2 into *r. */
static int velocity_measurement(const anchor_config *cfg, const anchor_gnss_in *in,
                                IOTNAV_REAL *z, IOTNAV_REAL *r)
{
    IOTNAV_REAL sigma = iotnav_positive(in->s_acc_mps) ? in->s_acc_mps : cfg->vel_noise_mps;
    *r = sigma * sigma;
    if (isfinite(in->vn) && isfinite(in->ve)) {
        z[0] = in->vn;
        z[1] = in->ve;
        if (isfinite(in->vd)) {
            z[2] = in->vd;
            return 3;
        }
        return 2;
    }
    if (in->course_valid && isfinite(in->speed_mps) && in->speed_mps >= cfg->min_course_speed_mps) {
        z[0] = in->speed_mps * IOTNAV_COS(in->course_rad);
        z[1] = in->speed_mps * IOTNAV_SIN(in->course_rad);
        return 2;
    }
    return 0;
}

/* TangentPlane._linearise at the fix `in` (height h_a, coordinates n_a, e_a): metres per 1e-7 deg. */
static void linearise(anchor_state *st, const anchor_gnss_in *in, IOTNAV_REAL n_a, IOTNAV_REAL e_a)
{
    iotnav_plane_scales(in->lat_e7, in->lat_frac_e7, in->height_m, &st->k_n, &st->k_e);
    st->lat_a_e7 = in->lat_e7;
    st->lon_a_e7 = in->lon_e7;
    st->lat_a_frac_e7 = in->lat_frac_e7;
    st->lon_a_frac_e7 = in->lon_frac_e7;
    st->n_a = n_a;
    st->e_a = e_a;
    st->inv_k_n = R(1.0) / st->k_n;
    st->inv_k_e = R(1.0) / st->k_e;
    st->n_anchors += 1;
}

int anchor_step_gnss(anchor_state *st, const anchor_gnss_in *in)
{
    const anchor_config *cfg = &st->cfg;
    IOTNAV_REAL z[3], r[3], zv[3], r_vel = R(0.0), dn, de;
    const IOTNAV_REAL d_max = R(ANCHOR_REANCHOR_DISTANCE_M);
    /* inside this square the squared distance is below d_max^2 (0.7^2 * 2 < 1): no products */
    const IOTNAV_REAL d_box = R(0.7 * ANCHOR_REANCHOR_DISTANCE_M);
    int n_vel, i, rc;
    if (!in->valid) return ANCHOR_REJECT_INVALID;
    if (in->num_sv < 0 && !cfg->accept_unknown_num_sv) return ANCHOR_REJECT_NUM_SV_UNKNOWN;
    if (in->num_sv >= 0 && in->num_sv < cfg->min_satellites) return ANCHOR_REJECT_NUM_SV;
    if (!isfinite(in->height_m)) return ANCHOR_ERR_UNSUPPORTED; /* 2D fixes: not implemented */
    if (!st->initialised) {
        /* the NED origin and the first anchor: the first fix */
        st->h0_m = in->height_m;
        linearise(st, in, R(0.0), R(0.0));
        if (cfg->gravity_mps2 <= R(0.0)) {
            st->g = iotnav_normal_gravity(((IOTNAV_REAL)in->lat_e7 + in->lat_frac_e7) * R(IOTNAV_DEG_E7_TO_RAD), in->height_m);
            st->half_g2 = R(0.5) * st->g * st->g;
        }
    }
    dn = ((IOTNAV_REAL)(in->lat_e7 - st->lat_a_e7) + (in->lat_frac_e7 - st->lat_a_frac_e7)) * st->k_n;
    de = ((IOTNAV_REAL)(in->lon_e7 - st->lon_a_e7) + (in->lon_frac_e7 - st->lon_a_frac_e7)) * st->k_e;
    z[0] = st->n_a + dn;
    z[1] = st->e_a + de;
    z[2] = st->h0_m - in->height_m;
    /* TangentPlane.follow: farther than the distance from the anchor, the fix becomes the anchor
     * (its coordinates z unchanged, so the state carries over); squared, no square root */
    if ((FABS(dn) > d_box || FABS(de) > d_box) && dn * dn + de * de > d_max * d_max) linearise(st, in, z[0], z[1]);
    iotnav_position_variances(cfg->uere_m, cfg->default_dop, in->h_acc_m, in->v_acc_m, in->hdop, in->pdop,
                              &r[0], &r[2]);
    r[1] = r[0];
    n_vel = cfg->use_velocity ? velocity_measurement(cfg, in, zv, &r_vel) : 0;
    if (!st->initialised) {
        for (i = 0; i < N * N; ++i) st->P[i] = R(0.0);
        for (i = 0; i < 3; ++i) {
            st->x[ANCHOR_POS + i] = z[i];
            st->x[ANCHOR_VEL + i] = i < n_vel ? zv[i] : R(0.0);
            st->P[(N + 1) * (ANCHOR_POS + i)] = r[i];
            st->P[(N + 1) * (ANCHOR_VEL + i)] = cfg->init_vel_std_mps * cfg->init_vel_std_mps;
        }
        st->initialised = 1;
        st->t_x = in->t;
        st->has_t_x = 1;
        st->t_fix = in->t;
        st->n_fixes += 1;
        return ANCHOR_OK;
    }
    predict_to(st, in->t);
    rc = update_axes(st, 0, z, r[0], r[2], 3);
    if (rc != ANCHOR_OK) return rc;
    st->n_rejected = 0;
    st->t_fix = in->t;
    st->n_fixes += 1;
    if (n_vel > 0) {
        rc = update_axes(st, 1, zv, r_vel, r_vel, n_vel);
        if (rc != ANCHOR_OK) return rc;
    }
    return ANCHOR_OK;
}

void anchor_output(const anchor_state *st, anchor_output_t *out)
{
    int i;
    IOTNAV_REAL dlat, dlon, flat, flon;
    out->has_position = st->initialised;
    for (i = 0; i < 3; ++i) {
        out->r_n[i] = st->x[ANCHOR_POS + i];
        out->v_n[i] = st->x[ANCHOR_VEL + i];
    }
    out->std_north = IOTNAV_SQRT(PP(0));
    out->std_east = out->std_north; /* the East block is the North one (predict_to) */
    if (!st->initialised) {
        out->source = ANCHOR_SRC_NONE;
        out->lat_e7 = out->lon_e7 = 0;
        out->lat_frac_e7 = out->lon_frac_e7 = out->height_m = R(0.0);
        return;
    }
    out->source = time_diff(st->t_last, st->t_fix) <= st->cfg.fix_hold_s ? ANCHOR_SRC_FIX : ANCHOR_SRC_DR;
    dlat = (st->x[ANCHOR_POS] - st->n_a) * st->inv_k_n + st->lat_a_frac_e7;
    dlon = (st->x[ANCHOR_POS + 1] - st->e_a) * st->inv_k_e + st->lon_a_frac_e7;
    flat = IOTNAV_FLOOR(dlat);
    flon = IOTNAV_FLOOR(dlon);
    out->lat_e7 = st->lat_a_e7 + (int32_t)flat;
    out->lon_e7 = st->lon_a_e7 + (int32_t)flon;
    out->lat_frac_e7 = dlat - flat;
    out->lon_frac_e7 = dlon - flon;
    out->height_m = st->h0_m - st->x[ANCHOR_POS + 2];
}

/* sizeof of the API structs (0 state, 1 config, 2 IMU input, 3 GNSS input, 4 output), for
 * bindings that check their layout (iotnav.firmware.host); 0 for another `which`. */
int32_t anchor_sizeof(int32_t which)
{
    switch (which) {
    case 0: return (int32_t)sizeof(anchor_state);
    case 1: return (int32_t)sizeof(anchor_config);
    case 2: return (int32_t)sizeof(anchor_imu_in);
    case 3: return (int32_t)sizeof(anchor_gnss_in);
    case 4: return (int32_t)sizeof(anchor_output_t);
    default: return 0;
    }
}
