/* The GNSS-only engine in C99 (see fixes.h and iotnav.engines.fixes / fixes_kernel): each
 * function below names the Python function it mirrors; the arithmetic is written in the same
 * order so that the float64 build equals Python to rounding. */
#include <math.h>

#include "fixes.h"
#include "iotnav_common.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define EXP exp
#else
#define EXP expf
#endif
#define NAN_R ((IOTNAV_REAL)NAN)
#define AX_N 0
#define AX_E 1
#define AX_D 2
/* g of the accelerometer sums' shift (the variance of |f| is that of |f| - G_SHIFT, with less
 * cancellation in float32) */
#define G_SHIFT 9.80665

int fixes_init(fixes_state *st, const fixes_config *cfg)
{
    unsigned char *b = (unsigned char *)st;
    unsigned long i;
    const IOTNAV_REAL lp_max = R(FIXES_LP_MAX);
    if (!(cfg->lp_n1 >= R(1.0) && cfg->lp_n2 >= R(1.0) && cfg->lp_n3 >= R(1.0) && cfg->lp_n1 <= lp_max &&
          cfg->lp_n2 <= lp_max && cfg->lp_n3 <= lp_max)) {
        return FIXES_ERR_UNSUPPORTED;
    }
    for (i = 0; i < sizeof *st; ++i) b[i] = 0; /* every flag 0, every count 0 */
    st->cfg = *cfg;
    st->lat_last_frac = st->lon_last_frac = NAN_R;
    return FIXES_OK;
}

int fixes_step_imu(fixes_state *st, iotnav_time t, const IOTNAV_REAL f_b[3], const IOTNAV_REAL w_b[3])
{
    IOTNAV_REAL a;
    int rc = FIXES_OK;
    /* InputGuard.admit */
    if (!isfinite(t.frac + f_b[0] + f_b[1] + f_b[2] + w_b[0] + w_b[1] + w_b[2])) return FIXES_IMU_NONFINITE;
    if (st->have_t_imu) {
        IOTNAV_REAL dt = iotnav_time_diff(t, st->t_imu);
        if (dt < R(0.0)) return FIXES_IMU_BACKWARDS;
        if (dt > R(FIXES_IMU_GAP_S)) rc = FIXES_IMU_GAP;
    }
    st->t_imu = t;
    st->have_t_imu = 1;
    /* fixes.acc_add, the sums shifted by G_SHIFT */
    a = IOTNAV_SQRT(f_b[0] * f_b[0] + f_b[1] * f_b[1] + f_b[2] * f_b[2]) - R(G_SHIFT);
    st->acc_n += 1;
    st->acc_s1 += a;
    st->acc_s2 += a * a;
    return rc;
}

/* fixes_kernel.predict_axis */
static void predict_axis(fixes_axis *x, IOTNAV_REAL dt, IOTNAV_REAL q)
{
    IOTNAV_REAL p00 = x->pp, p01 = x->pv, p11 = x->vv;
    x->p += dt * x->v;
    x->pp = p00 + dt * (R(2.0) * p01 + dt * p11) + q * dt * dt * dt / R(3.0);
    x->pv = p01 + dt * p11 + R(0.5) * q * dt * dt;
    x->vv = p11 + q * dt;
}

/* fixes_kernel.update_axis: component j (0 position, 1 velocity) measured as z, variance r */
static void update_axis(fixes_axis *x, int j, IOTNAV_REAL z, IOTNAV_REAL r)
{
    IOTNAV_REAL p00 = x->pp, p01 = x->pv, p11 = x->vv, s, k0, k1, y, n00, n01, n11;
    s = (j == 0 ? p00 : p11) + r;
    k0 = (j == 0 ? p00 : p01) / s;
    k1 = (j == 0 ? p01 : p11) / s;
    y = z - (j == 0 ? x->p : x->v);
    x->p += k0 * y;
    x->v += k1 * y;
    if (j == 0) {
        IOTNAV_REAL a00 = R(1.0) - k0, a10 = -k1;
        n00 = a00 * a00 * p00;
        n01 = a00 * (a10 * p00 + p01);
        n11 = a10 * a10 * p00 + R(2.0) * a10 * p01 + p11;
    } else {
        IOTNAV_REAL a01 = -k0, a11 = R(1.0) - k1;
        n00 = p00 + R(2.0) * a01 * p01 + a01 * a01 * p11;
        n01 = a11 * (p01 + a01 * p11);
        n11 = a11 * a11 * p11;
    }
    x->pp = n00 + k0 * k0 * r;
    x->pv = n01 + k0 * k1 * r;
    x->vv = n11 + k1 * k1 * r;
}

/* fixes_kernel.init_axis */
static void init_axis(fixes_axis *x, IOTNAV_REAL p, IOTNAV_REAL v, IOTNAV_REAL var_p, IOTNAV_REAL var_v)
{
    x->p = p;
    x->v = v;
    x->pp = var_p;
    x->pv = R(0.0);
    x->vv = var_v;
}

static void predict_all(fixes_axis *kf, IOTNAV_REAL dt, IOTNAV_REAL q_h, IOTNAV_REAL q_v)
{
    predict_axis(&kf[AX_N], dt, q_h);
    predict_axis(&kf[AX_E], dt, q_h);
    predict_axis(&kf[AX_D], dt, q_v);
}

static void copy_axes(fixes_axis *dst, const fixes_axis *src)
{
    int a;
    for (a = 0; a < 3; ++a) dst[a] = src[a];
}

/* lowpass3.lowpass3_reset */
static void lowpass_reset(fixes_state *st)
{
    st->lp_k1 = st->lp_k2 = st->lp_k3 = st->lp_since2 = 0;
    st->have_lp = 0;
}

