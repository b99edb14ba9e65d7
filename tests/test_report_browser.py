"""The report in a real headless browser: it loads offline, every figure decodes, no console errors.

Skips only when Chromium is not installed (CI installs Debian's ``chromium``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from _browser import chromium, load_page
from iotnav import sim
from iotnav.engines.base import run_batch
from iotnav.engines.registry import make_engine
from iotnav.io import ingest
from iotnav.report import build_report
from iotnav.runs import load_stored_position, write_run

pytestmark = pytest.mark.skipif(
    chromium() is None, reason="chromium not installed (apt-get install chromium)"
)


def _visible(png: Path) -> np.ndarray:
    im = np.asarray(Image.open(png).convert("RGB"), dtype=float)
    assert im.shape[0] > 500 and im.shape[1] >= 1000
    return im


def test_checker_catches_a_broken_page(tmp_path: Path) -> None:
    """The probe is not vacuous: a bad image and a script error are seen."""
    good = "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg=="
    page = tmp_path / "bad.html"
    page.write_text(
        "<!DOCTYPE html><html><head><title>t</title></head><body>"
        f'<img src="data:image/png;base64,{good}"><img src="data:image/png;base64,AAAA">'
        "<script>no_such_function();</script></body></html>"
    )
    res = load_page(page, tmp_path / "bad.png", height=600)
    assert (res.images_ok, res.images_total) == (1, 2)
    assert res.errors >= 1
    assert any("no_such_function" in c for c in res.console)


def test_report_of_simulated_runs_renders_in_browser(tmp_path: Path) -> None:
    """A cold-boot walk fused by two engines, compared against truth, viewed in Chromium."""
    result = sim.build("walk-cold-boot", seed=3)
    sim_dir = tmp_path / "sim"
    sim.write(result, sim_dir)
    log = ingest([sim_dir / "gnss.nmea", sim_dir / "imu.csv"])
    stored = load_stored_position(sim_dir / "last_position.json")
    runs = []
    for name in ("pipeline", "eskf"):
        track = run_batch(make_engine(name, None, stored=stored, store=None), log)
        write_run(tmp_path / name, track, log, name, 0.0)
        runs.append(tmp_path / name)
    rep = build_report(runs, tmp_path / "report" / "index.html", sim_dir / "truth.csv")
    # the walk has a boot with rejected fixes, static periods and truth
    assert {"map", "errors", "boot", "static", "events"} <= {p.stem.split("_", 1)[1] for p in rep.figures}
    assert set(rep.accuracy) >= {"pipeline", "eskf"}

    shot = tmp_path / "shot.png"
    res = load_page(rep.html, shot)
    assert res.images_total == len(rep.figures) > 5
    assert res.images_ok == res.images_total, "some figure did not decode in the browser"
    assert res.errors == 0
    assert res.console == []
    im = _visible(shot)
    assert im.std() > 20.0  # not a blank page
    assert len(np.unique(im.reshape(-1, 3), axis=0)) > 100  # figures, not just text on white
