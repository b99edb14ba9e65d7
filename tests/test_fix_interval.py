"""Fix-interval study, ``iotnav study fix-interval`` and the ``run --fixes`` helper."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import typer
from typer.testing import CliRunner

from iotnav import sim
from iotnav.cli import study as study_cli
from iotnav.eval.fix_interval import FixIntervalConfig, format_tables, study
from iotnav.io import ingest

SHORT = (("motion.laps", 1), ("motion.wait_start_s", 5.0), ("motion.wait_end_s", 2.0))


def test_study_table_layout_and_error_growth_with_the_interval() -> None:
    df = study(FixIntervalConfig(intervals_s=(1.0, 5.0), modes=("none", "fixes"), seed=11, overrides=SHORT))
    assert set(df["mode"]) == {"none", "fixes"}
    assert sorted(df["interval_s"].unique()) == [1.0, 5.0]
    for mode in ("none", "fixes"):
        sub = df[df["mode"] == mode].set_index("interval_s")
        assert sub.loc[5.0, "h_mean"] > sub.loc[1.0, "h_mean"]
        for k in ("n", "e"):
            assert sub.loc[1.0, f"{k}_mean"] <= sub.loc[1.0, f"{k}_p95"]
    md = format_tables(df)
    assert "**fixes** (m)" in md and "| N |" in md and "| E |" in md


def test_cli_fix_interval_prints_the_tables(tmp_path: Path) -> None:
    app = typer.Typer()
    study_cli.register(app)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps "study" a sub-command
        pass

    out = tmp_path / "t.md"
    args = ["study", "fix-interval", "--intervals", "2", "--runs", "1", "--markdown", str(out)]
    for k, v in SHORT:
        args += ["--set", f"{k}={v}"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "bias/drift from fixes" in res.output
    assert "Table 4" in res.output
    assert "**reference** (m)" in out.read_text()
    bad = CliRunner().invoke(app, ["study", "fix-interval", "--intervals", "x"])
    assert bad.exit_code == 2


def test_run_fixes_reads_the_file_and_fuses(tmp_path: Path) -> None:
    res = sim.build("pedestrian-fixes", seed=12, overrides={**dict(SHORT), "duration_s": 30.0})
    d = tmp_path / "log"
    sim.write(res, d)
    log = ingest([d / "imu.csv"])
    track = study_cli.run_fixes(log, d / "fixes.csv")
    assert len(track) == len(log.imu)
    s = track.attrs["summary"]
    assert s["fixes_ingest"]["records"]["fix"] == len(res.fixes)
    # 0.5 s latency: every fix is applied at its t_valid by re-propagation ("applied")
    assert s["counts"]["applied"] == len(res.fixes) - (res.fixes["t_arrival"] > log.imu["t"].max()).sum()
    assert (track["source"] == "dr").sum() > 0
    assert isinstance(track, pd.DataFrame)
    try:
        study_cli.run_fixes(log, d / "fixes.csv", engine="eskf")
    except ValueError as exc:
        assert "absfix" in str(exc)
    else:  # pragma: no cover
        raise AssertionError("expected ValueError")
