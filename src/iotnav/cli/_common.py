"""Shared CLI helpers: console, user-facing errors, progress bars."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import wraps
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from iotnav.io.errors import IngestError

console = Console()
err_console = Console(stderr=True)

F = TypeVar("F", bound=Callable[..., Any])


def user_errors(func: F) -> F:
    """Turn errors caused by the user's input into a message and exit code 2."""

    @wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except (IngestError, FileNotFoundError, IsADirectoryError, ValueError) as exc:
            # soft_wrap: the message is one line (paths copy whole); escape: a "[" in a path
            # or value is text, not rich markup.
            err_console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(code=2) from None

    return wrapper  # type: ignore[return-value]


@contextmanager
def progress(description: str, total: float | None) -> Iterator[Callable[[float], None]]:
    """A rich progress bar; yields ``advance(n)``. Silent when not on a terminal."""
    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
        disable=not err_console.is_terminal,
    ) as prog:
        task = prog.add_task(description, total=total)

        def advance(n: float = 1.0) -> None:
            prog.advance(task, n)

        yield advance


def parse_sets(items: list[str] | None, example: str = "duration_s=600") -> dict[str, str]:
    """``--set key=value`` options (repeatable) as an ordered dict of strings.

    Raises
    ------
    ValueError
        For an item without ``=`` or with an empty key (shown to the user by :func:`user_errors`).
    """
    out: dict[str, str] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {item!r}: expected key=value, e.g. {example}")
        out[key.strip()] = value.strip()
    return out


def parse_positive_floats(text: str, option: str, what: str) -> tuple[float, ...]:
    """A comma-separated list of positive numbers (``--lengths 15,30,60``).

    Raises
    ------
    ValueError
        For a non-number, an empty list or a value <= 0; ``what`` names the values in the
        message (e.g. "outage lengths").
    """
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"{option} {text!r}: expected numbers separated by commas") from None
    if not values or min(values) <= 0:
        raise ValueError(f"{option}: expected positive {what}")
    return values
