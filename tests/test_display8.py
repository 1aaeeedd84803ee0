"""8-bit sRGB by table (core.model.display8) against the formula it replaces."""

from __future__ import annotations

import numpy as np
import torch

from core.model.display8 import encode_reference, encode_srgb8, tables
from core.model.frame import to_display


def test_every_threshold_and_its_neighbours_encode_as_the_formula():
    """Each step of the 8-bit output, its float32 neighbours (±3 ulps) and each bucket
    start encode as the formula does, except within 1 ulp of a step: there torch's own
    ``pow`` rounds differently in its vector body and its scalar tail, so the formula
    gives either level depending on where the value sits in the tensor."""
    base, thr = tables()
    steps = thr[np.isfinite(thr)]
    assert 0 < len(steps) <= 255 and base[0] == 0 and base[-1] == 255
    bits = steps.view(np.int32).astype(np.int64)
    offsets = np.arange(-3, 4)
    near = (bits[:, None] + offsets[None, :]).reshape(-1)
    starts = np.arange(len(base), dtype=np.int64) << 16
    probe = np.concatenate([near, starts, starts - 1]).clip(0, 0x3F800000).astype(np.int32)
    x = torch.from_numpy(probe.view(np.float32).copy())
    got, want = encode_srgb8(x), encode_reference(x).numpy()
    off = np.concatenate([np.tile(offsets, len(steps)), np.full(2 * len(starts), 99)])
    differ = got != want
    assert np.all(np.abs(off[differ]) <= 1)
    assert np.all(np.abs(got.astype(int) - want.astype(int)) <= 1)
    for i in np.nonzero(differ)[0]:  # the formula itself disagrees with itself there
        alone = int(encode_reference(x[i : i + 1])[0])
        in_bulk = int(encode_reference(x[max(i - 500, 0) : i + 500])[min(i, 500)])
        assert got[i] in (alone, in_bulk)


def test_images_and_out_of_range_values():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(97, 131, 3, generator=g) ** 3 * 1.2 - 0.05  # below 0 and above 1
    img[0, 0] = torch.tensor([0.0, -0.0, 1.0])
    img[0, 1] = torch.tensor([float("inf"), -float("inf"), 1e-45])
    out = encode_srgb8(img)
    assert out.dtype == np.uint8 and out.shape == (97, 131, 3)
    np.testing.assert_array_equal(out, encode_reference(img).numpy())
    np.testing.assert_array_equal(to_display(img.double()), out)  # float64 in: as float32
    # the stated answers: 0 -> 0, 1 -> 255, 18% grey -> 118 (sRGB 0.4614)
    assert encode_srgb8(torch.tensor([0.0, 1.0, 0.18])).tolist() == [0, 255, 118]


def test_nan_encodes_as_black():
    assert encode_srgb8(torch.tensor([float("nan"), 0.5])).tolist() == [0, 188]
