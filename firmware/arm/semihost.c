/* ARM semihosting calls (see semihost.h): operation in r0, argument block in r1, BKPT 0xAB
 * (Arm "Semihosting for AArch32 and AArch64", version 2.0, operations SYS_OPEN 0x01,
 * SYS_CLOSE 0x02, SYS_WRITE0 0x04, SYS_WRITE 0x05, SYS_READ 0x06, SYS_EXIT 0x18). */
#include "semihost.h"

static int32_t call(int32_t op, const void *arg)
{
    register int32_t r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ __volatile__("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

static uint32_t length(const char *s)
{
    uint32_t n = 0;
    while (s[n]) ++n;
    return n;
}

int32_t sh_open(const char *name, int32_t mode)
{
    uint32_t a[3];
    a[0] = (uint32_t)(uintptr_t)name;
    a[1] = (uint32_t)mode;
    a[2] = length(name);
    return call(0x01, a);
}

int32_t sh_close(int32_t fd)
{
    uint32_t a[1];
    a[0] = (uint32_t)fd;
    return call(0x02, a);
}

int32_t sh_read(int32_t fd, void *buf, uint32_t n)
{
    uint32_t a[3];
    int32_t left;
    a[0] = (uint32_t)fd;
    a[1] = (uint32_t)(uintptr_t)buf;
    a[2] = n;
    left = call(0x06, a); /* bytes NOT read */
    return left < 0 || (uint32_t)left > n ? -1 : (int32_t)(n - (uint32_t)left);
}

int32_t sh_write(int32_t fd, const void *buf, uint32_t n)
{
    uint32_t a[3];
    a[0] = (uint32_t)fd;
    a[1] = (uint32_t)(uintptr_t)buf;
    a[2] = n;
    return call(0x05, a); /* bytes NOT written */
}

void sh_puts(const char *s) { (void)call(0x04, s); }

void sh_put_u32(const char *key, uint32_t v)
{
    char buf[48];
    char dig[11];
    uint32_t n = 0, k = 0;
    while (key[n] && n < 32) {
        buf[n] = key[n];
        ++n;
    }
    buf[n++] = ' ';
    do {
        dig[k++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    while (k) buf[n++] = dig[--k];
    buf[n++] = '\n';
    buf[n] = 0;
    sh_puts(buf);
}

void sh_exit(int ok)
{
    /* ADP_Stopped_ApplicationExit (0x20026) for success, ADP_Stopped_RunTimeErrorUnknown otherwise */
    (void)call(0x18, (const void *)(uintptr_t)(ok ? 0x20026u : 0x20023u));
    for (;;) {
    }
}
