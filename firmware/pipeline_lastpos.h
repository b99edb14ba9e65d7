/* Forno et al. 2020 pipeline, block 1: the last known position's boot and save logic
 * (iotnav.techniques.last_position.LastPositionLogic) in C99. A GNSS fix is acceptable when the
 * receiver declares it valid, its coordinates are finite, PDOP <= max_pdop (or unknown, when
 * accepted) and, optionally, num_sv >= min_num_sv; without a stored position the first fix must
 * also pass the settling gate (the PDOP fell by less than settle_ratio over the valid fixes of
 * the last settle_window_s, and is at most settle_max_pdop unless those fixes cover the whole
 * window); the first acceptable fix farther than moved_threshold_m from the stored position is
 * a "moved while off" event; a save is due every save_interval_s. The module docstring of
 * iotnav.techniques.last_position gives the rules; the store itself (flash, EEPROM) is the
 * caller's.
 *
 * pl_lastpos_check_fix mirrors LastPositionLogic.check_fix, pl_lastpos_first_fix first_fix,
 * pl_lastpos_due due. No dynamic memory, no global state (one pl_lastpos_state per device),
 * nothing from libc but <math.h> (sin, cos, asin, sqrt, isfinite). */
#ifndef IOTNAV_PIPELINE_LASTPOS_H
#define IOTNAV_PIPELINE_LASTPOS_H

#include "pipeline_config.h"

#ifndef PL_OK
#define PL_OK 0
#define PL_ERR_UNSUPPORTED (-1) /* a configuration this library does not implement */
#endif

/* pl_lastpos_check_fix's results: LastPositionLogic.check_fix's reasons (None: PL_FIX_OK) */
#define PL_FIX_OK 0
#define PL_FIX_INVALID 1      /* "invalid" */
#define PL_FIX_NO_POSITION 2  /* "no_position" */
#define PL_FIX_PDOP 3         /* "pdop" */
#define PL_FIX_PDOP_UNKNOWN 4 /* "pdop_unknown" */
#define PL_FIX_NUM_SV 5       /* "num_sv" */
#define PL_FIX_SETTLING 6     /* "settling" */

typedef struct {
    pl_lastpos_config cfg;
    int32_t has_stored;         /* a stored position was loaded at boot */
    IOTNAV_REAL stored_lat_deg; /* its geodetic latitude and longitude, degrees */
    IOTNAV_REAL stored_lon_deg;
    int32_t first_fix_seen;     /* first_fix_seen */
    int32_t saved;              /* a save was due once (t_saved > -inf) */
    iotnav_time t_saved;        /* time of the latest save, s (t_saved; meaningful when saved) */
    /* the settling gate's (t, PDOP) of the valid fixes before the first (_pdop_hist), oldest
     * first; more than PL_LASTPOS_HIST_MAX within settle_window_s: the oldest is dropped and
     * counted in n_hist_dropped (Python keeps them all) */
    iotnav_time hist_t[PL_LASTPOS_HIST_MAX];
    IOTNAV_REAL hist_pdop[PL_LASTPOS_HIST_MAX];
    int32_t n_hist;
    int32_t n_hist_dropped;
} pl_lastpos_state;

/* Set up `st`; has_stored: a stored position (stored_lat_deg, stored_lon_deg, degrees) was
 * loaded at boot. Returns PL_OK (0). */
int pl_lastpos_init(pl_lastpos_state *st, const pl_lastpos_config *cfg, int has_stored,
                    IOTNAV_REAL stored_lat_deg, IOTNAV_REAL stored_lon_deg);
/* A fix: receiver validity flag, geodetic degrees, PDOP (NaN: unknown), satellites used, device
 * time t (s; t.frac NaN: unknown, no settling gate). Returns PL_FIX_OK or the PL_FIX_* reason. */
int pl_lastpos_check_fix(pl_lastpos_state *st, int valid, IOTNAV_REAL lat_deg, IOTNAV_REAL lon_deg,
                         IOTNAV_REAL pdop, int32_t num_sv, iotnav_time t);
/* Call on the first acceptable fix (degrees). Returns 1 ("moved while off": farther than
 * moved_threshold_m from the stored position; the distance in *distance_m, m) or 0. */
int pl_lastpos_first_fix(pl_lastpos_state *st, IOTNAV_REAL lat_deg, IOTNAV_REAL lon_deg, IOTNAV_REAL *distance_m);
/* 1 when a save is due at device time t (s), and marks it done; else 0. */
int pl_lastpos_due(pl_lastpos_state *st, iotnav_time t);
/* Haversine distance between two points (degrees) on the mean Earth sphere, m
 * (iotnav.techniques.last_position.horizontal_distance_m). */
IOTNAV_REAL pl_horizontal_distance_m(IOTNAV_REAL lat1, IOTNAV_REAL lon1, IOTNAV_REAL lat2, IOTNAV_REAL lon2);

/* sizeof(pl_lastpos_state), for bindings that check their layout. */
int32_t pl_lastpos_sizeof(void);

#endif
