"""Published low-effort localisation techniques, one module each (Forno et al. 2020, Fig. 1).

Block numbers follow the paper's Fig. 1:

1. :mod:`~iotnav.techniques.last_position` -- saving and reloading the last known position;
2. :mod:`~iotnav.techniques.cascade` -- the cascaded Kalman filter of the input pre-processing,
   built from :mod:`~iotnav.techniques.tilt_kf`, :mod:`~iotnav.techniques.yaw_kf` and
   :mod:`~iotnav.techniques.gyro_bias_kf` (after Zihajehzadeh et al. 2015);
3. :mod:`~iotnav.techniques.static` -- static case determination;
4. :mod:`~iotnav.techniques.lowpass3` -- the 3-level low-pass GPS filter;
5. :mod:`~iotnav.techniques.mount` -- yaw mounting-angle alignment;
6. :mod:`~iotnav.techniques.fusion_kf` -- the 9-state linear GPS/INS fusion filter.

:mod:`~iotnav.techniques.cost` gives the analytic operation counts of Table I.

Reference: E. Forno, S. Moio, M. Schenatti, E. Macii, G. Urgese, "Techniques for improving
localization applications running on low-cost IoT devices", 2020 (AEIT Automotive).
"""
