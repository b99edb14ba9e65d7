"""Table I operation counts (analytic formulas of iotnav.techniques.cost)."""

from __future__ import annotations

from iotnav.techniques.cost import cholesky_cost, kf_predict_cost, kf_update_cost, table_i


def test_predict_reproduces_fusion_filter_row() -> None:
    assert kf_predict_cost(9, 3) == (1476, 1566)  # paper Table I, block 6


def test_predict_333_mults_match_paper_without_control() -> None:
    sums, mults = kf_predict_cost(3, 0)
    assert mults == 63  # paper
    assert sums == 51  # paper says 54 (see module docstring)


def test_cholesky_counts_small_cases() -> None:
    # 1x1: one sqrt; 2x2: sqrt, division, square, subtraction, sqrt
    assert cholesky_cost(1) == (0, 1)
    assert cholesky_cost(2) == (1, 4)


def test_table_has_ours_and_paper() -> None:
    t = table_i()
    assert t["kf953_update"]["paper"]["mults"] == 2869
    assert set(t["kf333_update"]) == {"ours", "ours_joseph", "paper"}
    assert kf_update_cost(3, 3)[1] < kf_update_cost(3, 3, joseph=True)[1]
