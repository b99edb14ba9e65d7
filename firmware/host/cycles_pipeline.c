/* Cost driver (not part of the library) for the Forno pipeline's blocks 3 and 4, block 1 and
 * block 2's gyro-bias KF: 130 s of a tracker standing still with vibration (100 Hz IMU,
 * horizontal specific force and gyroscope from a fixed pseudo-random sequence) and 1 Hz GNSS
 * (speed, position, PDOP), blocks wired as the pipeline wires them (block 1 without a stored
 * position: its settling gate runs until the first fix; the bias KF predicted every sample,
 * updated while static; the tilt KF predicted and updated every sample; the yaw KF predicted
 * every sample and aided by a heading at every GNSS epoch, as by the course; C_nb built from the
 * tilt and yaw rows and the yaw state set to its first row, as pl_cascade_step does). Built for the ATmega128 (avr-gcc, simavr; Timer1 at the CPU clock counts the
 * cycles of each call), for the Cortex-M boards QEMU emulates (arm-none-eabi-gcc with
 * arm/startup.c, arm/semihost.c, arm/mps2.ld; SysTick ticks under -icount, see arm/measure.h)
 * and for the host (gcc; the reference final state). Prints "key decimal" lines as
 * host/cycles.c does; benchmarks/bench_firmware.py reads them. */
#include <math.h>

#include "../pipeline_gyrobias.h"
#include "../pipeline_lastpos.h"
#include "../pipeline_lowpass3.h"
#include "../pipeline_static.h"
#include "../pipeline_tilt.h"
#include "../pipeline_yaw.h"

#include "measure.h"

static uint32_t lcg = 12345u;
static IOTNAV_REAL noise(void) { return lcg_noise(&lcg); }
/* blocks 1 and 2 have their own sequence: blocks 3 and 4 see the inputs they saw before */
static uint32_t lcg2 = 54321u;
static IOTNAV_REAL noise2(void) { return lcg_noise(&lcg2); }

