"""bench.edge_error: the rings and the sub-pixel silhouette it measures against."""

import numpy as np

from bench.edge_error import SUBPIXEL, ring_masks, signed_edge_distance


def _vertical_edge(edge_x: float, size: int = 24) -> np.ndarray:
    """Box-filtered coverage of the half-plane x < edge_x (pixel x spans [x, x+1))."""
    cov = np.clip(edge_x - np.arange(size), 0.0, 1.0)
    return np.tile(cov, (size, 1))


def test_signed_distance_finds_a_sub_pixel_edge() -> None:
    edge = 10.3
    sd = signed_edge_distance(_vertical_edge(edge))
    row = sd[12 * SUBPIXEL]
    centres = (np.arange(row.size) + 0.5) / SUBPIXEL
    inner = (centres > 4) & (centres < 20)  # away from the image border
    np.testing.assert_allclose(row[inner], centres[inner] - edge, atol=1.0 / SUBPIXEL)


def test_rings_partition_the_image_by_distance() -> None:
    cov = _vertical_edge(10.3)
    rings = ring_masks(cov)
    total = sum(r.astype(int) for r in rings.values())
    assert (total == 1).all()
    assert set(np.nonzero(rings["out 1"][5])[0]) == {10}  # coverage 0.3: outside
    assert set(np.nonzero(rings["in 1"][5])[0]) == {9}
    assert set(np.nonzero(rings["in 1-3"][5])[0]) == {7, 8}
