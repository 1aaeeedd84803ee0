"""Adaptive resolution: pick the render scale that keeps a moving camera at a target rate.

Render time is modelled as ``ms = a + b · pixels`` (a: per-frame cost of projecting and
sorting every Gaussian, b: per-pixel blending and encoding), fitted by least squares to
the last few frames. A pure "ms per pixel" estimate would over-charge small frames for
the fixed cost and spiral the scale down to its minimum on big models. When the camera
rests the caller asks for full resolution instead.
"""

from __future__ import annotations

import math
from collections import deque


class ResolutionGovernor:
    """Scale (0, 1] for the next moving frame, from measured frame times."""

    # Share of the frame interval a render + encode may take: the rest is the frame's
    # trip through the event loop and the socket (~2 ms measured by bench.viewer).
    RENDER_SHARE = 0.93

    def __init__(self, target_fps: float = 30.0, min_scale: float = 0.2, window: int = 12) -> None:
        self.budget_ms = self.RENDER_SHARE * 1000.0 / target_fps
        self.min_scale = min_scale
        self.samples: deque[tuple[float, float]] = deque(maxlen=window)  # (pixels, ms)
        self.scale = 0.5  # first moving frame: a guess, corrected after one sample

    def observe(self, pixels: int, ms: float) -> None:
        """Record one frame's size and total render + encode time."""
        if pixels > 0 and ms >= 0 and math.isfinite(ms):
            self.samples.append((float(pixels), float(ms)))

    def fit(self) -> tuple[float, float] | None:
        """(a, b) of ``ms = a + b·px`` with a, b ≥ 0, or None before any sample."""
        if not self.samples:
            return None
        n = len(self.samples)
        mx = sum(p for p, _ in self.samples) / n
        my = sum(m for _, m in self.samples) / n
        var = sum((p - mx) ** 2 for p, _ in self.samples)
        if var < (0.05 * mx) ** 2 * n:  # one size only: all cost per pixel (conservative)
            return 0.0, my / max(mx, 1.0)
        b = sum((p - mx) * (m - my) for p, m in self.samples) / var
        b = max(b, 1e-9)
        a = max(my - b * mx, 0.0)
        return a, b

    def next_scale(self, full_pixels: int) -> float:
        """The scale for a moving frame of ``full_pixels`` at full resolution."""
        ab = self.fit()
        if ab is None:
            return self.scale
        a, b = ab
        room = self.budget_ms - a
        s = self.min_scale if room <= 0 else math.sqrt(max(room / b, 1.0) / max(full_pixels, 1))
        s = min(max(s, self.min_scale), 1.0)
        # Move halfway towards the estimate and round to 1/20 steps: no size flicker.
        s = 0.5 * (self.scale + s)
        self.scale = min(max(round(s * 20) / 20, self.min_scale), 1.0)
        return self.scale
