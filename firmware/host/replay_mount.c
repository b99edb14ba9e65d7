/* Host-only test driver (not part of the library): block 5 of the Forno pipeline (the mount
 * aligner, pipeline_mount.c) fed from a byte stream, float32 build, run under AddressSanitizer +
 * UndefinedBehaviorSanitizer by tests/test_firmware_mount.py. stdin: pl_mount_config (struct
 * bytes), then records
 *   'I' float f_b[3], r                                 pl_mount_add_imu_body;
 *   'G' int32 s, float frac, float speed, course, int32 course_valid, is_static   pl_mount_add_gnss;
 *   'R' float f_b[3], int32 s, float frac               pl_mount_set_gravity_reference.
 * stdout: per 'G' that evaluated a buffer, the pl_mount_event (struct bytes). Exit status 2 when
 * pl_mount_init refuses the configuration or a record is truncated. */
#include <stdio.h>

#include "../pipeline_mount.h"

static int read_time(iotnav_time *t) { return fread(&t->s, 4, 1, stdin) == 1 && fread(&t->frac, 4, 1, stdin) == 1; }

int main(void)
{
    pl_mount_config cfg;
    pl_mount_state st;
    pl_mount_event ev;
    int kind;
    if (fread(&cfg, sizeof cfg, 1, stdin) != 1 || pl_mount_init(&st, &cfg) != PL_MOUNT_OK) return 2;
    while ((kind = getchar()) != EOF) {
        float v[4];
        iotnav_time t;
        int32_t flags[2];
        if (kind == 'I') {
            if (fread(v, 4, 4, stdin) != 4) return 2;
            pl_mount_add_imu_body(&st, v[0], v[1], v[2], v[3]);
        } else if (kind == 'G') {
            if (!read_time(&t) || fread(v, 4, 2, stdin) != 2 || fread(flags, 4, 2, stdin) != 2) return 2;
            if (pl_mount_add_gnss(&st, t, v[0], v[1], flags[0], flags[1], &ev)) fwrite(&ev, sizeof ev, 1, stdout);
        } else if (kind == 'R') {
            if (fread(v, 4, 3, stdin) != 3 || !read_time(&t)) return 2;
            pl_mount_set_gravity_reference(&st, v, t);
        } else {
            return 2;
        }
    }
    return 0;
}
