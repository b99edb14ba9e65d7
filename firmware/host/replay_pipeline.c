/* Host-only test driver (not part of the library): blocks 3 and 4 of the Forno pipeline wired as
 * the pipeline wires them, block 1 and block 2's gyro-bias KF as the pipeline drives them
 * (tests/test_firmware_pipeline.py), float32 build. stdin: pl_static_config, pl_lowpass3_config,
 * pl_lastpos_config (struct bytes), int32 has_stored, float stored lat, lon (degrees),
 * pl_gyrobias_config, float b0[3] (rad/s), pl_tilt_config, pl_yaw_config, float gate_nis, then records
 *   'G' int32 s, float frac, float speed, float r_n[3]   a GNSS epoch: its speed into block 3,
 *                                                        its fix into block 4 while static;
 *   'I' int32 s, float frac, float acc_north, acc_east, fallback speed   an IMU sample;
 *   'F' int32 s, float frac, int32 valid, float lat, lon, pdop, int32 num_sv   a fix into block 1
 *                                                        (first_fix on the first acceptable one,
 *                                                        due on every acceptable one);
 *   'B' float dt, gx, gy, gz, int32 static               a gyro sample into the bias KF;
 *   'T' float dt, wx, wy, wz, bias_var, fx, fy, fz, g, a_veh   a sample into the tilt KF;
 *   'Y' float dt, wx, wy, wz, bias_var, x3[3], int32 aid, float v[3]   a sample into the yaw KF
 *                                                        (predict; aid 1: heading psi_b = v[0],
 *                                                        sigma v[1]; aid 2: magnetometer v);
 *   'K' int32 s, float frac, float f[3], w[3], dt, int32 was, float g, a_long, v_gnss,
 *       int32 s_speed, float frac_speed, float v_dr, psi_b   blocks 2 and 3 (pl_front_end_step on
 *                                                        the cascade and block 3's state), then
 *                                                        the course aid when psi_b is finite.
 * stdout: per 'I' int32 static, float acc_h, float speed; per fix pushed into block 4 int32
 * changed, float out[3], int32 n_fixes, int32 level; per 'F' int32 reason, int32 first (1: this
 * was the first acceptable fix, 3: and "moved while off"), float distance (NaN unless moved),
 * int32 due; per 'B' int32 used, float x[3], float P[9]; per 'T' int32 used, float x[3], P[9], nis;
 * per 'Y' int32 aid result (0 none, 1 refused, 2 applied), float x[3], P[9], nis, C_nb[9]; per 'K'
 * int32 static, float y_n[3], C_nb[9] (after the aid). Built with -fsanitize=address,undefined. */
#include <stdio.h>

#include <math.h>

#include "../pipeline_cascade.h"
#include "../pipeline_gyrobias.h"
#include "../pipeline_lastpos.h"
#include "../pipeline_lowpass3.h"
#include "../pipeline_tilt.h"
#include "../pipeline_static.h"
#include "../pipeline_yaw.h"

static int read_time(iotnav_time *t) { return fread(&t->s, 4, 1, stdin) == 1 && fread(&t->frac, 4, 1, stdin) == 1; }

