/* Cost driver (not part of the library): a fixed 10 s drive of 100 Hz IMU steps and 1 Hz GNSS
 * updates through the anchor KF, built for the ATmega128 (avr-gcc, run under simavr) and for
 * the host (gcc). Timer1 at the CPU clock counts the cycles of each call on the AVR. Prints
 * lines "key decimal" on UART0 (AVR) or stdout (host): the cycle counts and the
 * IEEE bits of the final state, which benchmarks/bench_firmware.py compares between the two. */
#include <math.h>

#include "../anchor.h"

#include "measure.h"

int main(void)
{
    static const anchor_config cfg = ANCHOR_CONFIG_DEFAULTS;
    anchor_state st;
    anchor_imu_in imu;
    anchor_gnss_in g;
    anchor_output_t out;
    uint32_t c0, imu_sum = 0, imu_max = 0, gnss_sum = 0, gnss_max = 0, out_sum = 0;
    uint32_t frame = 0, frame_sum = 0, frame_max = 0; /* a 10 ms frame with a GNSS epoch */
    int k, i, n_imu = 0, n_gnss = 0;
    const IOTNAV_REAL v = IOTNAV_R(10.0), w = IOTNAV_R(0.05); /* 10 m/s, turning 0.05 rad/s */
    setup();
    anchor_init(&st, &cfg);
    for (i = 0; i < 9; ++i) imu.C_nb[i] = (i % 4 == 0) ? IOTNAV_R(1.0) : IOTNAV_R(0.0);
    imu.tilt_p_trace = IOTNAV_R(1e-5);
    imu.yaw_p_trace = IOTNAV_R(1e-3);
    for (k = 0; k <= 1000; ++k) {
        IOTNAV_REAL t = IOTNAV_R(0.01) * (IOTNAV_REAL)k, psi = w * t;
        imu.t.s = k / 100;
        imu.t.frac = IOTNAV_R(0.01) * (IOTNAV_REAL)(k % 100);
        imu.C_nb[0] = imu.C_nb[4] = IOTNAV_COS(psi);
        imu.C_nb[1] = -IOTNAV_SIN(psi);
        imu.C_nb[3] = IOTNAV_SIN(psi);
        imu.f_b[0] = IOTNAV_R(0.02);
        imu.f_b[1] = v * w; /* centripetal */
        imu.f_b[2] = -st.g;
        if (k % 100 == 0) {
            IOTNAV_REAL north = v / w * IOTNAV_SIN(psi), east = v / w * (IOTNAV_R(1.0) - IOTNAV_COS(psi));
            IOTNAV_REAL dlat = north / IOTNAV_R(0.0111132), dlon = east / IOTNAV_R(0.0078618);
            g.t = imu.t;
            g.valid = 1;
            g.num_sv = 9;
            g.lat_e7 = 450628000 + (int32_t)IOTNAV_FLOOR(dlat);
            g.lat_frac_e7 = dlat - IOTNAV_FLOOR(dlat);
            g.lon_e7 = 76861000 + (int32_t)IOTNAV_FLOOR(dlon);
            g.lon_frac_e7 = dlon - IOTNAV_FLOOR(dlon);
            g.height_m = IOTNAV_R(250.0);
            g.h_acc_m = IOTNAV_R(2.5);
            g.v_acc_m = IOTNAV_R(4.0);
            g.hdop = IOTNAV_R(1.1);
            g.pdop = IOTNAV_R(1.9);
            g.vn = v * IOTNAV_COS(psi);
            g.ve = v * IOTNAV_SIN(psi);
            g.vd = IOTNAV_R(0.0);
            g.speed_mps = v;
            g.course_rad = psi;
            g.course_valid = 1;
            g.s_acc_mps = IOTNAV_R(0.3);
            c0 = cycles();
            anchor_step_gnss(&st, &g);
            c0 = cycles() - c0;
            frame = c0;
            if (k > 0) { /* the first fix only initialises */
                gnss_sum += c0;
                gnss_max = c0 > gnss_max ? c0 : gnss_max;
                ++n_gnss;
            }
        }
        c0 = cycles();
        anchor_step_imu(&st, &imu);
        c0 = cycles() - c0;
        if (k > 100) {
            imu_sum += c0;
            imu_max = c0 > imu_max ? c0 : imu_max;
            ++n_imu;
        }
        frame += c0;
        c0 = cycles();
        anchor_output(&st, &out);
        c0 = cycles() - c0;
        out_sum += c0;
        if (k > 0 && k % 100 == 0) { /* GNSS update, IMU step and output of the same sample */
            frame += c0;
            frame_sum += frame;
            frame_max = frame > frame_max ? frame : frame_max;
        }
    }
    put_u32("imu_mean", imu_sum / (uint32_t)n_imu);
    put_u32("imu_max", imu_max);
    put_u32("gnss_mean", gnss_sum / (uint32_t)n_gnss);
    put_u32("gnss_max", gnss_max);
    put_u32("output_mean", out_sum / 1001u);
    put_u32("frame_mean", frame_sum / (uint32_t)n_gnss);
    put_u32("frame_max", frame_max);
    for (i = 0; i < 6; ++i) {
        char key[3] = {'x', (char)('0' + i), 0};
        put_real(key, st.x[i]);
    }
    put_real("p00", st.P[0]);
    put_real("p44", st.P[28]);
    put_str("done\n");
#ifdef __AVR__
    cli();
    for (;;) {
        /* simavr: sleep with interrupts off ends the simulation */
        __asm__ __volatile__("sleep");
    }
#endif
    return 0;
}
