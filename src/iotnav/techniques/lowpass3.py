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
"""

from __future__ import annotations

from dataclasses import dataclass

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
