/* The Forno pipeline's blocks 1-6 as one engine in C99 (see pipeline.h and
 * iotnav.engines.pipeline): every function names the Python code it mirrors. */
#include <math.h>

#include "iotnav_common.h"
#include "pipeline.h"

#define R IOTNAV_R
#ifdef IOTNAV_REAL_DOUBLE
#define ATAN2 atan2
#define ASIN asin
#define HYPOT hypot
#else
#define ATAN2 atan2f
#define ASIN asinf
#define HYPOT hypotf
#endif

enum { G_IMU = 0, G_GNSS = 1, G_MAG = 2 };

static IOTNAV_REAL tdiff(iotnav_time a, iotnav_time b) { return iotnav_time_diff(a, b); }

int pl_init(pl_state *st, const pl_pipeline_config *cfg)
{
    int rc, i;
    const pl_engine_config *e = &cfg->pipeline;
    st->cfg = *cfg;
    if (cfg->fusion.smoothing) return PL_ERR_UNSUPPORTED; /* the RTS smoother's log is not in C */
    /* a gate probability without its chi-square quantile (the C cannot compute it) */
    if (cfg->fusion.gate_probability > R(0.0) && !(cfg->fusion_gate_nis > R(0.0))) return PL_ERR_UNSUPPORTED;
    rc = pl_cascade_init(&st->att, &cfg->gyro_bias, &cfg->tilt, &cfg->yaw, cfg->yaw_gate_nis);
    if (rc != PL_OK) return rc;
    if (pl_static_init(&st->det, &cfg->static_case) != PL_OK) return PL_ERR_UNSUPPORTED;
    if (pl_lowpass3_init(&st->lp, &cfg->lowpass3) != PL_OK) return PL_ERR_UNSUPPORTED;
    pl_lastpos_init(&st->boot, &cfg->last_position, 0, R(NAN), R(NAN));
    if (pl_mount_init(&st->mount, &cfg->mount) != PL_MOUNT_OK) return PL_ERR_UNSUPPORTED;
    if (pl_fusion_init(&st->fus, &cfg->fusion, cfg->fusion_gate_nis) != PL_FUSION_OK) return PL_ERR_UNSUPPORTED;
    st->have_frame = st->origin_2d = st->has_stored = 0;
    st->plane.n_anchors = 0;
    st->has_t_prev = st->is_static = 0;
    st->t_prev.s = 0;
    st->t_prev.frac = R(0.0);
    st->a_long = st->v_gnss = R(0.0);
    st->g = e->gravity_mps2 > R(0.0) ? e->gravity_mps2 : R(PL_G_STD);
    st->t_speed.s = 0;
    st->t_speed.frac = -(IOTNAV_REAL)INFINITY;
    st->t_fix = st->t_boot_move = st->t_gnss = st->t_prev;
    st->has_t_fix = st->has_boot_move = st->has_t_gnss = 0;
    for (i = 0; i < 3; ++i) {
        st->guard_t[i] = st->t_prev;
        st->guard_has[i] = 0;
    }
    for (i = 0; i < PL_N_SKIP; ++i) st->n_skipped[i] = 0u;
    st->fix_reason = PL_FIX_OK;
    st->skip_reason = -1;
    st->moved_distance_m = st->vertical_jump_m = st->nis = R(NAN);
    st->row_t = st->t_prev;
    st->row_source = PL_SRC_NONE;
    st->row_static = st->row_has_position = st->row_mount_known = 0;
    st->row_mu = st->cs_mu = st->row_cos_mu = st->row_sin_mu = R(NAN);
    return PL_OK;
}

/* TangentPlane._linearise at the point (lat, lon in 1e-7 deg + fraction, height h_a) whose
 * coordinates are (n_a, e_a) */
static void linearise(pl_plane *p, const pl_geo *g, IOTNAV_REAL h_a, IOTNAV_REAL n_a, IOTNAV_REAL e_a)
{
    iotnav_plane_scales(g->lat_e7, g->lat_frac_e7, h_a, &p->k_n, &p->k_e);
    p->lat_a_e7 = g->lat_e7;
    p->lon_a_e7 = g->lon_e7;
    p->lat_a_frac_e7 = g->lat_frac_e7;
    p->lon_a_frac_e7 = g->lon_frac_e7;
    p->n_a = n_a;
    p->e_a = e_a;
    p->inv_k_n = R(1.0) / p->k_n;
    p->inv_k_e = R(1.0) / p->k_e;
    p->n_anchors += 1;
}

