/* Forno pipeline block 2's gyro-bias KF in C99 (see pipeline_gyrobias.h and
 * iotnav.techniques.gyro_bias_kf). */
#include <math.h>

#include "pipeline_gyrobias.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define FABS fabs
#else
#define FABS fabsf
#endif

int pl_gyrobias_init(pl_gyrobias_state *st, const pl_gyrobias_config *cfg, const IOTNAV_REAL *b0)
{
    int i;
    IOTNAV_REAL v = cfg->init_std_rad_s * cfg->init_std_rad_s;
    st->cfg = *cfg;
    for (i = 0; i < 3; ++i) st->x[i] = b0 ? b0[i] : R(0.0);
    for (i = 0; i < 9; ++i) st->P[i] = R(0.0);
    st->P[0] = st->P[4] = st->P[8] = v;
    st->q_b = cfg->bias_rw_rad_s2_rthz * cfg->bias_rw_rad_s2_rthz;
    st->r = cfg->gyro_noise_rad_s * cfg->gyro_noise_rad_s;
    return PL_OK;
}

/* gyro_bias_predict */
void pl_gyrobias_predict(pl_gyrobias_state *st, IOTNAV_REAL dt)
{
    IOTNAV_REAL q;
    if (dt <= R(0.0)) return;
    q = st->q_b * dt;
    st->P[0] += q;
    st->P[4] += q;
    st->P[8] += q;
}

/* gyro_bias_update: kf3.update3 with R = r I and no gate, term by term in Python's order (the
 * zero off-diagonal terms of R dropped: the same values) */
int pl_gyrobias_update(pl_gyrobias_state *st, IOTNAV_REAL gx, IOTNAV_REAL gy, IOTNAV_REAL gz)
{
    const IOTNAV_REAL *P = st->P, r = st->r, lim = st->cfg.max_rate_rad_s;
    IOTNAV_REAL y0, y1, y2, l00, l10, l20, l11, l21, l22, i00, i11, i22, i10, i21, i20;
    IOTNAV_REAL a00, a01, a02, a11, a12, a22, Si[9], k[9], A[9], AP[9], Pn[9];
    int i, j;
    if (!(FABS(gx) <= lim && FABS(gy) <= lim && FABS(gz) <= lim)) return 0;
    if (P[1] == R(0.0) && P[2] == R(0.0) && P[3] == R(0.0) && P[5] == R(0.0) && P[6] == R(0.0) && P[7] == R(0.0)) {
        /* a diagonal P (the cascade's: it starts diagonal and F = I, Q and R are diagonal): the
         * general update below reduces to three scalar ones, its other terms all zero, with the
         * same operations in the same order, so the same values (float64 still bit-equal to
         * Python; only the sign of a zero off-diagonal may differ) at a fraction of the cost */
        const IOTNAV_REAL g[3] = {gx, gy, gz};
        for (i = 0; i < 3; ++i) {
            IOTNAV_REAL p = st->P[4 * i], l = IOTNAV_SQRT(p + r), inv = R(1.0) / l, kk = p * (inv * inv), a;
            st->x[i] = st->x[i] + kk * (g[i] - st->x[i]);
            a = R(1.0) - kk;
            st->P[4 * i] = (a * p) * a + (kk * r) * kk;
        }
        return 1;
    }
    y0 = gx - st->x[0];
    y1 = gy - st->x[1];
    y2 = gz - st->x[2];
    /* S = P + R (symmetrised) = L L^T */
    l00 = IOTNAV_SQRT(P[0] + r);
    l10 = (R(0.5) * (P[3] + P[1])) / l00;
    l20 = (R(0.5) * (P[6] + P[2])) / l00;
    l11 = IOTNAV_SQRT((P[4] + r) - l10 * l10);
    l21 = ((R(0.5) * (P[7] + P[5])) - l20 * l10) / l11;
    l22 = IOTNAV_SQRT((P[8] + r) - l20 * l20 - l21 * l21);
    /* L^-1, S^-1 = L^-T L^-1 */
    i00 = R(1.0) / l00;
    i11 = R(1.0) / l11;
    i22 = R(1.0) / l22;
    i10 = -l10 * i00 * i11;
    i21 = -l21 * i11 * i22;
    i20 = -(l20 * i00 + l21 * i10) * i22;
    a00 = i00 * i00 + i10 * i10 + i20 * i20;
    a01 = i10 * i11 + i20 * i21;
    a02 = i20 * i22;
    a11 = i11 * i11 + i21 * i21;
    a12 = i21 * i22;
    a22 = i22 * i22;
    Si[0] = a00; Si[1] = a01; Si[2] = a02;
    Si[3] = a01; Si[4] = a11; Si[5] = a12;
    Si[6] = a02; Si[7] = a12; Si[8] = a22;
    /* K = P S^-1 */
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            k[3 * i + j] = P[3 * i] * Si[j] + P[3 * i + 1] * Si[3 + j] + P[3 * i + 2] * Si[6 + j];
    for (i = 0; i < 3; ++i) st->x[i] = st->x[i] + k[3 * i] * y0 + k[3 * i + 1] * y1 + k[3 * i + 2] * y2;
    /* Joseph form: P = (I - K) P (I - K)^T + K R K^T, then symmetrised */
    for (i = 0; i < 9; ++i) A[i] = -k[i];
    A[0] = R(1.0) - k[0];
    A[4] = R(1.0) - k[4];
    A[8] = R(1.0) - k[8];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            AP[3 * i + j] = A[3 * i] * P[j] + A[3 * i + 1] * P[3 + j] + A[3 * i + 2] * P[6 + j];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            IOTNAV_REAL v = AP[3 * i] * A[3 * j] + AP[3 * i + 1] * A[3 * j + 1] + AP[3 * i + 2] * A[3 * j + 2];
            v += (k[3 * i] * r) * k[3 * j] + (k[3 * i + 1] * r) * k[3 * j + 1] + (k[3 * i + 2] * r) * k[3 * j + 2];
            Pn[3 * i + j] = v;
        }
    for (i = 0; i < 3; ++i)
        for (j = i + 1; j < 3; ++j) Pn[3 * i + j] = Pn[3 * j + i] = R(0.5) * (Pn[3 * i + j] + Pn[3 * j + i]);
    for (i = 0; i < 9; ++i) st->P[i] = Pn[i];
    return 1;
}

/* sizeof(pl_gyrobias_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_gyrobias_sizeof(void) { return (int32_t)sizeof(pl_gyrobias_state); }
