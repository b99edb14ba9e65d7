"""The ``iotnav`` command line: the only place that knows about terminals.

Each sub-module registers its commands on :data:`app` through a ``register(app)`` function;
the maths lives below and never imports this package.
"""

from __future__ import annotations

import typer

from iotnav.cli import _commands

app = typer.Typer(
    name="iotnav",
    help="Clean, high-rate positions from low-cost IoT trackers (GNSS + MEMS IMU).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_commands.register_all(app)


def main() -> None:
    """Entry point of the ``iotnav`` console script."""
    app()
