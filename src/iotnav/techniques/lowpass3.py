"""Three-level low-pass GPS filter, active only while static (Forno et al. 2020, block 4).

While block 3 reports static, GPS positions fill a level-1 buffer of ``n1`` fixes. When it is
full, its mean is pushed into the level-2 circular buffer (``n2`` slots) and level 1 starts
again; every ``n2`` pushes into level 2 (i.e. each time it has been filled with fresh
entries), the mean of level 2 is pushed into the level-3 circular buffer (``n3`` slots).
The filter output is the mean of the highest non-empty level::

    out = mean(L3) if L3 else mean(L2) if L2 else (nothing yet)

so it changes every ``n1`` fixes at first and every ``n1 * n2`` fixes once level 3 is in use:
position updates slow down the longer the device stands still ("sleep mode"). Leaving the
static state (the first horizontal acceleration above theta_A, decided by block 3) resets the
buffers and the normal update regime resumes at once. Positions are NED metres.

Two forms of the same rules: :class:`Lowpass3` (numpy, the reading of the paper, used by the
pipeline) and the compiled :func:`lowpass3_push` / :func:`lowpass3_reset` /
:func:`lowpass3_n_fixes` on a state vector (layout ``LP_*``, :data:`LP_SIZE` floats) and three
buffers, which compiled engines (:mod:`iotnav.engines.fixes_kernel`) call from their own
kernels; tests check the two give equal outputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Lowpass3Config:
    """Buffer sizes (the paper gives no values).

    Attributes
    ----------
    n1, n2, n3 : int
        Lengths of the level-1 buffer and of the level-2 and level-3 circular buffers.
    """

    n1: int = 10
    n2: int = 6
    n3: int = 10


class Lowpass3:
    """Block 4; hot state in three numpy buffers and integer counters."""

    def __init__(self, config: Lowpass3Config | None = None) -> None:
        self.config = config or Lowpass3Config()
        c = self.config
        self.buf1 = np.zeros((c.n1, 3))
        self.buf2 = np.zeros((c.n2, 3))
        self.buf3 = np.zeros((c.n3, 3))
        self.reset()

    def reset(self) -> None:
        """Empty every level (called when the static state ends or starts)."""
        self.k1 = 0  # fixes in level 1
        self.k2 = 0  # total pushes into level 2
        self.k3 = 0  # total pushes into level 3
        self.since2 = 0  # pushes into level 2 since the last push into level 3

    @property
    def level(self) -> int:
        """Highest non-empty averaging level (0: no output yet, 2 or 3)."""
        return 3 if self.k3 else (2 if self.k2 else 0)

    @property
    def n_fixes(self) -> int:
        """Number of fixes averaged into the current output (0 when there is none)."""
        c = self.config
        if self.k3:
            return min(self.k3, c.n3) * c.n2 * c.n1
        if self.k2:
            return min(self.k2, c.n2) * c.n1
        return 0

    def output(self) -> FloatArray | None:
        """The current filtered position (NED, m) or None when no level is available."""
        if self.k3:
            return np.mean(self.buf3[: min(self.k3, self.buf3.shape[0])], axis=0)
        if self.k2:
            return np.mean(self.buf2[: min(self.k2, self.buf2.shape[0])], axis=0)
        return None

    def push(self, r_n: FloatArray) -> FloatArray | None:
        """Add one fix (NED, m).

        Returns
        -------
        numpy.ndarray or None
            The new output when this fix changed it, else None.
        """
        c = self.config
        self.buf1[self.k1] = r_n
        self.k1 += 1
        if self.k1 < c.n1:
            return None
        self.k1 = 0
        self.buf2[self.k2 % c.n2] = self.buf1.mean(axis=0)
        self.k2 += 1
        self.since2 += 1
        if self.since2 >= c.n2:
            self.since2 = 0
            self.buf3[self.k3 % c.n3] = self.buf2.mean(axis=0)
            self.k3 += 1
            return self.output()
        if self.k3:
            return None  # level 3 in use: level-2 changes do not reach the output
        return self.output()


# --------------------------------------------------------------------------- compiled form
#: State vector of the compiled form: output present, output (NED, 3), level counters.
LP_HAVE, LP_N, LP_K1, LP_K2, LP_K3, LP_SINCE2 = 0, 1, 4, 5, 6, 7
LP_SIZE = 8


@numba.njit(cache=True)
def _level_mean(s: FloatArray, buf: FloatArray, m: int) -> None:
    """The mean of the first ``m`` rows of a level's buffer as the output."""
    for c in range(3):
        acc = 0.0
        for i in range(m):
            acc += buf[i, c]
        s[LP_N + c] = acc / m
    s[LP_HAVE] = 1.0


@numba.njit(cache=True)
def lowpass3_push(
    s: FloatArray,
    b1: FloatArray,
    b2: FloatArray,
    b3: FloatArray,
    n1: int,
    n2: int,
    n3: int,
    r0: float,
    r1: float,
    r2: float,
) -> bool:
    """:meth:`Lowpass3.push` of the fix ``(r0, r1, r2)`` (NED, m) on state ``s`` and buffers ``b1, b2, b3``.

    Returns True when the output ``s[LP_N : LP_N + 3]`` changed.
    """
    k1 = int(s[LP_K1])
    b1[k1, 0], b1[k1, 1], b1[k1, 2] = r0, r1, r2
    k1 += 1
    if k1 < n1:
        s[LP_K1] = k1
        return False
    s[LP_K1] = 0.0
    k2 = int(s[LP_K2])
    for c in range(3):
        acc = 0.0
        for i in range(n1):
            acc += b1[i, c]
        b2[k2 % n2, c] = acc / n1
    k2 += 1
    s[LP_K2] = k2
    since2 = int(s[LP_SINCE2]) + 1
    k3 = int(s[LP_K3])
    if since2 >= n2:
        since2 = 0
        for c in range(3):
            acc = 0.0
            for i in range(n2):
                acc += b2[i, c]
            b3[k3 % n3, c] = acc / n2
        k3 += 1
        s[LP_K3] = k3
        s[LP_SINCE2] = since2
        _level_mean(s, b3, min(k3, n3))
        return True
    s[LP_SINCE2] = since2
    if k3 > 0:
        return False  # level 3 in use: level-2 changes do not reach the output
    _level_mean(s, b2, min(k2, n2))
    return True


@numba.njit(cache=True)
def lowpass3_n_fixes(s: FloatArray, n1: int, n2: int, n3: int) -> int:
    """:attr:`Lowpass3.n_fixes` of state ``s``."""
    k2, k3 = int(s[LP_K2]), int(s[LP_K3])
    if k3:
        return min(k3, n3) * n2 * n1
    if k2:
        return min(k2, n2) * n1
    return 0


@numba.njit(cache=True)
def lowpass3_reset(s: FloatArray) -> None:
    """:meth:`Lowpass3.reset` of state ``s`` (the output is gone too)."""
    s[LP_K1] = 0.0
    s[LP_K2] = 0.0
    s[LP_K3] = 0.0
    s[LP_SINCE2] = 0.0
    s[LP_HAVE] = 0.0
