/* Cortex-M test program (not part of the library): firmware/host/replay_fixes.c's stream through
 * the fixes engine on an emulated board. Reads `replay_in.bin` (fixes_config, then 'I' + time,
 * f_b[3], w_b[3] or 'G' + fixes_gnss_in records, the struct bytes of a float32 build: every
 * member is 4 bytes, so the layout is the host's) and writes `replay_out.bin` (per 'I' the int32
 * return code, per 'G' the int32 return code and the fixes_output_t) through semihosting. Prints
 * the SysTick counts of each call (measure.h), the stack high-water mark and sizeof(fixes_state). */
#include "../fixes.h"
#include "measure.h"

typedef struct {
    iotnav_time t;
    IOTNAV_REAL f_b[3], w_b[3];
} imu_record;

int main(void)
{
    static fixes_state st;
    fixes_config cfg;
    fixes_gnss_in gnss;
    fixes_output_t out;
    imu_record imu;
    tally t_imu = {0, 0, 0}, t_gnss = {0, 0, 0};
    uint32_t t0, dt;
    int32_t fin, fout, rc;
    char kind;
    int ok = 1;

    if (!replay_open(&fin, &fout, &cfg, sizeof cfg)) return 1;
    if (fixes_init(&st, &cfg) != FIXES_OK) {
        sh_puts("error: fixes_init refused the configuration\n");
        return 1;
    }
    while (ok && sh_read(fin, &kind, 1) == 1) {
        if (kind == 'I' && read_all(fin, &imu, sizeof imu)) {
            t0 = SYST_CVR;
            rc = fixes_step_imu(&st, imu.t, imu.f_b, imu.w_b);
            add(&t_imu, since(t0));
            ok = sh_write(fout, &rc, sizeof rc) == 0;
        } else if (kind == 'G' && read_all(fin, &gnss, sizeof gnss)) {
            t0 = SYST_CVR;
            rc = fixes_step_gnss(&st, &gnss, &out);
            dt = since(t0);
            if (rc == FIXES_R_OK && st.init && !(out.events & FIXES_EV_INIT)) add(&t_gnss, dt); /* a filter step */
            ok = sh_write(fout, &rc, sizeof rc) == 0 && sh_write(fout, &out, sizeof out) == 0;
        } else {
            ok = 0;
        }
    }
    sh_close(fin);
    sh_close(fout);
    put_tally("imu", &t_imu);
    put_tally("gnss", &t_gnss);
    sh_put_u32("stack_bytes", stack_used());
    sh_put_u32("state_bytes", (uint32_t)sizeof st);
    sh_puts(ok ? "done\n" : "error: bad record or write failure\n");
    return ok ? 0 : 1;
}
