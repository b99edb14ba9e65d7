"""The kernel warm-up run before the test suite: how it shares the engines, its bad arguments."""

from __future__ import annotations

import pytest

from iotnav import warmup


def test_split_shares_the_costliest_engines_over_the_jobs() -> None:
    assert warmup.split(warmup.ENGINES, 2) == [
        ["eskf", "pipeline", "pdr", "absfix"],
        ["qekf", "fixes", "anchor"],
    ]
    assert warmup.split(["anchor", "eskf"], 4) == [["eskf"], ["anchor"]]
    assert warmup.split(["fixes"], 0) == [["fixes"]]


def test_every_registered_engine_is_warmed() -> None:
    from iotnav.engines.registry import available_engines

    assert sorted(warmup.ENGINES) == sorted(available_engines())


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["nosuch"], "unknown engine(s) nosuch"), (["--jobs", "two"], "--jobs 'two': expected a whole number")],
)
def test_bad_arguments_are_a_clear_error(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        warmup.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
