/* Forno pipeline block 5 in C99 (see pipeline_mount.h and iotnav.techniques.mount): the mounting
 * angle from the non-holonomic constraint, Eqs. 2-3 of the paper in iotnav's least-squares form. */
#include <math.h>

#include "iotnav_common.h"
#include "pipeline_mount.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define ATAN2 atan2
#define HYPOT hypot
#define POW pow
#define PI_R 3.141592653589793
#else
#define ATAN2 atan2f
#define HYPOT hypotf
#define POW powf
#define PI_R 3.14159265f
#endif

/* the AUTO_MIN_BUFFERS of mount.py: innovations the demeaned form needs before it can be chosen */
#define AUTO_MIN_BUFFERS 4
enum { AS_X, AS_Y, DV, DT, AV_Y };

IOTNAV_REAL pl_mount_wrap(IOTNAV_REAL a)
{
    IOTNAV_REAL w = ATAN2(IOTNAV_SIN(a), IOTNAV_COS(a));
    return w == -(IOTNAV_REAL)PI_R ? (IOTNAV_REAL)PI_R : w;
}

/* Python's round() of a non-negative count: to the nearest integer, ties to even */
static IOTNAV_REAL round_half_even(IOTNAV_REAL v)
{
    IOTNAV_REAL r = IOTNAV_FLOOR(v + R(0.5));
    if (r - v == R(0.5) && IOTNAV_FLOOR(r * R(0.5)) * R(2.0) != r) r -= R(1.0);
    return r;
}

int pl_mount_init(pl_mount_state *st, const pl_mount_config *cfg)
{
    int32_t i, m, n_buf, w_ref, rows;
    IOTNAV_REAL s2 = R(0.0);
    n_buf = cfg->buffer_epochs > 2 ? cfg->buffer_epochs : 2;
    w_ref = cfg->ref_window_epochs > 1 ? cfg->ref_window_epochs : 1;
    m = cfg->smooth_epochs > 1 ? cfg->smooth_epochs : 1;
    rows = 2 * m - 1;
    if (cfg->method != PL_MOUNT_METHOD_LSQ || n_buf > PL_MOUNT_BUF_MAX || w_ref > PL_MOUNT_REF_MAX ||
        rows > PL_MOUNT_SMOOTH_ROWS_MAX)
        return PL_MOUNT_ERR_UNSUPPORTED;
    st->cfg = *cfg;
    st->mount_yaw_rad = cfg->initial_mount_yaw_rad;
    st->known = st->provisional = st->accepted_once = st->done = 0;
    st->n_buf = n_buf;
    st->k = 0;
    for (i = 0; i < 2; ++i) {
        int j;
        for (j = 0; j < 4; ++j) st->fu[i].acc[j] = R(0.0);
        st->fu[i].n = st->fu[i].w2 = st->fu[i].z2 = st->fu[i].nz = R(0.0);
    }
    st->fu[0].demean = cfg->demean_buffers && !cfg->auto_demean;
    st->fu[1].demean = 1;
    st->hist_first = st->hist_n = st->n_hist_dropped = 0;
    st->sx = st->sy = st->sr = st->ssq = R(0.0);
    st->n_imu = st->body = 0;
    st->fb[0] = st->fb[1] = st->fb[2] = R(0.0);
    st->t_prev.s = 0;
    st->t_prev.frac = R(0.0);
    st->have_prev = 0;
    st->v_prev = (IOTNAV_REAL)NAN;
    st->n_ring = w_ref;
    st->i_ring = st->ring_full = 0;
    for (i = 0; i < PL_MOUNT_REF_MAX; ++i) st->ring_ok[i] = 0;
    st->f_ref[0] = st->f_ref[1] = st->f_ref[2] = (IOTNAV_REAL)NAN;
    st->t_ref.s = 0;
    st->t_ref.frac = R(0.0);
    st->have_ref = 0;
    /* w = [1, ..., M, ..., 1], overlap = (sum w)^2 / sum w^2 */
    st->n_sm = rows;
    st->k_sm = 0;
    st->sw = R(0.0);
    for (i = 0; i < rows; ++i) {
        st->smooth_w[i] = (IOTNAV_REAL)(i < m ? i + 1 : rows - i);
        st->sw += st->smooth_w[i];
        s2 += st->smooth_w[i] * st->smooth_w[i];
    }
    st->overlap = st->sw * st->sw / s2;
    return PL_MOUNT_OK;
}