/* lowpass3._level_mean */
static void level_mean(fixes_state *st, IOTNAV_REAL (*buf)[3], int m)
{
    int c, i;
    for (c = 0; c < 3; ++c) {
        IOTNAV_REAL acc = R(0.0);
        for (i = 0; i < m; ++i) acc += buf[i][c];
        st->lp_out[c] = acc / (IOTNAV_REAL)m;
    }
    st->have_lp = 1;
}

/* lowpass3.lowpass3_push: 1 when the output changed */
static int lowpass_push(fixes_state *st, IOTNAV_REAL r0, IOTNAV_REAL r1, IOTNAV_REAL r2)
{
    int n1 = (int)st->cfg.lp_n1, n2 = (int)st->cfg.lp_n2, n3 = (int)st->cfg.lp_n3, k1 = st->lp_k1, c, i;
    int k2, k3, since2;
    st->lp1[k1][0] = r0;
    st->lp1[k1][1] = r1;
    st->lp1[k1][2] = r2;
    k1 += 1;
    if (k1 < n1) {
        st->lp_k1 = k1;
        return 0;
    }
    st->lp_k1 = 0;
    k2 = st->lp_k2;
    for (c = 0; c < 3; ++c) {
        IOTNAV_REAL acc = R(0.0);
        for (i = 0; i < n1; ++i) acc += st->lp1[i][c];
        st->lp2[k2 % n2][c] = acc / (IOTNAV_REAL)n1;
    }
    k2 += 1;
    st->lp_k2 = k2;
    since2 = st->lp_since2 + 1;
    k3 = st->lp_k3;
    if (since2 >= n2) {
        since2 = 0;
        for (c = 0; c < 3; ++c) {
            IOTNAV_REAL acc = R(0.0);
            for (i = 0; i < n2; ++i) acc += st->lp2[i][c];
            st->lp3[k3 % n3][c] = acc / (IOTNAV_REAL)n2;
        }
        k3 += 1;
        st->lp_k3 = k3;
        st->lp_since2 = since2;
        level_mean(st, st->lp3, k3 < n3 ? k3 : n3);
        return 1;
    }
    st->lp_since2 = since2;
    if (k3 > 0) return 0;
    level_mean(st, st->lp2, k2 < n2 ? k2 : n2);
    return 1;
}

/* lowpass3.lowpass3_n_fixes */
static int lowpass_n_fixes(const fixes_state *st)
{
    int n1 = (int)st->cfg.lp_n1, n2 = (int)st->cfg.lp_n2, n3 = (int)st->cfg.lp_n3;
    if (st->lp_k3) return (st->lp_k3 < n3 ? st->lp_k3 : n3) * n2 * n1;
    if (st->lp_k2) return (st->lp_k2 < n2 ? st->lp_k2 : n2) * n1;
    return 0;
}

/* fixes_kernel.chi2_quantile_wh (Wilson-Hilferty 1931) */
static IOTNAV_REAL chi2_quantile_wh(IOTNAV_REAL dof, IOTNAV_REAL z)
{
    IOTNAV_REAL c = R(2.0) / (R(9.0) * dof), b = R(1.0) - c + z * IOTNAV_SQRT(c);
    return dof * b * b * b;
}

/* fixes_kernel._select: the k-th smallest of a[0 .. n-1], reordering a (Hoare's quickselect) */
static IOTNAV_REAL select_kth(IOTNAV_REAL *a, int n, int k)
{
    int lo = 0, hi = n - 1;
    while (lo < hi) {
        IOTNAV_REAL pivot = a[(lo + hi) / 2], tmp;
        int i = lo, j = hi;
        while (i <= j) {
            while (a[i] < pivot) ++i;
            while (a[j] > pivot) --j;
            if (i <= j) {
                tmp = a[i];
                a[i] = a[j];
                a[j] = tmp;
                ++i;
                --j;
            }
        }
        if (k <= j) {
            hi = j;
        } else if (k >= i) {
            lo = i;
        } else {
            break;
        }
    }
    return a[k];
}

/* fixes_kernel.median_inplace */
static IOTNAV_REAL median_inplace(IOTNAV_REAL *a, int n)
{
    int h = n / 2, i;
    IOTNAV_REAL upper = select_kth(a, n, h), lower;
    if (n % 2) return upper;
    lower = a[0];
    for (i = 1; i < h; ++i) lower = a[i] > lower ? a[i] : lower;
    return R(0.5) * (lower + upper);
}

static int ring_index(int32_t k) { return (int)(((k % FIXES_RING_MAX) + FIXES_RING_MAX) % FIXES_RING_MAX); }

