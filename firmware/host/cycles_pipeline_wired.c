/* Cost driver (not part of the library) of the wired Forno pipeline (pipeline.h, blocks 1-6 as
 * one engine) with the pipeline's own configuration (PL_PIPELINE_CONFIG_DEFAULTS, generated from
 * iotnav.engines.config.PipelineConfig()): N_SECONDS of a car near 45 deg N with the sensor
 * mounted 0.5 rad off the vehicle's forward axis, level: 8 s at rest, 6 s accelerating at
 * 1.2 m/s^2, then a speed oscillating about 8 m/s while turning at up to 0.12 rad/s, a 10 s stop
 * at 60 s; 100 Hz IMU (sensor-frame specific force and rate from the kinematics with noise from
 * a fixed pseudo-random sequence), 1 Hz GNSS (position as 1e-7 deg + fraction, height, hAcc /
 * vAcc / sAcc, PDOP / HDOP, speed and course, NED velocity). Times pl_step_imu, pl_step_gnss and
 * pl_output per call; prints the final state ("key decimal" lines, float32 bits for reals) that
 * iotnav.firmware.targets compares with the host float32 build before
 * benchmarks/bench_firmware_pipeline.py reports a target's counts. Built for the ATmega1284P
 * (simavr, Timer1 cycles), the Cortex-M boards QEMU emulates (SysTick under -icount) and the host. */
#include <math.h>

#include "../pipeline.h"

#include "measure.h"

#ifndef N_SECONDS
#define N_SECONDS 90
#endif
#define IMU_HZ 100
#define G IOTNAV_R(9.80665)
/* 1e-7 deg of latitude / longitude at 45 deg N, m (approximate: the engine linearises itself) */
#define M_PER_E7_LAT IOTNAV_R(0.0111132)
#define M_PER_E7_LON IOTNAV_R(0.0078847)

static uint32_t lcg = 13579u;
static IOTNAV_REAL noise(void) { return lcg_noise(&lcg); }
/* a metre offset as 1e-7 deg plus fraction */
static void split(IOTNAV_REAL m, IOTNAV_REAL per_e7, int32_t base, int32_t *e7, IOTNAV_REAL *frac)
{
    IOTNAV_REAL v = m / per_e7, f = IOTNAV_FLOOR(v);
    *e7 = base + (int32_t)f;
    *frac = settle(v - f);
}


static pl_state st; /* one device */
static const pl_pipeline_config cfg = PL_PIPELINE_CONFIG_DEFAULTS;

