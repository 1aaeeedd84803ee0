"""The resolution governor keeps a moving camera near the frame budget."""

from __future__ import annotations

import pytest

from viewer_web.adaptive import ResolutionGovernor


def simulate(a_ms: float, b_ms_per_px: float, full_px: int, frames: int = 30) -> float:
    gov = ResolutionGovernor(target_fps=10)  # 100 ms budget
    scale = gov.scale
    for _ in range(frames):
        px = int(full_px * scale * scale)
        gov.observe(px, a_ms + b_ms_per_px * px)
        scale = gov.next_scale(full_px)
    return scale


def test_scale_meets_budget_with_fixed_cost() -> None:
    full = 1000 * 1000
    scale = simulate(a_ms=40.0, b_ms_per_px=240 / full, full_px=full)  # 280 ms at full res
    ms = 40.0 + 240 * scale * scale
    assert ms == pytest.approx(ResolutionGovernor.RENDER_SHARE * 100.0, rel=0.25), (scale, ms)


def test_fast_renders_go_full_and_slow_ones_hit_the_floor() -> None:
    assert simulate(a_ms=1.0, b_ms_per_px=1e-6, full_px=640 * 480) == 1.0
    assert simulate(a_ms=500.0, b_ms_per_px=1e-6, full_px=640 * 480) == pytest.approx(0.2)