/* fixes_kernel._spread_static: 1 consistent with standing still, 0 not, -1 undecided */
static int spread_static(fixes_state *st, iotnav_time t)
{
    const fixes_config *p = &st->cfg;
    int m = st->ring_n < FIXES_RING_MAX ? (int)st->ring_n : FIXES_RING_MAX, cnt = 0, j, used = 0;
    IOTNAV_REAL cn, ce, mn = R(0.0), me = R(0.0), chi = R(0.0);
    if (m < 2) return -1;
    for (j = 0; j < m; ++j) {
        const fixes_fix *f = &st->ring[ring_index(st->ring_n - 1 - j)];
        if (iotnav_time_diff(t, f->t) > p->window_s && (IOTNAV_REAL)cnt >= p->min_fixes) break;
        ++cnt;
    }
    if ((IOTNAV_REAL)cnt < p->min_fixes) return -1;
    if (cnt == m && iotnav_time_diff(t, st->ring[ring_index(st->ring_n - cnt)].t) < p->window_s) return -1;
    for (j = 0; j < cnt; ++j) {
        const fixes_fix *f = &st->ring[ring_index(st->ring_n - 1 - j)];
        st->work_n[j] = f->n;
        st->work_e[j] = f->e;
    }
    cn = median_inplace(st->work_n, cnt);
    ce = median_inplace(st->work_e, cnt);
    for (j = 0; j < cnt; ++j) {
        const fixes_fix *f = &st->ring[ring_index(st->ring_n - 1 - j)];
        IOTNAV_REAL dn = f->n - cn, de = f->e - ce;
        if ((dn * dn + de * de) / f->s2 <= R(FIXES_SPREAD_OUT)) {
            mn += f->n;
            me += f->e;
            ++used;
            st->work_n[j] = R(1.0); /* keep */
        } else {
            st->work_n[j] = R(0.0);
        }
    }
    if ((IOTNAV_REAL)used < p->min_fixes) return 0;
    mn /= (IOTNAV_REAL)used;
    me /= (IOTNAV_REAL)used;
    for (j = 0; j < cnt; ++j) {
        if (st->work_n[j] != R(0.0)) {
            const fixes_fix *f = &st->ring[ring_index(st->ring_n - 1 - j)];
            IOTNAV_REAL dn = f->n - mn, de = f->e - me;
            chi += (dn * dn + de * de) / f->s2;
        }
    }
    return chi <= chi2_quantile_wh(R(2.0) * (IOTNAV_REAL)(used - 1), p->spread_z) ? 1 : 0;
}

/* fixes_kernel._measured_velocity: 1 and v[0..2] (vd may be NaN), or 0 */
static int measured_velocity(const fixes_config *p, const fixes_gnss_in *in, IOTNAV_REAL *v)
{
    IOTNAV_REAL sp = in->speed_mps;
    if (isfinite(in->vn) && isfinite(in->ve)) {
        v[0] = in->vn;
        v[1] = in->ve;
        v[2] = in->vd;
        return 1;
    }
    if (in->course_valid != 0 && isfinite(sp) && sp >= p->min_course_speed && isfinite(in->course_rad)) {
        v[0] = sp * IOTNAV_COS(in->course_rad);
        v[1] = sp * IOTNAV_SIN(in->course_rad);
        v[2] = NAN_R;
        return 1;
    }
    v[0] = v[1] = v[2] = NAN_R;
    return 0;
}

static IOTNAV_REAL velocity_variance(const fixes_config *p, const fixes_gnss_in *in)
{
    IOTNAV_REAL sv = iotnav_positive(in->s_acc_mps) ? in->s_acc_mps : p->vel_sigma;
    return sv * sv;
}

/* fixes_kernel._init_filter at (n, e, d) with the fix's variances rh (north/east) and rv (down) */
static void init_filter(fixes_state *st, const fixes_gnss_in *in, iotnav_time t, IOTNAV_REAL n, IOTNAV_REAL e,
                        IOTNAV_REAL d, IOTNAV_REAL rh, IOTNAV_REAL rv)
{
    const fixes_config *p = &st->cfg;
    IOTNAV_REAL v[3], s2 = velocity_variance(p, in), v0 = p->init_vel_std * p->init_vel_std;
    int have_v = measured_velocity(p, in, v);
    init_axis(&st->kf[AX_N], n, have_v ? v[0] : R(0.0), rh, have_v ? s2 : v0);
    init_axis(&st->kf[AX_E], e, have_v ? v[1] : R(0.0), rh, have_v ? s2 : v0);
    if (isfinite(d)) {
        int have_vd = isfinite(v[2]);
        init_axis(&st->kf[AX_D], d, have_vd ? v[2] : R(0.0), rv, have_vd ? s2 : v0);
        st->have_d = 1;
    } else {
        init_axis(&st->kf[AX_D], R(0.0), R(0.0), R(1e12), v0);
        st->have_d = 0;
    }
    st->init = 1;
    st->t_x = t;
    st->t_fix = t;
    st->n_rej = R(0.0);
    st->cand_n = 0;
    st->ring_n = 0;
    st->is_static = 0;
    st->snap = 0;
    st->floor_v[0] = st->floor_v[1] = rh;
    lowpass_reset(st);
}

static int same_coordinates(const fixes_state *st, const fixes_gnss_in *in)
{
    return in->lat_e7 == st->lat_last_e7 && in->lat_frac_e7 == st->lat_last_frac &&
           in->lon_e7 == st->lon_last_e7 && in->lon_frac_e7 == st->lon_last_frac;
}

