/* Forno pipeline block 2's yaw KF in C99 (see pipeline_yaw.h and iotnav.techniques.yaw_kf). */
#include <math.h>

#include "pipeline_yaw.h"
#include "pipeline_kf3.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define FABS fabs
#define ASIN asin
#define ATAN2 atan2
#else
#define FABS fabsf
#define ASIN asinf
#define ATAN2 atan2f
#endif

int pl_yaw_init(pl_yaw_state *st, const pl_yaw_config *cfg, IOTNAV_REAL gate_nis)
{
    int i;
    st->cfg = *cfg;
    st->x[0] = R(1.0);
    st->x[1] = st->x[2] = R(0.0);
    for (i = 0; i < 9; ++i) st->P[i] = R(0.0);
    st->P[0] = st->P[4] = st->P[8] = R(1.0);
    st->initialised = 0;
    st->nis = (IOTNAV_REAL)NAN;
    st->gated = cfg->gate_probability > R(0.0);
    st->gate = st->gated ? gate_nis : (IOTNAV_REAL)INFINITY;
    st->gyro_var = cfg->gyro_noise_rad_s * cfg->gyro_noise_rad_s;
    st->mag_var = cfg->mag_noise * cfg->mag_noise;
    st->cos_decl = IOTNAV_COS(cfg->declination_rad);
    st->sin_decl = IOTNAV_SIN(cfg->declination_rad);
    if (st->gated && !(gate_nis > R(0.0))) return PL_ERR_UNSUPPORTED;
    return PL_OK;
}

/* yaw_predict: kf3.predict_row3 (no renormalisation) */
void pl_yaw_predict(pl_yaw_state *st, IOTNAV_REAL wx, IOTNAV_REAL wy, IOTNAV_REAL wz, IOTNAV_REAL dt,
                    IOTNAV_REAL bias_var)
{
    pl_kf3_predict_row3_sym(st->x, st->P, wx, wy, wz, dt, st->gyro_var + bias_var, st->cfg.q_floor);
}

/* kf3.update3 (H = I, full R, NIS gate) term by term; returns 1 when accepted (x, P updated) */
static int update3(IOTNAV_REAL *xs, IOTNAV_REAL *Ps, IOTNAV_REAL z0, IOTNAV_REAL z1, IOTNAV_REAL z2,
                   const IOTNAV_REAL *Rm, IOTNAV_REAL gate, IOTNAV_REAL *nis)
{
    const IOTNAV_REAL *P = Ps;
    IOTNAV_REAL y0 = z0 - xs[0], y1 = z1 - xs[1], y2 = z2 - xs[2];
    IOTNAV_REAL l00, l10, l20, l11, l21, l22, u0, u1, u2, i00, i11, i22, i10, i21, i20;
    IOTNAV_REAL Si[9], k[9], A[9], AP[9], KR[9], Pn[9];
    int i, j;
    l00 = IOTNAV_SQRT(P[0] + Rm[0]);
    l10 = (R(0.5) * ((P[3] + Rm[3]) + (P[1] + Rm[1]))) / l00;
    l20 = (R(0.5) * ((P[6] + Rm[6]) + (P[2] + Rm[2]))) / l00;
    l11 = IOTNAV_SQRT((P[4] + Rm[4]) - l10 * l10);
    l21 = ((R(0.5) * ((P[7] + Rm[7]) + (P[5] + Rm[5]))) - l20 * l10) / l11;
    l22 = IOTNAV_SQRT((P[8] + Rm[8]) - l20 * l20 - l21 * l21);
    u0 = y0 / l00;
    u1 = (y1 - l10 * u0) / l11;
    u2 = (y2 - l20 * u0 - l21 * u1) / l22;
    *nis = u0 * u0 + u1 * u1 + u2 * u2;
    if (*nis > gate) return 0;
    i00 = R(1.0) / l00;
    i11 = R(1.0) / l11;
    i22 = R(1.0) / l22;
    i10 = -l10 * i00 * i11;
    i21 = -l21 * i11 * i22;
    i20 = -(l20 * i00 + l21 * i10) * i22;
    Si[0] = i00 * i00 + i10 * i10 + i20 * i20;
    Si[1] = Si[3] = i10 * i11 + i20 * i21;
    Si[2] = Si[6] = i20 * i22;
    Si[4] = i11 * i11 + i21 * i21;
    Si[5] = Si[7] = i21 * i22;
    Si[8] = i22 * i22;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            k[3 * i + j] = P[3 * i] * Si[j] + P[3 * i + 1] * Si[3 + j] + P[3 * i + 2] * Si[6 + j];
    for (i = 0; i < 3; ++i) xs[i] = xs[i] + k[3 * i] * y0 + k[3 * i + 1] * y1 + k[3 * i + 2] * y2;
    for (i = 0; i < 9; ++i) A[i] = -k[i];
    A[0] = R(1.0) - k[0];
    A[4] = R(1.0) - k[4];
    A[8] = R(1.0) - k[8];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            AP[3 * i + j] = A[3 * i] * P[j] + A[3 * i + 1] * P[3 + j] + A[3 * i + 2] * P[6 + j];
            KR[3 * i + j] = k[3 * i] * Rm[j] + k[3 * i + 1] * Rm[3 + j] + k[3 * i + 2] * Rm[6 + j];
        }
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            IOTNAV_REAL v = AP[3 * i] * A[3 * j] + AP[3 * i + 1] * A[3 * j + 1] + AP[3 * i + 2] * A[3 * j + 2];
            v += KR[3 * i] * k[3 * j] + KR[3 * i + 1] * k[3 * j + 1] + KR[3 * i + 2] * k[3 * j + 2];
            Pn[3 * i + j] = v;
        }
    pl_kf3_symmetrise(Pn);
    for (i = 0; i < 9; ++i) Ps[i] = Pn[i];
    return 1;
}

