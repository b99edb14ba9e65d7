/* Helpers the engines of the iotnav firmware library share (static inline: no object of its own,
 * no global state): time differences, the reading of a fix's accuracy figures
 * (iotnav.gnss_accuracy.position_sigmas) and the tangent plane's scale factors
 * (iotnav.engines.tangent_plane.TangentPlane._linearise). */
#ifndef IOTNAV_COMMON_H
#define IOTNAV_COMMON_H

#include <math.h>

#include "iotnav_real.h"

/* WGS84 (iotnav.geo): semi-major axis, first eccentricity squared as TangentPlane uses it. */
#define IOTNAV_WGS84_A 6378137.0
#define IOTNAV_WGS84_E2_TP 6.69437999014e-3
#define IOTNAV_DEG_E7_TO_RAD (3.14159265358979323846 / 180.0 * 1e-7)
/* iotnav.gnss_accuracy.VDOP_PER_HDOP, and 1 / hypot(1, VDOP_PER_HDOP) */
#define IOTNAV_VDOP_PER_HDOP 1.5
#define IOTNAV_INV_HYPOT_1_VDOP_PER_HDOP 0.55470019622522912

/* a - b, s: the whole seconds first, so float32 keeps sub-microsecond differences. */
static inline IOTNAV_REAL iotnav_time_diff(iotnav_time a, iotnav_time b)
{
    return (IOTNAV_REAL)(a.s - b.s) + (a.frac - b.frac);
}

/* a reported figure: finite and positive (iotnav.gnss_accuracy._positive) */
static inline int iotnav_positive(IOTNAV_REAL v) { return isfinite(v) && v > IOTNAV_R(0.0); }

/* iotnav.gnss_accuracy.position_sigmas as variances: north/east (each) into *ne and down into *d,
 * m^2. The DOPs are read only when an accuracy is missing (the same values). */
static inline void iotnav_position_variances(IOTNAV_REAL uere_m, IOTNAV_REAL default_dop, IOTNAV_REAL h_acc_m,
                                             IOTNAV_REAL v_acc_m, IOTNAV_REAL hdop, IOTNAV_REAL pdop,
                                             IOTNAV_REAL *ne, IOTNAV_REAL *d)
{
    IOTNAV_REAL h2d, v;
    if (iotnav_positive(h_acc_m)) {
        h2d = h_acc_m;
        v = IOTNAV_R(IOTNAV_VDOP_PER_HDOP) * h_acc_m;
    } else {
        int has_hdop = iotnav_positive(hdop), has_pdop = iotnav_positive(pdop);
        IOTNAV_REAL h_dop, v_dop;
        if (has_hdop) {
            h_dop = hdop;
        } else if (has_pdop) {
            h_dop = pdop * IOTNAV_R(IOTNAV_INV_HYPOT_1_VDOP_PER_HDOP);
        } else {
            h_dop = default_dop;
        }
        if (has_hdop && has_pdop && pdop > hdop) {
            v_dop = IOTNAV_SQRT(pdop * pdop - hdop * hdop);
        } else {
            v_dop = IOTNAV_R(IOTNAV_VDOP_PER_HDOP) * h_dop;
        }
        h2d = uere_m * h_dop;
        v = uere_m * v_dop;
    }
    if (iotnav_positive(v_acc_m)) v = v_acc_m;
    *ne = IOTNAV_R(0.5) * h2d * h2d; /* (h2d / sqrt(2))^2 */
    *d = v * v;
}

/* TangentPlane._linearise at latitude lat_e7 + frac_e7 (1e-7 deg), height h (m): metres per
 * 1e-7 deg of latitude (*k_n) and of longitude (*k_e). */
static inline void iotnav_plane_scales(int32_t lat_e7, IOTNAV_REAL frac_e7, IOTNAV_REAL h, IOTNAV_REAL *k_n,
                                       IOTNAV_REAL *k_e)
{
    IOTNAV_REAL lat = ((IOTNAV_REAL)lat_e7 + frac_e7) * IOTNAV_R(IOTNAV_DEG_E7_TO_RAD);
    IOTNAV_REAL s = IOTNAV_SIN(lat), w = IOTNAV_SQRT(IOTNAV_R(1.0) - IOTNAV_R(IOTNAV_WGS84_E2_TP) * s * s);
    *k_n = IOTNAV_R(IOTNAV_DEG_E7_TO_RAD) *
           (IOTNAV_R(IOTNAV_WGS84_A * (1.0 - IOTNAV_WGS84_E2_TP)) / (w * w * w) + h);
    *k_e = IOTNAV_R(IOTNAV_DEG_E7_TO_RAD) * (IOTNAV_R(IOTNAV_WGS84_A) / w + h) * IOTNAV_COS(lat);
}

/* Somigliana normal gravity (iotnav.geo.normal_gravity) at geodetic latitude lat_rad (rad) and
 * ellipsoidal height h (m), m/s^2. */
#define IOTNAV_G_E 9.7803253359
#define IOTNAV_G_K 0.00193185265241
#define IOTNAV_G_E2 0.00669437999013
#define IOTNAV_G_F (1.0 / 298.257223563)
#define IOTNAV_G_GM 3.986004418e14
#define IOTNAV_G_OMEGA 7.292115e-5
static inline IOTNAV_REAL iotnav_normal_gravity(IOTNAV_REAL lat_rad, IOTNAV_REAL h)
{
    IOTNAV_REAL s = IOTNAV_SIN(lat_rad), s2 = s * s;
    IOTNAV_REAL g0 = IOTNAV_R(IOTNAV_G_E) * (IOTNAV_R(1.0) + IOTNAV_R(IOTNAV_G_K) * s2) / IOTNAV_SQRT(IOTNAV_R(1.0) - IOTNAV_R(IOTNAV_G_E2) * s2);
    IOTNAV_REAL mm = IOTNAV_R(IOTNAV_G_OMEGA * IOTNAV_G_OMEGA * IOTNAV_WGS84_A * IOTNAV_WGS84_A * (IOTNAV_WGS84_A * (1.0 - IOTNAV_G_F)) / IOTNAV_G_GM);
    return g0 * (IOTNAV_R(1.0) - IOTNAV_R(2.0 / IOTNAV_WGS84_A) * (IOTNAV_R(1.0 + IOTNAV_G_F) + mm - IOTNAV_R(2.0 * IOTNAV_G_F) * s2) * h +
                 IOTNAV_R(3.0 / (IOTNAV_WGS84_A * IOTNAV_WGS84_A)) * h * h);
}


#endif
