/* Scalar type of the iotnav firmware library: float32 by default, double with
 * -DIOTNAV_REAL_DOUBLE (the host build checked against Python to 1e-9). */
#ifndef IOTNAV_REAL_H
#define IOTNAV_REAL_H

#include <stdint.h>

#ifdef IOTNAV_REAL_DOUBLE
typedef double IOTNAV_REAL;
#define IOTNAV_SQRT sqrt
#define IOTNAV_SIN sin
#define IOTNAV_COS cos
#define IOTNAV_FLOOR floor
#define IOTNAV_LOG log
#else
typedef float IOTNAV_REAL;
#define IOTNAV_SQRT sqrtf
#define IOTNAV_SIN sinf
#define IOTNAV_COS cosf
#define IOTNAV_FLOOR floorf
#define IOTNAV_LOG logf
#endif

/* A literal of the library's scalar type. */
#define IOTNAV_R(x) ((IOTNAV_REAL)(x))

/* A time stamp as whole seconds plus a fraction (s): differences keep sub-microsecond
 * resolution in float32 whatever the clock's epoch. */
typedef struct {
    int32_t s;
    IOTNAV_REAL frac;
} iotnav_time;

#endif