int main(void)
{
    cost_tally t_imu = {0, 0, 0}, t_gnss = {0, 0, 0}, t_buf = {0, 0, 0}, t_out = {0, 0, 0};
    uint32_t c0, n_ev[13] = {0};
    int32_t k, rc, i, n_src[5] = {0, 0, 0, 0, 0};
    IOTNAV_REAL v = IOTNAV_R(0.0), rN = IOTNAV_R(0.0), rE = IOTNAV_R(0.0), cpsi, spsi, nrm;
    const IOTNAV_REAL cmu = IOTNAV_R(0.8775825618903728), smu = IOTNAV_R(0.479425538604203); /* 0.5 rad */
    pl_output_t out;
#ifdef __AVR__
    paint_stack();
#endif
    setup();
    rc = pl_init(&st, &cfg);
    put_u32("init_rc", (uint32_t)(rc + 100));
    cpsi = IOTNAV_R(0.9800665778412416); /* initial heading 0.2 rad */
    spsi = IOTNAV_R(0.19866933079506122);
    for (k = 0; k < N_SECONDS * IMU_HZ; ++k) {
        IOTNAV_REAL t = (IOTNAV_REAL)k / IOTNAV_R(IMU_HZ), ax, r, dpsi;
        int flags;
        if (t < IOTNAV_R(8.0) || (t >= IOTNAV_R(60.0) && t < IOTNAV_R(70.0))) {
            ax = IOTNAV_R(0.0);
            r = IOTNAV_R(0.0);
            if (t >= IOTNAV_R(60.0)) v = IOTNAV_R(0.0);
        } else if (t < IOTNAV_R(14.0) || (t >= IOTNAV_R(70.0) && t < IOTNAV_R(76.0))) {
            ax = IOTNAV_R(1.2);
            r = IOTNAV_R(0.0);
        } else if (t >= IOTNAV_R(57.0) && t < IOTNAV_R(60.0)) {
            ax = -v / (IOTNAV_R(60.0) - t + IOTNAV_R(0.01)); /* brake to the stop */
            r = IOTNAV_R(0.0);
        } else {
            IOTNAV_REAL ph = t - IOTNAV_R(14.0);
            ax = IOTNAV_R(1.0) * IOTNAV_COS(IOTNAV_R(0.4) * ph);
            r = IOTNAV_R(0.12) * IOTNAV_SIN(IOTNAV_R(0.25) * ph);
        }
        if (k % IMU_HZ == 0) { /* a GNSS epoch at the whole second, before that second's IMU sample */
            pl_gnss_in g;
            g.t.s = k / IMU_HZ;
            g.t.frac = IOTNAV_R(0.0);
            g.valid = 1;
            g.num_sv = 12;
            split(rN + IOTNAV_R(0.6) * noise(), M_PER_E7_LAT, 450000000, &g.lat_e7, &g.lat_frac_e7);
            split(rE + IOTNAV_R(0.6) * noise(), M_PER_E7_LON, 76600000, &g.lon_e7, &g.lon_frac_e7);
            g.height_m = settle(IOTNAV_R(250.0) + IOTNAV_R(1.0) * noise());
            g.h_acc_m = IOTNAV_R(2.5);
            g.v_acc_m = IOTNAV_R(4.0);
            g.s_acc_mps = IOTNAV_R(0.3);
            g.pdop = IOTNAV_R(1.6);
            g.hdop = IOTNAV_R(0.9);
            g.speed_mps = settle(v + IOTNAV_R(0.05) * noise());
            g.course_rad = settle(atan2f(spsi, cpsi) + IOTNAV_R(0.01) * noise());
            g.course_valid = v > IOTNAV_R(0.5);
            g.vn = settle(v * cpsi + IOTNAV_R(0.05) * noise());
            g.ve = settle(v * spsi + IOTNAV_R(0.05) * noise());
            g.vd = settle(IOTNAV_R(0.05) * noise());
            c0 = cycles();
            flags = pl_step_gnss(&st, &g);
            c0 = ELAPSED(c0);
            count(&t_gnss, c0);
            if (flags & PL_EV_MOUNT) count(&t_buf, c0);
            for (i = 0; i < 13; ++i) n_ev[i] += (uint32_t)((flags >> i) & 1);
        }
        {
            /* sensor-frame specific force f_b = Rz(mu)^T [ax, v r, -g] + noise; rate [0, 0, r] + noise */
            pl_imu_in in;
            IOTNAV_REAL ay = v * r;
            in.t.s = k / IMU_HZ;
            in.t.frac = IOTNAV_R(0.01) * (IOTNAV_REAL)(k % IMU_HZ);
            in.f_b[0] = settle(cmu * ax + smu * ay + IOTNAV_R(0.03) * noise());
            in.f_b[1] = settle(-smu * ax + cmu * ay + IOTNAV_R(0.03) * noise());
            in.f_b[2] = settle(-G + IOTNAV_R(0.03) * noise());
            in.w_b[0] = settle(IOTNAV_R(0.002) * noise());
            in.w_b[1] = settle(IOTNAV_R(0.002) * noise());
            in.w_b[2] = settle(r + IOTNAV_R(0.002) * noise());
            c0 = cycles();
            flags = pl_step_imu(&st, &in);
            count(&t_imu, ELAPSED(c0));
            for (i = 0; i < 13; ++i) n_ev[i] += (uint32_t)((flags >> i) & 1);
            c0 = cycles();
            pl_output(&st, &out);
            count(&t_out, ELAPSED(c0));
            n_src[out.source] += 1;
        }
        /* integrate the kinematics (heading by a renormalised rotation) */
        rN += v * cpsi / IOTNAV_R(IMU_HZ);
        rE += v * spsi / IOTNAV_R(IMU_HZ);
        v += ax / IOTNAV_R(IMU_HZ);
        if (v < IOTNAV_R(0.0)) v = IOTNAV_R(0.0);
        dpsi = r / IOTNAV_R(IMU_HZ);
        {
            IOTNAV_REAL c2 = cpsi - dpsi * spsi, s2 = spsi + dpsi * cpsi;
            nrm = IOTNAV_SQRT(c2 * c2 + s2 * s2);
            cpsi = c2 / nrm;
            spsi = s2 / nrm;
        }
    }
    put_mean_max("imu_mean", "imu_max", &t_imu);
    put_mean_max("gnss_mean", "gnss_max", &t_gnss);
    put_mean_max("gnss_buffer_mean", "gnss_buffer_max", &t_buf);
    put_mean_max("output_mean", "output_max", &t_out);
    put_u32("n_imu", t_imu.n);
    put_u32("n_gnss", t_gnss.n);
    {
        static const char *const ek[13] = {"ev_fix_rejected", "ev_moved", "ev_first_fix", "ev_vertical", "ev_mount",
                                           "ev_save", "ev_static_start", "ev_static_end", "ev_boot_move", "ev_skipped",
                                           "ev_imu_gap", "ev_course", "ev_numeric"};
        static const char *const sk[5] = {"src_none", "src_fix", "src_dr", "src_lowpass", "src_last_position"};
        static const char *const xk[9] = {"x0", "x1", "x2", "x3", "x4", "x5", "x6", "x7", "x8"};
        static const char *const pk[9] = {"p0", "p1", "p2", "p3", "p4", "p5", "p6", "p7", "p8"};
        static const char *const ck[9] = {"c0", "c1", "c2", "c3", "c4", "c5", "c6", "c7", "c8"};
        for (i = 0; i < 13; ++i) put_u32(ek[i], n_ev[i]);
        for (i = 0; i < 5; ++i) put_u32(sk[i], (uint32_t)n_src[i]);
        for (i = 0; i < 9; ++i) {
            put_real(xk[i], st.fus.x[i]);
            put_real(pk[i], st.fus.P[10 * i]);
            put_real(ck[i], st.att.C[i]);
        }
    }
    put_u32("mount_known", (uint32_t)st.mount.known);
    put_real("mount_yaw", st.mount.mount_yaw_rad);
    put_real("out_lat_frac", out.geo.lat_frac_e7);
    put_u32("out_lat_e7", (uint32_t)out.geo.lat_e7);
    put_real("out_yaw", out.yaw);
    put_u32("sizeof_state", (uint32_t)sizeof(pl_state));
    put_u32("sizeof_config", (uint32_t)sizeof(pl_pipeline_config));
#ifdef __AVR__
    put_u32("stack_bytes", avr_stack_used());
#endif
    finish();
    return 0;
}
