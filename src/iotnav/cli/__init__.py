"""The ``iotnav`` command line: the only place that knows about terminals.

Each sub-module registers its commands on an app through a ``register(app)`` function; the
maths lives below and never imports this package. :data:`app` lists the commands from
:data:`iotnav.cli._commands.COMMANDS` and imports a command's module only when that command
runs, so ``iotnav --help`` starts in a fraction of a second.
"""

from __future__ import annotations

import typer

from iotnav.cli._commands import LazyGroup

app = typer.Typer(
    name="iotnav",
    help="Clean, high-rate positions from low-cost IoT trackers (GNSS + MEMS IMU).",
    cls=LazyGroup,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    # a callback makes typer build a group even though no command is registered up front
    return None


def main() -> None:
    """Entry point of the ``iotnav`` console script."""
    app()