/* fixes_kernel.screen_epoch: FIXES_R_*; *clock_change (s) when the UTC reference moved */
static int screen_epoch(fixes_state *st, const fixes_gnss_in *in, int *clock_event, IOTNAV_REAL *clock_change)
{
    const fixes_config *p = &st->cfg;
    *clock_event = 0;
    if (st->have_t_last) {
        IOTNAV_REAL dt = iotnav_time_diff(in->t, st->t_last);
        if (dt < R(0.0)) return FIXES_R_BACKWARDS;
        if (dt == R(0.0)) return same_coordinates(st, in) ? FIXES_R_DUPLICATE : FIXES_R_REPEAT;
    }
    if (in->has_utc && isfinite(in->utc.frac)) {
        iotnav_time off;
        off.s = in->utc.s - in->t.s;
        off.frac = in->utc.frac - in->t.frac;
        if (!st->have_off) {
            st->off_ref = off;
            st->have_off = 1;
        } else {
            IOTNAV_REAL d = iotnav_time_diff(off, st->off_ref);
            if (d > p->clock_tol || d < -p->clock_tol) {
                IOTNAV_REAL dc = iotnav_time_diff(off, st->off_cand);
                if (st->off_n > 0 && dc <= p->clock_tol && dc >= -p->clock_tol) {
                    st->off_n += 1;
                } else {
                    st->off_n = 1;
                    st->off_cand = off;
                }
                if ((IOTNAV_REAL)st->off_n < p->reloc_n) return d > R(0.0) ? FIXES_R_FUTURE : FIXES_R_PAST;
                *clock_change = iotnav_time_diff(off, st->off_ref);
                *clock_event = 1;
                st->off_ref = off; /* consistent epochs: the reference was wrong */
                st->off_n = 0;
            } else {
                st->off_n = 0;
            }
        }
    }
    st->t_last = in->t;
    st->have_t_last = 1;
    st->lat_last_e7 = in->lat_e7;
    st->lon_last_e7 = in->lon_e7;
    st->lat_last_frac = in->lat_frac_e7;
    st->lon_last_frac = in->lon_frac_e7;
    if (in->valid == 0 || !(isfinite(in->lat_frac_e7) && isfinite(in->lon_frac_e7))) return FIXES_R_INVALID;
    if (in->lat_e7 == 0 && in->lat_frac_e7 == R(0.0) && in->lon_e7 == 0 && in->lon_frac_e7 == R(0.0)) {
        return FIXES_R_ZERO;
    }
    if (isfinite(in->pdop)) {
        if (in->pdop > p->max_pdop) return FIXES_R_PDOP;
    } else if (p->accept_unknown_pdop == R(0.0)) {
        return FIXES_R_PDOP_UNKNOWN;
    }
    if (p->min_sv > R(0.0) && (IOTNAV_REAL)in->num_sv < p->min_sv) return FIXES_R_NUM_SV;
    return FIXES_R_OK;
}

/* LastPositionLogic.check_fix's settling gate (no stored position): 1 when the fix must wait */
static int settling(fixes_state *st, const fixes_gnss_in *in)
{
    const fixes_config *p = &st->cfg;
    IOTNAV_REAL w = p->settle_window_s, pdop = in->pdop, mx = R(0.0);
    int covered, keep = 0, i, have_recent = 0, falling;
    if (st->first_fix_seen || !(p->settle_ratio > R(0.0)) || !isfinite(pdop)) return 0;
    covered = st->settle_n > 0 && iotnav_time_diff(in->t, st->settle_t[0]) >= w - R(1e-9);
    for (i = 0; i < st->settle_n; ++i) {
        IOTNAV_REAL age = iotnav_time_diff(in->t, st->settle_t[i]);
        if (age <= w + R(1e-9)) { /* tk >= t - window - 1e-9: kept */
            if (age > R(0.0)) {   /* tk < t: recent */
                mx = have_recent && mx >= st->settle_pdop[i] ? mx : st->settle_pdop[i];
                have_recent = 1;
            }
            st->settle_t[keep] = st->settle_t[i];
            st->settle_pdop[keep] = st->settle_pdop[i];
            ++keep;
        }
    }
    if (keep == FIXES_SETTLE_MAX) { /* full: the oldest goes (counted; fixes_config.h) */
        for (i = 1; i < keep; ++i) {
            st->settle_t[i - 1] = st->settle_t[i];
            st->settle_pdop[i - 1] = st->settle_pdop[i];
        }
        --keep;
        st->settle_dropped += 1;
    }
    st->settle_t[keep] = in->t;
    st->settle_pdop[keep] = pdop;
    st->settle_n = keep + 1;
    falling = have_recent && pdop < (R(1.0) - p->settle_ratio) * mx;
    return falling || (!covered && pdop > p->settle_max_pdop);
}

/* TangentPlane(lat, lon, h) of the first fix */
static void set_frame(fixes_state *st, const fixes_gnss_in *in)
{
    st->lat0_e7 = in->lat_e7;
    st->lon0_e7 = in->lon_e7;
    st->lat0_frac = in->lat_frac_e7;
    st->lon0_frac = in->lon_frac_e7;
    st->h0 = isfinite(in->height_m) ? in->height_m : R(0.0);
    iotnav_plane_scales(in->lat_e7, in->lat_frac_e7, st->h0, &st->k_n, &st->k_e);
    st->inv_k_n = R(1.0) / st->k_n;
    st->inv_k_e = R(1.0) / st->k_e;
    st->have_frame = 1;
}

/* fixes_departure._not_jump: the departure test's fix (n, e) at t is no jump */
static void not_jump(fixes_state *st, IOTNAV_REAL n, IOTNAV_REAL e, iotnav_time t)
{
    st->good_n = n;
    st->good_e = e;
    st->good_t = t;
    st->in_jump = 0;
}

