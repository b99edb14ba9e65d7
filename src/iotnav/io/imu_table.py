"""Layout sniffing and fast numeric parsing of delimited IMU text (the parsing half of :mod:`iotnav.io.imu_csv`).

The delimiter, the preamble, the header and the field count are sniffed from the head of the
file; the body is then parsed by :mod:`pyarrow.csv` straight into float columns, and only when a
needed field is not a number is the file re-read as text and the bad fields found with
vectorised pattern matching. Damaged rows are classified by :mod:`iotnav.io.imu_csv`.
"""

from __future__ import annotations

import bisect
import contextlib
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from io import BytesIO
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from iotnav.io.errors import IngestError
from iotnav.io.report import FileReport, SkipReason

# --------------------------------------------------------------------------------------------
# Sniffing
# --------------------------------------------------------------------------------------------


def _is_number(tok: str) -> bool:
    t = tok.strip().strip("\"'")
    if not t:
        return True  # an empty field is data (missing), not a name
    try:
        float(t)
    except ValueError:
        return False
    return True


@dataclass
class _Layout:
    delimiter: str
    skip_rows: int  # physical lines before the first data line (preamble + header)
    n_fields: int
    header: list[str] | None
    preamble_ignored: dict[str, int]


_PREAMBLE = ("#", "%", "//", ";")
#: A number, and the tokens read as a missing value, as whole-field patterns (pyarrow regex).
_NUM_RE = r"^[-+]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][-+]?[0-9]+)?$"
_NANTOK_RE = r"(?i)^[-+]?(nan|inf|infinity|null|none|n/a|na)?$"


def _sniff(head: bytes, complete: bool, n_fields_hint: int | None) -> _Layout:
    text = head.decode("utf-8", errors="replace")
    if text.startswith("\ufeff"):
        text = text[1:]
    lines = text.splitlines()
    if not complete and lines:
        lines = lines[:-1]  # possibly cut in the middle
    i = 0
    comments: list[str] = []
    blank = 0
    while i < len(lines) and (not lines[i].strip() or lines[i].lstrip().startswith(_PREAMBLE)):
        if lines[i].strip():
            comments.append(lines[i])
        else:
            blank += 1
        i += 1
    body = [ln for ln in lines[i : i + 200] if ln.strip()]
    delim = ","
    best = -1.0
    for d in (",", ";", "\t", "|", " "):
        counts = [ln.count(d) for ln in body[:50]] or [0]
        if max(counts) == 0:
            continue
        mode = max(set(counts), key=counts.count)
        score = counts.count(mode) / len(counts) + (0.01 if d == "," else 0.0)
        if mode > 0 and score > best:
            delim, best = d, score
    field_counts = [ln.count(delim) + 1 for ln in body[:200]]
    n_mode = max(set(field_counts), key=field_counts.count) if field_counts else 0
    header: list[str] | None = None
    skip = i
    ignored = {"comment": len(comments) - 0, "blank": blank}
    first = lines[i] if i < len(lines) else ""
    toks = [t.strip().strip("\"'") for t in first.split(delim)] if first else []
    if toks and not all(_is_number(t) for t in toks):
        header = toks
        skip = i + 1
        ignored["header"] = 1
    elif comments:
        # a commented header just before the data: "# gpst_s,acc_x_g,..."
        last = comments[-1].lstrip().lstrip("#%/;").strip()
        ctoks = [t.strip().strip("\"'") for t in last.split(delim)]
        if len(ctoks) == (n_fields_hint or n_mode) and not any(_is_number(t) for t in ctoks):
            header = ctoks
            ignored["comment"] -= 1
            ignored["header"] = 1
    n_fields = n_fields_hint or (len(header) if header else n_mode)
    if header is not None and n_fields_hint is None and n_mode == len(header) + 1 and body:
        if all(ln.rstrip().endswith(delim) for ln in body[1:20] or body):
            header = [*header, ""]  # consistent trailing delimiter
            n_fields = len(header)
    return _Layout(delim, skip, max(n_fields, 1), header, {k: v for k, v in ignored.items() if v})


# --------------------------------------------------------------------------------------------
# Fast numeric reading
# --------------------------------------------------------------------------------------------


@dataclass
class _Table:
    values: dict[int, npt.NDArray[np.float64]]  # field index -> float column (NaN for missing)
    malformed: npt.NDArray[np.bool_] | None  # rows with a needed field that is not a number
    empty: npt.NDArray[np.bool_]  # rows whose needed fields are all missing
    n: int
    first_line: int  # physical line number (1-based) of the first data line
    bad_lines: list[int]  # physical line numbers consumed by the invalid-row handler

    def line_of(self, row: int) -> int:
        """Physical line number of data row ``row``."""
        k = 0
        while True:
            line = self.first_line + row + k
            k_new = bisect.bisect_right(self.bad_lines, line)
            if k_new == k:
                return line
            k = k_new


