"""Reports of runs: figures (matplotlib) and a self-contained HTML page.

Data flows one way (STYLE §13): :mod:`~iotnav.report.load` reads a run directory written by
``iotnav run`` (and a truth file), :mod:`~iotnav.report.prepare` re-expresses it in one local
frame and collects periods and event tables (statistics from :mod:`iotnav.eval.metrics`),
:mod:`~iotnav.report.figures` draws, :mod:`~iotnav.report.page` assembles the HTML.

Usage::

    from iotnav.report import build_report

    rep = build_report(["out/run"], truth_path="sim/truth.csv")
    print(rep.html, rep.figures, rep.omitted)
"""

from __future__ import annotations

from iotnav.report.load import Run, Truth, load_run, load_truth
from iotnav.report.page import Report, build_report

__all__ = ["Report", "Run", "Truth", "build_report", "load_run", "load_truth"]
