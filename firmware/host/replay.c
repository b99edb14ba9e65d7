/* Host-only test driver (not part of the library): replays recorded inputs through the anchor
 * KF. stdin: anchor_config, then records 'I' + anchor_imu_in or 'G' + anchor_gnss_in (the
 * struct bytes of this build); stdout: per 'I' the anchor_output_t, per 'G' the int32 return
 * code. Built with -fsanitize=address,undefined by tests/test_firmware_anchor.py. */
#include <stdio.h>

#include "../anchor.h"

int main(void)
{
    anchor_config cfg;
    anchor_state st;
    anchor_imu_in imu;
    anchor_gnss_in gnss;
    anchor_output_t out;
    int kind;
    if (fread(&cfg, sizeof cfg, 1, stdin) != 1) return 2;
    if (anchor_init(&st, &cfg) != ANCHOR_OK) return 3;
    while ((kind = getchar()) != EOF) {
        if (kind == 'I') {
            if (fread(&imu, sizeof imu, 1, stdin) != 1) return 4;
            if (anchor_step_imu(&st, &imu) != ANCHOR_OK) return 5;
            anchor_output(&st, &out);
            fwrite(&out, sizeof out, 1, stdout);
        } else if (kind == 'G') {
            int32_t rc;
            if (fread(&gnss, sizeof gnss, 1, stdin) != 1) return 4;
            rc = anchor_step_gnss(&st, &gnss);
            fwrite(&rc, sizeof rc, 1, stdout);
        } else {
            return 6;
        }
    }
    return 0;
}