/* Pipeline._set_origin */
static void set_origin(pl_state *st, const pl_geo *g)
{
    st->plane.n_anchors = 0;
    st->plane.h0_m = g->height_m;
    linearise(&st->plane, g, g->height_m, R(0.0), R(0.0));
    st->have_frame = 1;
    if (st->cfg.pipeline.gravity_mps2 <= R(0.0))
        st->g = iotnav_normal_gravity(((IOTNAV_REAL)g->lat_e7 + g->lat_frac_e7) * R(IOTNAV_DEG_E7_TO_RAD),
                                      g->height_m);
}

/* TangentPlane.from_ned */
static void from_ned(const pl_plane *p, const IOTNAV_REAL r[3], pl_geo *g)
{
    IOTNAV_REAL dlat = (r[0] - p->n_a) * p->inv_k_n + p->lat_a_frac_e7;
    IOTNAV_REAL dlon = (r[1] - p->e_a) * p->inv_k_e + p->lon_a_frac_e7;
    IOTNAV_REAL flat = IOTNAV_FLOOR(dlat), flon = IOTNAV_FLOOR(dlon);
    g->lat_e7 = p->lat_a_e7 + (int32_t)flat;
    g->lon_e7 = p->lon_a_e7 + (int32_t)flon;
    g->lat_frac_e7 = dlat - flat;
    g->lon_frac_e7 = dlon - flon;
    g->height_m = p->h0_m - r[2];
}

void pl_set_stored(pl_state *st, const pl_geo *pos, IOTNAV_REAL mount_yaw_rad)
{
    IOTNAV_REAL lat = ((IOTNAV_REAL)pos->lat_e7 + pos->lat_frac_e7) * R(1e-7);
    IOTNAV_REAL lon = ((IOTNAV_REAL)pos->lon_e7 + pos->lon_frac_e7) * R(1e-7);
    pl_lastpos_init(&st->boot, &st->cfg.last_position, 1, lat, lon);
    st->has_stored = 1;
    set_origin(st, pos);
    if (isfinite(mount_yaw_rad)) pl_mount_set_stored(&st->mount, mount_yaw_rad);
}

/* InputGuard.admit's time rule for stream k: 0 when t is earlier than the previous accepted one */
static int guard_time(pl_state *st, int k, iotnav_time t)
{
    if (st->guard_has[k] && tdiff(t, st->guard_t[k]) < R(0.0)) return 0;
    return 1;
}

static int skip(pl_state *st, int reason)
{
    st->n_skipped[reason] += 1u;
    st->skip_reason = reason;
    return PL_EV_SKIPPED;
}

