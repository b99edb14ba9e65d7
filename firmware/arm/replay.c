/* Cortex-M test program (not part of the library): firmware/host/replay.c's stream through the
 * anchor KF on an emulated board. Reads `anchor_in.bin` (anchor_config, then 'I' +
 * anchor_imu_in or 'G' + anchor_gnss_in records, the struct bytes of a float32 build: every
 * member is 4 bytes, so the layout is the host's) and writes `anchor_out.bin` (per 'I' the
 * anchor_output_t, per 'G' the int32 return code) through semihosting, in QEMU's working
 * directory. Prints on the console the SysTick counts of each call (under `qemu-system-arm
 * -icount shift=N` the virtual clock advances 2^N ns per instruction and SysTick counts the
 * 25 MHz board clock: instructions = ticks * 40 / 2^N), a calibration loop of known length, the
 * stack high-water mark and sizeof(anchor_state). */
#include "../anchor.h"
#include "semihost.h"

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define PAINT 0xA5A5A5A5u
#define CALIB_LOOPS 10000u

extern uint32_t _sstack, _estack;

/* SysTick counts down from 2^24 - 1: elapsed ticks since `t0` (below 2^24). */
static uint32_t since(uint32_t t0) { return (t0 - SYST_CVR) & 0xFFFFFFu; }

typedef struct {
    uint32_t n, sum, max;
} tally;

static void add(tally *t, uint32_t v)
{
    t->n += 1u;
    t->sum += v;
    if (v > t->max) t->max = v;
}

static void put_tally(const char *name, const tally *t)
{
    char key[32];
    static const char *const suffix[3] = {"_n", "_sum", "_max"};
    const uint32_t val[3] = {t->n, t->sum, t->max};
    int k;
    for (k = 0; k < 3; ++k) {
        int n = 0, m = 0;
        while (name[n]) {
            key[n] = name[n];
            ++n;
        }
        while (suffix[k][m]) key[n++] = suffix[k][m++];
        key[n] = 0;
        sh_put_u32(key, val[k]);
    }
}

static int read_all(int32_t fd, void *buf, uint32_t n) { return sh_read(fd, buf, n) == (int32_t)n; }

int main(void)
{
    static anchor_state st;
    anchor_config cfg;
    anchor_imu_in imu;
    anchor_gnss_in gnss;
    anchor_output_t out;
    tally t_imu = {0, 0, 0}, t_gnss = {0, 0, 0}, t_out = {0, 0, 0};
    uint32_t t0, *w, overhead, calib = CALIB_LOOPS;
    uintptr_t sp;
    int32_t fin, fout, rc;
    char kind;
    int ok = 1;

    /* paint the stack below this frame, to find its high-water mark afterwards */
    __asm__ __volatile__("mov %0, sp" : "=r"(sp));
    for (w = &_sstack; (uintptr_t)w < sp - 256u; ++w) *w = PAINT;
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enable, processor clock, no interrupt */

    t0 = SYST_CVR;
    overhead = since(t0);
    t0 = SYST_CVR;
    __asm__ __volatile__("1: subs %0, %0, #1\n\tbne 1b" : "+r"(calib) : : "cc"); /* 2 instructions a loop */
    calib = since(t0);

    fin = sh_open("anchor_in.bin", SH_MODE_RB);
    fout = sh_open("anchor_out.bin", SH_MODE_WB);
    if (fin < 0 || fout < 0 || !read_all(fin, &cfg, sizeof cfg)) {
        sh_puts("error: cannot open or read anchor_in.bin / anchor_out.bin\n");
        return 1;
    }
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
    for (w = &_sstack; w < &_estack && *w == PAINT; ++w) {
    }
    sh_put_u32("tick_overhead", overhead);
    sh_put_u32("calib_loops", CALIB_LOOPS);
    sh_put_u32("calib_ticks", calib);
    put_tally("imu", &t_imu);
    put_tally("gnss", &t_gnss);
    put_tally("output", &t_out);
    sh_put_u32("stack_bytes", (uint32_t)((uintptr_t)&_estack - (uintptr_t)w));
    sh_put_u32("state_bytes", (uint32_t)sizeof st);
    sh_puts(ok ? "done\n" : "error: bad record or write failure\n");
    return ok ? 0 : 1;
}
