/* ARM semihosting (the host's files and console through the debugger or QEMU's
 * -semihosting), for the Cortex-M test programs only: not part of the library. */
#ifndef IOTNAV_SEMIHOST_H
#define IOTNAV_SEMIHOST_H

#include <stdint.h>

#define SH_MODE_RB 1 /* fopen "rb" */
#define SH_MODE_WB 5 /* fopen "wb" */

/* Open `name` (host path); a handle >= 0, or -1. */
int32_t sh_open(const char *name, int32_t mode);
int32_t sh_close(int32_t fd);
/* Read up to n bytes into buf; the number read (0 at end of file), or -1. */
int32_t sh_read(int32_t fd, void *buf, uint32_t n);
/* Write n bytes; 0 on success. */
int32_t sh_write(int32_t fd, const void *buf, uint32_t n);
/* Print a NUL-terminated string on the host console. */
void sh_puts(const char *s);
/* Print "key value\n" on the host console. */
void sh_put_u32(const char *key, uint32_t v);
/* End the emulation: QEMU exits with status 0 when ok, 1 otherwise. */
void sh_exit(int ok) __attribute__((noreturn));

#endif