/* fixes_departure._departed: the departure test of a parked device at the fix (n, e), variance rh */
static int departed(fixes_state *st, const fixes_gnss_in *in, iotnav_time t, IOTNAV_REAL n, IOTNAV_REAL e,
                    IOTNAV_REAL rh, IOTNAV_REAL step_dt)
{
    const fixes_config *p = &st->cfg;
    const fixes_axis *kf = st->kf;
    IOTNAV_REAL hn = st->have_lp ? st->lp_out[0] : st->hold[0], he = st->have_lp ? st->lp_out[1] : st->hold[1];
    IOTNAV_REAL dn = n - hn, de = e - he, sn2 = kf[AX_N].pp + rh, se2 = kf[AX_E].pp + rh, sp = in->speed_mps;
    IOTNAV_REAL dt, d, span, gn, ge;
    int displaced = dn * dn / sn2 + de * de / se2 > p->dep_gate;
    if (!displaced && !(isfinite(sp) && sp > p->exit_speed)) {
        st->dep_n = R(0.0);
        st->t_still = t;
        st->dep_vmax = isfinite(sp) ? sp : R(0.0);
        st->dep_d0 = IOTNAV_SQRT(dn * dn + de * de);
        not_jump(st, n, e, t);
        return 0;
    }
    if (!displaced) not_jump(st, n, e, t); /* a fast fix inside the bound */
    dt = iotnav_time_diff(t, st->t_still);
    if (dt >= p->lp_tau) return 1; /* displaced (or fast) for longer than the errors' correlation time */
    if (isfinite(sp)) st->dep_vmax = sp > st->dep_vmax ? sp : st->dep_vmax;
    d = IOTNAV_SQRT(dn * dn + de * de);
    if (displaced) { /* reachable from inside the bound since the last still fix? else a jump */
        IOTNAV_REAL b = IOTNAV_SQRT(p->dep_gate * (sn2 > se2 ? sn2 : se2)), reach, vm;
        int jump;
        if (isfinite(sp)) {
            IOTNAV_REAL sa = isfinite(in->s_acc_mps) ? in->s_acc_mps : R(0.0);
            vm = st->dep_vmax + R(3.0) * (sa > p->vel_sigma ? sa : p->vel_sigma);
            reach = b + vm * dt;
        } else {
            vm = IOTNAV_SQRT(R(2.0) * p->dep_acc * b);
            reach = b + vm * dt + R(0.5) * p->dep_acc * dt * dt;
        }
        jump = d > reach;
        if (!jump) { /* the step from the last fix that was no jump, or from the latest jump fix */
            IOTNAV_REAL dtj = iotnav_time_diff(t, st->jump_t), dtg = iotnav_time_diff(t, st->good_t);
            IOTNAV_REAL lim_j = IOTNAV_SQRT(R(2.0) * p->dep_gate * rh * (R(1.0) - EXP(-dtj / p->lp_tau))) + vm * dtj;
            IOTNAV_REAL lim_g = IOTNAV_SQRT(R(2.0) * p->dep_gate * rh * (R(1.0) - EXP(-dtg / p->lp_tau))) + vm * dtg;
            IOTNAV_REAL jn = n - st->jump_n, je = e - st->jump_e, qn = n - st->good_n, qe = e - st->good_e;
            if (st->in_jump && IOTNAV_SQRT(jn * jn + je * je) <= lim_j) {
                jump = 1; /* it goes on from the jump fix before: the same outlier */
            } else if (IOTNAV_SQRT(qn * qn + qe * qe) > lim_g) {
                jump = 1; /* a step off the fixes before */
            }
        }
        if (jump) { /* only a full run decides until the next still fix */
            st->jump_n = n;
            st->jump_e = e;
            st->jump_t = t;
            st->in_jump = 1;
            st->dep_n = R(0.0);
            st->dep_d0 = (IOTNAV_REAL)INFINITY;
            return 0;
        }
        not_jump(st, n, e, t);
    }
    if (st->dep_n == R(0.0)) {
        st->dep_t = t;
        st->dep_pn = n;
        st->dep_pe = e;
    }
    st->dep_n += R(1.0);
    span = iotnav_time_diff(t, st->dep_t);
    if (st->dep_n >= p->exit_run && span > R(0.0)) {
        gn = st->dep_pn - hn;
        ge = st->dep_pe - he;
        return d - IOTNAV_SQRT(gn * gn + ge * ge) >= p->speed_thr * span;
    }
    if (dt >= p->exit_run) { /* sparse fixes: as long as the run would take at 1 Hz */
        if (step_dt >= p->exit_run && isfinite(sp) && sp > p->exit_speed) return 1; /* a lone fast fix */
        return d - st->dep_d0 >= p->speed_thr * dt;
    }
    return 0;
}

/* the static decision of fixes_kernel (evidence and no veto; parked: the departure test, which
 * re-initialises the filter at a departure and sets *segment); updates the speed run */
static int static_decision(fixes_state *st, const fixes_gnss_in *in, iotnav_time t, int was, int *segment,
                           int32_t acc_n, IOTNAV_REAL acc_s1, IOTNAV_REAL acc_s2, IOTNAV_REAL n,
                           IOTNAV_REAL e, IOTNAV_REAL d, IOTNAV_REAL rh, IOTNAV_REAL rv, IOTNAV_REAL step_dt,
                           fixes_output_t *out)
{
    const fixes_config *p = &st->cfg;
    IOTNAV_REAL sp = in->speed_mps, thr = p->speed_thr, acc_std = NAN_R;
    int veto, evidence, spread, moved;
    if (acc_n >= 2) {
        IOTNAV_REAL m1 = acc_s1 / (IOTNAV_REAL)acc_n, var = acc_s2 / (IOTNAV_REAL)acc_n - m1 * m1;
        acc_std = IOTNAV_SQRT(var > R(0.0) ? var : R(0.0));
    }
    if (isfinite(sp) && sp > p->speed_thr) {
        st->speed_run += R(1.0);
    } else {
        st->speed_run = R(0.0);
    }
    moved = in->motion == 1 || (isfinite(acc_std) && acc_std > p->acc_move);
    if (was && !*segment) {
        if (departed(st, in, t, n, e, rh, step_dt) && !moved) {
            IOTNAV_REAL span = st->dep_n > R(0.0) ? iotnav_time_diff(t, st->dep_t) : R(0.0), v[3];
            IOTNAV_REAL pn = st->dep_pn, pe = st->dep_pe;
            init_filter(st, in, t, n, e, d, rh, rv);
            if (span > R(0.0) && !measured_velocity(p, in, v)) {
                IOTNAV_REAL vn = (n - pn) / span, ve = (e - pe) / span;
                if (isfinite(sp)) { /* no faster than the departure's reach allows (reported speeds) */
                    IOTNAV_REAL sa = isfinite(in->s_acc_mps) ? in->s_acc_mps : R(0.0), vr = IOTNAV_SQRT(vn * vn + ve * ve);
                    IOTNAV_REAL f = (st->dep_vmax + R(3.0) * (sa > p->vel_sigma ? sa : p->vel_sigma)) /
                                    (vr > R(1e-9) ? vr : R(1e-9));
                    if (f < R(1.0)) {
                        vn *= f;
                        ve *= f;
                    }
                }
                st->kf[AX_N].v = vn;
                st->kf[AX_E].v = ve;
            }
            out->events &= ~FIXES_EV_REJECT;
            out->events |= FIXES_EV_DEPART;
            out->event_value = span;
            *segment = 1;
            /* after every departure the next static period needs more than one slow fix (below) */
            st->dep_n = R(-1.0);
        }
        return !moved && !*segment;
    }
    if (was) return 0;
    veto = (isfinite(sp) && sp > thr) || st->speed_run >= p->exit_run || moved;
    spread = veto ? -1 : spread_static(st, t);
    veto = veto || spread == 0;
    evidence = (isfinite(sp) && sp < thr) || in->motion == 0 || in->ignition == 0 || spread == 1 ||
               (isfinite(acc_std) && acc_std < p->acc_thr);
    if (st->dep_n < R(0.0)) { /* since a departure: exit_run fixes with static evidence */
        int ok = evidence && !veto && !*segment;
        if (ok) st->dep_n -= R(1.0);
        return ok && (spread == 1 || -st->dep_n - R(1.0) >= p->exit_run);
    }
    return evidence && !veto && !*segment;
}

