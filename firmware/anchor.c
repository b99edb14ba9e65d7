/* Anchor-node Kalman filter in C99 (see anchor.h and iotnav.engines.anchor). */
#include <math.h>

#include "anchor.h"

#define N ANCHOR_N_STATES
#define R IOTNAV_R

/* WGS84 (iotnav.geo): semi-major axis, first eccentricity squared as TangentPlane uses it. */
#define WGS84_A 6378137.0
#define WGS84_E2_TP 6.69437999014e-3
/* Somigliana normal gravity (iotnav.geo.normal_gravity). */
#define G_E 9.7803253359
#define G_K 0.00193185265241
#define G_E2 0.00669437999013
#define G_F (1.0 / 298.257223563)
#define G_GM 3.986004418e14
#define G_OMEGA 7.292115e-5
#define DEG_E7_TO_RAD (3.14159265358979323846 / 180.0 * 1e-7)
/* iotnav.gnss_accuracy.VDOP_PER_HDOP */
#define VDOP_PER_HDOP 1.5

static IOTNAV_REAL time_diff(iotnav_time a, iotnav_time b)
{
    return (IOTNAV_REAL)(a.s - b.s) + (a.frac - b.frac);
}

static int positive(IOTNAV_REAL v) { return isfinite(v) && v > R(0.0); }

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
    st->t_x.s = st->t_fix.s = st->t_last.s = 0;
    st->t_x.frac = st->t_fix.frac = st->t_last.frac = R(0.0);
    st->has_t_x = st->initialised = st->n_fixes = st->n_rejected = 0;
    st->lat0_e7 = st->lon0_e7 = 0;
    st->lat0_frac_e7 = st->lon0_frac_e7 = st->h0_m = st->k_n = st->k_e = R(0.0);
    return ANCHOR_OK;
}

/* anchor_predict_to: x- = F x + B u, P- = sym(F P F^T + Q) per 3 x 3 block. */
static void predict_to(anchor_state *st, iotnav_time t)
{
    IOTNAV_REAL dt, q_a, h, q3, q2, q1;
    int i, j;
    if (!st->initialised || !st->has_t_x) {
        st->t_x = t;
        st->has_t_x = 1;
        return;
    }
    dt = time_diff(t, st->t_x);
    if (dt <= R(0.0)) return;
    q_a = st->cfg.acc_psd_m2_s3;
    if (st->cfg.attitude_in_q != 0) {
        IOTNAV_REAL since = time_diff(st->t_x, st->t_fix);
        IOTNAV_REAL s_f = (since > R(0.0) ? since : R(0.0)) + R(0.5) * dt;
        q_a += R(3.0) * st->sigma_a2 * s_f;
    }
    h = R(0.5) * dt * dt;
    for (i = 0; i < 3; ++i) {
        IOTNAV_REAL u = st->a_n[i];
        st->x[i] += dt * st->x[3 + i] + h * u;
        st->x[3 + i] += dt * u;
    }
    q3 = q_a * dt * dt * dt / R(3.0);
    q2 = q_a * dt * dt / R(2.0);
    q1 = q_a * dt;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            IOTNAV_REAL a = st->P[N * i + j];
            IOTNAV_REAL b = st->P[N * i + 3 + j];
            IOTNAV_REAL bt = st->P[N * (3 + i) + j];
            IOTNAV_REAL d = st->P[N * (3 + i) + 3 + j];
            st->P[N * i + j] = a + dt * (b + bt) + dt * dt * d;
            st->P[N * i + 3 + j] = b + dt * d;
            st->P[N * (3 + i) + j] = bt + dt * d;
        }
        st->P[(N + 1) * i] += q3;
        st->P[N * i + 3 + i] += q2;
        st->P[N * (3 + i) + i] += q2;
        st->P[(N + 1) * (3 + i)] += q1;
    }
    for (i = 0; i < N; ++i) {
        for (j = i + 1; j < N; ++j) {
            IOTNAV_REAL v = R(0.5) * (st->P[N * i + j] + st->P[N * j + i]);
            st->P[N * i + j] = v;
            st->P[N * j + i] = v;
        }
    }
    st->t_x = t;
}

