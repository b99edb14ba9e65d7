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

import hashlib
import os
import shutil
import time
from pathlib import Path

__version__ = "0.1.0"


def _numba_cache_dir() -> None:
    """Point numba's on-disk cache at a folder keyed by the package's source (before numba loads).

    numba's ``cache=True`` checks only the time stamp of the file that defines a compiled
    function; a kernel that calls compiled functions of other modules would keep running their
    old code after those change. Keying the folder by every module's path, size and
    modification time (``os.stat``, no file is read: about 1 ms for the package's ~200 modules)
    makes any edit, upgrade or checkout start a fresh cache. Folders beyond the latest five are
    removed once a day old.
    ``NUMBA_CACHE_DIR`` set by the user wins.
    """
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    root = Path(__file__).parent
    h = hashlib.sha1(__version__.encode())
    try:
        for p in sorted(root.rglob("*.py")):
            st = p.stat()
            h.update(f"{p.relative_to(root)}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "iotnav" / "numba"
        target = base / h.hexdigest()[:16]
        if not target.is_dir():
            target.mkdir(parents=True)
            old = sorted((d for d in base.iterdir() if d.is_dir()), key=lambda d: d.stat().st_mtime)
            stale = time.time() - 86_400.0  # never a folder a running process may still use
            for d in old[:-5]:
                if d.stat().st_mtime < stale:
                    shutil.rmtree(d, ignore_errors=True)
    except OSError:  # read-only home or package: numba's default (__pycache__) applies
        return
    os.environ["NUMBA_CACHE_DIR"] = str(target)


_numba_cache_dir()