void pl_mount_set_stored(pl_mount_state *st, IOTNAV_REAL mount_yaw_rad)
{
    st->mount_yaw_rad = mount_yaw_rad;
    st->known = 1;
    st->accepted_once = 1; /* only accepted angles are stored */
    st->done = st->cfg.one_off;
}

/* accumulate_levelled */
void pl_mount_add_imu(pl_mount_state *st, IOTNAV_REAL a_x, IOTNAV_REAL a_y, IOTNAV_REAL r)
{
    st->sx += a_x;
    st->sy += a_y;
    st->sr += r;
    st->ssq += a_x * a_x + a_y * a_y;
    st->n_imu += 1;
}

/* accumulate_body */
void pl_mount_add_imu_body(pl_mount_state *st, IOTNAV_REAL fx, IOTNAV_REAL fy, IOTNAV_REAL fz, IOTNAV_REAL r)
{
    st->body = 1;
    st->fb[0] += fx;
    st->fb[1] += fy;
    st->fb[2] += fz;
    st->sr += r;
    st->n_imu += 1;
}

void pl_mount_set_gravity_reference(pl_mount_state *st, const IOTNAV_REAL f_b[3], iotnav_time t)
{
    st->f_ref[0] = f_b[0];
    st->f_ref[1] = f_b[1];
    st->f_ref[2] = f_b[2];
    st->t_ref = t;
    st->have_ref = 1;
}

/* mount.levelled: a_b's horizontal components in the levelled sensor frame (z along u, x along
 * the horizontal projection of the sensor x axis) */
static void levelled(const IOTNAV_REAL a[3], const IOTNAV_REAL u[3], IOTNAV_REAL out[2])
{
    IOTNAV_REAL x0 = R(1.0) - u[0] * u[0], x1 = -u[0] * u[1], x2 = -u[0] * u[2];
    IOTNAV_REAL nx = IOTNAV_SQRT(x0 * x0 + x1 * x1 + x2 * x2), y0, y1, y2;
    x0 = x0 / nx;
    x1 = x1 / nx;
    x2 = x2 / nx;
    y0 = u[1] * x2 - u[2] * x1; /* u x x_s */
    y1 = u[2] * x0 - u[0] * x2;
    y2 = u[0] * x1 - u[1] * x0;
    out[0] = x0 * a[0] + x1 * a[1] + x2 * a[2];
    out[1] = y0 * a[0] + y1 * a[1] + y2 * a[2];
}

/* MountAligner._close_body: the interval's levelled acceleration against the gravity reference
 * (returns 1 when there is one), and the reference renewed from an unaccelerated window */