/* pipeline_imu_kernel for one sample (after InputGuard) */
int pl_step_imu(pl_state *st, const pl_imu_in *in)
{
    const pl_pipeline_config *c = &st->cfg;
    const pl_engine_config *e = &c->pipeline;
    const IOTNAV_REAL *f = in->f_b, *w = in->w_b;
    const int hold = e->use_lowpass && e->static_hold;
    const IOTNAV_REAL *C = st->att.C;
    IOTNAV_REAL dt, v_dr, y[3];
    int flags = 0, was, now, init, i;
    /* InputGuard.admit */
    if (!isfinite(in->t.frac + f[0] + f[1] + f[2] + w[0] + w[1] + w[2])) return skip(st, PL_SKIP_IMU_NONFINITE);
    /* the step from the previous accepted sample, formed once: InputGuard's time and gap rules
     * and the kernel's dt use the same difference (t_prev and guard_t[G_IMU] are both the
     * previous accepted sample's time, set together below) */
    dt = st->guard_has[G_IMU] ? tdiff(in->t, st->guard_t[G_IMU]) : R(0.0);
    if (st->guard_has[G_IMU] && dt < R(0.0)) return skip(st, PL_SKIP_IMU_TIME_BACKWARDS);
    if (st->guard_has[G_IMU] && dt > R(PL_IMU_GAP_S)) {
        st->n_skipped[PL_SKIP_IMU_GAP] += 1u;
        flags |= PL_EV_IMU_GAP;
    }
    st->guard_t[G_IMU] = in->t;
    st->guard_has[G_IMU] = 1;
    /* the kernel */
    st->t_prev = in->t;
    st->has_t_prev = 1;
    was = st->is_static;
    init = st->fus.initialised;
    v_dr = init ? HYPOT(st->fus.x[3], st->fus.x[4]) : R(NAN);
    now = pl_front_end_step(&st->att, &st->det, in->t, f[0], f[1], f[2], w[0], w[1], w[2], dt, was, st->g,
                            st->a_long, st->v_gnss, st->t_speed, v_dr, y);
    st->is_static = now;
    if (now != was) {
        flags |= now ? PL_EV_STATIC_START : PL_EV_STATIC_END;
        pl_lowpass3_reset(&st->lp); /* Pipeline.imu_block, on the event */
    }
    if (e->use_mount) {
        IOTNAV_REAL r_yaw = C[6] * st->att.omega[0] + C[7] * st->att.omega[1] + C[8] * st->att.omega[2];
        pl_mount_add_imu_body(&st->mount, f[0], f[1], f[2], r_yaw);
    }
    if (!(now && hold)) {
        if (!st->att.yaw.initialised || (e->use_mount && !st->mount.known)) {
            /* heading unresolved: the horizontal specific force is process noise, not an input */
            IOTNAV_REAL qa = c->fusion.acc_psd_m2_s3 + (y[0] * y[0] + y[1] * y[1]) * R(PL_UNRESOLVED_CORR_S);
            pl_fusion_predict(&st->fus, R(0.0), R(0.0), y[2] + st->g, C, dt, qa);
        } else {
            pl_fusion_predict(&st->fus, y[0], y[1], y[2] + st->g, C, dt, c->fusion.acc_psd_m2_s3);
        }
    }
    /* the row (write_attitude, write_position) */
    st->row_t = in->t;
    st->row_static = now;
    for (i = 0; i < 9; ++i) st->row_C[i] = C[i];
    if (st->mount.known && !(st->cs_mu == st->mount.mount_yaw_rad)) { /* a new angle: the same values */
        st->cs_mu = st->mount.mount_yaw_rad;
        st->row_cos_mu = IOTNAV_COS(st->mount.mount_yaw_rad);
        st->row_sin_mu = IOTNAV_SIN(st->mount.mount_yaw_rad);
    }
    st->row_mu = st->mount.mount_yaw_rad;
    st->row_mount_known = st->mount.known;
    st->row_plane = st->plane;
    if (init) {
        for (i = 0; i < 3; ++i) {
            st->row_r[i] = st->fus.x[i];
            st->row_v[i] = st->fus.x[3 + i];
        }
        st->row_std_n = IOTNAV_SQRT(st->fus.P[0]);
        st->row_std_e = IOTNAV_SQRT(st->fus.P[10]);
        st->row_has_position = 1;
        if (now && e->use_lowpass) {
            st->row_source = PL_SRC_LOWPASS;
        } else if (st->has_t_fix && tdiff(in->t, st->t_fix) <= e->fix_hold_s) {
            st->row_source = PL_SRC_FIX;
        } else {
            st->row_source = PL_SRC_DR;
        }
    } else if (st->have_frame) { /* stored last position, no fix yet */
        IOTNAV_REAL std = c->last_position.stored_std_m;
        int source = PL_SRC_LAST_POSITION;
        if (!now && !st->has_boot_move && dt > R(0.0)) {
            st->t_boot_move = in->t;
            st->has_boot_move = 1;
            flags |= PL_EV_BOOT_MOVE;
        }
        if (st->has_boot_move) {
            std = std + c->last_position.boot_walk_speed_mps * tdiff(in->t, st->t_boot_move);
            source = PL_SRC_DR;
        }
        for (i = 0; i < 3; ++i) st->row_r[i] = st->row_v[i] = R(0.0);
        st->row_std_n = st->row_std_e = std;
        st->row_source = source;
        st->row_has_position = 1;
    } else {
        st->row_has_position = 0;
        st->row_source = PL_SRC_NONE;
    }
    return flags;
}

/* gnss_noise: R's diagonal (m^2) from the receiver's figures, floored at min_pos_std_m */
static void gnss_noise(const pl_fusion_config *fc, const pl_gnss_in *in, IOTNAV_REAL rv[3], IOTNAV_REAL *sigma_v)
{
    IOTNAV_REAL fl = fc->min_pos_std_m * fc->min_pos_std_m;
    iotnav_position_variances(fc->uere_m, fc->default_dop, in->h_acc_m, in->v_acc_m, in->hdop, in->pdop, &rv[0],
                              &rv[2]);
    if (rv[0] < fl) rv[0] = fl;
    if (rv[2] < fl) rv[2] = fl;
    rv[1] = rv[0];
    *sigma_v = isfinite(in->s_acc_mps) && in->s_acc_mps > R(0.0) ? in->s_acc_mps : fc->speed_noise_mps;
}

