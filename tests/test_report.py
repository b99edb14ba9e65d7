"""The report on a hand-built run with known errors: statistics, figures, omissions, CLI."""

from __future__ import annotations

import base64
import io
import json
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from _report_synth import GAP, HOSTILE, OFFSET_E, OFFSET_N, gnss_north_offsets, write_synthetic_run
from iotnav.cli import report as report_cli
from iotnav.report import build_report, load_run, load_truth
from iotnav.report.prepare import GNSS_ONLY, gnss_outages, rejected_fixes, static_periods


class _Tables(HTMLParser):
    """Rows of every ``<table class="stats">`` and the ``<img>`` sources."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self.imgs: list[dict[str, str]] = []
        self._in: bool = False
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag == "table" and a.get("class") == "stats":
            self.tables.append([])
            self._in = True
        elif tag == "tr" and self._in:
            self.tables[-1].append([])
        elif tag in ("td", "th") and self._in:
            self._cell = []
        elif tag == "img":
            self.imgs.append(a)

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._in = False
        elif tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append("".join(self._cell))
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def _parse(path: Path) -> _Tables:
    p = _Tables()
    p.feed(path.read_text(encoding="utf-8"))
    return p


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return write_synthetic_run(tmp_path_factory.mktemp("synth"))


@pytest.fixture(scope="module")
def built(synth: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory):
    run, truth = synth
    out = tmp_path_factory.mktemp("rep") / "page.html"
    return build_report([run], out, truth)


def test_outages_found_from_gaps(synth: tuple[Path, Path]) -> None:
    run = load_run(synth[0])
    assert gnss_outages(run.gnss, 3.0) == [GAP]
    # a gap shorter than factor x median is not an outage
    assert gnss_outages(run.gnss, 20.0) == []
    # a run that goes on after the last fix has a trailing outage
    assert gnss_outages(run.gnss, 3.0, t_end=130.0) == [GAP, (100.0, 130.0)]
    assert gnss_outages(run.gnss, 3.0, t_end=101.0) == [GAP]


def test_periods_and_rejections_read_from_run(synth: tuple[Path, Path]) -> None:
    run = load_run(synth[0])
    assert static_periods(run) == [(0.0, 19.9)]
    rej = rejected_fixes(run)
    assert list(rej["t"]) == [0.0, 1.0, 2.0, 60.0]
    assert np.allclose(rej["pdop"], [15.0, 15.0, 15.0, 2.0])
    assert np.isfinite(rej["lat_deg"]).all()
    assert load_truth(synth[1]).mount_yaw_rad == 0.5


def test_statistics_table_matches_known_errors(built) -> None:
    page = _parse(built.html)
    stats = next(t for t in page.tables if t and t[0][:2] == ["solution", "epochs"])
    header, rows = stats[0], {r[0]: r for r in stats[1:]}
    assert set(rows) == {GNSS_ONLY, "run"}
    col = {h: i for i, h in enumerate(header)}
    # fused: truth + (3, 4) m everywhere -> 5 m horizontal, 3 m |N|, 4 m |E|, on 1001 epochs
    fused = rows["run"]
    assert fused[col["epochs"]] == "1001"
    for c in ("h mean", "h rms", "h p67", "h p95", "h max"):
        assert float(fused[col[c]]) == pytest.approx(np.hypot(OFFSET_N, OFFSET_E), abs=5e-3)
    assert float(fused[col["|N| p95"]]) == pytest.approx(OFFSET_N, abs=5e-3)
    assert float(fused[col["|E| mean"]]) == pytest.approx(OFFSET_E, abs=5e-3)
    # raw fixes: k % 4 m North only
    off = gnss_north_offsets()
    g = rows[GNSS_ONLY]
    assert g[col["epochs"]] == str(off.size)
    expect = {
        "h mean": off.mean(),
        "h rms": np.sqrt(np.mean(off**2)),
        "h p67": np.percentile(off, 67),
        "h p95": np.percentile(off, 95),
        "h max": off.max(),
        "|E| p95": 0.0,
    }
    for c, v in expect.items():
        assert float(g[col[c]]) == pytest.approx(v, rel=5e-3, abs=5e-3), c
    assert built.accuracy["run"]["h_err_mean"] == pytest.approx(5.0, abs=1e-6)


def test_every_figure_is_embedded_and_written_beside(built) -> None:
    page = _parse(built.html)
    names = {p.name for p in built.figures}
    for key in ("map", "errors", "error-distribution", "static", "mount", "boot", "states", "nis", "events"):
        assert f"page_{key}.png" in names, key
    assert len(page.imgs) == len(built.figures)
    for img, png in zip(page.imgs, built.figures, strict=True):
        assert png.parent == built.html.parent
        assert img["data-file"] == png.name
        data = base64.b64decode(img["src"].removeprefix("data:image/png;base64,"))
        assert data == png.read_bytes()
        im = np.asarray(Image.open(io.BytesIO(data)).convert("L"))
        assert im.shape[0] > 200 and im.shape[1] > 400
        assert im.std() > 5.0  # not blank
    # the outage drift table: 5 m at the end of the 30-40 s gap, over 50 m driven
    drift = next(t for t in page.tables if t and t[0][0] == "start, s")
    assert [float(x) for x in drift[1][:4]] == pytest.approx([30.0, 40.0, 10.0, 50.0], abs=0.05)
    assert float(drift[1][4]) == pytest.approx(5.0, abs=5e-3)
    assert built.omitted == {}


def test_page_is_offline_and_escaped(built) -> None:
    """No script but the opt-in tile view's (which requests nothing before the click), no
    external resource, hostile strings escaped."""
    from iotnav.report.page import TILE_SCRIPT

    text = built.html.read_text(encoding="utf-8")
    assert text.count(TILE_SCRIPT) == 1
    data = re.search(r'<script type="application/json" id="tiles-data">(.*?)</script>', text, re.S)
    assert data is not None and json.loads(data.group(1))["series"]
    text = text.replace(TILE_SCRIPT, "").replace(data.group(0), "")
    assert "<script" not in text.lower().replace("&lt;script", "")
    assert not re.search(
        r'(src|href)="(https?:)?//', text.replace('<a href="https://www.openstreetmap.org', "")
    )
    assert "<link" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text
    assert HOSTILE not in text


def test_figures_that_do_not_apply_are_left_out_with_a_note(tmp_path: Path) -> None:
    run, _ = write_synthetic_run(tmp_path, with_events=False)
    rep = build_report([run], tmp_path / "r.html")
    assert set(rep.omitted) >= {"errors", "static", "mount", "boot", "nis"}
    text = rep.html.read_text(encoding="utf-8")
    for note in rep.omitted.values():
        assert note.replace("×", "&#215;") in text or note in text
    names = {p.name for p in rep.figures}
    assert names == {"r_map.png", "r_states.png", "r_events.png"}
    assert len(_parse(rep.html).imgs) == 3
    assert rep.accuracy == {}


def test_load_errors_name_the_file(tmp_path: Path, synth: tuple[Path, Path]) -> None:
    with pytest.raises(FileNotFoundError, match=r"no track\.csv"):
        load_run(tmp_path)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "track.csv").write_text((synth[0] / "track.csv").read_text())
    (bad / "events.json").write_text("[{oops")
    with pytest.raises(ValueError, match=r"events\.json.*not valid JSON"):
        load_run(bad)
    (bad / "events.json").unlink()
    (bad / "track.csv").write_text("t,x\n0,1\n")
    with pytest.raises(ValueError, match=r"track\.csv: missing column\(s\) lat, lon"):
        load_run(bad)


def test_cli_compare_writes_report_with_a_row_per_run(synth: tuple[Path, Path], tmp_path: Path) -> None:
    run, truth = synth
    other = tmp_path / "other"
    other.mkdir()
    for f in ("events.json", "summary.json", "gnss.csv", "track.csv"):
        (other / f).write_bytes((run / f).read_bytes())
    app = typer.Typer()
    report_cli.register(app)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps typer in multi-command mode
        pass

    runner = CliRunner()
    html = tmp_path / "cli" / "x.html"
    args = ["report", str(run), "--truth", str(truth), "--compare", str(other), "--html", str(html)]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert html.is_file() and "x.html" in "".join(res.output.split())
    text = html.read_text(encoding="utf-8")
    assert "run vs other" in text
    rows = {r[0] for t in _parse(html).tables for r in t[1:] if t and t[0][:2] == ["solution", "epochs"]}
    assert rows == {GNSS_ONLY, "run", "other"}  # one baseline: both runs share gnss.csv
    assert "5.00" in res.output  # the accuracy table printed
    res = runner.invoke(app, ["report", str(tmp_path)])
    assert res.exit_code == 2
    assert "no track.csv" in " ".join(res.output.split())
