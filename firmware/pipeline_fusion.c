/* Forno pipeline block 6 in C99 (see pipeline_fusion.h and iotnav.techniques.fusion_kf): the
 * 9-state fusion KF of the paper's Table I ([n, m, p] = [9, 5, 3]). */
#include <math.h>

#include "pipeline_fusion.h"

#define R IOTNAV_R
#define N PL_FUSION_N

int pl_fusion_init(pl_fusion_state *st, const pl_fusion_config *cfg, IOTNAV_REAL gate_nis)
{
    int i;
    if (cfg->smoothing) return PL_FUSION_ERR_UNSUPPORTED;
    st->cfg = *cfg;
    for (i = 0; i < N; ++i) st->x[i] = R(0.0);
    for (i = 0; i < N * N; ++i) st->P[i] = (i % (N + 1)) == 0 ? R(1.0) : R(0.0); /* FusionKF: P = I */
    st->initialised = 0;
    st->n_rejected = 0;
    st->gate = cfg->gate_probability > R(0.0) ? gate_nis : R(0.0);
    st->nis = (IOTNAV_REAL)NAN;
    return PL_FUSION_OK;
}

void pl_fusion_initialise(pl_fusion_state *st, const IOTNAV_REAL r_n[3], const IOTNAV_REAL r_var[3],
                          const IOTNAV_REAL *v_n)
{
    int i;
    IOTNAV_REAL vv = st->cfg.init_vel_std_mps * st->cfg.init_vel_std_mps;
    IOTNAV_REAL bb = st->cfg.acc_bias_init_mps2 * st->cfg.acc_bias_init_mps2;
    for (i = 0; i < N * N; ++i) st->P[i] = R(0.0);
    for (i = 0; i < 3; ++i) {
        st->x[i] = r_n[i];
        st->x[3 + i] = v_n != 0 ? v_n[i] : R(0.0);
        st->x[6 + i] = R(0.0);
        st->P[N * i + i] = r_var[i];
        st->P[N * (3 + i) + 3 + i] = vv;
        st->P[N * (6 + i) + 6 + i] = bb;
    }
    st->initialised = 1;
}

/* fusion_predict per 3 x 3 block: x- = F x + B u, P- = F P F^T + Q. With P's blocks
 * [[A, B, D], [B^T, E, G], [D^T, G^T, H]] (p, v, b) and F's ([[I, dt I, -h C], [0, I, -dt C],
 * [0, 0, I]], h = dt^2 / 2), M = F P has the rows p: [A + dt B^T - h C D^T, B + dt E - h C G^T,
 * D + dt G - h C H], v: [., E - dt C G^T, G - dt C H], b: P's own; then P- = M F^T has
 * P-_pp = M_pp + dt M_pv - h M_pb C^T, P-_pv = M_pv - dt M_pb C^T, P-_pb = M_pb,
 * P-_vv = M_vv - dt M_vb C^T, P-_vb = M_vb, P-_bb = H. Only the upper triangle is computed and
 * mirrored (P- is symmetric: Python's sym() of it, each pair once), the identity and zero blocks
 * of F skipped, Q's constant factors (dt^3 / 3, dt^2 / 2) formed once per call. */