/* the measurement updates of an accepted fix (fixes_kernel, "measurement updates") */
static int update_fix(fixes_state *st, const fixes_gnss_in *in, iotnav_time t, int is_static, int was,
                      IOTNAV_REAL n, IOTNAV_REAL e, IOTNAV_REAL d, IOTNAV_REAL rh, IOTNAV_REAL rv)
{
    const fixes_config *p = &st->cfg;
    fixes_axis *kf = st->kf;
    int have_d = isfinite(d), src, a;
    if (have_d && !st->have_d) {
        init_axis(&kf[AX_D], d, R(0.0), rv, p->init_vel_std * p->init_vel_std);
        st->have_d = 1;
        have_d = 0; /* the fix's height is in the reset */
    }
    if (is_static) {
        src = FIXES_SRC_LOWPASS;
        if (!was) { /* the fix that starts a static period still counts as a fix */
            update_axis(&kf[AX_N], 0, n, rh);
            update_axis(&kf[AX_E], 0, e, rh);
            if (have_d) update_axis(&kf[AX_D], 0, d, rv);
        }
        for (a = 0; a < 3; ++a) update_axis(&kf[a], 1, R(0.0), p->zupt * p->zupt);
        if (p->use_lowpass != R(0.0) && lowpass_push(st, n, e, isfinite(d) ? d : kf[AX_D].p)) {
            IOTNAV_REAL since = iotnav_time_diff(t, st->t_fix), dt_fix, n_eff;
            dt_fix = since > R(0.0) && since <= R(2.5) ? since : R(1.0);
            n_eff = R(1.0) + (IOTNAV_REAL)lowpass_n_fixes(st) * dt_fix / (R(2.0) * p->lp_tau);
            st->lp_var = rh / n_eff;
            update_axis(&kf[AX_N], 0, st->lp_out[0], rh / n_eff);
            update_axis(&kf[AX_E], 0, st->lp_out[1], rh / n_eff);
            if (isfinite(d) && st->have_d) update_axis(&kf[AX_D], 0, st->lp_out[2], rv / n_eff);
        }
    } else {
        IOTNAV_REAL v[3];
        src = FIXES_SRC_FIX;
        update_axis(&kf[AX_N], 0, n, rh);
        update_axis(&kf[AX_E], 0, e, rh);
        if (have_d) update_axis(&kf[AX_D], 0, d, rv);
        if (measured_velocity(p, in, v) && p->use_vel != R(0.0)) {
            IOTNAV_REAL r = velocity_variance(p, in), y0 = v[0] - kf[AX_N].v, y1 = v[1] - kf[AX_E].v;
            IOTNAV_REAL nv = y0 * y0 / (kf[AX_N].vv + r) + y1 * y1 / (kf[AX_E].vv + r);
            if (nv <= p->vel_gate) {
                update_axis(&kf[AX_N], 1, v[0], r);
                update_axis(&kf[AX_E], 1, v[1], r);
                if (isfinite(v[2]) && st->have_d) update_axis(&kf[AX_D], 1, v[2], r);
            }
        }
    }
    st->t_fix = t;
    st->n_used += R(1.0);
    st->floor_v[0] = st->floor_v[1] = rh;
    return src;
}

/* a rejected fix (fixes_kernel): the relocation candidates, relocation or forced reset;
 * 1 when the filter was re-initialised */
