"""The ``iotnav`` command table: listed without importing the commands, agreeing with them (layer a)."""

from __future__ import annotations

import importlib
import subprocess
import sys

import typer
import typer.main
from typer.testing import CliRunner

from iotnav.cli import _commands, app

runner = CliRunner()
HEAVY = ("numba", "pandas", "matplotlib", "scipy", "iotnav.engines", "iotnav.io")


def _registered() -> dict[str, tuple[str, str]]:
    """What every command module's ``register(app)`` adds: name -> (module, first paragraph of its help)."""
    out: dict[str, tuple[str, str]] = {}
    for module in _commands.command_modules():
        sub = typer.Typer()
        importlib.import_module(f"iotnav.cli.{module}").register(sub)
        sub.callback()(lambda: None)
        for name, cmd in typer.main.get_group(sub).commands.items():
            text = cmd.short_help or cmd.help or ""
            out[name] = (module, " ".join(text.split("\n\n")[0].split()))
    return out


def test_table_agrees_with_the_modules() -> None:
    # a new command module or command: add its line to _commands.COMMANDS (name, module, help)
    assert _registered() == {n: (m, " ".join(h.split())) for n, (m, h) in _commands.COMMANDS.items()}


def test_help_imports_no_command_module() -> None:
    code = (
        "import sys\n"
        "from iotnav.cli import main\n"
        "sys.argv = ['iotnav', '--help']\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert e.code == 0, e.code\n"
        f"print(sorted(m for m in sys.modules if m.startswith({HEAVY!r})))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "run" in res.stdout and "calibrate-mag" in res.stdout  # the listing was printed
    assert res.stdout.strip().splitlines()[-1] == "[]"


def test_every_listed_command_runs_its_own_help() -> None:
    for name in _commands.COMMANDS:
        res = runner.invoke(app, [name, "--help"])
        assert res.exit_code == 0, (name, res.output)
        assert "Usage" in res.output, name


def test_unknown_and_unlisted_commands(monkeypatch) -> None:
    res = runner.invoke(app, ["ruun"])
    assert res.exit_code == 2
    assert "Did you mean 'run'" in res.output
    # A command a module registers but the table misses still runs (every module is imported).
    table = dict(_commands.COMMANDS)
    del table["cost"]
    monkeypatch.setattr(_commands, "COMMANDS", table)
    res = runner.invoke(app, ["cost", "--help"])
    assert res.exit_code == 0, res.output
    assert "Table I" in res.output
