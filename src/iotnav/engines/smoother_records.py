"""Bounded-memory storage of RTS smoothing records and the compiled backward pass.

A record point of :class:`SmoothingLog` (below; re-exported by :mod:`iotnav.engines.smoother`)
holds the prior and posterior state and covariance and the transition from the previous record: ``1 + 2 n + 3 n^2``
floats, 21.8 KB for eskf's 30 states; at eskf's 10 records a second that is 210 KB per second
of data (issue 21: 19 GB per device-day). :class:`RecordStore` keeps them exactly, in less
room and with a bounded part in RAM:

* **What is stored**: the covariances as their upper triangles (every engine records them
  exactly symmetric; one that is not is kept whole, aside, so nothing is approximated), and
  every array as its nonzero pattern (one bit per element) plus its nonzero values, float64
  (the transitions are sparse: 15 % nonzero for eskf, whose prior state is always zero).
  Stored values are the recorded ones, bit for bit (a ``-0.0`` reads back as ``0.0``).
* **Where**: records are encoded in chunks of :data:`CHUNK` records; the chunks past
  ``memory_bytes`` are written to an anonymous temporary file (:func:`tempfile.TemporaryFile`
  in ``spill_dir``, the system's temporary folder by default; it has no name and is gone
  when the log is), read back one chunk at a time.
* **Backward pass**: :func:`rts_backward_records` walks the chunks from the last,
  decodes one into dense arrays and runs the compiled :func:`rts_chunk` over it, carrying the
  smoothed state and covariance to the previous chunk. It returns the smoothed states and
  either every smoothed covariance or only their diagonals (what the output rows need), so
  its memory is one chunk plus ``O(K n)``.

The gain is computed as the Python pass did, ``G = P+ Phi^T (P-)^-1`` by a Cholesky factor of
``P-`` (least squares when ``P-`` is not positive definite), in compiled loops: the results
equal the earlier scipy pass to round-off (``tests/test_smoother.py``).
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterator, Sequence
from typing import IO, Any

import numba
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Records per encoded chunk (eskf: about 2.3 MB a chunk once encoded, 5.5 MB decoded).
CHUNK = 256

#: Encoded chunks kept in RAM before the later ones go to the temporary file, bytes.
MEMORY_BYTES = 32 * 2**20

#: The five arrays of a record, in storage order; ``True`` for the symmetric covariances.
FIELDS: tuple[tuple[str, bool], ...] = (
    ("x_prior", False),
    ("P_prior", True),
    ("Phi", False),
    ("x_post", False),
    ("P_post", True),
)


class _Chunk:
    """One encoded chunk: per field, the packed nonzero bits ``(m, nbytes)`` and the nonzero values."""

    def __init__(self, m: int, masks: list[npt.NDArray[np.uint8]], values: list[FloatArray]) -> None:
        self.m = m
        self.masks: list[npt.NDArray[np.uint8]] | None = masks
        self.values: list[FloatArray] | None = values
        self.offset = -1  # in the spill file once written
        self.sizes = [(a.size, b.size) for a, b in zip(masks, values, strict=True)]

    def nbytes(self) -> int:
        return sum(a + 8 * b for a, b in self.sizes)


class RecordStore:
    """Append-only store of smoothing records for ``n`` states (module docstring).

    Parameters
    ----------
    n : int
        Number of states.
    memory_bytes : int
        Encoded chunks held in RAM before spilling to the temporary file, bytes.
    spill_dir : str, optional
        Folder of the temporary file (the system's temporary folder by default).
    """

    def __init__(self, n: int, memory_bytes: int = MEMORY_BYTES, spill_dir: str | None = None) -> None:
        self.n = n
        self.memory_bytes = memory_bytes
        self.spill_dir = spill_dir
        self._iu = np.triu_indices(n)
        self._len = [n, len(self._iu[0]), n * n, n, len(self._iu[0])]
        self._open: list[list[FloatArray]] = [[] for _ in FIELDS]  # dense rows of the open chunk
        self._chunks: list[_Chunk] = []
        self._asym: dict[tuple[int, int], FloatArray] = {}  # (record, field) -> whole matrix
        self._ram = 0
        self._file: IO[bytes] | None = None
        self._cache: tuple[int, dict[int, FloatArray]] = (-1, {})  # one chunk's decoded fields
        self.count = 0

    # ------------------------------------------------------------------ writing
    def append(self, arrays: Sequence[FloatArray]) -> None:
        """Append one record: ``x_prior (n,), P_prior (n, n), Phi (n, n), x_post (n,), P_post (n, n)``."""
        self.extend([np.asarray(a, dtype=float)[None] for a in arrays])

    def extend(self, arrays: Sequence[FloatArray]) -> None:
        """Append ``m`` records given as five stacked arrays ``(m, n)``, ``(m, n, n)``, ... (copied)."""
        m = int(np.asarray(arrays[0]).shape[0])
        n = self.n
        if self._cache[0] >= len(self._chunks):  # the open chunk's decoded copy goes stale
            self._cache = (-1, {})
        for j, ((_name, sym), a) in enumerate(zip(FIELDS, arrays, strict=True)):
            a = np.asarray(a, dtype=float)
            if sym:
                a = a.reshape(m, n, n)
                tri = a[:, self._iu[0], self._iu[1]]
                low = a[:, self._iu[1], self._iu[0]]
                bad = np.flatnonzero(~np.all((tri == low) | (np.isnan(tri) & np.isnan(low)), axis=1))
                for r in bad.tolist():
                    self._asym[(self.count + r, j)] = a[r].copy()
                self._open[j].extend(tri)
            else:
                self._open[j].extend(a.reshape(m, -1).copy())
        self.count += m
        while len(self._open[0]) >= CHUNK:
            self._close_chunk(CHUNK)

    def _close_chunk(self, m: int) -> None:
        masks, values = [], []
        for j in range(len(FIELDS)):
            rows = np.asarray(self._open[j][:m])
            del self._open[j][:m]
            nz = rows != 0.0
            masks.append(np.packbits(nz, axis=1))
            values.append(rows[nz])
        ch = _Chunk(m, masks, values)
        self._chunks.append(ch)
        self._ram += ch.nbytes()
        if self._ram > self.memory_bytes:
            self._spill(ch)

    def _spill(self, ch: _Chunk) -> None:
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="iotnav-smoothing-", dir=self.spill_dir)
        f = self._file
        f.seek(0, 2)
        ch.offset = f.tell()
        assert ch.masks is not None and ch.values is not None
        for a, b in zip(ch.masks, ch.values, strict=True):
            f.write(a.tobytes())
            f.write(b.tobytes())
        self._ram -= ch.nbytes()
        ch.masks = ch.values = None

    # ------------------------------------------------------------------ reading
    @property
    def spilled_bytes(self) -> int:
        """Bytes written to the temporary file so far."""
        return sum(c.nbytes() for c in self._chunks if c.offset >= 0)

    @property
    def ram_bytes(self) -> int:
        """Bytes of the encoded chunks in RAM plus the open chunk's dense rows."""
        return self._ram + 8 * len(self._open[0]) * sum(self._len)

    def n_chunks(self) -> int:
        """Chunks of :meth:`chunk` (the last one is the open chunk when it holds records)."""
        return len(self._chunks) + (1 if self._open[0] else 0)

    def chunk_start(self, c: int) -> int:
        """Index of the first record of chunk ``c``."""
        return c * CHUNK

    def chunk(self, c: int) -> list[FloatArray]:
        """Chunk ``c`` decoded: five dense arrays ``(m, n)``, ``(m, n, n)``, ``(m, n, n)``, ``(m, n)``, ``(m, n, n)``."""
        return [self.chunk_field(c, j) for j in range(len(FIELDS))]

    def chunk_field(self, c: int, j: int) -> FloatArray:
        """Array ``j`` (index into :data:`FIELDS`) of the records of chunk ``c``, decoded, stacked."""
        if self._cache[0] != c:
            self._cache = (c, {})
        got = self._cache[1].get(j)
        if got is not None:
            return got
        n = self.n
        if c == len(self._chunks):
            m = len(self._open[j])
            flat = np.asarray(self._open[j]).reshape(m, -1)
        else:
            ch = self._chunks[c]
            m = ch.m
            masks, values = self._encoded(ch, j)
            nz = np.unpackbits(masks.reshape(m, -1), axis=1, count=self._len[j]).astype(bool)
            flat = np.zeros((m, self._len[j]))
            flat[nz] = values
        out: FloatArray
        if FIELDS[j][1]:
            out = np.empty((m, n, n))
            out[:, self._iu[0], self._iu[1]] = flat
            out[:, self._iu[1], self._iu[0]] = flat
        elif j == 2:
            out = flat.reshape(m, n, n)
        else:
            out = flat
        if self._asym:
            k0 = c * CHUNK
            for (k, jj), A in self._asym.items():
                if jj == j and k0 <= k < k0 + m:
                    out[k - k0] = A
        self._cache[1][j] = out
        return out

    def _encoded(self, ch: _Chunk, j: int) -> tuple[npt.NDArray[np.uint8], FloatArray]:
        if ch.masks is not None and ch.values is not None:
            return ch.masks[j], ch.values[j]
        assert self._file is not None
        f = self._file
        f.seek(ch.offset + sum(a + 8 * b for a, b in ch.sizes[:j]))
        a, b = ch.sizes[j]
        return np.frombuffer(f.read(a), dtype=np.uint8), np.frombuffer(f.read(8 * b), dtype=np.float64)

    def get(self, k: int, j: int) -> FloatArray:
        """Array ``j`` (index into :data:`FIELDS`) of record ``k`` (a copy)."""
        c = k // CHUNK
        return np.array(self.chunk_field(c, j)[k - c * CHUNK])

    def column(self, j: int, stop: int) -> FloatArray:
        """Array ``j`` of records ``0 .. stop-1`` stacked."""
        parts = []
        for c in range(self.n_chunks()):
            k0 = c * CHUNK
            if k0 >= stop:
                break
            parts.append(self.chunk_field(c, j)[: stop - k0])
        shape = (0, self.n) if j in (0, 3) else (0, self.n, self.n)
        return np.concatenate(parts) if parts else np.zeros(shape)

    def __getstate__(self) -> dict[str, Any]:
        # copies and pickles (engine checkpoints) hold the records in RAM, without the file
        state = self.__dict__.copy()
        chunks = []
        for ch in self._chunks:
            enc = [self._encoded(ch, j) for j in range(len(FIELDS))]
            c = _Chunk(ch.m, [np.array(a) for a, _ in enc], [np.array(b) for _, b in enc])
            chunks.append(c)
        state["_chunks"] = chunks
        state["_ram"] = sum(c.nbytes() for c in chunks)
        state["_file"] = None
        state["_cache"] = (-1, {})
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    def close(self) -> None:
        """Drop the temporary file (also done when the store is collected)."""
        if self._file is not None:
            self._file.close()
            self._file = None


class RecordColumn(Sequence[FloatArray]):
    """Read-only sequence view of one array of the records (``log.P_prior[k]`` etc.).

    Items are copies, as ``(n,)`` or ``(n, n)`` float64 arrays; ``numpy.asarray`` stacks them.
    The view covers the records ``0 .. len-1`` of the store plus the log's optional tail.
    """

    def __init__(self, store: RecordStore, j: int, stop: int | None, tail: FloatArray | None) -> None:
        self._store = store
        self._j = j
        self._stop = stop
        self._tail = tail

    def _n_store(self) -> int:
        return self._store.count if self._stop is None else self._stop

    def __len__(self) -> int:
        return self._n_store() + (0 if self._tail is None else 1)

    def __getitem__(self, k: Any) -> Any:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        n = len(self)
        k = int(k)
        if k < 0:
            k += n
        if not 0 <= k < n:
            raise IndexError("record index out of range")
        if k == self._n_store():
            assert self._tail is not None
            return np.array(self._tail)
        return self._store.get(k, self._j)

    def __iter__(self) -> Iterator[FloatArray]:
        for k in range(len(self)):
            yield self[k]

    def __array__(self, dtype: Any = None, copy: Any = None) -> FloatArray:
        a = self._store.column(self._j, self._n_store())
        if self._tail is not None:
            a = np.concatenate([a, np.asarray(self._tail, dtype=float)[None]])
        return a if dtype is None else a.astype(dtype)


# ---------------------------------------------------------------------------- backward pass


@numba.njit(cache=True)
def _gain(P_post: FloatArray, Phi: FloatArray, P_prior_next: FloatArray) -> FloatArray:
    """``G = P+ Phi^T (P-)^-1`` (Cholesky of ``P-``; least squares when it is not positive definite)."""
    n = P_post.shape[0]
    A = Phi @ P_post  # (P+ Phi^T)^T
    L = np.zeros((n, n))
    ok = True
    for j in range(n):  # lower Cholesky factor, column by column (LAPACK's potrf criterion)
        s = P_prior_next[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            ok = False
            break
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = P_prior_next[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    if not ok:
        sol = np.linalg.lstsq(P_prior_next, A, rcond=np.finfo(np.float64).eps * n)[0]
        return np.ascontiguousarray(sol.T)
    m = A.shape[1]
    Y = A.copy()
    # L Y = A, then L^T Z = Y, in place, row by row (the inner loops run along contiguous rows)
    for i in range(n):
        for k in range(i):
            lik = L[i, k]
            for c in range(m):
                Y[i, c] -= lik * Y[k, c]
        d = L[i, i]
        for c in range(m):
            Y[i, c] /= d
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, n):
            lki = L[k, i]
            for c in range(m):
                Y[i, c] -= lki * Y[k, c]
        d = L[i, i]
        for c in range(m):
            Y[i, c] /= d
    return np.ascontiguousarray(Y.T)


@numba.njit(cache=True)
def rts_chunk(
    x_prior: FloatArray,
    P_prior: FloatArray,
    Phi: FloatArray,
    x_post: FloatArray,
    P_post: FloatArray,
    carry_x: FloatArray,
    carry_P: FloatArray,
    next_Phi: FloatArray,
    next_P_prior: FloatArray,
    next_x_prior: FloatArray,
    has_next: bool,
    out_x: FloatArray,
    out_diag: FloatArray,
    out_P: FloatArray,
    full: bool,
) -> None:
    """RTS backward over one chunk of records (dense arrays), last record first.

    ``carry_x``, ``carry_P`` hold the smoothed state and covariance of the record after the
    chunk and ``next_*`` its transition, prior covariance and prior state (``has_next``
    False for the last chunk of the log, whose last record is its own smoothed value); on
    return they hold those of the chunk's first record. Writes the smoothed states
    ``out_x (m, n)``, the diagonals of the smoothed covariances ``out_diag (m, n)`` and, with
    ``full``, the covariances ``out_P (m, n, n)``.
    """
    m, n = x_post.shape
    for r in range(m - 1, -1, -1):
        Pp = P_post[r]
        if not has_next:
            xs = x_post[r].copy()
            Ps = Pp.copy()
            has_next = True
        else:
            G = _gain(Pp, next_Phi, next_P_prior)
            xs = x_post[r] + G @ (carry_x - next_x_prior)
            B = Pp + G @ (carry_P - next_P_prior) @ G.T
            Ps = 0.5 * (B + B.T)
        out_x[r] = xs
        for i in range(n):
            out_diag[r, i] = Ps[i, i]
        if full:
            out_P[r] = Ps
        carry_x[:] = xs
        carry_P[:, :] = Ps
        next_Phi[:, :] = Phi[r]
        next_P_prior[:, :] = P_prior[r]
        next_x_prior[:] = x_prior[r]


def rts_backward_records(
    chunks: Sequence[Sequence[FloatArray]], n: int, K: int, full: bool
) -> tuple[FloatArray, FloatArray]:
    """Backward RTS pass over records given chunk by chunk (module docstring).

    Parameters
    ----------
    chunks : sequence of sequence of numpy.ndarray
        Chunk ``c`` is five dense arrays (``x_prior, P_prior, Phi, x_post, P_post``, stacked
        per record) of consecutive records, in order; read from the last.
    n : int
        Number of states.
    K : int
        Total number of records (the sum of the chunk lengths).
    full : bool
        Return the smoothed covariances ``(K, n, n)``; else only their diagonals ``(K, n)``.

    Returns
    -------
    x_s : numpy.ndarray
        Smoothed states ``(K, n)``.
    P_s : numpy.ndarray
        Smoothed covariances ``(K, n, n)``, or their diagonals ``(K, n)``.
    """
    x_s = np.empty((K, n))
    d_s = np.empty((K, n))
    P_s = np.empty((K, n, n)) if full else np.empty((1, n, n))
    carry_x, carry_P = np.zeros(n), np.zeros((n, n))
    nxt_Phi, nxt_Pm, nxt_xm = np.zeros((n, n)), np.zeros((n, n)), np.zeros(n)
    has_next = False
    stop = K
    for c in range(len(chunks) - 1, -1, -1):
        xm, Pm, Phi, xp, Pp = (np.ascontiguousarray(a, dtype=np.float64) for a in chunks[c])
        m = xp.shape[0]
        a = stop - m
        rts_chunk(
            xm,
            Pm,
            Phi,
            xp,
            Pp,
            carry_x,
            carry_P,
            nxt_Phi,
            nxt_Pm,
            nxt_xm,
            has_next,
            x_s[a:stop],
            d_s[a:stop],
            P_s[a:stop] if full else P_s,
            full,
        )
        has_next = True
        stop = a
    return x_s, (P_s if full else d_s)


class SmoothingLog:
    """Forward-run record for the RTS smoother, stored compactly (:mod:`iotnav.engines.smoother_records`).

    Parameters
    ----------
    record_every : int
        Output rows between record points when there is no measurement.
    memory_bytes : int, optional
        Encoded records held in RAM before the later ones are written to an anonymous
        temporary file (:data:`~iotnav.engines.smoother_records.MEMORY_BYTES` by default).
    spill_dir : str, optional
        Folder of that file (the system's temporary folder by default).

    Attributes
    ----------
    record_every : int
        As given.
    t : list of float
        Record times, s.
    x_prior, P_prior, x_post, P_post, Phi : sequence of numpy.ndarray
        Per record point (see the module docstring): read-only views of the store
        (:class:`~iotnav.engines.smoother_records.RecordColumn`; items are copies, ``numpy.asarray``
        stacks them). Records are added by :meth:`record` and :func:`drain_records`, exactly
        as given (covariances must be symmetric to be stored as triangles; others are kept whole).
    dropped_information : list of tuple of float
        Filled by :func:`~iotnav.engines.smoother.augment_acceleration_error`: ``(t, lam_min / max |lam|)`` of each
        record whose update information ``P+^-1 - P-^-1`` had a significantly negative
        eigenvalue (an update that *widened* the covariance, which a re-run cannot replay),
        left out of the re-run.
    """

    def __init__(
        self, record_every: int = 1, *, memory_bytes: int | None = None, spill_dir: str | None = None
    ) -> None:
        self.record_every = record_every
        self.t: list[float] = []
        self.dropped_information: list[tuple[float, float]] = []
        self._memory = MEMORY_BYTES if memory_bytes is None else memory_bytes
        self._spill_dir = spill_dir
        self._store: RecordStore | None = None  # created with the first record (n known then)
        self._stop: int | None = None  # a view's number of stored records
        self._tail: list[FloatArray] | None = None  # a view's extra last record

    def _store_for(self, n: int) -> RecordStore:
        if self._stop is not None:
            raise ValueError("a SmoothingLog view (with_tail) is read-only")
        if self._store is None:
            self._store = RecordStore(n, self._memory, self._spill_dir)
        if self._store.n != n:
            raise ValueError(f"records of {n} states in a log of {self._store.n}")
        return self._store

    def record(
        self,
        t: float,
        x_prior: FloatArray,
        P_prior: FloatArray,
        Phi: FloatArray,
        x_post: FloatArray,
        P_post: FloatArray,
    ) -> None:
        """Append one record point (arrays are copied)."""
        x = np.asarray(x_prior, dtype=float)
        self._store_for(x.size).append([x, P_prior, Phi, x_post, P_post])
        self.t.append(float(t))

    def extend(self, t: Sequence[float], arrays: Sequence[FloatArray]) -> None:
        """Append records given as times and five stacked arrays (``x_prior (m, n)``, ``P_prior (m, n, n)``, ...)."""
        m = len(t)
        if m == 0:
            return
        self._store_for(np.asarray(arrays[0]).shape[1]).extend(arrays)
        self.t.extend(float(v) for v in t)

    def with_tail(
        self,
        t: float,
        x_prior: FloatArray,
        P_prior: FloatArray,
        Phi: FloatArray,
        x_post: FloatArray,
        P_post: FloatArray,
    ) -> SmoothingLog:
        """A read-only view: the records so far plus one more (not stored); shares the store."""
        v = SmoothingLog(self.record_every, memory_bytes=self._memory, spill_dir=self._spill_dir)
        n = len(self)
        v._store = self._store if self._store is not None else RecordStore(np.asarray(x_prior).size)
        v._stop = n
        v._tail = [np.array(a, dtype=float) for a in (x_prior, P_prior, Phi, x_post, P_post)]
        v.t = [*self.t[:n], float(t)]
        v.dropped_information = list(self.dropped_information)
        return v

    def _n_stored(self) -> int:
        if self._stop is not None:
            return self._stop
        return 0 if self._store is None else self._store.count

    def _column(self, j: int) -> Sequence[FloatArray]:
        tail = None if self._tail is None else self._tail[j]
        if self._store is None:
            return [] if tail is None else [tail.copy()]
        return RecordColumn(self._store, j, self._stop, tail)

    @property
    def x_prior(self) -> Sequence[FloatArray]:
        """Prior states ``x-_k``."""
        return self._column(0)

    @property
    def P_prior(self) -> Sequence[FloatArray]:
        """Prior covariances ``P-_k``."""
        return self._column(1)

    @property
    def Phi(self) -> Sequence[FloatArray]:
        """Transitions ``Phi_k`` from record ``k - 1``."""
        return self._column(2)

    @property
    def x_post(self) -> Sequence[FloatArray]:
        """Posterior states ``x+_k``."""
        return self._column(3)

    @property
    def P_post(self) -> Sequence[FloatArray]:
        """Posterior covariances ``P+_k``."""
        return self._column(4)

    @property
    def n_states(self) -> int:
        """Number of states (0 before the first record)."""
        if self._store is not None:
            return self._store.n
        return 0

    def chunks(self) -> Sequence[list[FloatArray]]:
        """The records as dense chunks (:func:`~iotnav.engines.smoother_records.rts_backward_records`'s input).

        A lazy list: chunk ``c`` is decoded (or read back from the temporary file) when indexed.
        """
        return _Chunks(self)

    @property
    def stored_bytes(self) -> tuple[int, int]:
        """``(in RAM, in the temporary file)`` bytes of the stored records."""
        if self._store is None:
            return 0, 0
        return self._store.ram_bytes, self._store.spilled_bytes

    def __len__(self) -> int:
        return self._n_stored() + (0 if self._tail is None else 1)


class _Chunks(Sequence[list[FloatArray]]):
    """Chunks of a :class:`SmoothingLog` decoded on access (a view's stop and tail respected)."""

    def __init__(self, log: SmoothingLog) -> None:
        self._log = log
        st, stop = log._store, log._n_stored()
        n_ch = 0 if st is None or stop == 0 else (stop - 1) // CHUNK + 1
        self._n = n_ch + (0 if log._tail is None else 1)
        self._n_ch = n_ch
        self._stop = stop

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, c: Any) -> Any:
        log = self._log
        if isinstance(c, slice):
            return [self[i] for i in range(*c.indices(self._n))]
        c = int(c) + (self._n if int(c) < 0 else 0)
        if c == self._n_ch:
            assert log._tail is not None
            return [np.asarray(a)[None] for a in log._tail]
        assert log._store is not None
        arrays = log._store.chunk(c)
        k0 = c * CHUNK
        m = min(self._stop - k0, arrays[0].shape[0])
        return [a[:m] for a in arrays]


def record_size(n: int) -> int:
    """Columns of one row of a compiled engine's record buffer for ``n`` states.

    Layout (:func:`write_record`): ``t``, then prior ``x`` (``n``) and ``P`` (``n^2``,
    row-major), ``Phi`` (``n^2``), posterior ``x`` and ``P``.
    """
    return 1 + 2 * n + 3 * n * n


@numba.njit(cache=True)
def write_record(
    rec: FloatArray, i: int, t: float, prior: FloatArray, post: FloatArray, Phi: FloatArray, n: int
) -> None:
    """Write one record point into row ``i`` of ``rec`` and restart ``Phi`` at the identity.

    For engine kernels that record smoothing points without leaving compiled code (layout of
    :func:`record_size`; :func:`drain_records` moves the rows to a :class:`SmoothingLog`).

    Parameters
    ----------
    rec : numpy.ndarray
        Record buffer ``(rows, record_size(n))``.
    i : int
        Row to write.
    t : float
        Time of the record point, s.
    prior, post : numpy.ndarray
        Filter arrays ``x`` (``n``) then ``P`` (``n^2``, row-major) before and after the
        measurement updates at ``t`` (the same array when there is none); only their first
        ``n + n^2`` elements are read.
    Phi : numpy.ndarray
        Transition since the previous record point (``n^2``, row-major); set to the identity.
    n : int
        Number of states.
    """
    m = n + n * n
    rec[i, 0] = t
    for j in range(m):
        rec[i, 1 + j] = prior[j]
        rec[i, 1 + m + n * n + j] = post[j]
    for j in range(n * n):
        rec[i, 1 + m + j] = Phi[j]
        Phi[j] = 1.0 if j % (n + 1) == 0 else 0.0


def drain_records(log: SmoothingLog | None, rec: FloatArray, count: int, n: int) -> None:
    """Append rows ``0 .. count-1`` of a record buffer (:func:`write_record`) to ``log`` (if any)."""
    if count <= 0 or log is None:
        return
    r = rec[:count]
    m = n + n * n
    phi, post = 1 + m, 1 + m + n * n
    log.extend(
        r[:, 0].tolist(),
        [
            r[:, 1 : 1 + n],
            r[:, 1 + n : phi].reshape(count, n, n),
            r[:, phi:post].reshape(count, n, n),
            r[:, post : post + n],
            r[:, post + n :].reshape(count, n, n),
        ],
    )
