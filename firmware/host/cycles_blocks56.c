/* Cost driver (not part of the library) for the Forno pipeline's blocks 5 (mount aligner,
 * pipeline_mount.c) and 6 (9-state fusion KF, pipeline_fusion.c): 40 s of a car with the sensor
 * mounted 0.5 rad off the vehicle's forward axis, level: 5 s at rest, 5 s accelerating at
 * 1.5 m/s^2, then a speed oscillating 7.5 +- 2.5 m/s while turning at up to 0.12 rad/s; 100 Hz
 * IMU (sensor-frame specific force and yaw rate from the kinematics with noise from a fixed
 * pseudo-random sequence), 4 Hz GNSS (NED position, NED velocity, speed, course). Blocks wired as
 * the pipeline wires them: every IMU sample to pl_mount_add_imu_body and pl_fusion_predict
 * (u = C_nb f_b + g_n, C_nb the true attitude), every GNSS epoch to pl_mount_add_gnss (static
 * below 0.5 m/s, as block 3 would) then pl_fusion_update_position and
 * pl_fusion_update_velocity_ned; block 5 with the pipeline's configuration
 * (iotnav.engines.config.PIPELINE_MOUNT_NAV, set below field by field), block 6 with
 * FusionConfig's defaults and the position gate PL_FUSION_GATE_NIS (the chi-square quantile,
 * passed by the caller: iotnav.kalman.gate_threshold(3, gate_probability)).
 *
 * COST_BLOCK5 / COST_BLOCK6 (default 1) drop a block (the ATmega128's 4 KB of RAM). Built for the
 * ATmega128 (simavr, Timer1 cycles), the Cortex-M boards QEMU emulates (SysTick under -icount)
 * and the host (gcc: the reference final state), as host/cycles_pipeline.c; prints "key decimal"
 * lines (float32 bits for reals) that iotnav.firmware.targets compares and
 * benchmarks/bench_firmware_blocks56.py reports. */
#include <math.h>

#ifndef COST_BLOCK5
#define COST_BLOCK5 1
#endif
#ifndef COST_BLOCK6
#define COST_BLOCK6 1
#endif
#ifndef PL_FUSION_GATE_NIS
#error "PL_FUSION_GATE_NIS (chi-square quantile, 3 dof) must be defined"
#endif

#include "../pipeline_fusion.h"
#include "../pipeline_mount.h"

#include "measure.h"

#define N_IMU 4000
#define IMU_PER_GNSS 25
#define DT IOTNAV_R(0.01)
#define G IOTNAV_R(9.80665)

static uint32_t lcg = 24680u;
static IOTNAV_REAL noise(void) { return lcg_noise(&lcg); }


#if COST_BLOCK5
static pl_mount_state mount; /* 3.4 KB in float32: off the stack */
#endif
#if COST_BLOCK6
static pl_fusion_state fus;
#endif

