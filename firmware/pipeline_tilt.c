/* Forno pipeline block 2's tilt KF in C99 (see pipeline_tilt.h and iotnav.techniques.tilt_kf). */
#include <math.h>

#include "pipeline_tilt.h"
#include "pipeline_kf3.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define FABS fabs
#else
#define FABS fabsf
#endif

int pl_tilt_init(pl_tilt_state *st, const pl_tilt_config *cfg, const IOTNAV_REAL *x0)
{
    int i;
    IOTNAV_REAL v = cfg->init_std * cfg->init_std;
    st->cfg = *cfg;
    if (x0) {
        IOTNAV_REAL n = IOTNAV_SQRT(x0[0] * x0[0] + x0[1] * x0[1] + x0[2] * x0[2]);
        for (i = 0; i < 3; ++i) st->x[i] = x0[i] / n;
    } else {
        st->x[0] = st->x[1] = R(0.0);
        st->x[2] = R(1.0);
    }
    for (i = 0; i < 9; ++i) st->P[i] = R(0.0);
    st->P[0] = st->P[4] = st->P[8] = v;
    st->initialised = x0 != 0;
    st->nis = (IOTNAV_REAL)NAN;
    st->gyro_var = cfg->gyro_noise_rad_s * cfg->gyro_noise_rad_s;
    st->acc_var = cfg->acc_noise_mps2 * cfg->acc_noise_mps2;
    return PL_OK;
}

static void renormalise(IOTNAV_REAL *x)
{
    IOTNAV_REAL n = IOTNAV_SQRT(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    x[0] /= n;
    x[1] /= n;
    x[2] /= n;
}

/* tilt_predict: kf3.predict_row3 term by term, then the renormalisation */
void pl_tilt_predict(pl_tilt_state *st, IOTNAV_REAL wx, IOTNAV_REAL wy, IOTNAV_REAL wz, IOTNAV_REAL dt,
                     IOTNAV_REAL bias_var)
{
    if (dt <= R(0.0)) return;
    pl_kf3_predict_row3(st->x, st->P, wx, wy, wz, dt, IOTNAV_SQRT(st->gyro_var + bias_var), st->cfg.q_floor);
    renormalise(st->x);
}

/* kf3.update3 with R = r I and no gate (its zero off-diagonal terms of R dropped: the same
 * values); returns the NIS */
static IOTNAV_REAL update3_diag(IOTNAV_REAL *xs, IOTNAV_REAL *Ps, IOTNAV_REAL z0, IOTNAV_REAL z1, IOTNAV_REAL z2,
                                IOTNAV_REAL r)
{
    const IOTNAV_REAL *P = Ps;
    IOTNAV_REAL y0 = z0 - xs[0], y1 = z1 - xs[1], y2 = z2 - xs[2];
    IOTNAV_REAL l00, l10, l20, l11, l21, l22, u0, u1, u2, i00, i11, i22, i10, i21, i20;
    IOTNAV_REAL Si[9], k[9], kr[9], A[9], AP[9], Pn[9];
    int i, j;
    l00 = IOTNAV_SQRT(P[0] + r);
    /* S's symmetrised off-diagonal terms 0.5 (P_ij + P_ji) are P_ij: this block keeps P
     * symmetric to the bit (predict and update symmetrise it), and 0.5 (p + p) = p exactly */
    l10 = P[1] / l00;
    l20 = P[2] / l00;
    l11 = IOTNAV_SQRT((P[4] + r) - l10 * l10);
    l21 = (P[5] - l20 * l10) / l11;
    l22 = IOTNAV_SQRT((P[8] + r) - l20 * l20 - l21 * l21);
    u0 = y0 / l00;
    u1 = (y1 - l10 * u0) / l11;
    u2 = (y2 - l20 * u0 - l21 * u1) / l22;
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
        for (j = 0; j < 3; ++j)
            AP[3 * i + j] = A[3 * i] * P[j] + A[3 * i + 1] * P[3 + j] + A[3 * i + 2] * P[6 + j];
    for (i = 0; i < 9; ++i) kr[i] = k[i] * r; /* K R's terms, each formed once */
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            IOTNAV_REAL v = AP[3 * i] * A[3 * j] + AP[3 * i + 1] * A[3 * j + 1] + AP[3 * i + 2] * A[3 * j + 2];
            v += kr[3 * i] * k[3 * j] + kr[3 * i + 1] * k[3 * j + 1] + kr[3 * i + 2] * k[3 * j + 2];
            Pn[3 * i + j] = v;
        }
    pl_kf3_symmetrise(Pn);
    for (i = 0; i < 9; ++i) Ps[i] = Pn[i];
    return u0 * u0 + u1 * u1 + u2 * u2;
}

/* tilt_update */
int pl_tilt_update(pl_tilt_state *st, IOTNAV_REAL fx, IOTNAV_REAL fy, IOTNAV_REAL fz, IOTNAV_REAL g,
                   IOTNAV_REAL a_veh)
{
    const pl_tilt_config *c = &st->cfg;
    IOTNAV_REAL norm = IOTNAV_SQRT(fx * fx + fy * fy + fz * fz), z0, z1, z2, e0, e1, e2, extra, r;
    if (norm <= R(0.0) || !isfinite(norm)) return 0;
    z0 = -fx / norm;
    z1 = -fy / norm;
    z2 = -fz / norm;
    if (!st->initialised) {
        st->x[0] = z0;
        st->x[1] = z1;
        st->x[2] = z2;
        st->initialised = 1;
        return 1;
    }
    if (FABS(norm - g) > c->reject_mps2) return 0;
    e0 = fx + g * st->x[0];
    e1 = fy + g * st->x[1];
    e2 = fz + g * st->x[2];
    extra = a_veh - c->gnss_acc_deadband_mps2;
    if (R(0.0) > extra) extra = R(0.0); /* Python's max(extra, 0.0) (a NaN stays NaN) */
    r = (st->acc_var + c->ext_acc_gain * (e0 * e0 + e1 * e1 + e2 * e2) + c->gnss_acc_gain * (extra * extra)) / (g * g);
    st->nis = update3_diag(st->x, st->P, z0, z1, z2, r);
    renormalise(st->x);
    return 1;
}

/* sizeof(pl_tilt_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_tilt_sizeof(void) { return (int32_t)sizeof(pl_tilt_state); }