static int close_body(pl_mount_state *st, iotnav_time t, IOTNAV_REAL speed, IOTNAV_REAL dt)
{
    const pl_mount_config *c = &st->cfg;
    int32_t n = st->n_imu, i, j, w = st->n_ring, all_ok = 1;
    IOTNAV_REAL f_mean[3];
    int ok = n > 0 && isfinite(speed) && isfinite(st->v_prev) && R(0.0) < dt && dt <= c->max_interval_s;
    int have = 0;
    for (j = 0; j < 3; ++j) f_mean[j] = n > 0 ? st->fb[j] / (IOTNAV_REAL)n : (IOTNAV_REAL)NAN;
    if (ok && st->have_ref && isfinite(st->f_ref[0]) && isfinite(st->f_ref[1]) && isfinite(st->f_ref[2]) &&
        iotnav_time_diff(t, st->t_ref) <= c->ref_max_age_s) {
        IOTNAV_REAL d[3], u[3], a_s[2], nf;
        nf = IOTNAV_SQRT(st->f_ref[0] * st->f_ref[0] + st->f_ref[1] * st->f_ref[1] + st->f_ref[2] * st->f_ref[2]);
        for (j = 0; j < 3; ++j) {
            d[j] = f_mean[j] - st->f_ref[j];
            u[j] = -st->f_ref[j] / nf; /* down axis in b */
        }
        levelled(d, u, a_s);
        st->sx = a_s[0] * (IOTNAV_REAL)n;
        st->sy = a_s[1] * (IOTNAV_REAL)n;
        st->ssq = (a_s[0] * a_s[0] + a_s[1] * a_s[1]) * (IOTNAV_REAL)n;
        have = 1;
    }
    i = st->i_ring;
    if (ok) {
        IOTNAV_REAL *row = st->ring[i];
        row[0] = f_mean[0];
        row[1] = f_mean[1];
        row[2] = f_mean[2];
        row[3] = (IOTNAV_REAL)n;
        row[4] = speed - st->v_prev;
        row[5] = dt;
        row[6] = R(0.5) * (speed + st->v_prev) * st->sr / (IOTNAV_REAL)n;
    }
    st->ring_ok[i] = ok;
    st->i_ring = i + 1 == w ? 0 : i + 1;
    if (st->i_ring == 0) st->ring_full = 1;
    for (i = 0; i < w; ++i) all_ok = all_ok && st->ring_ok[i];
    if (st->ring_full && all_ok) {
        IOTNAV_REAL T = R(0.0), sdv = R(0.0), slat = R(0.0), sw = R(0.0), f_bar[3], spread2 = R(0.0);
        IOTNAV_REAL a_long, a_lat;
        f_bar[0] = f_bar[1] = f_bar[2] = R(0.0);
        for (i = 0; i < w; ++i) {
            T += st->ring[i][5];
            sdv += st->ring[i][4];
            slat += st->ring[i][6] * st->ring[i][5];
            sw += st->ring[i][3];
            for (j = 0; j < 3; ++j) f_bar[j] += st->ring[i][j] * st->ring[i][3];
        }
        a_long = sdv / T;
        a_lat = slat / T;
        for (j = 0; j < 3; ++j) f_bar[j] = f_bar[j] / sw;
        for (i = 0; i < w; ++i) {
            IOTNAV_REAL e0 = st->ring[i][0] - f_bar[0], e1 = st->ring[i][1] - f_bar[1], e2 = st->ring[i][2] - f_bar[2];
            IOTNAV_REAL e = e0 * e0 + e1 * e1 + e2 * e2;
            if (e > spread2 || i == 0) spread2 = e;
        }
        if (HYPOT(a_long, a_lat) < c->ref_max_accel_mps2 && IOTNAV_SQRT(spread2) < c->ref_max_spread_mps2) {
            pl_mount_set_gravity_reference(st, f_bar, t);
        }
    }
    st->fb[0] = st->fb[1] = st->fb[2] = R(0.0);
    return have;
}

/* MountAligner._smooth: the matched triangular mean of the last 2M - 1 contiguous rows into
 * row; returns 0 while fewer have arrived */
static int smooth(pl_mount_state *st, const IOTNAV_REAL raw[PL_MOUNT_COLS], IOTNAV_REAL row[PL_MOUNT_COLS])
{
    int32_t i, j, n = st->n_sm;
    if (n == 1) {
        for (j = 0; j < PL_MOUNT_COLS; ++j) row[j] = raw[j];
        return 1;
    }
    for (i = 0; i + 1 < n; ++i)
        for (j = 0; j < PL_MOUNT_COLS; ++j) st->sm[i][j] = st->sm[i + 1][j];
    for (j = 0; j < PL_MOUNT_COLS; ++j) st->sm[n - 1][j] = raw[j];
    if (st->k_sm < n) st->k_sm += 1; /* Python counts on; only k_sm < n is read */
    if (st->k_sm < n) return 0;
    for (j = 0; j < PL_MOUNT_COLS; ++j) {
        IOTNAV_REAL s = R(0.0);
        for (i = 0; i < n; ++i) s += st->smooth_w[i] * st->sm[i][j];
        row[j] = s / st->sw;
    }
    return 1;
}

