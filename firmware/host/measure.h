/* Timing and output of the cost drivers (host/cycles.c, host/cycles_pipeline.c; not part of the
 * library): cycles() and setup() per target (ATmega128: Timer1 at the CPU clock with its
 * overflow count, UART0 out; Cortex-M under QEMU: SysTick ticks under -icount, semihosting out,
 * see arm/measure.h; host: no timer, stdout), ELAPSED(c0) over the counter's width, and lines
 * "key decimal" (put_u32; put_real writes a value's float32 IEEE bits) that
 * benchmarks/bench_firmware.py reads. Included once, by the driver's translation unit. */
#ifndef IOTNAV_HOST_MEASURE_H
#define IOTNAV_HOST_MEASURE_H

#include <stdint.h>

#include "../iotnav_real.h"

#ifdef __AVR__
#include <avr/interrupt.h>
#include <avr/io.h>
#ifdef TIMSK1 /* the ATmega1284P (blocks 5 and 6's RAM check): Timer1's own mask and flag registers */
#define TIMSK TIMSK1
#define TIFR TIFR1
#endif
static volatile uint16_t ovf;
ISR(TIMER1_OVF_vect) { ++ovf; }
static void putch(char c)
{
    while (!(UCSR0A & (1 << UDRE0))) {
    }
    UDR0 = (uint8_t)c;
}
static uint32_t cycles(void)
{
    uint16_t lo, hi;
    uint8_t sreg = SREG;
    cli();
    lo = TCNT1;
    hi = ovf;
    if ((TIFR & (1 << TOV1)) && lo < 0x8000u) ++hi;
    SREG = sreg;
    return ((uint32_t)hi << 16) | lo;
}
static void setup(void)
{
    UBRR0H = 0;
    UBRR0L = 3;
    UCSR0B = (1 << TXEN0);
    TCCR1A = 0;
    TCCR1B = (1 << CS10);
    TIMSK |= (1 << TOIE1);
    sei();
}
#elif defined(__arm__)
#include "../arm/measure.h"
#define TICK_MASK 0xFFFFFFu /* SysTick is 24 bits */
static uint32_t cycles(void) { return 0xFFFFFFu - SYST_CVR; }
static void setup(void) { measure_start(); }
#else
#include <stdio.h>
static void putch(char c) { putchar(c); }
static uint32_t cycles(void) { return 0; }
static void setup(void) {}
#endif
#ifndef TICK_MASK
#define TICK_MASK 0xFFFFFFFFu
#endif
#define ELAPSED(c0) ((cycles() - (c0)) & TICK_MASK)

#ifdef __arm__
static void put_u32(const char *key, uint32_t v) { sh_put_u32(key, v); }
#else
static void put_str(const char *s)
{
    while (*s) putch(*s++);
}
static void put_u32(const char *key, uint32_t v)
{
    char buf[11];
    int n = 0;
    put_str(key);
    putch(' ');
    do {
        buf[n++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    while (n) putch(buf[--n]);
    putch('\n');
}
#endif
static void put_real(const char *key, IOTNAV_REAL x)
{
    union {
        float f;
        uint32_t u;
    } b;
    b.f = (float)x;
    put_u32(key, b.u);
}

#ifdef __AVR__
/* AVR stack high-water mark: the RAM between the end of bss and the stack is painted at start
 * (paint_stack) and the untouched part counted at the end (avr_stack_used), bytes. */
extern uint8_t __heap_start;
static inline void paint_stack(void)
{
    uint8_t *p = &__heap_start;
    uint8_t *sp = (uint8_t *)SP;
    while (p < sp - 32) *p++ = 0xA5u;
}
static inline uint32_t avr_stack_used(void)
{
    const uint8_t *p = &__heap_start;
    while (p <= (const uint8_t *)RAMEND && *p == 0xA5u) ++p;
    return (uint32_t)((const uint8_t *)RAMEND + 1 - p);
}
#endif

/* Uniform in [-1, 1) from the fixed linear congruential sequence of state *s (the drivers' test
 * inputs; constants of Numerical Recipes' ranqd1). Inline, as every helper below: a driver that
 * does not use one gets no warning. */
static inline IOTNAV_REAL lcg_noise(uint32_t *s)
{
    *s = *s * 1664525u + 1013904223u;
    return (IOTNAV_REAL)(int32_t)(*s >> 8) / IOTNAV_R(8388608.0) - IOTNAV_R(1.0);
}

/* Count, sum and largest cost of a measured call, and its "mean" / "max" output lines. */
typedef struct {
    uint32_t n, sum, max;
} cost_tally;
static inline void count(cost_tally *t, uint32_t c)
{
    t->n += 1u;
    t->sum += c;
    t->max = c > t->max ? c : t->max;
}
static inline void put_mean_max(const char *mean, const char *max, const cost_tally *t)
{
    put_u32(mean, t->sum / (t->n > 0u ? t->n : 1u));
    put_u32(max, t->max);
}

/* A value through a volatile: computed before the timer is read (soft-float arithmetic is free
 * to move across the timer's volatile read otherwise, and would be counted as the call's). */
static inline IOTNAV_REAL settle(IOTNAV_REAL x)
{
    volatile IOTNAV_REAL v = x;
    return v;
}

/* The driver's last lines: "done 1", then on a Cortex-M its stack use and the semihosting exit
 * (QEMU ends); on an ATmega sleep with interrupts off, which ends simavr's run; on the host it
 * returns (main returns 0). Inline: a driver that ends otherwise (host/cycles.c) gets no warning. */
static inline void finish(void)
{
    put_u32("done", 1u);
#ifdef __arm__
    put_u32("stack_bytes", stack_used());
    sh_puts("done\n");
    sh_exit(1);
#endif
#ifdef __AVR__
    cli();
    for (;;) {
        __asm__ __volatile__("sleep");
    }
#endif
}

#endif /* IOTNAV_HOST_MEASURE_H */