/* Pipeline._gnss (after InputGuard) */
int pl_step_gnss(pl_state *st, const pl_gnss_in *in_raw)
{
    const pl_pipeline_config *c = &st->cfg;
    const pl_engine_config *e = &c->pipeline;
    pl_gnss_in s = *in_raw;
    pl_gnss_in *in = &s;
    pl_geo fix;
    IOTNAV_REAL lat_deg, lon_deg, h, r[3], rv[3], sigma_v, dt_fix, d_gnss, v_ne[2], v_ned[3], dn, de;
    int flags = 0, vertical_reset, have_ned, moving_course, after_outage, return_after_init, reason, rc, i;
    const IOTNAV_REAL d_max = R(PL_REANCHOR_DISTANCE_M);
    /* InputGuard.admit */
    if (!isfinite(in->t.frac) || (in->valid && !isfinite(in->lat_frac_e7 + in->lon_frac_e7)))
        return skip(st, PL_SKIP_GNSS_NONFINITE);
    if (!guard_time(st, G_GNSS, in->t)) return skip(st, PL_SKIP_GNSS_TIME_BACKWARDS);
    st->guard_t[G_GNSS] = in->t;
    st->guard_has[G_GNSS] = 1;
    if (in->course_valid && !isfinite(in->course_rad + in->speed_mps)) {
        st->n_skipped[PL_SKIP_GNSS_COURSE_NONFINITE] += 1u;
        flags |= PL_EV_COURSE_REPAIRED;
        in->course_valid = 0;
    }
    /* block 1 */
    lat_deg = ((IOTNAV_REAL)in->lat_e7 + in->lat_frac_e7) * R(1e-7);
    lon_deg = ((IOTNAV_REAL)in->lon_e7 + in->lon_frac_e7) * R(1e-7);
    reason = pl_lastpos_check_fix(&st->boot, in->valid, lat_deg, lon_deg, in->pdop, in->num_sv, in->t);
    if (reason != PL_FIX_OK) {
        st->fix_reason = reason;
        return flags | PL_EV_FIX_REJECTED;
    }
    /* a 2D fix takes the filter's own height */
    if (isfinite(in->height_m)) {
        h = in->height_m;
    } else if (!st->have_frame) {
        h = R(0.0);
        st->origin_2d = 1;
    } else if (st->fus.initialised) {
        h = st->plane.h0_m - st->fus.x[2];
    } else {
        h = st->plane.h0_m;
    }
    vertical_reset = st->origin_2d && isfinite(in->height_m);
    fix.lat_e7 = in->lat_e7;
    fix.lon_e7 = in->lon_e7;
    fix.lat_frac_e7 = in->lat_frac_e7;
    fix.lon_frac_e7 = in->lon_frac_e7;
    fix.height_m = h;
    if (!st->boot.first_fix_seen) {
        IOTNAV_REAL d = R(NAN);
        if (pl_lastpos_first_fix(&st->boot, lat_deg, lon_deg, &d)) {
            st->moved_distance_m = d;
            flags |= PL_EV_MOVED_WHILE_OFF;
        }
        if (!st->have_frame) set_origin(st, &fix);
        flags |= PL_EV_FIRST_FIX;
    }
    d_gnss = st->has_t_gnss ? tdiff(in->t, st->t_gnss) : R(NAN);
    dt_fix = d_gnss > R(0.0) && d_gnss <= R(2.5) ? d_gnss : R(1.0);
    after_outage = d_gnss > c->fusion.reacquire_after_s; /* NaN: 0 */
    st->t_gnss = in->t;
    st->has_t_gnss = 1;
    /* TangentPlane.to_ned, then follow */
    dn = ((IOTNAV_REAL)(in->lat_e7 - st->plane.lat_a_e7) + (in->lat_frac_e7 - st->plane.lat_a_frac_e7)) *
         st->plane.k_n;
    de = ((IOTNAV_REAL)(in->lon_e7 - st->plane.lon_a_e7) + (in->lon_frac_e7 - st->plane.lon_a_frac_e7)) *
         st->plane.k_e;
    r[0] = st->plane.n_a + dn;
    r[1] = st->plane.e_a + de;
    r[2] = st->plane.h0_m - h;
    if (HYPOT(r[0] - st->plane.n_a, r[1] - st->plane.e_a) > d_max) linearise(&st->plane, &fix, h, r[0], r[1]);
    gnss_noise(&c->fusion, in, rv, &sigma_v);
    if (vertical_reset && st->fus.initialised) {
        IOTNAV_REAL *P = st->fus.P;
        st->vertical_jump_m = r[2] - st->fus.x[2];
        for (i = 0; i < PL_FUSION_N; ++i) P[PL_FUSION_N * 2 + i] = P[PL_FUSION_N * i + 2] = R(0.0);
        P[PL_FUSION_N * 2 + 2] = R(1e6);
        st->fus.x[2] = r[2];
        st->origin_2d = 0;
        flags |= PL_EV_VERTICAL_RESET;
    }
    v_ned[0] = in->vn;
    v_ned[1] = in->ve;
    v_ned[2] = in->vd;
    have_ned = c->fusion.use_ned_velocity && isfinite(in->vn) && isfinite(in->ve) && isfinite(in->vd);
    moving_course = in->course_valid && isfinite(in->speed_mps) && in->speed_mps >= c->yaw.min_course_speed_mps;
    v_ne[0] = v_ne[1] = R(0.0);
    if (moving_course) {
        v_ne[0] = in->speed_mps * IOTNAV_COS(in->course_rad);
        v_ne[1] = in->speed_mps * IOTNAV_SIN(in->course_rad);
    }
    return_after_init = 0;
    if (!st->fus.initialised) {
        IOTNAV_REAL v0[3];
        const IOTNAV_REAL *pv = 0;
        if (have_ned) {
            pv = v_ned;
        } else if (moving_course) {
            v0[0] = v_ne[0];
            v0[1] = v_ne[1];
            v0[2] = R(0.0);
            pv = v0;
        }
        pl_fusion_initialise(&st->fus, r, rv, pv);
        st->t_fix = in->t;
        st->has_t_fix = 1;
        return_after_init = 1;
    }
    pl_static_update_speed(&st->det, in->t, in->speed_mps);
    if (isfinite(in->speed_mps)) {
        IOTNAV_REAL dt_v = st->t_speed.frac == -(IOTNAV_REAL)INFINITY ? R(NAN) : tdiff(in->t, st->t_speed);
        st->a_long = dt_v > R(0.0) && dt_v <= R(2.5) ? (in->speed_mps - st->v_gnss) / dt_v : R(0.0);
        st->v_gnss = in->speed_mps;
        st->t_speed = in->t;
    }
    if (moving_course && !st->is_static)
        pl_cascade_aid_heading(&st->att, pl_mount_wrap(in->course_rad + st->mount.mount_yaw_rad), R(NAN));
    if (e->use_mount) {
        IOTNAV_REAL old = st->mount.mount_yaw_rad;
        if (pl_mount_add_gnss(&st->mount, in->t, in->speed_mps, in->course_rad, in->course_valid, st->is_static,
                              &st->mount_event)) {
            flags |= PL_EV_MOUNT;
            if (st->mount_event.applied)
                pl_cascade_rotate_heading(&st->att, pl_mount_wrap(st->mount.mount_yaw_rad - old));
        }
    }
    if (return_after_init) return flags;
    if (st->is_static && e->use_lowpass) {
        IOTNAV_REAL zero[2] = {R(0.0), R(0.0)};
        if (pl_lowpass3_push(&st->lp, r)) {
            IOTNAV_REAL n_eff = R(1.0) + (IOTNAV_REAL)pl_lowpass3_n_fixes(&st->lp) * dt_fix /
                                             (R(2.0) * e->lowpass_corr_time_s);
            IOTNAV_REAL rl[3];
            for (i = 0; i < 3; ++i) rl[i] = rv[i] / n_eff;
            rc = pl_fusion_update_position(&st->fus, st->lp.out, rl, 0);
            if (rc == PL_FUSION_ERR_NUMERIC) flags |= PL_EV_NUMERIC;
        }
        if (pl_fusion_update_velocity(&st->fus, zero[0], zero[1], e->zupt_noise_mps) != PL_FUSION_OK)
            flags |= PL_EV_NUMERIC;
    } else {
        rc = pl_fusion_update_position(&st->fus, r, rv, after_outage);
        st->nis = st->fus.nis;
        if (rc == PL_FUSION_OK) {
            st->t_fix = in->t;
            st->has_t_fix = 1;
        } else if (rc == PL_FUSION_REJECTED) {
            st->fix_reason = PL_FIX_NIS;
            flags |= PL_EV_FIX_REJECTED;
        } else {
            flags |= PL_EV_NUMERIC;
        }
        if (have_ned) {
            rc = pl_fusion_update_velocity_ned(&st->fus, v_ned, sigma_v);
        } else if (moving_course) {
            rc = pl_fusion_update_velocity(&st->fus, v_ne[0], v_ne[1], sigma_v);
        } else {
            rc = PL_FUSION_OK;
        }
        if (rc != PL_FUSION_OK) flags |= PL_EV_NUMERIC;
    }
    if (pl_lastpos_due(&st->boot, in->t)) {
        from_ned(&st->plane, st->fus.x, &st->save.pos);
        st->save.t = in->t;
        /* a provisional angle is not stored: it would come back as a calibration */
        st->save.mount_yaw_rad = st->mount.known && !st->mount.provisional ? st->mount.mount_yaw_rad : R(NAN);
        flags |= PL_EV_SAVE;
    }
    return flags;
}