int main(void)
{
    cost_tally t_imu = {0, 0, 0}, t_gnss = {0, 0, 0}, t_buf = {0, 0, 0};
    cost_tally t_pred = {0, 0, 0}, t_pos = {0, 0, 0}, t_vel = {0, 0, 0};
    uint32_t c0;
    int32_t k;
    (void)t_imu, (void)t_gnss, (void)t_buf, (void)t_pred, (void)t_pos, (void)t_vel;
    IOTNAV_REAL v = IOTNAV_R(0.0), psi = IOTNAV_R(0.2), rN = IOTNAV_R(0.0), rE = IOTNAV_R(0.0);
    IOTNAV_REAL cpsi, spsi;
    const IOTNAV_REAL cmu = IOTNAV_R(0.8775825618903728), smu = IOTNAV_R(0.479425538604203); /* 0.5 rad */
#if COST_BLOCK5
    pl_mount_config mc = PL_MOUNT_CONFIG_DEFAULTS;
    pl_mount_event ev;
    int32_t n_eval = 0, n_acc = 0, n_app = 0, n_prov = 0, n_set = 0, n_out = 0, n_dem = 0;
    IOTNAV_REAL last_cand = IOTNAV_R(0.0), last_std = IOTNAV_R(0.0), last_coh = IOTNAV_R(0.0);
#endif
#if COST_BLOCK6
    const pl_fusion_config fc = PL_FUSION_CONFIG_DEFAULTS;
    int32_t n_pos_ok = 0, n_pos_rej = 0, n_vel_ok = 0;
#endif
#ifdef __AVR__
    paint_stack();
#endif
    setup();
    cpsi = IOTNAV_R(0.9800665778412416); /* cos, sin of the initial heading 0.2 rad */
    spsi = IOTNAV_R(0.19866933079506122);
#if COST_BLOCK5
    /* iotnav.engines.config.PIPELINE_MOUNT_NAV */
    mc.smooth_epochs = 3;
    mc.min_speed_mps = IOTNAV_R(1.0);
    mc.require_course = 0;
    mc.max_std_rad = IOTNAV_R(0.017453292519943295);
    mc.forget_ref_s = IOTNAV_R(8.0);
    mc.weighted_variance = 1;
    mc.gate_sigma = IOTNAV_R(3.0);
    mc.auto_demean = 1;
    mc.settle_s = IOTNAV_R(60.0);
    mc.provisional_sigmas = IOTNAV_R(3.0);
    if (pl_mount_init(&mount, &mc) != PL_MOUNT_OK) put_u32("error_mount_init", 1u);
#endif
#if COST_BLOCK6
    pl_fusion_init(&fus, &fc, IOTNAV_R(PL_FUSION_GATE_NIS));
#endif
    for (k = 0; k <= N_IMU; ++k) {
        IOTNAV_REAL t = DT * (IOTNAV_REAL)k, ax, ay, r, dpsi, nrm;
        /* the vehicle's longitudinal acceleration and yaw rate */
        if (t < IOTNAV_R(5.0)) {
            ax = IOTNAV_R(0.0);
            r = IOTNAV_R(0.0);
        } else if (t < IOTNAV_R(10.0)) {
            ax = IOTNAV_R(1.5);
            r = IOTNAV_R(0.0);
        } else {
            IOTNAV_REAL ph = t - IOTNAV_R(10.0);
            ax = IOTNAV_R(1.25) * cosf(IOTNAV_R(0.5) * ph);
            r = IOTNAV_R(0.12) * sinf(IOTNAV_R(0.3) * ph);
        }
        ay = v * r;
        if (k % IMU_PER_GNSS == 0) {
            iotnav_time tg;
            IOTNAV_REAL pos[3], var[3], vel[3], spd, crs;
            tg.s = k / 100;
            tg.frac = IOTNAV_R(0.01) * (IOTNAV_REAL)(k % 100);
            pos[0] = rN + IOTNAV_R(0.5) * noise();
            pos[1] = rE + IOTNAV_R(0.5) * noise();
            pos[2] = IOTNAV_R(-2.0) + IOTNAV_R(0.8) * noise();
            var[0] = var[1] = IOTNAV_R(3.6) * IOTNAV_R(3.6); /* (uere 3 m * HDOP 1.2)^2 */
            var[2] = IOTNAV_R(6.0) * IOTNAV_R(6.0);
            vel[0] = v * cpsi + IOTNAV_R(0.05) * noise();
            vel[1] = v * spsi + IOTNAV_R(0.05) * noise();
            vel[2] = IOTNAV_R(0.05) * noise();
            spd = v + IOTNAV_R(0.05) * noise(); /* drawn with either block: the same inputs */
            crs = atan2f(spsi, cpsi) + IOTNAV_R(0.01) * noise();
            for (c0 = 0; c0 < 3; ++c0) {
                pos[c0] = settle(pos[c0]);
                vel[c0] = settle(vel[c0]);
            }
            spd = settle(spd);
            crs = settle(crs);
            (void)tg;
            (void)pos;
            (void)vel;
            (void)spd;
            (void)crs;
            (void)var;
#if COST_BLOCK5
            {
                int got;
                c0 = cycles();
                got = pl_mount_add_gnss(&mount, tg, spd, crs, v > IOTNAV_R(0.5), v < IOTNAV_R(0.5), &ev);
                c0 = ELAPSED(c0);
                count(&t_gnss, c0);
                if (got) {
                    count(&t_buf, c0);
                    ++n_eval;
                    n_acc += ev.accepted;
                    n_app += ev.applied;
                    n_prov += ev.provisional;
                    n_set += ev.settled;
                    n_out += ev.buffer_outlier;
                    n_dem += ev.demeaned;
                    last_cand = ev.candidate_rad;
                    last_std = ev.std_rad;
                    last_coh = ev.coherence;
                }
            }
#endif
#if COST_BLOCK6
            if (k == 0) {
                pl_fusion_initialise(&fus, pos, var, 0);
            } else {
                int rc;
                c0 = cycles();
                rc = pl_fusion_update_position(&fus, pos, var, 0);
                count(&t_pos, ELAPSED(c0));
                n_pos_ok += rc == PL_FUSION_OK;
                n_pos_rej += rc == PL_FUSION_REJECTED;
                c0 = cycles();
                n_vel_ok += pl_fusion_update_velocity_ned(&fus, vel, fc.speed_noise_mps) == PL_FUSION_OK;
                count(&t_vel, ELAPSED(c0));
            }
#endif
        }
        if (k == N_IMU) break;
        {
            /* sensor-frame specific force: f_b = Rz(mu)^T [ax, ay, -g] plus noise; C_nb = Rz(psi + mu) */
            IOTNAV_REAL fx = cmu * ax + smu * ay + IOTNAV_R(0.02) * noise();
            IOTNAV_REAL fy = -smu * ax + cmu * ay + IOTNAV_R(0.02) * noise();
            IOTNAV_REAL fz = -G + IOTNAV_R(0.02) * noise();
            IOTNAV_REAL rb = r + IOTNAV_R(0.002) * noise();
            fx = settle(fx);
            fy = settle(fy);
            fz = settle(fz);
            rb = settle(rb);
            (void)rb;
#if COST_BLOCK5
            c0 = cycles();
            pl_mount_add_imu_body(&mount, fx, fy, fz, rb);
            count(&t_imu, ELAPSED(c0));
#endif
#if COST_BLOCK6
            {
                IOTNAV_REAL C[9];
                IOTNAV_REAL ch = settle(cpsi * cmu - spsi * smu), sh = settle(spsi * cmu + cpsi * smu);
                IOTNAV_REAL u0 = settle(ch * fx - sh * fy), u1 = settle(sh * fx + ch * fy), u2 = settle(fz + G);
                C[0] = ch;
                C[1] = -sh;
                C[2] = IOTNAV_R(0.0);
                C[3] = sh;
                C[4] = ch;
                C[5] = IOTNAV_R(0.0);
                C[6] = IOTNAV_R(0.0);
                C[7] = IOTNAV_R(0.0);
                C[8] = IOTNAV_R(1.0);
                c0 = cycles();
                pl_fusion_predict(&fus, u0, u1, u2, C, DT,
                                  fc.acc_psd_m2_s3);
                count(&t_pred, ELAPSED(c0));
            }
#endif
        }
        /* integrate the kinematics (heading by a renormalised rotation: no libm in the loop) */
        rN += DT * v * cpsi;
        rE += DT * v * spsi;
        v += DT * ax;
        dpsi = DT * r;
        psi += dpsi;
        {
            IOTNAV_REAL c2 = cpsi - dpsi * spsi, s2 = spsi + dpsi * cpsi;
            nrm = sqrtf(c2 * c2 + s2 * s2);
            cpsi = c2 / nrm;
            spsi = s2 / nrm;
        }
    }
#if COST_BLOCK5
    put_mean_max("mount_imu_mean", "mount_imu_max", &t_imu);
    put_mean_max("mount_gnss_mean", "mount_gnss_max", &t_gnss);
    put_mean_max("mount_buffer_mean", "mount_buffer_max", &t_buf);
    put_u32("n_gnss", t_gnss.n);
    put_u32("n_eval", (uint32_t)n_eval);
    put_u32("n_accepted", (uint32_t)n_acc);
    put_u32("n_applied", (uint32_t)n_app);
    put_u32("n_provisional", (uint32_t)n_prov);
    put_u32("n_settled", (uint32_t)n_set);
    put_u32("n_outlier", (uint32_t)n_out);
    put_u32("n_demeaned", (uint32_t)n_dem);
    put_u32("known", (uint32_t)mount.known);
    put_u32("have_ref", (uint32_t)mount.have_ref);
    put_u32("n_hist_dropped", (uint32_t)mount.n_hist_dropped);
    put_real("mount_yaw", mount.mount_yaw_rad);
    put_real("candidate", last_cand);
    put_real("std", last_std);
    put_real("coherence", last_coh);
    put_real("fref0", mount.f_ref[0]);
    put_real("fref1", mount.f_ref[1]);
    put_real("fref2", mount.f_ref[2]);
    put_u32("sizeof_mount", (uint32_t)sizeof(pl_mount_state));
#endif
#if COST_BLOCK6
    put_mean_max("fusion_predict_mean", "fusion_predict_max", &t_pred);
    put_mean_max("fusion_position_mean", "fusion_position_max", &t_pos);
    put_mean_max("fusion_velocity_mean", "fusion_velocity_max", &t_vel);
    put_u32("n_pos_ok", (uint32_t)n_pos_ok);
    put_u32("n_pos_rejected", (uint32_t)n_pos_rej);
    put_u32("n_vel_ok", (uint32_t)n_vel_ok);
    {
        static const char *const xk[9] = {"x0", "x1", "x2", "x3", "x4", "x5", "x6", "x7", "x8"};
        static const char *const pk[9] = {"p0", "p1", "p2", "p3", "p4", "p5", "p6", "p7", "p8"};
        int i;
        for (i = 0; i < 9; ++i) {
            put_real(xk[i], fus.x[i]);
            put_real(pk[i], fus.P[10 * i]);
        }
    }
    put_real("nis", fus.nis);
    put_u32("sizeof_fusion", (uint32_t)sizeof(pl_fusion_state));
#endif
#ifdef __AVR__
    put_u32("stack_bytes", avr_stack_used());
    put_u32("stack_room", (uint32_t)((const uint8_t *)RAMEND + 1 - &__heap_start)); /* RAM above bss */
#endif
    finish();
    return 0;
}
