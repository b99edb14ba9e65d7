"""Which module holds each command, and a command group that imports a module only when needed.

``iotnav --help`` lists every command from :data:`COMMANDS` alone (a name, its module and its
one-line help), so it imports no engine, no numba, no pandas and no matplotlib; running a
command imports its module only. ``tests/test_cli_startup.py`` checks that the table agrees
with what the modules register. A command missing from the table still runs: an unknown
name makes the group import every command module (:func:`command_modules`) before it gives up.
"""

from __future__ import annotations

import gc
import importlib
from typing import Any

import typer
import typer.main
from typer.core import TyperCommand, TyperGroup

#: Command name -> (module under ``iotnav.cli`` whose ``register(app)`` adds it, one-line help).
#: In the order ``iotnav --help`` lists them.
COMMANDS: dict[str, tuple[str, str]] = {
    "ingest": ("ingest", "Read tracker logs, merge them into one timeline, print the ingest report."),
    "export": ("ingest", "Export a track to CSV, GeoJSON, GPX 1.1 or KML."),
    "demo": ("demo", "Ingest the bundled real log, then simulate, fuse and evaluate a scenario."),
    "eval": (
        "evaluate",
        "Print and write OUT/eval.json: horizontal error statistics (metres) against truth.",
    ),
    "simulate": (
        "simulate",
        "Simulate a scenario: gnss.nmea, imu.csv, truth.csv, scenario.json (and more) in --out.",
    ),
    "characterize": (
        "characterize",
        "IMU noise from a static recording: Table 2 RMS, Allan terms, plot and noise_model.toml.",
    ),
    "calibrate-mag": (
        "magcal",
        "Fit hard and soft iron (the device must turn about all its axes) and write them as config.",
    ),
    "run": (
        "run",
        "Fuse a log with an engine; write OUT/track.csv, events.json, summary.json, trips.csv, GeoJSON, GPX.",
    ),
    "cost": (
        "run",
        "Print Table I of Forno et al. 2020 for the configured pipeline: ours / paper, and time per call.",
    ),
    "run-many": (
        "fleet",
        "Fuse every device's log with an engine; write OUT/<device>/ (as iotnav run) and "
        "OUT/fleet_summary.json.",
    ),
    "study": ("study", "Studies: paper tables on simulated scenarios, outages on real drives."),
    "attitude": (
        "attitude",
        "Estimate attitude per sample; print BROAD's RMSE metrics when the file has truth.",
    ),
    "nodes": (
        "nodes",
        "Localize non-GNSS nodes from anchor tracks and RSSI reports (anchor-node mechanism).",
    ),
    "report": ("report", "Write OUT/report.html (self-contained, offline) and its PNG figures beside it."),
    "bench": ("bench", "Run every benchmark script and regenerate BENCHMARKS.md."),
    "serve": (
        "serve",
        "Serve trackers live: Teltonika on TCP, OsmAnd and OwnTracks on HTTP, a Traccar-compatible API.",
    ),
    "worker": (
        "worker",
        "Process a share of the fleet from NATS JetStream: partitions by lease, state in the database.",
    ),
    "reprocess": (
        "reprocess",
        "Re-run the stored fixes of every (device, UTC day) with ENGINE; write one CSV per device-day.",
    ),
    "firmware": ("firmware", "C99 firmware library of the engines (firmware/)."),
    "plan": ("plan", "Plan a tracker: battery life per GNSS duty cycle beside the accuracy it costs."),
}


#: Modules of ``iotnav.cli`` whose ``register`` adds to a sub-app, not to the top level.
SUB_APP_MODULES = frozenset({"outages"})  # registered by study.register on the study sub-app


def command_modules() -> list[str]:
    """Every module of ``iotnav.cli`` that registers top-level commands.

    Those of :data:`COMMANDS` first, then any other found by listing the package folder
    (without importing it).
    """
    import pkgutil

    import iotnav.cli

    found = sorted(
        m.name
        for m in pkgutil.iter_modules(iotnav.cli.__path__)
        if not m.name.startswith("_") and m.name not in SUB_APP_MODULES
    )
    return list(dict.fromkeys([*(m for m, _ in COMMANDS.values()), *found]))


# Commands and contexts are typed Any: recent typer (0.29) carries its own copy of click, older
# versions use click itself, and TyperCommand / TyperGroup derive from whichever it is.


def module_commands(module: str) -> dict[str, Any]:
    """The click commands that ``iotnav.cli.<module>``'s ``register(app)`` adds, by name."""
    mod = importlib.import_module(f"iotnav.cli.{module}")
    sub = typer.Typer()
    mod.register(sub)
    sub.callback()(_noop)  # always a group, also for a module with one command
    return dict(typer.main.get_group(sub).commands)


def _noop() -> None:
    return None


class LazyGroup(TyperGroup):
    """The top-level ``iotnav`` group: commands listed from :data:`COMMANDS`, loaded when run."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._loaded: dict[str, Any] = {}
        self._modules: set[str] = set()

    def _load(self, module: str) -> None:
        if module not in self._modules:
            for name, cmd in module_commands(module).items():
                self._loaded[name] = cmd
                self.add_command(cmd, name)  # also what click's "did you mean" looks in
            self._modules.add(module)
            # the imported modules' objects live as long as the process: moved out of the
            # collector's generations, its full collections no longer walk them (a run of
            # `iotnav run` spent 0.15-0.2 s in them, most of it on these objects)
            gc.freeze()

    def list_commands(self, ctx: Any) -> list[str]:
        return [*COMMANDS, *(n for n in self._loaded if n not in COMMANDS)]

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        """The real command once loaded; for the help listing, a stand-in with the one-line help."""
        if cmd_name in self._loaded:
            return self._loaded[cmd_name]
        if cmd_name in COMMANDS:
            return TyperCommand(cmd_name, help=COMMANDS[cmd_name][1])
        return None

    def resolve_command(self, ctx: Any, args: list[str]) -> Any:
        """Import the module of the command about to run (every module for a name not listed)."""
        if args:
            name = args[0]
            if name in COMMANDS:
                self._load(COMMANDS[name][0])
            elif name not in self._loaded and not name.startswith("-"):
                for module in command_modules():
                    self._load(module)
        return super().resolve_command(ctx, args)