int anchor_step_imu(anchor_state *st, const anchor_imu_in *in)
{
    const IOTNAV_REAL *C = in->C_nb;
    IOTNAV_REAL f0, f1, f2, g = st->g;
    predict_to(st, in->t); /* with the previous sample's acceleration (mean over [t_k-1, t_k)) */
    f0 = C[0] * in->f_b[0] + C[1] * in->f_b[1] + C[2] * in->f_b[2];
    f1 = C[3] * in->f_b[0] + C[4] * in->f_b[1] + C[5] * in->f_b[2];
    f2 = C[6] * in->f_b[0] + C[7] * in->f_b[1] + C[8] * in->f_b[2];
    st->a_n[0] = f0;
    st->a_n[1] = f1;
    st->a_n[2] = f2 + g;
    st->sigma_a2 = g * g * R(0.5) * in->tilt_p_trace + (f0 * f0 + f1 * f1) * in->yaw_p_trace;
    st->t_last = in->t;
    return ANCHOR_OK;
}

/* iotnav.kalman.update_selected: Cholesky of S, K = P H^T S^-1, Joseph form, symmetrised P.
 * H has one unit row per measured state idx[a]; R diagonal r[a] (m <= 3). */
static int update_selected(anchor_state *st, const int *idx, const IOTNAV_REAL *z,
                           const IOTNAV_REAL *r, int m)
{
    IOTNAV_REAL y[3], L[3][3], K[N][3], w[3], A[N][N], AP[N][N];
    int i, j, a, b, c;
    for (a = 0; a < m; ++a) y[a] = z[a] - st->x[idx[a]];
    for (a = 0; a < m; ++a) {
        for (b = 0; b <= a; ++b) {
            IOTNAV_REAL s = R(0.5) * ((st->P[N * idx[a] + idx[b]] + (a == b ? r[a] : R(0.0))) +
                                      (st->P[N * idx[b] + idx[a]] + (a == b ? r[a] : R(0.0))));
            for (c = 0; c < b; ++c) s -= L[a][c] * L[b][c];
            if (a == b) {
                if (!(s > R(0.0))) return ANCHOR_ERR_NUMERIC;
                L[a][a] = IOTNAV_SQRT(s);
            } else {
                L[a][b] = s / L[b][b];
            }
        }
    }
    for (i = 0; i <= N; ++i) {
        for (a = 0; a < m; ++a) { /* forward substitution */
            IOTNAV_REAL v = i == N ? y[a] : st->P[N * i + idx[a]];
            for (c = 0; c < a; ++c) v -= L[a][c] * w[c];
            w[a] = v / L[a][a];
        }
        if (i == N) break;
        for (a = m - 1; a >= 0; --a) { /* back substitution */
            IOTNAV_REAL v = w[a];
            for (c = a + 1; c < m; ++c) v -= L[c][a] * K[i][c];
            K[i][a] = v / L[a][a];
        }
    }
    for (i = 0; i < N; ++i)
        for (a = 0; a < m; ++a) st->x[i] += K[i][a] * y[a];
    for (i = 0; i < N; ++i)
        for (j = 0; j < N; ++j) A[i][j] = i == j ? R(1.0) : R(0.0);
    for (i = 0; i < N; ++i)
        for (a = 0; a < m; ++a) A[i][idx[a]] -= K[i][a];
    for (i = 0; i < N; ++i)
        for (j = 0; j < N; ++j) {
            IOTNAV_REAL v = R(0.0);
            for (c = 0; c < N; ++c) v += A[i][c] * st->P[N * c + j];
            AP[i][j] = v;
        }
    /* Pn = AP A^T + K R K^T, stored in A's place row by row is unsafe: use P's place, symmetrise */
    for (i = 0; i < N; ++i)
        for (j = 0; j < N; ++j) {
            IOTNAV_REAL v = R(0.0), kr = R(0.0);
            for (c = 0; c < N; ++c) v += AP[i][c] * A[j][c];
            for (a = 0; a < m; ++a) kr += K[i][a] * r[a] * K[j][a];
            st->P[N * i + j] = v + kr;
        }
    for (i = 0; i < N; ++i)
        for (j = i + 1; j < N; ++j) {
            IOTNAV_REAL v = R(0.5) * (st->P[N * i + j] + st->P[N * j + i]);
            st->P[N * i + j] = v;
            st->P[N * j + i] = v;
        }
    return ANCHOR_OK;
}