int main(void)
{
    pl_static_config sc;
    pl_lowpass3_config lc;
    pl_static_state det;
    pl_lowpass3_state lp;
    pl_lastpos_config bc;
    pl_lastpos_state boot;
    pl_gyrobias_config gc;
    pl_gyrobias_state bias;
    pl_tilt_config tc;
    pl_tilt_state tilt;
    pl_yaw_config yc;
    pl_yaw_state yaw;
    float gate_nis;
    pl_cascade_state att;
    int32_t has_stored;
    float stored[2], b0[3];
    int kind, was = 0;
    if (fread(&sc, sizeof sc, 1, stdin) != 1 || fread(&lc, sizeof lc, 1, stdin) != 1) return 2;
    if (fread(&bc, sizeof bc, 1, stdin) != 1 || fread(&has_stored, 4, 1, stdin) != 1 ||
        fread(stored, 4, 2, stdin) != 2 || fread(&gc, sizeof gc, 1, stdin) != 1 || fread(b0, 4, 3, stdin) != 3 ||
        fread(&tc, sizeof tc, 1, stdin) != 1 || fread(&yc, sizeof yc, 1, stdin) != 1 ||
        fread(&gate_nis, 4, 1, stdin) != 1)
        return 2;
    if (pl_static_init(&det, &sc) != PL_OK || pl_lowpass3_init(&lp, &lc) != PL_OK) return 3;
    if (pl_lastpos_init(&boot, &bc, has_stored, stored[0], stored[1]) != PL_OK) return 3;
    if (pl_gyrobias_init(&bias, &gc, b0) != PL_OK || pl_tilt_init(&tilt, &tc, 0) != PL_OK) return 3;
    if (pl_yaw_init(&yaw, &yc, gate_nis) != PL_OK) return 3;
    if (pl_cascade_init(&att, &gc, &tc, &yc, gate_nis) != PL_OK) return 3;
    while ((kind = getchar()) != EOF) {
        iotnav_time t;
        float v[4];
        if (kind == 'G') {
            if (!read_time(&t) || fread(v, 4, 4, stdin) != 4) return 4;
            pl_static_update_speed(&det, t, v[0]);
            if (was) {
                int32_t changed = pl_lowpass3_push(&lp, v + 1), n = pl_lowpass3_n_fixes(&lp),
                        level = pl_lowpass3_level(&lp);
                fwrite(&changed, 4, 1, stdout);
                fwrite(lp.out, 4, 3, stdout);
                fwrite(&n, 4, 1, stdout);
                fwrite(&level, 4, 1, stdout);
            }
        } else if (kind == 'I') {
            int32_t now;
            float speed;
            if (!read_time(&t) || fread(v, 4, 3, stdin) != 3) return 4;
            now = pl_static_step(&det, t, v[0], v[1], v[2]);
            if (now != was) pl_lowpass3_reset(&lp);
            was = now;
            speed = pl_static_speed(&det);
            fwrite(&now, 4, 1, stdout);
            fwrite(&det.acc_h, 4, 1, stdout);
            fwrite(&speed, 4, 1, stdout);
        } else if (kind == 'F') {
            int32_t valid, num_sv, reason, first = 0, due = 0;
            float d = NAN;
            if (!read_time(&t) || fread(&valid, 4, 1, stdin) != 1 || fread(v, 4, 3, stdin) != 3 ||
                fread(&num_sv, 4, 1, stdin) != 1)
                return 4;
            reason = pl_lastpos_check_fix(&boot, valid, v[0], v[1], v[2], num_sv, t);
            if (reason == PL_FIX_OK) {
                if (!boot.first_fix_seen) first = pl_lastpos_first_fix(&boot, v[0], v[1], &d) ? 3 : 1;
                if (first != 3) d = NAN;
                due = pl_lastpos_due(&boot, t);
            }
            fwrite(&reason, 4, 1, stdout);
            fwrite(&first, 4, 1, stdout);
            fwrite(&d, 4, 1, stdout);
            fwrite(&due, 4, 1, stdout);
        } else if (kind == 'B') {
            int32_t st, used = 0;
            if (fread(v, 4, 4, stdin) != 4 || fread(&st, 4, 1, stdin) != 1) return 4;
            pl_gyrobias_predict(&bias, v[0]);
            if (st) used = pl_gyrobias_update(&bias, v[1], v[2], v[3]);
            fwrite(&used, 4, 1, stdout);
            fwrite(bias.x, 4, 3, stdout);
            fwrite(bias.P, 4, 9, stdout);
        } else if (kind == 'T') {
            float w[10];
            int32_t used;
            if (fread(w, 4, 10, stdin) != 10) return 4;
            pl_tilt_predict(&tilt, w[1], w[2], w[3], w[0], w[4]);
            used = pl_tilt_update(&tilt, w[5], w[6], w[7], w[8], w[9]);
            fwrite(&used, 4, 1, stdout);
            fwrite(tilt.x, 4, 3, stdout);
            fwrite(tilt.P, 4, 9, stdout);
            fwrite(&tilt.nis, 4, 1, stdout);
        } else if (kind == 'Y') {
            float w[8], a[3], C[9];
            int32_t aid, res = 0;
            if (fread(w, 4, 8, stdin) != 8 || fread(&aid, 4, 1, stdin) != 1 || fread(a, 4, 3, stdin) != 3) return 4;
            pl_yaw_predict(&yaw, w[1], w[2], w[3], w[0], w[4]);
            if (aid == 1) res = 1 + pl_yaw_update_heading(&yaw, a[0], w + 5, a[1]);
            if (aid == 2) res = 1 + pl_yaw_update_mag(&yaw, a[0], a[1], a[2], w + 5);
            pl_dcm_rows(yaw.x, w + 5, C);
            fwrite(&res, 4, 1, stdout);
            fwrite(yaw.x, 4, 3, stdout);
            fwrite(yaw.P, 4, 9, stdout);
            fwrite(&yaw.nis, 4, 1, stdout);
            fwrite(C, 4, 9, stdout);
        } else if (kind == 'K') {
            float w[7], c[3], e[2], y[3];
            int32_t prev, now;
            iotnav_time ts;
            if (!read_time(&t) || fread(w, 4, 7, stdin) != 7 || fread(&prev, 4, 1, stdin) != 1 ||
                fread(c, 4, 3, stdin) != 3 || !read_time(&ts) || fread(e, 4, 2, stdin) != 2)
                return 4;
            now = pl_front_end_step(&att, &det, t, w[0], w[1], w[2], w[3], w[4], w[5], w[6], prev, c[0], c[1], c[2],
                                    ts, e[0], y);
            if (isfinite(e[1])) pl_cascade_aid_heading(&att, e[1], (float)NAN);
            fwrite(&now, 4, 1, stdout);
            fwrite(y, 4, 3, stdout);
            fwrite(att.C, 4, 9, stdout);
        } else {
            return 6;
        }
    }
    return 0;
}