/* dcm_rows_into */
void pl_dcm_rows(const IOTNAV_REAL *x1, const IOTNAV_REAL *x3, IOTNAV_REAL *C)
{
    IOTNAV_REAL i3 = R(1.0) / IOTNAV_SQRT(x3[0] * x3[0] + x3[1] * x3[1] + x3[2] * x3[2]);
    IOTNAV_REAL d0 = x3[0] * i3, d1 = x3[1] * i3, d2 = x3[2] * i3;
    IOTNAV_REAL p = x1[0] * d0 + x1[1] * d1 + x1[2] * d2;
    IOTNAV_REAL n0 = x1[0] - p * d0, n1 = x1[1] - p * d1, n2 = x1[2] - p * d2;
    IOTNAV_REAL nn = IOTNAV_SQRT(n0 * n0 + n1 * n1 + n2 * n2);
    if (nn < R(1e-9)) { /* degenerate: any horizontal direction */
        if (FABS(d1) < R(0.9)) {
            n0 = -d2;
            n1 = R(0.0);
            n2 = d0;
        } else {
            n0 = R(0.0);
            n1 = d2;
            n2 = -d1;
        }
        nn = IOTNAV_SQRT(n0 * n0 + n1 * n1 + n2 * n2);
    }
    nn = R(1.0) / nn;
    n0 = n0 * nn;
    n1 = n1 * nn;
    n2 = n2 * nn;
    C[0] = n0;
    C[1] = n1;
    C[2] = n2;
    C[3] = d1 * n2 - d2 * n1;
    C[4] = d2 * n0 - d0 * n2;
    C[5] = d0 * n1 - d1 * n0;
    C[6] = d0;
    C[7] = d1;
    C[8] = d2;
}

static void constrain(pl_yaw_state *st, const IOTNAV_REAL *x3)
{
    IOTNAV_REAL C[9];
    pl_dcm_rows(st->x, x3, C);
    st->x[0] = C[0];
    st->x[1] = C[1];
    st->x[2] = C[2];
}