static IOTNAV_REAL normal_gravity(IOTNAV_REAL lat_rad, IOTNAV_REAL h)
{
    IOTNAV_REAL s = IOTNAV_SIN(lat_rad), s2 = s * s;
    IOTNAV_REAL g0 = R(G_E) * (R(1.0) + R(G_K) * s2) / IOTNAV_SQRT(R(1.0) - R(G_E2) * s2);
    IOTNAV_REAL mm = R(G_OMEGA * G_OMEGA * WGS84_A * WGS84_A * (WGS84_A * (1.0 - G_F)) / G_GM);
    return g0 * (R(1.0) - R(2.0 / WGS84_A) * (R(1.0 + G_F) + mm - R(2.0 * G_F) * s2) * h +
                 R(3.0 / (WGS84_A * WGS84_A)) * h * h);
}

/* iotnav.gnss_accuracy.position_sigmas: north/east sigma (each) and down sigma, m. */
static void position_sigmas(const anchor_config *cfg, const anchor_gnss_in *in, IOTNAV_REAL *ne,
                            IOTNAV_REAL *d)
{
    int has_hdop = positive(in->hdop), has_pdop = positive(in->pdop);
    IOTNAV_REAL h_dop, v_dop, h2d, v;
    if (has_hdop) {
        h_dop = in->hdop;
    } else if (has_pdop) {
        h_dop = in->pdop / IOTNAV_SQRT(R(1.0 + VDOP_PER_HDOP * VDOP_PER_HDOP));
    } else {
        h_dop = cfg->default_dop;
    }
    if (has_hdop && has_pdop && in->pdop > in->hdop) {
        v_dop = IOTNAV_SQRT(in->pdop * in->pdop - in->hdop * in->hdop);
    } else {
        v_dop = R(VDOP_PER_HDOP) * h_dop;
    }
    if (positive(in->h_acc_m)) {
        h2d = in->h_acc_m;
        v = R(VDOP_PER_HDOP) * in->h_acc_m;
    } else {
        h2d = cfg->uere_m * h_dop;
        v = cfg->uere_m * v_dop;
    }
    if (positive(in->v_acc_m)) v = in->v_acc_m;
    *ne = h2d / IOTNAV_SQRT(R(2.0));
    *d = v;
}