static int reject_fix(fixes_state *st, const fixes_gnss_in *in, iotnav_time t, IOTNAV_REAL n, IOTNAV_REAL e,
                      IOTNAV_REAL d, IOTNAV_REAL rh, IOTNAV_REAL rv, IOTNAV_REAL yn, IOTNAV_REAL ye,
                      fixes_output_t *out)
{
    const fixes_config *p = &st->cfg;
    int c = st->cand_n, j, reloc, forced;
    st->n_rej += R(1.0);
    if (c > 0) { /* consistent with the previous rejected fix? */
        const fixes_fix *f = &st->cand[c - 1];
        IOTNAV_REAL tol = IOTNAV_SQRT(p->gate * (rh + f->s2)) + p->max_speed * iotnav_time_diff(t, f->t);
        IOTNAV_REAL dn = n - f->n, de = e - f->e;
        if (IOTNAV_SQRT(dn * dn + de * de) > tol) c = 0;
    }
    if (c >= FIXES_CAND_MAX) {
        for (j = 0; j < FIXES_CAND_MAX - 1; ++j) st->cand[j] = st->cand[j + 1];
        c = FIXES_CAND_MAX - 1;
    }
    st->cand[c].t = t;
    st->cand[c].n = n;
    st->cand[c].e = e;
    st->cand[c].d = d;
    st->cand[c].s2 = rh;
    c += 1;
    st->cand_n = c;
    /* while parked a relocation is a departure: the departure test decides */
    reloc = !st->is_static && (IOTNAV_REAL)c >= p->reloc_n && iotnav_time_diff(t, st->cand[0].t) >= p->reloc_min_s;
    forced = !st->is_static && st->n_rej >= p->max_rej;
    if (!(reloc || forced)) return 0;
    {
        IOTNAV_REAL jump = IOTNAV_SQRT(yn * yn + ye * ye), span = iotnav_time_diff(t, st->cand[0].t);
        IOTNAV_REAL n0 = st->cand[0].n, e0 = st->cand[0].e;
        init_filter(st, in, t, n, e, d, rh, rv);
        if (reloc && c >= 2 && span > R(0.0)) {
            st->kf[AX_N].v = (n - n0) / span;
            st->kf[AX_E].v = (e - e0) / span;
        }
        out->events |= reloc ? FIXES_EV_RELOCATE : FIXES_EV_FORCED;
        out->event_value = jump;
    }
    return 1;
}

/* the output row (fixes_kernel, "output row"; base.write_position) */
static void write_row(const fixes_state *st, int is_static, int src, fixes_output_t *out)
{
    const fixes_axis *kf = st->kf;
    IOTNAV_REAL dlat, dlon, flat, flon, pv, sn, se;
    int a;
    for (a = 0; a < 3; ++a) {
        out->r_n[a] = is_static ? (st->have_lp ? st->lp_out[a] : st->hold[a]) : kf[a].p;
        out->v_n[a] = is_static ? R(0.0) : kf[a].v;
    }
    /* parked on the low-pass: no surer than its own variance; never than the last fix's own */
    pv = is_static && st->have_lp ? st->lp_var : R(0.0);
    sn = kf[AX_N].pp > pv ? kf[AX_N].pp : pv;
    se = kf[AX_E].pp > pv ? kf[AX_E].pp : pv;
    out->std_north = IOTNAV_SQRT(sn > st->floor_v[0] ? sn : st->floor_v[0]);
    out->std_east = IOTNAV_SQRT(se > st->floor_v[1] ? se : st->floor_v[1]);
    dlat = out->r_n[0] * st->inv_k_n + st->lat0_frac;
    dlon = out->r_n[1] * st->inv_k_e + st->lon0_frac;
    flat = IOTNAV_FLOOR(dlat);
    flon = IOTNAV_FLOOR(dlon);
    out->lat_e7 = st->lat0_e7 + (int32_t)flat;
    out->lon_e7 = st->lon0_e7 + (int32_t)flon;
    out->lat_frac_e7 = dlat - flat;
    out->lon_frac_e7 = dlon - flon;
    out->height_m = st->h0 - out->r_n[2];
    out->has_down = st->have_d;
    if (!st->have_d) out->height_m = out->r_n[2] = out->v_n[2] = NAN_R;
    out->is_static = is_static;
    out->source = src;
}

