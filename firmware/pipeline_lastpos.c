/* Forno pipeline block 1 in C99 (see pipeline_lastpos.h and iotnav.techniques.last_position). */
#include <math.h>

#include "iotnav_common.h"
#include "pipeline_lastpos.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define SIN sin
#define COS cos
#define ASIN asin
#define SQRT sqrt
#else
#define SIN sinf
#define COS cosf
#define ASIN asinf
#define SQRT sqrtf
#endif
/* math.radians: x * (pi / 180) */
#define RAD(x) ((x) * (R(3.141592653589793) / R(180.0)))
/* the settling gate's tolerance on times, s (Python: 1e-9; nothing in float32) */
#define T_EPS R(1e-9)

int pl_lastpos_init(pl_lastpos_state *st, const pl_lastpos_config *cfg, int has_stored,
                    IOTNAV_REAL stored_lat_deg, IOTNAV_REAL stored_lon_deg)
{
    st->cfg = *cfg;
    st->has_stored = has_stored != 0;
    st->stored_lat_deg = stored_lat_deg;
    st->stored_lon_deg = stored_lon_deg;
    st->first_fix_seen = 0;
    st->saved = 0;
    st->t_saved.s = 0;
    st->t_saved.frac = R(0.0);
    st->n_hist = 0;
    st->n_hist_dropped = 0;
    return PL_OK;
}

/* fix_rejection_reason */
static int rejection_reason(const pl_lastpos_config *c, int valid, IOTNAV_REAL lat, IOTNAV_REAL lon,
                            IOTNAV_REAL pdop, int32_t num_sv)
{
    if (!valid) return PL_FIX_INVALID;
    if (!(isfinite(lat) && isfinite(lon))) return PL_FIX_NO_POSITION;
    if (isfinite(pdop)) {
        if (pdop > c->max_pdop) return PL_FIX_PDOP;
    } else if (!c->accept_unknown_pdop) {
        return PL_FIX_PDOP_UNKNOWN;
    }
    if (c->min_num_sv > 0 && num_sv < c->min_num_sv) return PL_FIX_NUM_SV;
    return PL_FIX_OK;
}

/* LastPositionLogic.check_fix */
int pl_lastpos_check_fix(pl_lastpos_state *st, int valid, IOTNAV_REAL lat_deg, IOTNAV_REAL lon_deg,
                         IOTNAV_REAL pdop, int32_t num_sv, iotnav_time t)
{
    const pl_lastpos_config *c = &st->cfg;
    int reason = rejection_reason(c, valid, lat_deg, lon_deg, pdop, num_sv);
    if (reason == PL_FIX_OK && !st->first_fix_seen && !st->has_stored && c->settle_ratio > R(0.0) &&
        isfinite(t.frac) && isfinite(pdop)) {
        const IOTNAV_REAL w = c->settle_window_s;
        int32_t i, n = 0, have_recent = 0;
        IOTNAV_REAL top = R(0.0);
        /* covered: the oldest entry (before the trim) at or before t - window (+ 1e-9) */
        int covered = st->n_hist > 0 && iotnav_time_diff(t, st->hist_t[0]) >= w - T_EPS;
        /* hist: the entries at or after t - window (- 1e-9), in order; recent: those before t */
        for (i = 0; i < st->n_hist; ++i) {
            IOTNAV_REAL age = iotnav_time_diff(t, st->hist_t[i]);
            if (age <= w + T_EPS) {
                if (age > R(0.0)) {
                    if (!have_recent || st->hist_pdop[i] > top) top = st->hist_pdop[i];
                    have_recent = 1;
                }
                st->hist_t[n] = st->hist_t[i];
                st->hist_pdop[n] = st->hist_pdop[i];
                ++n;
            }
        }
        if (n == PL_LASTPOS_HIST_MAX) { /* full: drop the oldest (counted) */
            for (i = 1; i < n; ++i) {
                st->hist_t[i - 1] = st->hist_t[i];
                st->hist_pdop[i - 1] = st->hist_pdop[i];
            }
            --n;
            st->n_hist_dropped += 1;
        }
        st->hist_t[n] = t;
        st->hist_pdop[n] = pdop;
        st->n_hist = n + 1;
        if ((have_recent && pdop < (R(1.0) - c->settle_ratio) * top) || (!covered && pdop > c->settle_max_pdop))
            return PL_FIX_SETTLING;
    }
    return reason;
}

/* horizontal_distance_m */
IOTNAV_REAL pl_horizontal_distance_m(IOTNAV_REAL lat1, IOTNAV_REAL lon1, IOTNAV_REAL lat2, IOTNAV_REAL lon2)
{
    /* dp as radians(lat2 - lat1), Python radians(lat2) - radians(lat1): the same to 1e-16 rad in
     * float64, and in float32 no cancellation (0.4 m at 45 degrees) */
    IOTNAV_REAL p1 = RAD(lat1), p2 = RAD(lat2), dp = RAD(lat2 - lat1), dl = RAD(lon2 - lon1);
    IOTNAV_REAL sp = SIN(dp / R(2.0)), sl = SIN(dl / R(2.0)), a = sp * sp + COS(p1) * COS(p2) * (sl * sl);
    IOTNAV_REAL q = SQRT(a);
    return R(2.0) * R(6371008.8) * ASIN(q < R(1.0) ? q : R(1.0)); /* Python's min(1.0, sqrt(a)) (NaN: 1) */
}

/* LastPositionLogic.first_fix */
int pl_lastpos_first_fix(pl_lastpos_state *st, IOTNAV_REAL lat_deg, IOTNAV_REAL lon_deg, IOTNAV_REAL *distance_m)
{
    IOTNAV_REAL d;
    st->first_fix_seen = 1;
    if (!st->has_stored) return 0;
    d = pl_horizontal_distance_m(st->stored_lat_deg, st->stored_lon_deg, lat_deg, lon_deg);
    *distance_m = d;
    return d > st->cfg.moved_threshold_m;
}

/* LastPositionLogic.due (t_saved = -inf before the first save: t - t_saved = +inf) */
int pl_lastpos_due(pl_lastpos_state *st, iotnav_time t)
{
    IOTNAV_REAL since = st->saved ? iotnav_time_diff(t, st->t_saved) : (IOTNAV_REAL)INFINITY;
    if (since >= st->cfg.save_interval_s) {
        st->t_saved = t;
        st->saved = 1;
        return 1;
    }
    return 0;
}

/* sizeof(pl_lastpos_state), for bindings that check their layout (iotnav.firmware.pipeline) */
int32_t pl_lastpos_sizeof(void) { return (int32_t)sizeof(pl_lastpos_state); }
