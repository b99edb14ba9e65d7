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

/* 1: recognise equal covariance blocks of the North and East axes and compute them once. It pays
 * where every float operation is a library call (no FPU: AVR, Cortex-M0/M3) and costs more than
 * it saves with one (Cortex-M4F: 206 -> 294 instructions per IMU step). The results are the same
 * bits either way (the same arithmetic on the same numbers). */
#ifndef IOTNAV_SHARE_BLOCKS
#if defined(__AVR__) || (defined(__arm__) && !defined(__ARM_FP))
#define IOTNAV_SHARE_BLOCKS 1
#else
#define IOTNAV_SHARE_BLOCKS 0
#endif
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
