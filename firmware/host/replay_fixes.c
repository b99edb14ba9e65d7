/* Host-only test driver (not part of the library): replays recorded inputs through the fixes
 * engine. stdin: fixes_config, then records 'I' + time, f_b[3], w_b[3] or 'G' + fixes_gnss_in
 * (the struct bytes of this build); stdout: per 'I' the int32 return code, per 'G' the int32
 * return code and the fixes_output_t. Built with -fsanitize=address,undefined by
 * tests/test_firmware_fixes.py. */
#include <stdio.h>

#include "../fixes.h"

typedef struct {
    iotnav_time t;
    IOTNAV_REAL f_b[3], w_b[3];
} imu_record;

int main(void)
{
    static fixes_state st; /* 10 KB: not on the stack */
    fixes_config cfg;
    fixes_gnss_in gnss;
    fixes_output_t out;
    imu_record imu;
    int32_t rc;
    int kind;
    if (fread(&cfg, sizeof cfg, 1, stdin) != 1) return 2;
    if (fixes_init(&st, &cfg) != FIXES_OK) return 3;
    while ((kind = getchar()) != EOF) {
        if (kind == 'I') {
            if (fread(&imu, sizeof imu, 1, stdin) != 1) return 4;
            rc = fixes_step_imu(&st, imu.t, imu.f_b, imu.w_b);
            fwrite(&rc, sizeof rc, 1, stdout);
        } else if (kind == 'G') {
            if (fread(&gnss, sizeof gnss, 1, stdin) != 1) return 4;
            rc = fixes_step_gnss(&st, &gnss, &out);
            fwrite(&rc, sizeof rc, 1, stdout);
            fwrite(&out, sizeof out, 1, stdout);
        } else {
            return 6;
        }
    }
    return 0;
}