void pl_fusion_predict(pl_fusion_state *st, IOTNAV_REAL an0, IOTNAV_REAL an1, IOTNAV_REAL an2,
                       const IOTNAV_REAL C[9], IOTNAV_REAL dt, IOTNAV_REAL qa)
{
    IOTNAV_REAL *s = st->x, *P = st->P;
    IOTNAV_REAL U1[9], U2[9], U3[9], Mpp[9], Mpv[9], Mpb[9], Mvb[9], V1[9];
    IOTNAV_REAL h, cb0, cb1, cb2, q3, q2, q1, qb;
    int i, j;
    if (dt <= R(0.0) || !st->initialised) return; /* as Python: dt <= 0 returns, a NaN dt goes on */
    h = R(0.5) * dt * dt;
    /* C b_a (NED), the bias seen in n */
    cb0 = C[0] * s[6] + C[1] * s[7] + C[2] * s[8];
    cb1 = C[3] * s[6] + C[4] * s[7] + C[5] * s[8];
    cb2 = C[6] * s[6] + C[7] * s[7] + C[8] * s[8];
    s[0] += dt * s[3] - h * cb0 + h * an0;
    s[1] += dt * s[4] - h * cb1 + h * an1;
    s[2] += dt * s[5] - h * cb2 + h * an2;
    s[3] += -dt * cb0 + dt * an0;
    s[4] += -dt * cb1 + dt * an1;
    s[5] += -dt * cb2 + dt * an2;
    /* U1 = C D^T (upper triangle), U2 = C G^T, U3 = C H; (D^T)_kj = P[9 j + 6 + k] */
    for (i = 0; i < 3; ++i) {
        const IOTNAV_REAL c0 = C[3 * i], c1 = C[3 * i + 1], c2 = C[3 * i + 2];
        for (j = 0; j < 3; ++j) {
            if (j >= i) U1[3 * i + j] = c0 * P[N * j + 6] + c1 * P[N * j + 7] + c2 * P[N * j + 8];
            U2[3 * i + j] = c0 * P[N * (3 + j) + 6] + c1 * P[N * (3 + j) + 7] + c2 * P[N * (3 + j) + 8];
            U3[3 * i + j] = c0 * P[54 + 6 + j] + c1 * P[63 + 6 + j] + c2 * P[72 + 6 + j];
        }
    }
    /* M's blocks (M_pp and M_vv: upper triangle) */
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            const int k = 3 * i + j;
            if (j >= i) Mpp[k] = P[N * i + j] + dt * P[N * (3 + i) + j] - h * U1[k];
            Mpv[k] = P[N * i + 3 + j] + dt * P[N * (3 + i) + 3 + j] - h * U2[k];
            Mpb[k] = P[N * i + 6 + j] + dt * P[N * (3 + i) + 6 + j] - h * U3[k];
            Mvb[k] = P[N * (3 + i) + 6 + j] - dt * U3[k];
        }
    /* V1 = M_pb C^T; then P-'s blocks, mirrored */
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            V1[3 * i + j] = Mpb[3 * i] * C[3 * j] + Mpb[3 * i + 1] * C[3 * j + 1] + Mpb[3 * i + 2] * C[3 * j + 2];
    q3 = qa * (dt * dt * dt) * R(1.0 / 3.0);
    q2 = qa * (dt * dt) * R(0.5);
    q1 = qa * dt;
    qb = st->cfg.acc_bias_rw_m2_s5 * dt;
    for (i = 0; i < 3; ++i)
        for (j = i; j < 3; ++j) {
            const int k = 3 * i + j;
            IOTNAV_REAL vv = P[N * (3 + i) + 3 + j] - dt * U2[k]; /* M_vv */
            IOTNAV_REAL pp = Mpp[k] + dt * Mpv[k] - h * V1[k];
            vv -= dt * (Mvb[3 * i] * C[3 * j] + Mvb[3 * i + 1] * C[3 * j + 1] + Mvb[3 * i + 2] * C[3 * j + 2]);
            if (i == j) {
                pp += q3;
                vv += q1;
            }
            P[N * i + j] = P[N * j + i] = pp;
            P[N * (3 + i) + 3 + j] = P[N * (3 + j) + 3 + i] = vv;
        }
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            const int k = 3 * i + j;
            IOTNAV_REAL pv = Mpv[k] - dt * V1[k];
            if (i == j) pv += q2;
            P[N * i + 3 + j] = P[N * (3 + j) + i] = pv;
            P[N * i + 6 + j] = P[N * (6 + j) + i] = Mpb[k];
            P[N * (3 + i) + 6 + j] = P[N * (6 + j) + 3 + i] = Mvb[k];
        }
    for (i = 0; i < 3; ++i) P[10 * (6 + i)] += qb;
}

/* iotnav.kalman.update_selected for the m <= 3 contiguous states i0 .. i0 + m - 1 and a diagonal
 * R (rv): Cholesky of S, K by forward and back substitution, NIS, the gate, then the Joseph form
 * P = A P A^T + K R K^T with A = I - K H written out (H selects states: A P = P - K (rows of P)),
 * symmetrised. Returns PL_FUSION_OK, PL_FUSION_REJECTED or PL_FUSION_ERR_NUMERIC. */
