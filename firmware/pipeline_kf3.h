/* What the cascade's three-state KFs share (iotnav.techniques.kf3), as static inline functions:
 * the symmetrisation of a 3 x 3 covariance and predict_row3, the propagation of a unit axis
 * (the tilt KF's down axis, the yaw KF's North axis, in the sensor frame b) by the gyro rate.
 * Header only, included by pipeline_tilt.c and pipeline_yaw.c; not part of the API. */
#ifndef IOTNAV_PIPELINE_KF3_H
#define IOTNAV_PIPELINE_KF3_H

#include "iotnav_real.h"

/* P = (P + P^T) / 2, row-major, in place */
static inline void pl_kf3_symmetrise(IOTNAV_REAL *P)
{
    int i, j;
    for (i = 0; i < 3; ++i)
        for (j = i + 1; j < 3; ++j)
            P[3 * i + j] = P[3 * j + i] = IOTNAV_R(0.5) * (P[3 * i + j] + P[3 * j + i]);
}

/* kf3.predict_row3 term by term, to the bit (the tilt KF's float64 build equals Python's
 * exactly): x <- F x, P <- F P F^T + Q with F = I - dt [w x] (w the rate in b, rad/s; dt s) and
 * Q = (dt sigma)^2 (I - x x^T) + q_floor I (sigma: gyro white noise and bias, rad/s), then
 * symmetrised; nothing for dt <= 0. Only F's unit diagonal is not multiplied (1 * p = p exactly:
 * each sum in Python's order, the same values). */
static inline void pl_kf3_predict_row3(IOTNAV_REAL *xs, IOTNAV_REAL *P, IOTNAV_REAL wx, IOTNAV_REAL wy,
                                       IOTNAV_REAL wz, IOTNAV_REAL dt, IOTNAV_REAL sigma, IOTNAV_REAL q_floor)
{
    IOTNAV_REAL f01, f02, f10, f12, f20, f21, x0, x1, x2, xv[3], M[9], Pn[9], q, ds, d;
    int i, j;
    if (dt <= IOTNAV_R(0.0)) return;
    f01 = dt * wz;
    f02 = -dt * wy;
    f10 = -dt * wz;
    f12 = dt * wx;
    f20 = dt * wy;
    f21 = -dt * wx;
    ds = dt * sigma;
    q = ds * ds;
    x0 = xv[0] = xs[0];
    x1 = xv[1] = xs[1];
    x2 = xv[2] = xs[2];
    xs[0] = x0 + f01 * x1 + f02 * x2;
    xs[1] = f10 * x0 + x1 + f12 * x2;
    xs[2] = f20 * x0 + f21 * x1 + x2;
    for (j = 0; j < 3; ++j) { /* M = F P */
        M[j] = P[j] + f01 * P[3 + j] + f02 * P[6 + j];
        M[3 + j] = f10 * P[j] + P[3 + j] + f12 * P[6 + j];
        M[6 + j] = f20 * P[j] + f21 * P[3 + j] + P[6 + j];
    }
    d = q + q_floor;
    for (i = 0; i < 3; ++i) { /* M F^T + Q, Q's terms as Python's: -q x_i x_j (+ q + q_floor) */
        const IOTNAV_REAL m0 = M[3 * i], m1 = M[3 * i + 1], m2 = M[3 * i + 2], nqx = -q * xv[i];
        IOTNAV_REAL q0 = nqx * x0, q1 = nqx * x1, q2 = nqx * x2;
        if (i == 0) q0 += d;
        if (i == 1) q1 += d;
        if (i == 2) q2 += d;
        Pn[3 * i] = (m0 + m1 * f01 + m2 * f02) + q0;
        Pn[3 * i + 1] = (m0 * f10 + m1 + m2 * f12) + q1;
        Pn[3 * i + 2] = (m0 * f20 + m1 * f21 + m2) + q2;
    }
    for (i = 0; i < 9; ++i) P[i] = Pn[i];
    pl_kf3_symmetrise(P);
}

/* kf3.predict_row3 for the yaw KF (its float64 build is checked to 1e-9): x <- F x, P <- F P F^T + Q with F = I - dt [w x] (w the rate in b, rad/s;
 * dt s) and Q = dt^2 var (I - x x^T) + q_floor I (var: the gyro's white-noise plus bias variance,
 * rad^2/s^2: Python's (dt sigma)^2 with sigma = sqrt(var), without the square root); nothing for
 * dt <= 0. F's unit diagonal is not multiplied (each sum in Python's order), and P (symmetric)
 * is computed once per pair (upper triangle, mirrored): Python's symmetrisation of it. */
static inline void pl_kf3_predict_row3_sym(IOTNAV_REAL *xs, IOTNAV_REAL *P, IOTNAV_REAL wx, IOTNAV_REAL wy,
                                               IOTNAV_REAL wz, IOTNAV_REAL dt, IOTNAV_REAL var, IOTNAV_REAL q_floor)
{
    IOTNAV_REAL f01, f02, f10, f12, f20, f21, x0, x1, x2, M[9], q, nq, d;
    int j;
    if (dt <= IOTNAV_R(0.0)) return;
    f01 = dt * wz;
    f02 = -dt * wy;
    f10 = -dt * wz;
    f12 = dt * wx;
    f20 = dt * wy;
    f21 = -dt * wx;
    q = (dt * dt) * var;
    x0 = xs[0];
    x1 = xs[1];
    x2 = xs[2];
    xs[0] = x0 + f01 * x1 + f02 * x2;
    xs[1] = f10 * x0 + x1 + f12 * x2;
    xs[2] = f20 * x0 + f21 * x1 + x2;
    for (j = 0; j < 3; ++j) { /* M = F P */
        M[j] = P[j] + f01 * P[3 + j] + f02 * P[6 + j];
        M[3 + j] = f10 * P[j] + P[3 + j] + f12 * P[6 + j];
        M[6 + j] = f20 * P[j] + f21 * P[3 + j] + P[6 + j];
    }
    nq = -q;
    d = q + q_floor;
    /* P = M F^T + Q, upper triangle */
    P[0] = (M[0] + M[1] * f01 + M[2] * f02) + (nq * x0 * x0 + d);
    P[1] = P[3] = (M[0] * f10 + M[1] + M[2] * f12) + nq * x0 * x1;
    P[2] = P[6] = (M[0] * f20 + M[1] * f21 + M[2]) + nq * x0 * x2;
    P[4] = (M[3] * f10 + M[4] + M[5] * f12) + (nq * x1 * x1 + d);
    P[5] = P[7] = (M[3] * f20 + M[4] * f21 + M[5]) + nq * x1 * x2;
    P[8] = (M[6] * f20 + M[7] * f21 + M[8]) + (nq * x2 * x2 + d);
}

#endif /* IOTNAV_PIPELINE_KF3_H */
