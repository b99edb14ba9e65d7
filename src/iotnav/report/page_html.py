"""HTML building blocks of the run report (:mod:`iotnav.report.page`).

A :class:`Section` is one part of the page (a figure, HTML, or a note why it is left out);
:func:`esc`, :func:`fmt` and :func:`table` write escaped text, numbers and tables;
:func:`png_bytes` renders a figure; ``_render`` lays the sections out as one self-contained page
(inline :data:`CSS`, figures as base64 PNG, no external resource).
"""

from __future__ import annotations

import base64
import html
import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure


@dataclass
class Section:
    """One part of the page: a figure and/or HTML, or a note saying why it is left out."""

    key: str
    title: str
    figure: Figure | None = None
    caption: str = ""
    body: str = ""
    note: str = ""
    png: Path | None = None


# ---------------------------------------------------------------------------- html helpers
def esc(x: Any) -> str:
    """HTML-escape ``str(x)``."""
    return html.escape(str(x), quote=True)


def fmt(x: Any, digits: int = 3) -> str:
    """A number for a table: NaN/None as an en dash, floats to ``digits`` significant digits."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        v = float(x)
        if not math.isfinite(v):
            return "–"
        if v != 0.0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
            return f"{v:.{digits}g}"
        return f"{v:.{max(0, digits - 1 - math.floor(math.log10(abs(v))) if v else 2)}f}"
    return str(x)


def table(header: Sequence[str], rows: Sequence[Sequence[Any]], cls: str = "") -> str:
    """An HTML table; cells are escaped and numbers formatted with :func:`fmt`."""
    h = "".join(f"<th>{esc(c)}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(fmt(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{esc(cls)}"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


def _flatten(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    if isinstance(d, dict):
        out: list[tuple[str, Any]] = []
        for k, v in d.items():
            out += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    if isinstance(d, list) and all(not isinstance(v, (dict, list)) for v in d):
        return [(prefix, ", ".join(fmt(v) for v in d))]
    if isinstance(d, list):
        out = []
        for k, v in enumerate(d):
            out += _flatten(v, f"{prefix}[{k}]")
        return out
    return [(prefix, d)]


def png_bytes(fig: Figure) -> bytes:
    """Render a figure to PNG bytes (100 dpi)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _slug(s: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", s.lower()).strip("-")


# ---------------------------------------------------------------------------- page
CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#1f3b57;color:#fff;padding:1rem 2rem}
header h1{margin:0 0 .3rem 0;font-size:1.5rem}
header p{margin:.1rem 0;opacity:.9}
nav{padding:.5rem 2rem;background:#e9eef3;font-size:.9rem}
nav a{margin-right:1rem;color:#1f3b57}
main{padding:0 2rem 2rem 2rem;max-width:1400px}
section{background:#fff;border:1px solid #ddd;border-radius:6px;padding:.5rem 1.2rem 1rem;margin:1rem 0}
h2{font-size:1.2rem;border-bottom:1px solid #eee;padding-bottom:.3rem}
figure{margin:.5rem 0}
figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.88rem;color:#444;margin-top:.3rem}
table{border-collapse:collapse;margin:.6rem 0;font-size:.85rem}
th,td{border:1px solid #ddd;padding:.2rem .5rem;text-align:right}
th{background:#f0f3f6}
td:first-child,th:first-child{text-align:left}
table.config td,table.kv td,table.events td{text-align:left}
table.events td:last-child{font-family:monospace;font-size:.78rem}
.note{color:#666;font-style:italic}
pre{font-size:.75rem;max-height:30rem;overflow:auto;background:#f6f6f6;padding:.5rem}
.tilemap{position:relative;overflow:hidden;border:1px solid #ddd;background:#eef}
.tilemap img{position:absolute;width:256px;height:256px}
.tilemap svg{position:absolute;left:0;top:0}
.tilemap .attribution{position:absolute;right:0;bottom:0;background:rgba(255,255,255,.8);font-size:.7rem;padding:0 .3rem}
"""


def _render(sections: list[Section], title: str, subtitle: str) -> str:
    nav = "".join(f'<a href="#{esc(s.key)}">{esc(s.title)}</a>' for s in sections)
    out = []
    for s in sections:
        parts = [f'<section id="{esc(s.key)}"><h2>{esc(s.title)}</h2>']
        if s.note:
            parts.append(f'<p class="note omitted">{esc(s.note)}</p>')
        if s.png is not None and s.figure is not None:
            data = base64.b64encode(s.png.read_bytes()).decode("ascii")
            parts.append(
                f'<figure><img src="data:image/png;base64,{data}" alt="{esc(s.title)}" '
                f'data-file="{esc(s.png.name)}"><figcaption>{esc(s.caption)}</figcaption></figure>'
            )
        parts.append(s.body)
        parts.append("</section>")
        out.append("".join(parts))
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title><style>{CSS}</style></head><body>"
        f"<header><h1>{esc(title)}</h1>{subtitle}</header><nav>{nav}</nav><main>"
        + "\n".join(out)
        + "</main></body></html>\n"
    )