static int update_selected(pl_fusion_state *st, int i0, int m, const IOTNAV_REAL *z, const IOTNAV_REAL *rv,
                           IOTNAV_REAL gate)
{
    IOTNAV_REAL *x = st->x, *P = st->P;
    IOTNAV_REAL y[3], L[9], K[N * 3], w[3], AP[N * N], nis = R(0.0);
    int a, b, c, i, j;
    for (a = 0; a < m; ++a) y[a] = z[a] - x[i0 + a];
    for (a = 0; a < m; ++a)
        for (b = 0; b <= a; ++b) {
            IOTNAV_REAL ra = a == b ? rv[a] : R(0.0);
            IOTNAV_REAL v = R(0.5) * ((P[N * (i0 + a) + i0 + b] + ra) + (P[N * (i0 + b) + i0 + a] + ra));
            for (c = 0; c < b; ++c) v -= L[3 * a + c] * L[3 * b + c];
            if (a == b) {
                if (!(v > R(0.0))) return PL_FUSION_ERR_NUMERIC;
                L[3 * a + a] = IOTNAV_SQRT(v);
            } else {
                L[3 * a + b] = v / L[3 * b + b];
            }
        }
    for (i = 0; i <= N; ++i) {
        for (a = 0; a < m; ++a) { /* forward substitution */
            IOTNAV_REAL v = i == N ? y[a] : P[N * i + i0 + a];
            for (c = 0; c < a; ++c) v -= L[3 * a + c] * w[c];
            w[a] = v / L[3 * a + a];
        }
        if (i == N) break;
        for (a = m - 1; a >= 0; --a) { /* back substitution */
            IOTNAV_REAL v = w[a];
            for (c = a + 1; c < m; ++c) v -= L[3 * c + a] * K[3 * i + c];
            K[3 * i + a] = v / L[3 * a + a];
        }
    }
    for (a = 0; a < m; ++a) nis += w[a] * w[a];
    st->nis = nis;
    if (gate > R(0.0) && nis > gate) return PL_FUSION_REJECTED;
    for (i = 0; i < N; ++i)
        for (a = 0; a < m; ++a) x[i] += K[3 * i + a] * y[a];
    for (i = 0; i < N; ++i)
        for (j = 0; j < N; ++j) {
            IOTNAV_REAL v = P[N * i + j];
            for (a = 0; a < m; ++a) v -= K[3 * i + a] * P[N * (i0 + a) + j];
            AP[N * i + j] = v;
        }
    for (i = 0; i < N; ++i)
        for (j = 0; j <= i; ++j) {
            IOTNAV_REAL u = AP[N * i + j], v = AP[N * j + i], kr = R(0.0);
            for (a = 0; a < m; ++a) {
                u -= AP[N * i + i0 + a] * K[3 * j + a];
                v -= AP[N * j + i0 + a] * K[3 * i + a];
                kr += K[3 * i + a] * rv[a] * K[3 * j + a];
            }
            P[N * i + j] = P[N * j + i] = R(0.5) * ((u + kr) + (v + kr));
        }
    return PL_FUSION_OK;
}

int pl_fusion_update_position(pl_fusion_state *st, const IOTNAV_REAL r_n[3], const IOTNAV_REAL r_var[3],
                              int stale)
{
    int rc, i, j;
    int forced = st->gate > R(0.0) && (st->n_rejected >= st->cfg.max_rejections || stale);
    if (forced) { /* forced re-convergence: forget the old position (P_pos += R + y y^T) */
        IOTNAV_REAL y[3];
        for (i = 0; i < 3; ++i) y[i] = r_n[i] - st->x[i];
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j) st->P[N * i + j] += (i == j ? r_var[i] : R(0.0)) + y[i] * y[j];
    }
    rc = update_selected(st, 0, 3, r_n, r_var, forced ? R(0.0) : st->gate);
    if (rc == PL_FUSION_OK) {
        st->n_rejected = 0;
    } else if (rc == PL_FUSION_REJECTED) {
        st->n_rejected += 1;
    }
    return rc;
}

int pl_fusion_update_velocity(pl_fusion_state *st, IOTNAV_REAL v_n, IOTNAV_REAL v_e, IOTNAV_REAL sigma_mps)
{
    IOTNAV_REAL z[2], rv[2];
    z[0] = v_n;
    z[1] = v_e;
    rv[0] = rv[1] = sigma_mps * sigma_mps;
    return update_selected(st, 3, 2, z, rv, R(0.0));
}

int pl_fusion_update_velocity_ned(pl_fusion_state *st, const IOTNAV_REAL v[3], IOTNAV_REAL sigma_mps)
{
    IOTNAV_REAL rv[3];
    rv[0] = rv[1] = rv[2] = sigma_mps * sigma_mps;
    return update_selected(st, 3, 3, v, rv, R(0.0));
}

/* sizeof(pl_fusion_state), for bindings that check their layout */
int32_t pl_fusion_sizeof(void) { return (int32_t)sizeof(pl_fusion_state); }
