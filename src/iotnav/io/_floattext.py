"""Floats rounded to 10 significant digits as text, compiled, the bytes pyarrow's cast writes.

:func:`iotnav.io.export.write_csv` writes a float column as the shortest round-trip text of
each value rounded to ten significant digits (:func:`iotnav.io.export.round_significant`),
which pyarrow's ``cast(float64 -> string)`` prints at about 70 ns a value: most of the time of
writing a long ``track.csv``. A value that is the nearest double to a decimal ``D`` of at most
ten significant digits has ``D`` (trailing zeros dropped) as its shortest round-trip text,
since two such decimals (fewer than 15 digits) never share a double. :func:`ten_digit_text`
prints those digits directly (about 30 ns a value), in pyarrow's notation: plain for
magnitudes in ``[1e-6, 1e9)``, ``0`` and ``-0`` for the zeros, ``1.5e-7`` from 1e-13 up to
1e-6 (pyarrow also uses exponents from 1e10 up). Each value is checked (its digits divided
back by their power of ten must give the same double); a column with any value outside that
range or failing the check is left to pyarrow, so the bytes are the same either way.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pyarrow as pa

_WIDTH = 20  # "-0." + 5 zeros + 10 digits = 18 bytes; "-d." + 9 digits + "e-13" = 16


def _kernel() -> object:
    from numba import njit

    @njit(cache=True, nogil=True)
    def fmt(
        x: npt.NDArray[np.float64],
        data: npt.NDArray[np.uint8],
        offsets: npt.NDArray[np.int32],
        pow10: npt.NDArray[np.float64],
        pairs: npt.NDArray[np.uint8],
    ) -> int:
        """Write the text of each value of ``x``; 1 when a value cannot be handled, else 0.

        ``pow10[i] = 10.0 ** (i - 13)`` for i in 0..35 (the exact powers 1..1e22 from 13 on);
        ``pairs[2 * i : 2 * i + 2]`` the two digits of ``i`` (0..99).
        """
        pos = 0
        digits = np.empty(10, np.uint8)
        e = 0  # decimal exponent, carried over: neighbouring values of a column share it
        for i in range(x.size):
            offsets[i] = pos
            v = x[i]
            if v != v:  # NaN: a null, no bytes
                continue
            neg = v < 0.0 or (v == 0.0 and np.signbit(v))
            a = -v if v < 0.0 else v
            if neg:
                data[pos] = 45  # '-'
                pos += 1
            if a == 0.0:
                data[pos] = 48
                pos += 1
                continue
            if not (a >= 1.0e-13 and a < 1.0e9):
                return 1
            while e < 8 and a >= pow10[e + 14]:
                e += 1
            while e > -13 and a < pow10[e + 13]:
                e -= 1
            m = int(np.rint(a * pow10[22 - e]))  # 9 - e + 13: an exact power of ten
            if m >= 10_000_000_000:  # the table's inexact negative powers misjudged e by one
                e += 1
                m = int(np.rint(a * pow10[22 - e]))
            elif m < 1_000_000_000:
                if e == -13:
                    return 1
                e -= 1
                m = int(np.rint(a * pow10[22 - e]))
            if m < 1_000_000_000 or m >= 10_000_000_000 or m / pow10[22 - e] != a:
                return 1
            for j in range(8, -1, -2):
                q = m // 100
                r = m - q * 100
                digits[j] = pairs[2 * r]
                digits[j + 1] = pairs[2 * r + 1]
                m = q
            last = 9
            while digits[last] == 48:
                last -= 1
            if e < -6:  # pyarrow's exponent notation: d[.ddd]e-N
                data[pos] = digits[0]
                pos += 1
                if last > 0:
                    data[pos] = 46
                    pos += 1
                    for j in range(1, last + 1):
                        data[pos] = digits[j]
                        pos += 1
                data[pos] = 101  # 'e'
                data[pos + 1] = 45
                pos += 2
                if -e >= 10:
                    data[pos] = 48 + (-e) // 10
                    pos += 1
                data[pos] = 48 + (-e) % 10
                pos += 1
            elif e >= 0:
                for j in range(e + 1):
                    data[pos] = digits[j]
                    pos += 1
                if last > e:
                    data[pos] = 46  # '.'
                    pos += 1
                    for j in range(e + 1, last + 1):
                        data[pos] = digits[j]
                        pos += 1
            else:
                data[pos] = 48
                data[pos + 1] = 46
                pos += 2
                for _ in range(-e - 1):
                    data[pos] = 48
                    pos += 1
                for j in range(last + 1):
                    data[pos] = digits[j]
                    pos += 1
        offsets[x.size] = pos
        return 0

    return fmt


#: Columns shorter than this are left to pyarrow: loading the compiled kernel from numba's cache
#: costs about 0.2-0.4 CPU-s in a fresh process (measured), more than pyarrow spends on them.
MIN_VALUES = 20_000

_FMT: list[object] = []
_POW10 = 10.0 ** np.arange(-13, 23, dtype=np.float64)
_PAIRS = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode(), np.uint8).copy()


def ten_digit_text(x: npt.NDArray[np.float64]) -> pa.Array | None:
    """Text of values already rounded to 10 significant digits, as ``pc.cast(.., pa.string())``.

    NaN is a null. Returns None (the caller casts the column with pyarrow) for fewer than
    :data:`MIN_VALUES` values, or when a value is infinite, non-zero outside ``[1e-13, 1e9)``
    in magnitude, or not the nearest double to a decimal of ten significant digits.
    """
    if x.size < MIN_VALUES:
        return None
    if not _FMT:
        _FMT.append(_kernel())
    fmt = _FMT[0]
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.size * _WIDTH >= 2**31:  # int32 offsets
        return None
    data = np.empty(x.size * _WIDTH, np.uint8)
    offsets = np.empty(x.size + 1, np.int32)
    if fmt(x, data, offsets, _POW10, _PAIRS):  # type: ignore[operator]
        return None
    nan = np.isnan(x)
    n_null = int(nan.sum())
    validity = pa.py_buffer(np.packbits(~nan, bitorder="little")) if n_null else None
    used = int(offsets[-1])
    return pa.Array.from_buffers(
        pa.string(), x.size, [validity, pa.py_buffer(offsets), pa.py_buffer(data[:used].copy())], n_null
    )
