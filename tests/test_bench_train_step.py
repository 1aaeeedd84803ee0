"""bench.train_step runs end to end on CPU and reports the ratios issue 5 asks for."""

from __future__ import annotations

import argparse
import math

import pytest

from bench.common import bench_camera
from bench.train_step import MASKED_STEP, format_table, neighbour_camera, paired_ratio, run


@pytest.mark.parametrize(("no_roughness", "compare"), [(False, "centre"), (True, None)])
def test_train_step_bench_runs_on_cpu(no_roughness: bool, compare: str | None):
    args = argparse.Namespace(
        compare_order=compare,
        compare_fresnel=compare is not None,
        no_roughness=no_roughness,
        device="cpu",
        backend="cpu",
        size=32,
        n=600,
        envmap=8,
        repeat=2,
        warmup=0,
        threads=1,
        split_threads=False,
    )
    res = run(args)
    names = [r["case"] for r in res["rows"]]
    assert names[0] == "plain render"
    order_case = ["full step (multi-view phase), splat_order centre"] if compare else []
    fresnel_case = [f"{MASKED_STEP}, without Fresnel"] if compare else []
    assert names[-2 - len(order_case) - len(fresnel_case) :] == [
        "full step (multi-view phase)",
        MASKED_STEP,
        *order_case,
        *fresnel_case,
    ]
    assert all(r["ms"] > 0 and math.isfinite(r["ms"]) for r in res["rows"])
    assert res["full_over_plain_step"] > 0 and res["deferred_fps"] > 0
    assert res["masked_full_over_plain_step"] > 0
    assert "full step / plain step" in format_table(res)
    for key in ("full_over_plain_range", "masked_full_over_plain_range"):
        r = res[key]
        assert r["min"] <= r["median"] <= r["max"]
    assert res["rounds"] == 2
    assert res["roughness"] is not no_roughness  # the full model as trained, or without it
    if compare:  # the default (plane order here) timed beside centre order, round by round
        r = res["order_over_full_range"]
        assert 0 < r["min"] <= r["median"] <= r["max"]
        assert "full step with splat_order centre / full step" in format_table(res)
        r = res["masked_over_no_fresnel_range"]  # Fresnel's cost, round by round
        assert 0 < r["min"] <= r["median"] <= r["max"]
        assert "without Fresnel" in format_table(res)


def test_neighbour_camera_keeps_the_target_in_view():
    cam = bench_camera(32)
    nb = neighbour_camera(cam, 10.0)
    # the origin (what the bench camera looks at) projects near the centre in both
    for c in (cam, nb):
        p = c.t  # the world origin in camera coordinates
        u = c.intrinsics.fx * p[0] / p[2] + c.intrinsics.cx
        assert abs(float(u) - 16.0) < 4.0
    assert not bool((nb.world_to_cam == cam.world_to_cam).all())


def test_ratios_pair_the_cases_round_by_round():
    # round 2 ran at half speed: both cases slowed, their ratio in that round did not
    r = paired_ratio([2.0, 4.0, 2.2], [1.0, 2.0, 1.0])
    assert r == {"min": 2.0, "median": 2.0, "max": 2.2}
    with pytest.raises(ValueError):
        paired_ratio([1.0], [1.0, 2.0])


def test_zero_rounds_is_refused_with_the_flag_named(capsys):
    from bench.train_step import main

    with pytest.raises(SystemExit):
        main(["--device", "cpu", "--repeat", "0"])
    assert "--repeat must be >= 1" in capsys.readouterr().err
