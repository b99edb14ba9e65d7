"""``iotnav simulate``: write a named scenario's simulated logs and truth to a directory."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from iotnav.cli._common import console, parse_sets, progress, user_errors


def register(app: typer.Typer) -> None:
    """Register ``simulate`` on ``app``."""

    @app.command("simulate")
    @user_errors
    def simulate_cmd(
        scenario: Annotated[str | None, typer.Argument(help="Scenario name (see --list).")] = None,
        out: Annotated[Path | None, typer.Option("--out", "-o", help="Output directory.")] = None,
        seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
        set_: Annotated[
            list[str] | None,
            typer.Option("--set", help="Override a parameter, key=value (repeatable), e.g. duration_s=600."),
        ] = None,
        list_: Annotated[bool, typer.Option("--list", help="List the scenarios and exit.")] = False,
        params: Annotated[bool, typer.Option("--params", help="List the scenario's parameter keys.")] = False,
    ) -> None:
        """Simulate a scenario: gnss.nmea, imu.csv, truth.csv, scenario.json (and more) in --out."""
        from iotnav import sim

        if list_:
            table = Table(title="scenarios")
            table.add_column("name")
            table.add_column("description")
            for name in sim.list_scenarios():
                table.add_row(name, sim.default_config(name).description)
            console.print(table)
            return
        if scenario is None:
            raise ValueError("give a scenario name (iotnav simulate --list shows them)")
        if params:
            cfg = sim.default_config(scenario)
            for key in sim.parameter_keys(cfg):
                console.print(key)
            return
        if out is None:
            raise ValueError("--out DIR is required")
        overrides = parse_sets(set_, "imu.preset=mpu6050")
        with progress(f"simulating {scenario}", total=100.0) as advance:
            done = [0.0]

            def report(frac: float, lo: float, span: float) -> None:
                target = 100.0 * (lo + span * frac)
                if target > done[0]:
                    advance(target - done[0])
                    done[0] = target

            result = sim.build(
                scenario, seed=seed, overrides=overrides, progress=lambda f: report(f, 0.0, 0.7)
            )
            files = sim.write(result, out, progress=lambda f: report(f, 0.7, 0.3))
        for f in files:
            console.print(f"wrote {f}")