int main(void)
{
    static const pl_static_config sc = PL_STATIC_CONFIG_DEFAULTS;
    static const pl_lowpass3_config lc = PL_LOWPASS3_CONFIG_DEFAULTS;
    pl_static_state det;
    static pl_lowpass3_state lp; /* 620 B: off the stack */
    static const pl_lastpos_config bc = PL_LASTPOS_CONFIG_DEFAULTS;
    static const pl_gyrobias_config gc = PL_GYROBIAS_CONFIG_DEFAULTS;
    static pl_lastpos_state boot; /* 844 B: off the stack */
    pl_gyrobias_state bias;
    static const pl_tilt_config tc = PL_TILT_CONFIG_DEFAULTS;
    pl_tilt_state tilt;
    static const pl_yaw_config yc = PL_YAW_CONFIG_DEFAULTS;
    pl_yaw_state yaw;
    uint32_t tp_sum = 0, tu_sum = 0, tu_max = 0, yp_sum = 0, yu_sum = 0, yu_max = 0, dcm_sum = 0;
    IOTNAV_REAL C[9];
    int32_t n_tilt = 0, n_yaw = 0;
    uint32_t c0, step_sum = 0, step_max = 0, speed_sum = 0, push_sum = 0, push_max = 0;
    uint32_t fix_sum = 0, fix_max = 0, pred_sum = 0, upd_sum = 0, upd_max = 0;
    int32_t k, n_push = 0, n_changed = 0, n_static = 0, was = 0, n_ok = 0, n_due = 0, n_upd = 0;
    setup();
    pl_static_init(&det, &sc);
    pl_lowpass3_init(&lp, &lc);
    pl_lastpos_init(&boot, &bc, 0, IOTNAV_R(0.0), IOTNAV_R(0.0));
    pl_gyrobias_init(&bias, &gc, 0);
    pl_tilt_init(&tilt, &tc, 0);
    pl_yaw_init(&yaw, &yc, PL_YAW_GATE_NIS);
    for (k = 0; k < 13000; ++k) {
        iotnav_time t;
        int32_t now;
        t.s = k / 100;
        t.frac = IOTNAV_R(0.01) * (IOTNAV_REAL)(k % 100);
        if (k % 100 == 0) {
            IOTNAV_REAL r[3];
            r[0] = IOTNAV_R(1234.5) + IOTNAV_R(2.0) * noise();
            r[1] = IOTNAV_R(-321.0) + IOTNAV_R(2.0) * noise();
            r[2] = IOTNAV_R(-3.0) + IOTNAV_R(4.0) * noise();
            c0 = cycles();
            pl_static_update_speed(&det, t, IOTNAV_R(0.1) + IOTNAV_R(0.1) * noise());
            speed_sum += ELAPSED(c0);
            {
                /* block 1: a PDOP converging from 6 to 2 over the first 40 s, then noisy */
                IOTNAV_REAL pdop = (k < 4000 ? IOTNAV_R(6.0) - IOTNAV_R(0.001) * (IOTNAV_REAL)k : IOTNAV_R(2.0)) +
                                   IOTNAV_R(0.05) * noise2();
                IOTNAV_REAL lat = IOTNAV_R(45.0) + IOTNAV_R(1e-6) * noise2(), lon = IOTNAV_R(7.6) + IOTNAV_R(1e-6) * noise2();
                IOTNAV_REAL d;
                c0 = cycles();
                if (pl_lastpos_check_fix(&boot, 1, lat, lon, pdop, 9, t) == PL_FIX_OK) {
                    ++n_ok;
                    if (!boot.first_fix_seen) pl_lastpos_first_fix(&boot, lat, lon, &d);
                    n_due += pl_lastpos_due(&boot, t);
                }
                c0 = ELAPSED(c0);
                fix_sum += c0;
                fix_max = c0 > fix_max ? c0 : fix_max;
            }
            if (was) {
                int changed;
                c0 = cycles();
                changed = pl_lowpass3_push(&lp, r);
                c0 = ELAPSED(c0);
                push_sum += c0;
                push_max = c0 > push_max ? c0 : push_max;
                ++n_push;
                n_changed += changed;
            }
        }
        c0 = cycles();
        now = pl_static_step(&det, t, IOTNAV_R(0.04) * noise(), IOTNAV_R(0.04) * noise(), (IOTNAV_REAL)NAN);
        c0 = ELAPSED(c0);
        step_sum += c0;
        step_max = c0 > step_max ? c0 : step_max;
        if (now != was) pl_lowpass3_reset(&lp);
        was = now;
        n_static += now;
        {
            IOTNAV_REAL gx = IOTNAV_R(0.004) + IOTNAV_R(0.01) * noise2(), gy = IOTNAV_R(-0.002) + IOTNAV_R(0.01) * noise2(),
                        gz = IOTNAV_R(0.001) + IOTNAV_R(0.01) * noise2();
            c0 = cycles();
            pl_gyrobias_predict(&bias, IOTNAV_R(0.01));
            pred_sum += ELAPSED(c0);
            if (now) {
                c0 = cycles();
                n_upd += pl_gyrobias_update(&bias, gx, gy, gz);
                c0 = ELAPSED(c0);
                upd_sum += c0;
                upd_max = c0 > upd_max ? c0 : upd_max;
            }
            {
                /* the tilt KF: the corrected rate, the bias variance, gravity tilted 0.1 rad with noise */
                IOTNAV_REAL bv = (bias.P[0] + bias.P[4] + bias.P[8]) / IOTNAV_R(3.0);
                IOTNAV_REAL fx = IOTNAV_R(0.98) + IOTNAV_R(0.05) * noise2(), fy = IOTNAV_R(0.05) * noise2(),
                            fz = IOTNAV_R(-9.757) + IOTNAV_R(0.05) * noise2();
                c0 = cycles();
                pl_tilt_predict(&tilt, gx - bias.x[0], gy - bias.x[1], gz - bias.x[2], IOTNAV_R(0.01), bv);
                tp_sum += ELAPSED(c0);
                c0 = cycles();
                n_tilt += pl_tilt_update(&tilt, fx, fy, fz, IOTNAV_R(9.80665), IOTNAV_R(0.0));
                c0 = ELAPSED(c0);
                tu_sum += c0;
                tu_max = c0 > tu_max ? c0 : tu_max;
                /* the yaw KF: predicted with the same rate, aided once a second by a heading
                 * near 0.3 rad (the first one initialises) at the tilt estimate */
                c0 = cycles();
                pl_yaw_predict(&yaw, gx - bias.x[0], gy - bias.x[1], gz - bias.x[2], IOTNAV_R(0.01), bv);
                yp_sum += ELAPSED(c0);
                /* the cascade's C_nb and the yaw state set to its first row (pl_cascade_step) */
                c0 = cycles();
                pl_dcm_rows(yaw.x, tilt.x, C);
                dcm_sum += ELAPSED(c0);
                yaw.x[0] = C[0];
                yaw.x[1] = C[1];
                yaw.x[2] = C[2];
                if (k % 100 == 50) {
                    IOTNAV_REAL psi = IOTNAV_R(0.3) + IOTNAV_R(0.05) * noise2();
                    c0 = cycles();
                    n_yaw += pl_yaw_update_heading(&yaw, psi, tilt.x, (IOTNAV_REAL)NAN);
                    c0 = ELAPSED(c0);
                    if (k > 50) { /* the first is the reset */
                        yu_sum += c0;
                        yu_max = c0 > yu_max ? c0 : yu_max;
                    }
                }
            }
        }
    }
    put_u32("step_mean", step_sum / 13000u);
    put_u32("step_max", step_max);
    put_u32("speed_mean", speed_sum / 130u);
    put_u32("push_mean", push_sum / (uint32_t)(n_push > 0 ? n_push : 1));
    put_u32("push_max", push_max);
    put_u32("n_push", (uint32_t)n_push);
    put_u32("n_changed", (uint32_t)n_changed);
    put_u32("n_static", (uint32_t)n_static);
    put_u32("level", (uint32_t)pl_lowpass3_level(&lp));
    put_real("acc_h", det.acc_h);
    put_real("out0", lp.out[0]);
    put_real("out1", lp.out[1]);
    put_real("out2", lp.out[2]);
    put_u32("fix_mean", fix_sum / 130u);
    put_u32("fix_max", fix_max);
    put_u32("n_ok", (uint32_t)n_ok);
    put_u32("n_due", (uint32_t)n_due);
    put_u32("bias_predict_mean", pred_sum / 13000u);
    put_u32("bias_update_mean", upd_sum / (uint32_t)(n_upd > 0 ? n_upd : 1));
    put_u32("bias_update_max", upd_max);
    put_u32("n_bias_updates", (uint32_t)n_upd);
    put_real("bias0", bias.x[0]);
    put_real("bias_p00", bias.P[0]);
    put_u32("tilt_predict_mean", tp_sum / 13000u);
    put_u32("tilt_update_mean", tu_sum / 13000u);
    put_u32("tilt_update_max", tu_max);
    put_u32("n_tilt_updates", (uint32_t)n_tilt);
    put_real("tilt0", tilt.x[0]);
    put_real("tilt_p01", tilt.P[1]);
    put_u32("yaw_predict_mean", yp_sum / 13000u);
    put_u32("yaw_update_mean", yu_sum / 129u);
    put_u32("yaw_update_max", yu_max);
    put_u32("dcm_mean", dcm_sum / 13000u);
    put_real("c5", C[5]);
    put_u32("n_yaw_updates", (uint32_t)n_yaw);
    put_real("yaw0", yaw.x[0]);
    put_real("yaw_p01", yaw.P[1]);
    put_u32("sizeof_static", (uint32_t)sizeof(pl_static_state));
    put_u32("sizeof_lowpass3", (uint32_t)sizeof(pl_lowpass3_state));
    put_u32("sizeof_lastpos", (uint32_t)sizeof(pl_lastpos_state));
    put_u32("sizeof_gyrobias", (uint32_t)sizeof(pl_gyrobias_state));
    put_u32("sizeof_tilt", (uint32_t)sizeof(pl_tilt_state));
    put_u32("sizeof_yaw", (uint32_t)sizeof(pl_yaw_state));
    finish();
    return 0;
}