def _read_numeric(
    src: str | bytes,
    layout: _Layout,
    needed: Sequence[int],
    rep: FileReport,
    label: str,
    capacity: int,
) -> _Table:
    """Read the ``needed`` fields of every row as float64; count rows of the wrong width.

    The file is streamed block by block (:func:`pyarrow.csv.open_csv`) into preallocated NumPy
    arrays of ``capacity`` rows (the physical line count), so Arrow never holds more than one
    block. Fields are parsed as float64; if a needed field is not a number, the file is read again
    with those fields as bytes and classified by vectorised pattern matching.
    """
    names = [f"c{i}" for i in range(layout.n_fields)]
    wanted = [names[i] for i in sorted(set(needed))]
    bad_lines: list[int] = []

    def on_invalid(row: Any) -> str:
        text = row.text or ""
        where = int(row.number) if row.number is not None else -1
        bad_lines.append(where)
        if text.lstrip().startswith(_PREAMBLE):
            rep.ignore("comment")
        elif not text.strip():
            rep.ignore("empty line")
        else:
            rep.skip(SkipReason.TRUNCATED, where, text)
        return "skip"

    snapshot = (rep.skipped.copy(), rep.ignored.copy(), {k: list(v) for k, v in rep.examples.items()})

    def stream(
        col_type: pa.DataType, encoding: str
    ) -> tuple[dict[int, npt.NDArray[np.float64]], npt.NDArray[np.bool_] | None, int]:
        bad_lines.clear()
        rep.skipped, rep.ignored = snapshot[0].copy(), snapshot[1].copy()
        rep.examples = {k: list(v) for k, v in snapshot[2].items()}
        values = {int(c[1:]): np.empty(capacity, dtype=np.float64) for c in wanted}
        malformed = np.zeros(capacity, dtype=bool) if col_type == pa.binary() else None
        reader = pacsv.open_csv(
            BytesIO(src) if isinstance(src, bytes) else src,
            read_options=pacsv.ReadOptions(
                column_names=names,
                skip_rows=layout.skip_rows,
                use_threads=False,
                block_size=1 << 22,
                encoding=encoding,
            ),
            parse_options=pacsv.ParseOptions(
                delimiter=layout.delimiter,
                quote_char=False,
                ignore_empty_lines=False,
                invalid_row_handler=on_invalid,
            ),
            convert_options=pacsv.ConvertOptions(
                column_types=dict.fromkeys(wanted, col_type),
                include_columns=wanted,
                null_values=[""],
                strings_can_be_null=True,
                check_utf8=False,
            ),
        )
        pos = 0
        for batch in reader:
            m = batch.num_rows
            if pos + m > capacity:  # cannot happen with capacity = line count; be safe
                raise IngestError(label, "more rows than lines while parsing (internal error)")
            for c in wanted:
                col = batch.column(c)
                if malformed is None:
                    _fill_float(values[int(c[1:])], pos, col)
                else:
                    txt = pc.replace_substring_regex(col, r"^[ \t\r]+|[ \t\r]+$", "")
                    is_num = pc.fill_null(pc.match_substring_regex(txt, _NUM_RE), False)
                    is_nan = pc.fill_null(pc.match_substring_regex(txt, _NANTOK_RE), True)
                    num = pc.cast(pc.if_else(is_num, txt, pa.scalar(None, pa.binary())), pa.float64())
                    _fill_float(values[int(c[1:])], pos, num)
                    malformed[pos : pos + m] |= ~(
                        np.asarray(is_num.to_numpy(zero_copy_only=False), bool)
                        | np.asarray(is_nan.to_numpy(zero_copy_only=False), bool)
                    )
            pos += m
        return values, malformed, pos

    # Attempts: float columns as UTF-8; a damaged line that is not valid UTF-8 makes pyarrow fail
    # before our row handler runs ("CSV parse error"), so the file is then re-read as latin-1
    # (every byte decodes; slower); a field that is not a number switches to the bytes path.
    col_type, encoding = pa.float64(), "utf8"
    while True:
        try:
            with _quiet_row_decode_errors():
                values, malformed, n = stream(col_type, encoding)
            break
        except pa.ArrowInvalid as exc:
            msg = str(exc).lower()
            if ("conversion error" in msg or "invalid value" in msg) and col_type == pa.float64():
                col_type = pa.binary()
            elif "parse error" in msg and encoding == "utf8":
                encoding = "latin-1"
            else:
                raise IngestError(label, f"cannot parse as delimited text: {exc}") from None
        except (pa.ArrowException, OSError, UnicodeError) as exc:
            raise IngestError(label, f"cannot parse as delimited text: {exc}") from None
    values = {k: v[:n] for k, v in values.items()}
    if malformed is not None:
        malformed = malformed[:n]
    empty = np.ones(n, dtype=bool)
    for v in values.values():
        empty &= np.isnan(v)
    if malformed is not None:
        empty &= ~malformed
    return _Table(values, malformed, empty, n, layout.skip_rows + 1, sorted(b for b in bad_lines if b >= 0))


@contextlib.contextmanager
def _quiet_row_decode_errors() -> Iterator[None]:
    """Silence the 'exception ignored' report pyarrow emits when it cannot decode an invalid row's
    text for the row handler (the read then fails and is retried as latin-1)."""
    previous = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if not isinstance(unraisable.exc_value, UnicodeDecodeError):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _fill_float(out: npt.NDArray[np.float64], pos: int, col: pa.Array | pa.ChunkedArray) -> None:
    """Write an Arrow float column into ``out[pos:]``, nulls as NaN."""
    chunks = col.chunks if isinstance(col, pa.ChunkedArray) else [col]
    for c in chunks:
        if c.null_count:
            c = pc.fill_null(c, np.nan)
        out[pos : pos + len(c)] = c.to_numpy(zero_copy_only=False)
        pos += len(c)
