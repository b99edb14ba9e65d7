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

/* kf3.predict_row3 term by term: x <- F x, P <- F P F^T + Q with F = I - dt [w x] (w the rate
 * in b, rad/s; dt s) and Q = (dt sigma)^2 (I - x x^T) + q_floor I (sigma: gyro white noise and
 * bias, rad/s), then symmetrised; nothing for dt <= 0 */
static inline void pl_kf3_predict_row3(IOTNAV_REAL *xs, IOTNAV_REAL *P, IOTNAV_REAL wx, IOTNAV_REAL wy,
                                       IOTNAV_REAL wz, IOTNAV_REAL dt, IOTNAV_REAL sigma, IOTNAV_REAL q_floor)
{
    IOTNAV_REAL F[9], x[3], M[9], q, ds;
    int i, j;
    if (dt <= IOTNAV_R(0.0)) return;
    F[0] = IOTNAV_R(1.0); F[1] = dt * wz;  F[2] = -dt * wy;
    F[3] = -dt * wz; F[4] = IOTNAV_R(1.0); F[5] = dt * wx;
    F[6] = dt * wy;  F[7] = -dt * wx; F[8] = IOTNAV_R(1.0);
    ds = dt * sigma;
    q = ds * ds;
    for (i = 0; i < 3; ++i) x[i] = xs[i];
    for (i = 0; i < 3; ++i) xs[i] = F[3 * i] * x[0] + F[3 * i + 1] * x[1] + F[3 * i + 2] * x[2];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) M[3 * i + j] = F[3 * i] * P[j] + F[3 * i + 1] * P[3 + j] + F[3 * i + 2] * P[6 + j];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            IOTNAV_REAL v = M[3 * i] * F[3 * j] + M[3 * i + 1] * F[3 * j + 1] + M[3 * i + 2] * F[3 * j + 2];
            IOTNAV_REAL qij = -q * x[i] * x[j];
            if (i == j) qij += q + q_floor;
            P[3 * i + j] = v + qij;
        }
    pl_kf3_symmetrise(P);
}

#endif /* IOTNAV_PIPELINE_KF3_H */
