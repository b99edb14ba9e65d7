"""The kernel warm-up run before the test suite: how it shares the targets, its bad arguments."""

from __future__ import annotations

import itertools

import pytest

from iotnav import warmup


def _loads(groups: list[list[str]]) -> list[float]:
    return [sum(warmup.COST_S[t] for t in g) for g in groups]


def test_split_shares_the_costliest_targets_over_the_jobs() -> None:
    groups = warmup.split(warmup.TARGETS, 2)
    assert sorted(itertools.chain(*groups)) == sorted(warmup.TARGETS)  # each target once
    for g in groups:
        assert [warmup.COST_S[t] for t in g] == sorted((warmup.COST_S[t] for t in g), reverse=True)
    # greedy by hand: eskf 40 | techniques 27, qekf 23 (50) | fixes 17 (57) | anchor 13 (63) | pipeline 12
    # (69) | pdr 6 (69) | absfix 3 goes to the first of the two equal loads
    assert groups == [["eskf", "fixes", "pipeline", "absfix"], ["techniques", "qekf", "anchor", "pdr"]]
    two_costliest = sorted(warmup.TARGETS, key=lambda t: -warmup.COST_S[t])[:2]
    assert {groups[0][0], groups[1][0]} == set(two_costliest)  # apart, each first in its process
    # greedy longest-first is within 7/6 of the best two-way split (Graham 1969), found here by
    # trying every subset
    total = sum(warmup.COST_S.values())
    best = min(
        max(s := sum(warmup.COST_S[t] for t in sub), total - s)
        for k in range(len(warmup.TARGETS) + 1)
        for sub in itertools.combinations(warmup.TARGETS, k)
    )
    assert max(_loads(groups)) <= 7.0 / 6.0 * best + 1e-9
    assert warmup.split(["anchor", "eskf"], 4) == [["eskf"], ["anchor"]]
    assert warmup.split(["fixes"], 0) == [["fixes"]]


def test_every_registered_engine_is_warmed() -> None:
    from iotnav.engines.registry import available_engines

    assert sorted(warmup.ENGINES) == sorted(available_engines())
    assert set(warmup.TARGETS) == {*warmup.ENGINES, "techniques"}
    assert set(warmup.COST_S) == set(warmup.TARGETS)


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