/* lsq_estimate: angle (rad), coherence, excitation (m/s^2), std (rad) of sums over n rows */
static IOTNAV_REAL lsq_estimate(const IOTNAV_REAL s[4], IOTNAV_REAL n, IOTNAV_REAL overlap, IOTNAV_REAL *coh,
                                IOTNAV_REAL *exc, IOTNAV_REAL *std)
{
    IOTNAV_REAL c = s[0], d = s[1], evv = s[2], ess = s[3], h = HYPOT(c, d), res, nn = n > R(1.0) ? n : R(1.0);
    *coh = evv > R(0.0) && ess > R(0.0) ? h / IOTNAV_SQRT(evv * ess) : R(0.0);
    res = ess + evv - R(2.0) * h;
    res = (res > R(0.0) ? res : R(0.0)) / nn;
    *std = evv > R(0.0) ? IOTNAV_SQRT(R(0.5) * res * overlap / evv) : (IOTNAV_REAL)INFINITY;
    if (!(*std <= (IOTNAV_REAL)PI_R)) *std = (IOTNAV_REAL)PI_R; /* min(sigma, pi) */
    *exc = IOTNAV_SQRT(evv / nn);
    return ATAN2(c, d);
}

/* MountAligner._ov_acc */
static IOTNAV_REAL ov_acc(const pl_mount_state *st, const pl_mount_fusion *fu)
{
    if (st->cfg.weighted_variance && fu->n > R(0.0)) return st->overlap * fu->w2 / fu->n;
    return st->overlap;
}

typedef struct {
    IOTNAV_REAL mu, coh, exc, std, consistency;
    IOTNAV_REAL mu_buf, coh_buf, exc_buf, std_buf;
    int useful, outlier;
} fuse_result;

/* MountAligner._fuse: one buffer (a_s, a_v rows) into the form fu with forgetting factor f */
static void fuse(pl_mount_state *st, pl_mount_fusion *fu, IOTNAV_REAL f, fuse_result *r)
{
    const pl_mount_config *c = &st->cfg;
    int32_t i, n = st->n_buf;
    IOTNAV_REAL m[4] = {0, 0, 0, 0}, sums[4] = {0, 0, 0, 0}, ov = st->overlap;
    if (fu->demean) {
        for (i = 0; i < n; ++i) {
            m[0] += st->buf[i][AS_X];
            m[1] += st->buf[i][AS_Y];
            m[2] += st->buf[i][DV] / st->buf[i][DT];
            m[3] += st->buf[i][AV_Y];
        }
        for (i = 0; i < 4; ++i) m[i] = m[i] / (IOTNAV_REAL)n;
    }
    for (i = 0; i < n; ++i) { /* lsq_sums */
        IOTNAV_REAL s0 = st->buf[i][AS_X] - m[0], s1 = st->buf[i][AS_Y] - m[1];
        IOTNAV_REAL v0 = st->buf[i][DV] / st->buf[i][DT] - m[2], v1 = st->buf[i][AV_Y] - m[3];
        if (!fu->demean) {
            s0 = st->buf[i][AS_X];
            s1 = st->buf[i][AS_Y];
            v0 = st->buf[i][DV] / st->buf[i][DT];
            v1 = st->buf[i][AV_Y];
        }
        sums[0] += s0 * v1 - s1 * v0;
        sums[1] += s0 * v0 + s1 * v1;
        sums[2] += v0 * v0 + v1 * v1;
        sums[3] += s0 * s0 + s1 * s1;
    }
    r->mu_buf = lsq_estimate(sums, (IOTNAV_REAL)n, ov, &r->coh_buf, &r->exc_buf, &r->std_buf);
    r->useful = r->exc_buf >= c->min_accel_mps2 && r->coh_buf >= c->min_coherence;
    r->outlier = 0;
    if (r->useful && fu->n > R(0.0)) {
        IOTNAV_REAL coh, exc, std_f, gap, var;
        IOTNAV_REAL mu_f = lsq_estimate(fu->acc, round_half_even(fu->n), ov_acc(st, fu), &coh, &exc, &std_f);
        gap = pl_mount_wrap(r->mu_buf - mu_f);
        if (gap < R(0.0)) gap = -gap;
        var = r->std_buf * r->std_buf + std_f * std_f;
        if (c->auto_demean) {
            fu->z2 = f * fu->z2 + gap * gap / var;
            fu->nz = f * fu->nz + R(1.0);
        }
        if (c->gate_sigma > R(0.0)) {
            r->outlier = gap > c->gate_sigma * IOTNAV_SQRT(var);
            r->useful = !r->outlier;
        }
    }
    if (r->useful) {
        for (i = 0; i < 4; ++i) fu->acc[i] = f * fu->acc[i] + sums[i];
        fu->n = f * fu->n + (IOTNAV_REAL)n;
        fu->w2 = f * f * fu->w2 + (IOTNAV_REAL)n;
    }
    if (fu->n > R(0.0)) {
        r->mu = lsq_estimate(fu->acc, round_half_even(fu->n), ov_acc(st, fu), &r->coh, &r->exc, &r->std);
    } else {
        r->mu = r->mu_buf;
        r->coh = r->coh_buf;
        r->exc = r->exc_buf;
        r->std = r->std_buf;
    }
    r->consistency = (IOTNAV_REAL)NAN;
    if (c->auto_demean) { /* Birge ratio, shrunk towards 1 by AUTO_MIN_BUFFERS pseudo-innovations */
        IOTNAV_REAL b = (fu->z2 + R(AUTO_MIN_BUFFERS)) / (fu->nz + R(AUTO_MIN_BUFFERS));
        b = IOTNAV_SQRT(b > R(1.0) ? b : R(1.0));
        r->consistency = b;
        r->std = r->std * b;
        if (!(r->std <= (IOTNAV_REAL)PI_R)) r->std = (IOTNAV_REAL)PI_R;
    }
}

