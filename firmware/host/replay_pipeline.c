/* Host-only test driver (not part of the library): blocks 3 and 4 of the Forno pipeline wired as
 * the pipeline wires them (tests/test_firmware_pipeline.py), float32 build. stdin:
 * pl_static_config, pl_lowpass3_config (struct bytes), then records
 *   'G' int32 s, float frac, float speed, float r_n[3]   a GNSS epoch: its speed into block 3,
 *                                                        its fix into block 4 while static;
 *   'I' int32 s, float frac, float acc_north, acc_east, fallback speed   an IMU sample.
 * stdout: per 'I' int32 static, float acc_h, float speed; per fix pushed into block 4 int32
 * changed, float out[3], int32 n_fixes, int32 level. Built with -fsanitize=address,undefined. */
#include <stdio.h>

#include "../pipeline_lowpass3.h"
#include "../pipeline_static.h"

static int read_time(iotnav_time *t) { return fread(&t->s, 4, 1, stdin) == 1 && fread(&t->frac, 4, 1, stdin) == 1; }

int main(void)
{
    pl_static_config sc;
    pl_lowpass3_config lc;
    pl_static_state det;
    pl_lowpass3_state lp;
    int kind, was = 0;
    if (fread(&sc, sizeof sc, 1, stdin) != 1 || fread(&lc, sizeof lc, 1, stdin) != 1) return 2;
    if (pl_static_init(&det, &sc) != PL_OK || pl_lowpass3_init(&lp, &lc) != PL_OK) return 3;
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
        } else {
            return 6;
        }
    }
    return 0;
}
