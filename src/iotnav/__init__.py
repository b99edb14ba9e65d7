"""iotnav: clean, high-rate positions from low-cost IoT trackers.

Conventions (stated once, carried in names everywhere in the package)
---------------------------------------------------------------------
Frames
    ``e``  ECEF (WGS84), metres.
    ``n``  local navigation frame, North-East-Down, origin at a chosen geodetic point.
    ``b``  IMU sensor ("body") frame, the axes printed on the chip.
    ``v``  vehicle frame: x forward, y right, z down.

Rotations
    ``C_nb`` maps a vector from ``b`` to ``n``: ``v_n = C_nb @ v_b``. A quaternion ``q_nb``
    (scalar first, ``[w, x, y, z]``) does the same. Euler angles are roll, pitch, yaw
    (ZYX, yaw positive clockwise seen from above, i.e. from North towards East).

Units
    SI inside: metres, seconds, radians, m/s, m/s^2 (specific force), rad/s.
    Geodetic latitude and longitude are degrees in tables and files (``lat``/``lat_deg``),
    as in every GNSS format; heights are ellipsoidal (WGS84) metres unless named ``alt_msl``.
    Magnetic field is microtesla and the name says so (``mag_x_ut``). Anything else non-SI
    carries its unit in its name (``gps_delay_ms``, ``noise_density_ug_rthz``). Readers, config
    files and the CLI convert once, at the edge.

Time
    ``t`` is device time in seconds (float64). Every table of a :class:`iotnav.io.Log`
    shares one device-time axis; ``Log.utc_offset_s`` maps it to UTC
    (``utc = t + utc_offset_s``, seconds since 1970-01-01 UTC).
"""

__version__ = "0.1.0"
