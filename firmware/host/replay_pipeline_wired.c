/* Host replay of the wired pipeline (pipeline.h): stdin holds a pl_pipeline_config of the build's
 * scalar type, then records, each a kind byte and its struct:
 *   'S' pl_geo, IOTNAV_REAL mount_yaw_rad   (a stored last position: pl_set_stored)
 *   'I' pl_imu_in                           (pl_step_imu)
 *   'G' pl_gnss_in                          (pl_step_gnss)
 *   'M' iotnav_time, IOTNAV_REAL m_b[3]     (pl_step_mag)
 * stdout: int32 pl_init's result, then per I record 'I', int32 flags, pl_output_t; per G record
 * 'G', int32 flags, int32 fix_reason, IOTNAV_REAL nis, moved_distance_m, vertical_jump_m,
 * pl_mount_event, pl_save; per M record 'M', int32 flags. The tests build it with
 * AddressSanitizer + UndefinedBehaviorSanitizer (iotnav.firmware.pipeline_engine). */
#include <stdio.h>
#include <stdlib.h>

#include "pipeline.h"

static int read_all(void *p, size_t n) { return fread(p, 1, n, stdin) == n; }
static void write_all(const void *p, size_t n) { (void)fwrite(p, 1, n, stdout); }

int main(void)
{
    pl_state *st = (pl_state *)malloc(sizeof(pl_state)); /* the host driver's, not the library's */
    pl_pipeline_config cfg;
    int32_t rc;
    int kind;
    if (st == NULL || !read_all(&cfg, sizeof cfg)) return 2;
    rc = (int32_t)pl_init(st, &cfg);
    write_all(&rc, sizeof rc);
    if (rc != PL_OK) {
        free(st);
        return 0;
    }
    while ((kind = getchar()) != EOF) {
        char k = (char)kind;
        int32_t flags;
        if (k == 'S') {
            pl_geo g;
            IOTNAV_REAL mu;
            if (!read_all(&g, sizeof g) || !read_all(&mu, sizeof mu)) break;
            pl_set_stored(st, &g, mu);
        } else if (k == 'I') {
            pl_imu_in in;
            pl_output_t out;
            if (!read_all(&in, sizeof in)) break;
            flags = (int32_t)pl_step_imu(st, &in);
            pl_output(st, &out);
            write_all(&k, 1);
            write_all(&flags, sizeof flags);
            write_all(&out, sizeof out);
        } else if (k == 'G') {
            pl_gnss_in in;
            int32_t reason;
            if (!read_all(&in, sizeof in)) break;
            flags = (int32_t)pl_step_gnss(st, &in);
            reason = st->fix_reason;
            write_all(&k, 1);
            write_all(&flags, sizeof flags);
            write_all(&reason, sizeof reason);
            write_all(&st->nis, sizeof st->nis);
            write_all(&st->moved_distance_m, sizeof st->moved_distance_m);
            write_all(&st->vertical_jump_m, sizeof st->vertical_jump_m);
            write_all(&st->mount_event, sizeof st->mount_event);
            write_all(&st->save, sizeof st->save);
        } else if (k == 'M') {
            iotnav_time t;
            IOTNAV_REAL m[3];
            if (!read_all(&t, sizeof t) || !read_all(m, sizeof m)) break;
            flags = (int32_t)pl_step_mag(st, t, m);
            write_all(&k, 1);
            write_all(&flags, sizeof flags);
        } else {
            free(st);
            return 3; /* a record this driver does not know */
        }
    }
    free(st);
    return 0;
}
