/* Forno pipeline block 2's cascade in C99 (see pipeline_cascade.h and iotnav.techniques.cascade). */
#include <math.h>

#include "iotnav_common.h"
#include "pipeline_cascade.h"

#ifdef IOTNAV_REAL_DOUBLE
#define ATAN2 atan2
#define HYPOT hypot
#define FABS fabs
#else
#define ATAN2 atan2f
#define HYPOT hypotf
#define FABS fabsf
#endif

int pl_cascade_init(pl_cascade_state *st, const pl_gyrobias_config *bias, const pl_tilt_config *tilt,
                    const pl_yaw_config *yaw, IOTNAV_REAL gate_nis)
{
    int i, rc;
    for (i = 0; i < 9; ++i) st->C[i] = IOTNAV_R(0.0);
    st->C[0] = st->C[4] = st->C[8] = IOTNAV_R(1.0);
    st->omega[0] = st->omega[1] = st->omega[2] = IOTNAV_R(0.0);
    if ((rc = pl_gyrobias_init(&st->bias, bias, 0)) != PL_OK) return rc;
    if ((rc = pl_tilt_init(&st->tilt, tilt, 0)) != PL_OK) return rc;
    return pl_yaw_init(&st->yaw, yaw, gate_nis);
}

/* cascade_step */
void pl_cascade_step(pl_cascade_state *st, IOTNAV_REAL ax, IOTNAV_REAL ay, IOTNAV_REAL az, IOTNAV_REAL gx,
                     IOTNAV_REAL gy, IOTNAV_REAL gz, IOTNAV_REAL dt, int is_static, IOTNAV_REAL g,
                     IOTNAV_REAL a_veh)
{
    IOTNAV_REAL wx, wy, wz, bias_var;
    pl_gyrobias_predict(&st->bias, dt);
    if (is_static) (void)pl_gyrobias_update(&st->bias, gx, gy, gz);
    wx = gx - st->bias.x[0];
    wy = gy - st->bias.x[1];
    wz = gz - st->bias.x[2];
    st->omega[0] = wx;
    st->omega[1] = wy;
    st->omega[2] = wz;
    bias_var = (st->bias.P[0] + st->bias.P[4] + st->bias.P[8]) * IOTNAV_R(1.0 / 3.0);
    pl_tilt_predict(&st->tilt, wx, wy, wz, dt, bias_var);
    (void)pl_tilt_update(&st->tilt, ax, ay, az, g, a_veh);
    pl_yaw_predict(&st->yaw, wx, wy, wz, dt, bias_var);
    pl_dcm_rows(st->yaw.x, st->tilt.x, st->C);
    st->yaw.x[0] = st->C[0];
    st->yaw.x[1] = st->C[1];
    st->yaw.x[2] = st->C[2];
}

int pl_cascade_aid_heading(pl_cascade_state *st, IOTNAV_REAL psi_b, IOTNAV_REAL sigma)
{
    int ok = pl_yaw_update_heading(&st->yaw, psi_b, st->tilt.x, sigma);
    pl_dcm_rows(st->yaw.x, st->tilt.x, st->C);
    return ok;
}

int pl_cascade_aid_mag(pl_cascade_state *st, IOTNAV_REAL mx, IOTNAV_REAL my, IOTNAV_REAL mz)
{
    int ok = pl_yaw_update_mag(&st->yaw, mx, my, mz, st->tilt.x);
    pl_dcm_rows(st->yaw.x, st->tilt.x, st->C);
    return ok;
}

void pl_cascade_rotate_heading(pl_cascade_state *st, IOTNAV_REAL delta_rad)
{
    const IOTNAV_REAL *P = st->yaw.P;
    if (!st->yaw.initialised) return;
    pl_yaw_reset_heading(&st->yaw, ATAN2(st->C[3], st->C[0]) + delta_rad, st->tilt.x,
                         IOTNAV_SQRT(P[0] + P[4] + P[8]));
    pl_dcm_rows(st->yaw.x, st->tilt.x, st->C);
}

/* front_end_step */
int pl_front_end_step(pl_cascade_state *st, pl_static_state *det, iotnav_time t, IOTNAV_REAL ax, IOTNAV_REAL ay,
                      IOTNAV_REAL az, IOTNAV_REAL gx, IOTNAV_REAL gy, IOTNAV_REAL gz, IOTNAV_REAL dt, int is_static,
                      IOTNAV_REAL g, IOTNAV_REAL a_long, IOTNAV_REAL v_gnss, iotnav_time t_speed, IOTNAV_REAL v_dr,
                      IOTNAV_REAL *y_n)
{
    const IOTNAV_REAL *C = st->C;
    IOTNAV_REAL r_prev = C[6] * st->omega[0] + C[7] * st->omega[1] + C[8] * st->omega[2], a_veh;
    if (iotnav_time_diff(t, t_speed) <= IOTNAV_R(2.5))
        a_veh = HYPOT(a_long, v_gnss * r_prev);
    else if (isfinite(v_dr))
        a_veh = FABS(v_dr * r_prev);
    else
        a_veh = IOTNAV_R(0.0);
    pl_cascade_step(st, ax, ay, az, gx, gy, gz, dt, is_static, g, a_veh);
    y_n[0] = C[0] * ax + C[1] * ay + C[2] * az;
    y_n[1] = C[3] * ax + C[4] * ay + C[5] * az;
    y_n[2] = C[6] * ax + C[7] * ay + C[8] * az;
    return pl_static_step(det, t, y_n[0], y_n[1], v_dr);
}

/* sizeof(pl_cascade_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_cascade_sizeof(void) { return (int32_t)sizeof(pl_cascade_state); }