int pl_step_mag(pl_state *st, iotnav_time t, const IOTNAV_REAL m_b[3])
{
    if (!isfinite(t.frac + m_b[0] + m_b[1] + m_b[2])) return skip(st, PL_SKIP_MAG_NONFINITE);
    if (!guard_time(st, G_MAG, t)) return skip(st, PL_SKIP_MAG_TIME_BACKWARDS);
    st->guard_t[G_MAG] = t;
    st->guard_has[G_MAG] = 1;
    if (st->cfg.yaw.use_mag) pl_cascade_aid_mag(&st->att, m_b[0], m_b[1], m_b[2]);
    return 0;
}

/* write_attitude and write_position of the latest row */
void pl_output(const pl_state *st, pl_output_t *out)
{
    const IOTNAV_REAL *C = st->row_C;
    IOTNAV_REAL c00, c10, c20, c21, s20;
    int i;
    out->t = st->row_t;
    out->source = st->row_source;
    out->is_static = st->row_static;
    out->has_position = st->row_has_position;
    if (st->row_has_position) {
        for (i = 0; i < 3; ++i) {
            out->r_n[i] = st->row_r[i];
            out->v_n[i] = st->row_v[i];
        }
        out->std_north = st->row_std_n;
        out->std_east = st->row_std_e;
        from_ned(&st->row_plane, st->row_r, &out->geo);
    } else {
        for (i = 0; i < 3; ++i) out->r_n[i] = out->v_n[i] = R(NAN);
        out->std_north = out->std_east = R(NAN);
        out->geo.lat_e7 = out->geo.lon_e7 = 0;
        out->geo.lat_frac_e7 = out->geo.lon_frac_e7 = out->geo.height_m = R(NAN);
    }
    if (st->row_mount_known) {
        IOTNAV_REAL cm = st->row_cos_mu, sm = st->row_sin_mu;
        c00 = C[0] * cm - C[1] * sm;
        c10 = C[3] * cm - C[4] * sm;
        c20 = C[6] * cm - C[7] * sm;
        c21 = C[6] * sm + C[7] * cm;
    } else {
        c00 = C[0];
        c10 = C[3];
        c20 = C[6];
        c21 = C[7];
    }
    s20 = -c20;
    if (s20 > R(1.0)) s20 = R(1.0);
    if (s20 < R(-1.0)) s20 = R(-1.0);
    out->roll = ATAN2(c21, C[8]);
    out->pitch = ASIN(s20);
    out->yaw = ATAN2(c10, c00);
}

int32_t pl_sizeof(int32_t which)
{
    switch (which) {
    case 0: return (int32_t)sizeof(pl_state);
    case 1: return (int32_t)sizeof(pl_pipeline_config);
    case 2: return (int32_t)sizeof(pl_imu_in);
    case 3: return (int32_t)sizeof(pl_gnss_in);
    case 4: return (int32_t)sizeof(pl_output_t);
    case 5: return (int32_t)sizeof(pl_geo);
    default: return 0;
    }
}
