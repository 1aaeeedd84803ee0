"""bench/single_view_target.py and bench/angle_error.py: the pure parts, on known inputs."""

from __future__ import annotations

import numpy as np

from bench.angle_error import bin_by_cos
from bench.single_view_target import gt_jumps


def test_gt_jumps_marks_both_sides_of_a_depth_step_and_the_silhouette():
    depth = np.full((6, 8), 2.0)
    depth[:, 4:] = 3.0  # a 50% jump between columns 3 and 4
    depth[:, 2] = 2.01  # 0.5%: smooth at 2% tolerance
    mask = np.ones((6, 8), bool)
    mask[0, :] = False  # silhouette along the top row
    j = gt_jumps(depth, mask, rel=0.02)
    assert j[1:, 3].all() and j[1:, 4].all()
    assert not j[2:, 0].any() and not j[2:, 1:3].any() and not j[2:, 5:].any()
    assert j[0].all() and j[1].all()  # both sides of the mask edge
    assert not gt_jumps(depth, mask, rel=0.6)[2:].any()


def test_bin_by_cos_reports_a_shortfall_at_grazing_only():
    cos = np.array([0.1, 0.1, 0.5, 0.9, 0.9, 0.95])
    err = np.zeros((6, 3))
    err[:2] = -0.1  # too dark where seen edge-on
    gt = np.full((6, 3), 0.5)
    bins = bin_by_cos(cos, err, gt, np.full(6, 0.2), np.full((6, 3), 0.05))
    by = {b["cos"]: b for b in bins}
    assert set(by) == {"[0, 0.2)", "[0.4, 0.6)", "[0.8, 1)"}
    assert abs(by["[0, 0.2)"]["signed_error"] + 0.1) < 1e-12
    assert by["[0, 0.2)"]["sq_error_share"] == 1.0
    assert by["[0.8, 1)"]["signed_error"] == 0.0 and by["[0.8, 1)"]["psnr"] == 120.0
    assert abs(by["[0.8, 1)"]["pixel_share"] - 0.5) < 1e-12


def test_bin_by_cos_reports_depth_error_per_bin_and_skips_missing_depths():
    cos = np.array([0.1, 0.1, 0.1, 0.5, 0.9, 0.9])
    flat = np.zeros((6, 3))
    depth_err = np.array([0.03, -0.01, np.nan, np.nan, 0.001, -0.003])
    bins = bin_by_cos(cos, flat, flat + 0.5, np.zeros(6), flat, depth_err)
    by = {b["cos"]: b for b in bins}
    assert abs(by["[0, 0.2)"]["depth_signed_median"] - 0.01) < 1e-12  # NaN left out
    assert abs(by["[0, 0.2)"]["depth_abs_mean"] - 0.02) < 1e-12
    assert by["[0.4, 0.6)"]["depth_signed_median"] is None  # no depth in that bin
    assert abs(by["[0.8, 1)"]["depth_abs_mean"] - 0.002) < 1e-12
    assert "depth_abs_mean" not in bin_by_cos(cos, flat, flat, np.zeros(6), flat)[0]