/* MountAligner._settled: record the fused angle of a useful buffer; 1 when it has settled */
static int settled(pl_mount_state *st, iotnav_time t, IOTNAV_REAL mu, IOTNAV_REAL std)
{
    const pl_mount_config *c = &st->cfg;
    int32_t i, k, n_recent = 0, slot, all_in = 1;
    if (c->settle_s <= R(0.0)) return 0;
    if (st->hist_n == PL_MOUNT_HIST_MAX) { /* full: drop the oldest (counted) */
        st->hist_first = (st->hist_first + 1) % PL_MOUNT_HIST_MAX;
        st->hist_n -= 1;
        st->n_hist_dropped += 1;
    }
    slot = (st->hist_first + st->hist_n) % PL_MOUNT_HIST_MAX;
    st->hist_t[slot] = t;
    st->hist_mu[slot] = mu;
    st->hist_n += 1;
    /* k: the first entry within settle_s; keep one entry before it */
    for (k = 0; k < st->hist_n; ++k)
        if (iotnav_time_diff(t, st->hist_t[(st->hist_first + k) % PL_MOUNT_HIST_MAX]) <= c->settle_s) break;
    if (k > 1) {
        st->hist_first = (st->hist_first + k - 1) % PL_MOUNT_HIST_MAX;
        st->hist_n -= k - 1;
    }
    for (i = 0; i < st->hist_n; ++i) {
        int32_t s = (st->hist_first + i) % PL_MOUNT_HIST_MAX;
        if (iotnav_time_diff(t, st->hist_t[s]) <= c->settle_s) {
            IOTNAV_REAL g = pl_mount_wrap(st->hist_mu[s] - mu);
            n_recent += 1;
            if (g < R(0.0)) g = -g;
            all_in = all_in && g <= c->max_std_rad;
        }
    }
    if (k == 0 || n_recent < c->settle_min_buffers || std > c->settle_std_factor * c->max_std_rad) return 0;
    return all_in;
}

