/* What the Cortex-M test programs measure (not part of the library): SysTick counts of calls
 * (under `qemu-system-arm -icount shift=N` the virtual clock advances 2^N ns per instruction and
 * SysTick counts the 25 MHz board clock: instructions = ticks * 40 / 2^N), a calibration loop
 * of known length, and the stack high-water mark (the stack painted before the replay). */
#ifndef IOTNAV_ARM_MEASURE_H
#define IOTNAV_ARM_MEASURE_H

#include <stdint.h>

#include "semihost.h"

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define MEASURE_PAINT 0xA5A5A5A5u
#define CALIB_LOOPS 10000u

extern uint32_t _sstack, _estack;

/* SysTick counts down from 2^24 - 1: elapsed ticks since `t0` (below 2^24). */
static inline uint32_t since(uint32_t t0) { return (t0 - SYST_CVR) & 0xFFFFFFu; }

typedef struct {
    uint32_t n, sum, max;
} tally;

static inline void add(tally *t, uint32_t v)
{
    t->n += 1u;
    t->sum += v;
    if (v > t->max) t->max = v;
}

static inline void put_tally(const char *name, const tally *t)
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

/* Paint the stack below the caller's frame, start SysTick, print the tick overhead and the
 * calibration loop (2 instructions a loop). Call first in main. */
static inline void measure_start(void)
{
    uintptr_t sp;
    uint32_t *w, t0, overhead, calib = CALIB_LOOPS;
    __asm__ __volatile__("mov %0, sp" : "=r"(sp));
    for (w = &_sstack; (uintptr_t)w < sp - 256u; ++w) *w = MEASURE_PAINT;
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enable, processor clock, no interrupt */
    t0 = SYST_CVR;
    overhead = since(t0);
    t0 = SYST_CVR;
    __asm__ __volatile__("1: subs %0, %0, #1\n\tbne 1b" : "+r"(calib) : : "cc");
    calib = since(t0);
    sh_put_u32("tick_overhead", overhead);
    sh_put_u32("calib_loops", CALIB_LOOPS);
    sh_put_u32("calib_ticks", calib);
}

/* The stack's high-water mark, bytes. */
static inline uint32_t stack_used(void)
{
    uint32_t *w;
    for (w = &_sstack; w < &_estack && *w == MEASURE_PAINT; ++w) {
    }
    return (uint32_t)((uintptr_t)&_estack - (uintptr_t)w);
}

static inline int read_all(int32_t fd, void *buf, uint32_t n) { return sh_read(fd, buf, n) == (int32_t)n; }

/* measure_start, then open replay_in.bin / replay_out.bin and read the configuration record of n
 * bytes into cfg; 0 (and a message) when that fails. */
static inline int replay_open(int32_t *fin, int32_t *fout, void *cfg, uint32_t n)
{
    measure_start();
    *fin = sh_open("replay_in.bin", SH_MODE_RB);
    *fout = sh_open("replay_out.bin", SH_MODE_WB);
    if (*fin < 0 || *fout < 0 || !read_all(*fin, cfg, n)) {
        sh_puts("error: cannot open or read replay_in.bin / replay_out.bin\n");
        return 0;
    }
    return 1;
}

#endif
