/* Configuration of the navigation blocks of the Forno et al. 2020 pipeline in C: block 6's
 * iotnav.techniques.fusion_kf.FusionConfig, member for member in the dataclass's order (bool and
 * int as int32_t, float as IOTNAV_REAL; SI units, as the names say). The bindings
 * (iotnav.firmware.pipeline_blocks56) fill it from a FusionConfig field by field. */
#ifndef IOTNAV_PIPELINE_NAV_CONFIG_H
#define IOTNAV_PIPELINE_NAV_CONFIG_H

#include "iotnav_real.h"

typedef struct {
    IOTNAV_REAL acc_psd_m2_s3;       /* q_a, m^2/s^3 */
    IOTNAV_REAL acc_bias_rw_m2_s5;   /* q_b, m^2/s^5 */
    IOTNAV_REAL acc_bias_init_mps2;  /* initial bias std, m/s^2 */
    IOTNAV_REAL uere_m;              /* user-equivalent range error, m (gnss_noise: not in C) */
    IOTNAV_REAL default_dop;         /* (gnss_noise: not in C) */
    IOTNAV_REAL speed_noise_mps;     /* velocity std per component, m/s */
    IOTNAV_REAL init_vel_std_mps;    /* initial velocity std, m/s */
    IOTNAV_REAL gate_probability;    /* chi-square probability of the position gate, 0: none */
    int32_t max_rejections;          /* gated fixes before a forced one */
    IOTNAV_REAL reacquire_after_s;   /* outage after which a fix is stale, s (the caller's test) */
    IOTNAV_REAL min_pos_std_m;       /* position std floor, m (gnss_noise: not in C) */
    int32_t use_ned_velocity;
    int32_t smoothing;               /* must be 0 in C */
    int32_t record_every;
    IOTNAV_REAL smoothing_accel_rw_mps2_sqrt_s;
    IOTNAV_REAL smoothing_accel_init_std_mps2;
} pl_fusion_config;

#endif