/* gnss_velocity_measurement: number of components (0, 2 or 3) into z, sigma^2 into *r. */
static int velocity_measurement(const anchor_config *cfg, const anchor_gnss_in *in,
                                IOTNAV_REAL *z, IOTNAV_REAL *r)
{
    IOTNAV_REAL sigma = positive(in->s_acc_mps) ? in->s_acc_mps : cfg->vel_noise_mps;
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

int anchor_step_gnss(anchor_state *st, const anchor_gnss_in *in)
{
    const anchor_config *cfg = &st->cfg;
    static const int pos_idx[3] = {ANCHOR_POS, ANCHOR_POS + 1, ANCHOR_POS + 2};
    static const int vel_idx[3] = {ANCHOR_VEL, ANCHOR_VEL + 1, ANCHOR_VEL + 2};
    IOTNAV_REAL z[3], r[3], zv[3], rv[3], sig_ne, sig_d, r_vel = R(0.0);
    int n_vel, i, rc;
    if (!in->valid) return ANCHOR_REJECT_INVALID;
    if (in->num_sv < 0 && !cfg->accept_unknown_num_sv) return ANCHOR_REJECT_NUM_SV_UNKNOWN;
    if (in->num_sv >= 0 && in->num_sv < cfg->min_satellites) return ANCHOR_REJECT_NUM_SV;
    if (!isfinite(in->height_m)) return ANCHOR_ERR_UNSUPPORTED; /* 2D fixes: not implemented */
    if (!st->initialised) {
        /* TangentPlane at the first fix; metres per 1e-7 deg */
        IOTNAV_REAL lat0 = ((IOTNAV_REAL)in->lat_e7 + in->lat_frac_e7) * R(DEG_E7_TO_RAD);
        IOTNAV_REAL s = IOTNAV_SIN(lat0), w = IOTNAV_SQRT(R(1.0) - R(WGS84_E2_TP) * s * s);
        st->lat0_e7 = in->lat_e7;
        st->lon0_e7 = in->lon_e7;
        st->lat0_frac_e7 = in->lat_frac_e7;
        st->lon0_frac_e7 = in->lon_frac_e7;
        st->h0_m = in->height_m;
        st->k_n = R(DEG_E7_TO_RAD) * (R(WGS84_A * (1.0 - WGS84_E2_TP)) / (w * w * w) + st->h0_m);
        st->k_e = R(DEG_E7_TO_RAD) * (R(WGS84_A) / w + st->h0_m) * IOTNAV_COS(lat0);
        if (cfg->gravity_mps2 <= R(0.0)) st->g = normal_gravity(lat0, in->height_m);
    }
    z[0] = ((IOTNAV_REAL)(in->lat_e7 - st->lat0_e7) + (in->lat_frac_e7 - st->lat0_frac_e7)) * st->k_n;
    z[1] = ((IOTNAV_REAL)(in->lon_e7 - st->lon0_e7) + (in->lon_frac_e7 - st->lon0_frac_e7)) * st->k_e;
    z[2] = st->h0_m - in->height_m;
    position_sigmas(cfg, in, &sig_ne, &sig_d);
    r[0] = r[1] = sig_ne * sig_ne;
    r[2] = sig_d * sig_d;
    n_vel = cfg->use_velocity ? velocity_measurement(cfg, in, zv, &r_vel) : 0;
    for (i = 0; i < 3; ++i) rv[i] = r_vel;
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
    rc = update_selected(st, pos_idx, z, r, 3);
    if (rc != ANCHOR_OK) return rc;
    st->n_rejected = 0;
    st->t_fix = in->t;
    st->n_fixes += 1;
    if (n_vel > 0) {
        rc = update_selected(st, vel_idx, zv, rv, n_vel);
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
    out->std_north = IOTNAV_SQRT(st->P[(N + 1) * ANCHOR_POS]);
    out->std_east = IOTNAV_SQRT(st->P[(N + 1) * (ANCHOR_POS + 1)]);
    if (!st->initialised) {
        out->source = ANCHOR_SRC_NONE;
        out->lat_e7 = out->lon_e7 = 0;
        out->lat_frac_e7 = out->lon_frac_e7 = out->height_m = R(0.0);
        return;
    }
    out->source = time_diff(st->t_last, st->t_fix) <= st->cfg.fix_hold_s ? ANCHOR_SRC_FIX : ANCHOR_SRC_DR;
    dlat = st->x[ANCHOR_POS] / st->k_n + st->lat0_frac_e7;
    dlon = st->x[ANCHOR_POS + 1] / st->k_e + st->lon0_frac_e7;
    flat = IOTNAV_FLOOR(dlat);
    flon = IOTNAV_FLOOR(dlon);
    out->lat_e7 = st->lat0_e7 + (int32_t)flat;
    out->lon_e7 = st->lon0_e7 + (int32_t)flon;
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
