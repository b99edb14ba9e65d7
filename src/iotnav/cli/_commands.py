"""Collects every command module's ``register(app)``."""

from __future__ import annotations

import typer


def register_all(app: typer.Typer) -> None:
    """Register the commands of every CLI module on ``app``."""
    from iotnav.cli import (
        attitude,
        bench,
        characterize,
        demo,
        evaluate,
        firmware,
        fleet,
        ingest,
        magcal,
        nodes,
        report,
        run,
        serve,
        simulate,
        study,
    )

    ingest.register(app)
    demo.register(app)
    evaluate.register(app)
    simulate.register(app)
    characterize.register(app)
    magcal.register(app)
    run.register(app)
    fleet.register(app)
    study.register(app)
    attitude.register(app)
    nodes.register(app)
    report.register(app)
    bench.register(app)
    serve.register(app)
    firmware.register(app)
