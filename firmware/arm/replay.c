/* Cortex-M test program (not part of the library): firmware/host/replay.c's stream through the
 * anchor KF on an emulated board. Reads `replay_in.bin` (anchor_config, then 'I' +
 * anchor_imu_in or 'G' + anchor_gnss_in records, the struct bytes of a float32 build: every
 * member is 4 bytes, so the layout is the host's) and writes `replay_out.bin` (per 'I' the
 * anchor_output_t, per 'G' the int32 return code) through semihosting, in QEMU's working
 * directory. Prints on the console the SysTick counts of each call (under `qemu-system-arm
 * -icount shift=N` the virtual clock advances 2^N ns per instruction and SysTick counts the
 * 25 MHz board clock: instructions = ticks * 40 / 2^N), a calibration loop of known length, the
 * stack high-water mark and sizeof(anchor_state). */
#include "../anchor.h"
#include "measure.h"

int main(void)
{
    static anchor_state st;
    anchor_config cfg;
    anchor_imu_in imu;
    anchor_gnss_in gnss;
    anchor_output_t out;
    tally t_imu = {0, 0, 0}, t_gnss = {0, 0, 0}, t_out = {0, 0, 0};
    uint32_t t0;
    int32_t fin, fout, rc;
    char kind;
    int ok = 1;

    if (!replay_open(&fin, &fout, &cfg, sizeof cfg)) return 1;
    if (anchor_init(&st, &cfg) != ANCHOR_OK) {
        sh_puts("error: anchor_init refused the configuration\n");
        return 1;
    }
    while (ok && sh_read(fin, &kind, 1) == 1) {
        if (kind == 'I' && read_all(fin, &imu, sizeof imu)) {
            t0 = SYST_CVR;
            rc = anchor_step_imu(&st, &imu);
            add(&t_imu, since(t0));
            t0 = SYST_CVR;
            anchor_output(&st, &out);
            add(&t_out, since(t0));
            ok = rc == ANCHOR_OK && sh_write(fout, &out, sizeof out) == 0;
        } else if (kind == 'G' && read_all(fin, &gnss, sizeof gnss)) {
            t0 = SYST_CVR;
            rc = anchor_step_gnss(&st, &gnss);
            if (st.n_fixes > 1 && rc == ANCHOR_OK) add(&t_gnss, since(t0)); /* an update, not the first fix */
            ok = sh_write(fout, &rc, sizeof rc) == 0;
        } else {
            ok = 0;
        }
    }
    sh_close(fin);
    sh_close(fout);
    put_tally("imu", &t_imu);
    put_tally("gnss", &t_gnss);
    put_tally("output", &t_out);
    sh_put_u32("stack_bytes", stack_used());
    sh_put_u32("state_bytes", (uint32_t)sizeof st);
    sh_puts(ok ? "done\n" : "error: bad record or write failure\n");
    return ok ? 0 : 1;
}
