"""Table I operation counts (analytic formulas of iotnav.techniques.cost)."""

from __future__ import annotations

from iotnav.techniques.cost import (
    cholesky_cost,
    full_table,
    kf_predict_cost,
    kf_update_cost,
    load_position_cost,
    lowpass3_worst_cost,
    mean_cost,
    mount_cost,
    table_i,
)


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


def test_mean_of_buffer_formula_and_paper_static_row() -> None:
    # mean of N d-vectors: d (N - 1) sums, d divisions; the paper's 40 FLOPs = 20 2-D positions
    assert mean_cost(20, 2) == (38, 2)
    assert sum(mean_cost(20, 2)) == 40
    assert mean_cost(10, 3) == (27, 3)


def test_lowpass3_worst_case_is_three_means() -> None:
    # n = 10, 6, 10 NED positions: 3 * (9 + 5 + 9) = 69 sums, 3 * 3 = 9 divisions
    assert lowpass3_worst_cost(10, 6, 10) == (69, 9)


def test_load_position_haversine_count() -> None:
    # 16 mults (3 radians, 2 halvings, 2 sin, 2 squares, 2 cos, 2 products, sqrt, asin, 2R)
    # and 5 sums (dlat, dlon, sum under the root, min(1, .), threshold comparison)
    assert load_position_cost() == (5, 16)


def test_mount_cost_by_hand() -> None:
    k, b, m = 100, 8, 3
    c = mount_cost(k, b, m)
    # mean of buffer: 2 K + 4 (K - 1) sums, 3 K + 4 mults
    assert c["mean_of_buffer"] == (200 + 396, 300 + 4)
    # per interval: levelling 15 / 29, row 2 / 3, smoothing 5 * 4 = 20 / 5 * 5 + 5 = 30
    per_interval = (15 + 2 + 20, 29 + 3 + 30)
    # per buffer: lsq sums 4 B + 4 (B - 1) / 8 B, forgetting 7 + 4 + 2 / 2 + 4 + 3,
    # gate 3 / 7, three estimates 9 / 48
    other = (8 * per_interval[0] + 60 + 13 + 3 + 9, 8 * per_interval[1] + 64 + 9 + 7 + 48)
    assert c["other_processing"] == other == (381, 624)
    assert c["rotm_conversion"] == (6, 14)  # 20 FLOPs, as in the paper
    assert c["total"] == (596 + 381 + 6, 304 + 624 + 14)


def test_full_table_rows_carry_paper_values() -> None:
    rows = {r["key"]: r for r in full_table(imu_rate_hz=100.0, gnss_rate_hz=1.0)}
    assert rows["load_position"]["paper"]["flops"] == 4
    assert rows["static_mean"]["paper"]["flops"] == 40
    assert rows["mount_total"]["paper"]["flops"] == 134
    assert rows["mount_rotm"]["flops"] == 20
    assert rows["tilt_total"]["paper"] == {"flops": 423, "sums": 267, "mults": 333}
    assert rows["gyro_bias_total"]["paper"]["flops"] == 303
    assert rows["fusion_total"]["paper"] == {"flops": 5243, "sums": 3969, "mults": 4435}
    assert rows["fusion_predict"]["sums"] == 1476 and rows["fusion_predict"]["mults"] == 1566
    # ours: every FLOP count is sums + mults, and totals are the sums of their parts
    for r in rows.values():
        assert r["flops"] == r["sums"] + r["mults"]
    assert rows["tilt_total"]["flops"] == rows["tilt_predict"]["flops"] + rows["tilt_update"]["flops"]
    assert rows["fusion_total"]["sums"] == rows["fusion_predict"]["sums"] + rows["fusion_update"]["sums"]
