/* Forno pipeline block 4 in C99 (see pipeline_lowpass3.h and iotnav.techniques.lowpass3). */
#include "pipeline_lowpass3.h"

int pl_lowpass3_init(pl_lowpass3_state *st, const pl_lowpass3_config *cfg)
{
    int i, c;
    if (cfg->n1 < 1 || cfg->n2 < 1 || cfg->n3 < 1 || cfg->n1 > PL_LOWPASS3_N_MAX || cfg->n2 > PL_LOWPASS3_N_MAX ||
        cfg->n3 > PL_LOWPASS3_N_MAX) {
        return PL_ERR_UNSUPPORTED;
    }
    st->cfg = *cfg;
    for (i = 0; i < PL_LOWPASS3_N_MAX; ++i) {
        for (c = 0; c < 3; ++c) st->b1[i][c] = st->b2[i][c] = st->b3[i][c] = IOTNAV_R(0.0);
    }
    for (c = 0; c < 3; ++c) st->out[c] = IOTNAV_R(0.0);
    pl_lowpass3_reset(st);
    return PL_OK;
}

/* lowpass3_reset */
void pl_lowpass3_reset(pl_lowpass3_state *st)
{
    st->k1 = st->k2 = st->k3 = st->since2 = 0;
    st->have = 0;
}

/* the mean of the first m rows of a buffer, summed in row order (lowpass3_push) */
static void mean_rows(IOTNAV_REAL (*buf)[3], int32_t m, IOTNAV_REAL *out)
{
    int32_t i, c;
    for (c = 0; c < 3; ++c) {
        IOTNAV_REAL acc = IOTNAV_R(0.0);
        for (i = 0; i < m; ++i) acc += buf[i][c];
        out[c] = acc / (IOTNAV_REAL)m;
    }
}

/* Lowpass3.push / lowpass3_push */
int pl_lowpass3_push(pl_lowpass3_state *st, const IOTNAV_REAL r_n[3])
{
    const pl_lowpass3_config *c = &st->cfg;
    int i;
    for (i = 0; i < 3; ++i) st->b1[st->k1][i] = r_n[i];
    st->k1 += 1;
    if (st->k1 < c->n1) return 0;
    st->k1 = 0;
    mean_rows(st->b1, c->n1, st->b2[st->k2 % c->n2]);
    st->k2 += 1;
    st->since2 += 1;
    if (st->since2 >= c->n2) {
        st->since2 = 0;
        mean_rows(st->b2, c->n2, st->b3[st->k3 % c->n3]);
        st->k3 += 1;
        mean_rows(st->b3, st->k3 < c->n3 ? st->k3 : c->n3, st->out);
        st->have = 1;
        return 1;
    }
    if (st->k3 > 0) return 0; /* level 3 in use: level-2 changes do not reach the output */
    mean_rows(st->b2, st->k2 < c->n2 ? st->k2 : c->n2, st->out);
    st->have = 1;
    return 1;
}

int32_t pl_lowpass3_n_fixes(const pl_lowpass3_state *st)
{
    const pl_lowpass3_config *c = &st->cfg;
    if (st->k3 > 0) return (st->k3 < c->n3 ? st->k3 : c->n3) * c->n2 * c->n1;
    if (st->k2 > 0) return (st->k2 < c->n2 ? st->k2 : c->n2) * c->n1;
    return 0;
}

int32_t pl_lowpass3_level(const pl_lowpass3_state *st) { return st->k3 > 0 ? 3 : (st->k2 > 0 ? 2 : 0); }

/* sizeof(pl_lowpass3_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_lowpass3_sizeof(void) { return (int32_t)sizeof(pl_lowpass3_state); }