/* YawKF._heading_meas: z = north_row(roll, pitch, psi_b), R = s^2 J J^T + (0.02 s)^2 I */
static void heading_meas(IOTNAV_REAL psi_b, const IOTNAV_REAL *x3, IOTNAV_REAL sigma, IOTNAV_REAL *z,
                         IOTNAV_REAL *Rm)
{
    IOTNAV_REAL m = -x3[0], pitch, roll, sr, cr, sp, cp, sy, cy, J[3], s2, f, f2;
    int i, j;
    if (m < R(-1.0)) m = R(-1.0); /* np.clip */
    if (m > R(1.0)) m = R(1.0);
    pitch = ASIN(m);
    roll = ATAN2(x3[1], x3[2]);
    sr = IOTNAV_SIN(roll);
    cr = IOTNAV_COS(roll);
    sp = IOTNAV_SIN(pitch);
    cp = IOTNAV_COS(pitch);
    sy = IOTNAV_SIN(psi_b);
    cy = IOTNAV_COS(psi_b);
    z[0] = cp * cy;
    z[1] = sr * sp * cy - cr * sy;
    z[2] = cr * sp * cy + sr * sy;
    J[0] = -cp * sy;
    J[1] = -sr * sp * sy - cr * cy;
    J[2] = -cr * sp * sy + sr * cy;
    s2 = sigma * sigma;
    f = R(0.02) * sigma;
    f2 = f * f;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) Rm[3 * i + j] = s2 * (J[i] * J[j]) + (i == j ? f2 : R(0.0));
}

void pl_yaw_reset_heading(pl_yaw_state *st, IOTNAV_REAL psi_b, const IOTNAV_REAL *x3, IOTNAV_REAL sigma)
{
    if (isnan(sigma)) sigma = st->cfg.course_noise_rad;
    heading_meas(psi_b, x3, sigma, st->x, st->P);
    st->initialised = 1;
}

int pl_yaw_update_heading(pl_yaw_state *st, IOTNAV_REAL psi_b, const IOTNAV_REAL *x3, IOTNAV_REAL sigma)
{
    IOTNAV_REAL z[3], Rm[9];
    int ok;
    if (isnan(sigma)) sigma = st->cfg.course_noise_rad;
    if (!st->initialised) {
        pl_yaw_reset_heading(st, psi_b, x3, sigma);
        return 1;
    }
    heading_meas(psi_b, x3, sigma, z, Rm);
    ok = update3(st->x, st->P, z[0], z[1], z[2], Rm, st->gate, &st->nis);
    if (ok) constrain(st, x3);
    return ok;
}

int pl_yaw_update_mag(pl_yaw_state *st, IOTNAV_REAL mx, IOTNAV_REAL my, IOTNAV_REAL mz, const IOTNAV_REAL *x3)
{
    IOTNAV_REAL d = mx * x3[0] + my * x3[1] + mz * x3[2], h0, h1, h2, nm, u0, u1, u2, z[3], Rm[9];
    int i;
    h0 = mx - d * x3[0];
    h1 = my - d * x3[1];
    h2 = mz - d * x3[2];
    nm = IOTNAV_SQRT(h0 * h0 + h1 * h1 + h2 * h2);
    if (nm <= R(0.0) || !isfinite(nm)) return 0;
    u0 = h0 / nm;
    u1 = h1 / nm;
    u2 = h2 / nm;
    z[0] = st->cos_decl * u0 - st->sin_decl * (x3[1] * u2 - x3[2] * u1);
    z[1] = st->cos_decl * u1 - st->sin_decl * (x3[2] * u0 - x3[0] * u2);
    z[2] = st->cos_decl * u2 - st->sin_decl * (x3[0] * u1 - x3[1] * u0);
    if (!st->initialised) {
        for (i = 0; i < 9; ++i) st->P[i] = R(0.0);
        st->P[0] = st->P[4] = st->P[8] = st->mag_var;
        st->x[0] = z[0];
        st->x[1] = z[1];
        st->x[2] = z[2];
        st->initialised = 1;
        return 1;
    }
    for (i = 0; i < 9; ++i) Rm[i] = R(0.0);
    Rm[0] = Rm[4] = Rm[8] = st->mag_var;
    update3(st->x, st->P, z[0], z[1], z[2], Rm, (IOTNAV_REAL)INFINITY, &st->nis);
    constrain(st, x3);
    return 1;
}

/* sizeof(pl_yaw_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_yaw_sizeof(void) { return (int32_t)sizeof(pl_yaw_state); }