/* MountAligner._evaluate, method "lsq" */
static void evaluate(pl_mount_state *st, iotnav_time t, pl_mount_event *ev)
{
    const pl_mount_config *c = &st->cfg;
    fuse_result res[2];
    int32_t i, n_forms = c->auto_demean ? 2 : 1, best = 0, useful = 0, accepted, is_settled = 0, prov;
    IOTNAV_REAL f = c->forget, mu, std;
    if (c->forget_ref_s > R(0.0)) {
        IOTNAV_REAL T = R(0.0);
        for (i = 0; i < st->n_buf; ++i) T += st->buf[i][DT];
        f = POW(c->forget, T / c->forget_ref_s);
    }
    for (i = 0; i < n_forms; ++i) fuse(st, &st->fu[i], f, &res[i]);
    /* the demeaned form takes over only once its consistency rests on a few buffers; min() keeps the first */
    if (n_forms == 2 && st->fu[1].nz >= R(AUTO_MIN_BUFFERS) && res[1].std < res[0].std) best = 1;
    for (i = 0; i < n_forms; ++i) useful = useful || res[i].useful;
    mu = res[best].mu;
    std = res[best].std;
    accepted = useful && std <= c->max_std_rad;
    if (useful && !accepted) is_settled = settled(st, t, mu, std);
    accepted = accepted || is_settled;
    prov = 0;
    if (useful && !accepted && !st->accepted_once && c->provisional_sigmas > R(0.0) &&
        std <= c->provisional_max_std_rad) {
        IOTNAV_REAL g = pl_mount_wrap(mu - st->mount_yaw_rad);
        if (g < R(0.0)) g = -g;
        prov = st->provisional || g > c->provisional_sigmas * std;
    }
    ev->accepted = accepted;
    ev->applied = accepted || prov;
    ev->provisional = prov;
    ev->settled = is_settled;
    ev->buffer_outlier = res[best].outlier;
    ev->demeaned = st->fu[best].demean;
    ev->candidate_rad = mu;
    ev->std_rad = std;
    ev->coherence = res[best].coh;
    ev->excitation_mps2 = res[best].exc;
    ev->consistency = res[best].consistency;
    ev->buffer_mount_yaw_rad = res[best].mu_buf;
    ev->buffer_coherence = res[best].coh_buf;
    ev->buffer_std_rad = res[best].std_buf;
    ev->buffer_excitation_mps2 = res[best].exc_buf;
    if (accepted || prov) {
        st->mount_yaw_rad = mu;
        st->known = 1;
        st->provisional = prov;
        st->accepted_once = st->accepted_once || accepted;
        if (c->one_off && accepted) st->done = 1; /* a provisional estimate never ends the calibration */
    }
    ev->mount_yaw_rad = st->mount_yaw_rad;
}

int pl_mount_add_gnss(pl_mount_state *st, iotnav_time t, IOTNAV_REAL speed, IOTNAV_REAL course_rad,
                      int course_valid, int is_static, pl_mount_event *ev)
{
    const pl_mount_config *c = &st->cfg;
    int ok_prev = isfinite(st->v_prev), have_acc = 1, good, evaluated = 0;
    IOTNAV_REAL dt = st->have_prev ? iotnav_time_diff(t, st->t_prev) : (IOTNAV_REAL)NAN;
    (void)course_rad; /* read by the paper form only */
    if (st->body) have_acc = close_body(st, t, speed, dt);
    good = have_acc && ok_prev && isfinite(speed) && (course_valid || !c->require_course) && !is_static &&
           st->n_imu > 0 && R(0.0) < dt && dt <= c->max_interval_s &&
           (speed < st->v_prev ? speed : st->v_prev) >= c->min_speed_mps;
    if (good && !st->done) {
        IOTNAV_REAL raw[PL_MOUNT_COLS], row[PL_MOUNT_COLS], n = (IOTNAV_REAL)st->n_imu;
        raw[AS_X] = st->sx / n;
        raw[AS_Y] = st->sy / n;
        raw[DV] = speed - st->v_prev;
        raw[DT] = dt;
        raw[AV_Y] = R(0.5) * (speed + st->v_prev) * (st->sr / n);
        if (smooth(st, raw, row)) {
            int j;
            for (j = 0; j < PL_MOUNT_COLS; ++j) st->buf[st->k][j] = row[j];
            st->k += 1;
            if (st->k == st->n_buf) {
                evaluate(st, t, ev);
                evaluated = 1;
                st->k = 0;
            }
        }
    } else if (!good) {
        st->k_sm = 0;
    }
    st->sx = st->sy = st->sr = st->ssq = R(0.0);
    st->n_imu = 0;
    st->t_prev = t;
    st->have_prev = 1;
    st->v_prev = isfinite(speed) ? speed : (IOTNAV_REAL)NAN;
    return evaluated;
}

/* sizeof(pl_mount_state), for bindings that check their layout */
int32_t pl_mount_sizeof(void) { return (int32_t)sizeof(pl_mount_state); }
