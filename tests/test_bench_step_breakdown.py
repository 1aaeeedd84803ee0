"""bench/step_breakdown: the real step's stages, forward and backward, add up to it."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from bench.step_breakdown import markdown, measure


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from core.scene.synthetic import write_synthetic_scene

    return write_synthetic_scene(
        tmp_path_factory.mktemp("scene"), "sphere", "glossy", n_train=8, n_test=2, size=32
    )


def test_the_stages_of_a_multiview_step(scene: Path) -> None:
    args = argparse.Namespace(
        scene=str(scene), run=None, phase="multiview", init_points=1500, iterations=600,
        steps=3, warmup=1, threads=1, set=["loss.multi_view=0.15"],
    )  # fmt: skip
    rows, head = measure(args)
    by = {r["stage"]: r for r in rows}
    assert head["phase"] == "multiview"
    # the rasteriser's custom autograd Functions get their backward attributed
    assert by["gbuffer/composite"]["backward_ms"] > 0
    assert by["gbuffer/project"]["backward_ms"] > 0
    assert by["backward/engine"]["backward_ms"] == 0  # the engine's own time is forward-side
    for name in ("rgb_loss", "optimizer", "deferred_shading/envmap_lookup", "gbuffer/bin"):
        assert by[name]["total_ms"] > 0, name
    assert abs(sum(r["share"] for r in rows) - 1.0) < 1e-9
    # every microsecond of the profiled steps is attributed, once
    total = sum(r["total_ms"] for r in rows)
    assert total == pytest.approx(head["profiled_ms"], rel=1e-6)
    text = markdown(rows, head)
    assert "| gbuffer/composite |" in text and "The rasteriser" in text