int fixes_step_gnss(fixes_state *st, const fixes_gnss_in *in, fixes_output_t *out)
{
    const fixes_config *p = &st->cfg;
    fixes_axis *kf = st->kf, prior[3];
    iotnav_time t = in->t;
    int32_t acc_n = st->acc_n;
    IOTNAV_REAL acc_s1 = st->acc_s1, acc_s2 = st->acc_s2, rh, rv, n, e, d, clock_change = R(0.0);
    IOTNAV_REAL step_dt = R(0.0); /* s since the previous epoch (the prediction's dt) */
    int reason, clock_event, is_static = 0, src = FIXES_SRC_FIX, was, accepted, segment = 0, rollback = 0;
    out->events = 0;
    out->event_value = NAN_R;
    /* FixesEngine.step: the InputGuard rule, then the accelerometer sums of this epoch */
    if (!isfinite(t.frac) || (in->valid && !(isfinite(in->lat_frac_e7) && isfinite(in->lon_frac_e7)))) {
        return FIXES_R_NONFINITE;
    }
    st->acc_n = 0;
    st->acc_s1 = st->acc_s2 = R(0.0);
    iotnav_position_variances(p->uere_m, p->default_hdop, in->h_acc_m, in->v_acc_m, in->hdop, in->pdop, &rh,
                              &rv);
    reason = screen_epoch(st, in, &clock_event, &clock_change);
    if (clock_event) {
        out->events |= FIXES_EV_CLOCK;
        out->event_value = clock_change;
    }
    if (reason != FIXES_R_OK) return reason;
    if (!st->init) {
        /* FixesEngine._boot_decision without a stored position: the settling gate, the origin */
        if (settling(st, in)) return FIXES_R_SETTLING;
        st->first_fix_seen = 1;
        if (!st->have_frame) set_frame(st, in);
        out->events |= FIXES_EV_FIRST_FIX;
    }
    n = ((IOTNAV_REAL)(in->lat_e7 - st->lat0_e7) + (in->lat_frac_e7 - st->lat0_frac)) * st->k_n;
    e = ((IOTNAV_REAL)(in->lon_e7 - st->lon0_e7) + (in->lon_frac_e7 - st->lon0_frac)) * st->k_e;
    d = st->h0 - in->height_m;
    if (!st->init) {
        init_filter(st, in, t, n, e, d, rh, rv);
        out->events |= FIXES_EV_INIT;
        st->n_used += R(1.0);
        write_row(st, 0, FIXES_SRC_FIX, out);
        return FIXES_R_OK;
    }
    {
        /* predict (q raised after rejections: manoeuvre; none while parked: hold) */
        IOTNAV_REAL dt = iotnav_time_diff(t, st->t_x), qf = R(1.0) + (p->reject_qf - R(1.0)) * st->n_rej;
        step_dt = dt;
        IOTNAV_REAL q_gate, yn, ye, nis;
        int hold = st->is_static && in->motion != 1;
        q_gate = hold && dt > R(0.0) ? p->q_h * dt * dt * dt / R(3.0) : R(0.0);
        if (hold) qf = R(0.0);
        if (dt > R(0.0)) {
            /* the floor grows as P_pp does (fixes_kernel S_FLOOR_N / S_FLOOR_E) */
            IOTNAV_REAL g_n = st->floor_v[0] - kf[AX_N].pp, g_e = st->floor_v[1] - kf[AX_E].pp;
            predict_all(kf, dt, p->q_h * qf, p->q_v * qf);
            st->t_x = t;
            st->floor_v[0] = kf[AX_N].pp + g_n;
            st->floor_v[1] = kf[AX_E].pp + g_e;
        }
        copy_axes(prior, kf);
        was = st->is_static;
        yn = n - kf[AX_N].p;
        ye = e - kf[AX_E].p;
        nis = yn * yn / (kf[AX_N].pp + q_gate + rh) + ye * ye / (kf[AX_E].pp + q_gate + rh);
        accepted = nis <= p->gate;
        if (!was && st->snap && iotnav_time_diff(t, st->snap_t) > p->rollback_s) st->snap = 0;
        if (!accepted && !was && st->snap) {
            /* rejected here, but consistent with the state before the doubtful fixes? */
            fixes_axis snap[3];
            IOTNAV_REAL dts = iotnav_time_diff(t, st->snap_t), sn, se, sn2, se2, nis_s, sc2, se2c;
            copy_axes(snap, st->snap_x);
            if (dts > R(0.0)) predict_all(snap, dts, p->q_h, p->q_v);
            sn = n - snap[AX_N].p;
            se = e - snap[AX_E].p;
            sn2 = snap[AX_N].pp + rh;
            se2 = snap[AX_E].pp + rh;
            nis_s = sn * sn / sn2 + se * se / se2;
            sc2 = kf[AX_N].pp + q_gate + rh;
            se2c = kf[AX_E].pp + q_gate + rh;
            if (nis_s <= p->gate && nis_s + IOTNAV_LOG(sn2 * se2) < nis + IOTNAV_LOG(sc2 * se2c)) {
                copy_axes(kf, snap);
                copy_axes(prior, snap);
                st->snap = 0;
                accepted = 1;
                rollback = 1;
                out->events |= FIXES_EV_ROLLBACK;
                out->event_value = nis_s;
            }
        }
        if (accepted) {
            IOTNAV_REAL v[3];
            int doubtful = (nis > p->soft_gate || st->n_rej > R(0.0)) && st->n_rej < p->reloc_n;
            if (doubtful && measured_velocity(p, in, v)) doubtful = 0;
            if (!was && !st->snap && doubtful && !rollback) {
                copy_axes(st->snap_x, prior);
                st->snap_t = t;
                st->snap = 1;
            }
            st->n_rej = R(0.0);
            st->cand_n = 0;
        } else {
            out->events |= FIXES_EV_REJECT;
            out->event_value = nis;
            segment = reject_fix(st, in, t, n, e, d, rh, rv, yn, ye, out);
        }
    }
    /* static decision; while static every fix counts for the spread test */
    is_static = was;
    if (accepted || segment || was) {
        if (!segment) {
            fixes_fix *f = &st->ring[ring_index(st->ring_n)];
            f->t = t;
            f->n = n;
            f->e = e;
            f->d = d;
            f->s2 = rh;
            st->ring_n += 1;
        }
        is_static =
            static_decision(st, in, t, was, &segment, acc_n, acc_s1, acc_s2, n, e, d, rh, rv, step_dt, out);
    }
    if (is_static != was) {
        st->is_static = is_static;
        st->in_jump = 0; /* the departure test's jump tracking starts afresh */
        out->events |= is_static ? FIXES_EV_STATIC_START : FIXES_EV_STATIC_END;
        lowpass_reset(st);
    }
    src = FIXES_SRC_DR;
    if (!segment && accepted) {
        src = update_fix(st, in, t, is_static, was, n, e, d, rh, rv);
    } else if (segment) {
        src = FIXES_SRC_FIX;
        st->t_fix = t;
        st->n_used += R(1.0);
    } else if (is_static) {
        src = FIXES_SRC_LOWPASS;
    }
    if (is_static && !was) {
        st->hold[0] = kf[AX_N].p;
        st->hold[1] = kf[AX_E].p;
        st->hold[2] = kf[AX_D].p;
        st->dep_n = R(0.0);
        st->t_still = t;
        st->dep_vmax = R(0.0);
    }
    write_row(st, is_static, src, out);
    return FIXES_R_OK;
}

/* sizeof of the API structs (0 state, 1 config, 2 GNSS input, 3 output); 0 for another `which`. */
int32_t fixes_sizeof(int32_t which)
{
    switch (which) {
    case 0: return (int32_t)sizeof(fixes_state);
    case 1: return (int32_t)sizeof(fixes_config);
    case 2: return (int32_t)sizeof(fixes_gnss_in);
    case 3: return (int32_t)sizeof(fixes_output_t);
    default: return 0;
    }
}
