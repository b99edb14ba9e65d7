/* Forno et al. 2020 pipeline, block 4: the three-level low-pass GPS filter used while static
 * (iotnav.techniques.lowpass3) in C99. Fixes fill a level-1 buffer of n1; each full level 1
 * pushes its mean into the level-2 ring (n2), every n2 such pushes the mean of level 2 goes into
 * the level-3 ring (n3); the output is the mean of the highest non-empty level (3, else 2), so
 * it changes every n1 fixes at first and every n1 n2 fixes once level 3 is in use.
 *
 * pl_lowpass3_push mirrors Lowpass3.push (and the compiled lowpass3_push), pl_lowpass3_reset
 * Lowpass3.reset, pl_lowpass3_n_fixes Lowpass3.n_fixes, pl_lowpass3_level Lowpass3.level.
 * Positions are NED metres. No dynamic memory, no global state, no libc. */
#ifndef IOTNAV_PIPELINE_LOWPASS3_H
#define IOTNAV_PIPELINE_LOWPASS3_H

#include "pipeline_config.h"

#ifndef PL_OK
#define PL_OK 0
#define PL_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */
#endif

typedef struct {
    pl_lowpass3_config cfg;
    IOTNAV_REAL b1[PL_LOWPASS3_N_MAX][3], b2[PL_LOWPASS3_N_MAX][3], b3[PL_LOWPASS3_N_MAX][3];
    IOTNAV_REAL out[3];       /* the output (NED, m) when have != 0 */
    int32_t have;             /* an output exists */
    int32_t k1;               /* fixes in level 1 */
    int32_t k2, k3;           /* pushes into level 2 / level 3 since the reset */
    int32_t since2;           /* pushes into level 2 since the last push into level 3 */
} pl_lowpass3_state;

/* Set up `st` (empty); PL_ERR_UNSUPPORTED unless 1 <= n1, n2, n3 <= PL_LOWPASS3_N_MAX. */
int pl_lowpass3_init(pl_lowpass3_state *st, const pl_lowpass3_config *cfg);
/* Empty every level (the static state ended or started); the output is gone too. */
void pl_lowpass3_reset(pl_lowpass3_state *st);
/* Add one fix r_n (NED, m). Returns 1 when the output changed (new value in st->out), else 0. */
int pl_lowpass3_push(pl_lowpass3_state *st, const IOTNAV_REAL r_n[3]);
/* Fixes averaged into the current output (0 when there is none). */
int32_t pl_lowpass3_n_fixes(const pl_lowpass3_state *st);
/* Highest non-empty averaging level: 0 (no output yet), 2 or 3. */
int32_t pl_lowpass3_level(const pl_lowpass3_state *st);

/* sizeof(pl_lowpass3_state), for bindings that check their layout. */
int32_t pl_lowpass3_sizeof(void);

#endif
