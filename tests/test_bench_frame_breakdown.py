"""bench.frame_breakdown names the stages of a viewer frame and accounts for all of it."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from bench import frame_breakdown as fb
from bench.viewer import write_run
from viewer_web.renderer import load_model, make_camera


def test_a_frame_is_split_into_the_renders_stages(tmp_path: Path):
    loaded = load_model(write_run(tmp_path, 3000, one_sided=True), torch.device("cpu"))
    rows, frame_ms, profiled_ms = fb.measure(loaded, fb.still_messages(64, 3), 85, 1)
    stages = {r["stage"]: r for r in rows}
    # the frozen render's own ranges, the rasteriser's inside the G-buffer's, the encodings
    for name in (
        "view_opacity",
        "near_plane",
        "visible",
        "gbuffer",
        "gbuffer/project",
        "gbuffer/bin",
        "gbuffer/composite",
        "deferred_shading",
        "display",
        "jpeg",
    ):
        assert name in stages, (name, sorted(stages))  # fmt: skip
    assert all(r["backward_ms"] == 0.0 for r in rows)  # frames have no backward
    # own times (nested ranges subtracted) add up to the profiled frame, shares to 1
    total = sum(r["forward_ms"] for r in rows)
    assert total == pytest.approx(profiled_ms, rel=1e-6)
    assert sum(r["share"] for r in rows) == pytest.approx(1.0)
    assert frame_ms > 0
    head = {"model": "m", "size": 64, "channel": "final", "frames": 3, "threads": 1}
    table = fb.markdown(rows, {**head, "frame_ms": frame_ms, "profiled_ms": profiled_ms})
    assert "| gbuffer/composite |" in table and "rasteriser" in table


def test_bad_arguments_are_refused(capsys):
    with pytest.raises(SystemExit) as exc:
        fb.main(["--frames", "0"])
    assert exc.value.code == 2
    assert "--frames" in capsys.readouterr().err


def test_the_still_cameras_look_at_the_origin_from_outside_the_sphere():
    for spec in fb.still_messages(32, 4):
        cam = make_camera(spec, 1.0)
        assert cam.width == cam.height == 32
        assert float(cam.center.norm()) == pytest.approx(math.hypot(2.2, 0.6), rel=1e-6)
