"""The CPU thread layout: torch on one thread, the compiled kernels on the rest."""

from __future__ import annotations

import pytest
import torch

from core.kernels import pool as kernel_pool
from core.kernels.threads import (
    ENV_VAR,
    configure_cpu_threads,
    kernel_threads_from_env,
    usable_cpus,
)


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    kernel_pool.set_kernel_threads(None)
    torch.set_num_threads(before)


def test_layout_puts_torch_on_one_thread_and_kernels_on_the_rest(restore_threads, monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert configure_cpu_threads() == usable_cpus()
    assert torch.get_num_threads() == 1
    assert kernel_pool.kernel_threads() == usable_cpus()
    assert configure_cpu_threads(3) == 3 and kernel_pool.kernel_threads() == 3
    monkeypatch.setenv(ENV_VAR, "2")
    assert configure_cpu_threads() == 2


def test_unset_kernel_threads_follow_torch(restore_threads):
    kernel_pool.set_kernel_threads(None)
    torch.set_num_threads(1)
    assert kernel_pool.kernel_threads() == 1
    with pytest.raises(ValueError, match=">= 1"):
        kernel_pool.set_kernel_threads(0)


@pytest.mark.parametrize("raw", ["zero", "0", "-2", "1.5"])
def test_bad_env_value_is_a_clear_error(raw, monkeypatch):
    monkeypatch.setenv(ENV_VAR, raw)
    with pytest.raises(ValueError, match=ENV_VAR):
        kernel_threads_from_env()


def test_cli_reports_a_bad_env_value(monkeypatch, capsys):
    from core.cli import main

    monkeypatch.setenv(ENV_VAR, "lots")
    assert main(["info"]) == 2
    assert ENV_VAR in capsys.readouterr().err


def test_results_do_not_depend_on_the_kernel_thread_count(restore_threads):
    """Tiles are assigned to workers statically; gradients are summed per worker slot."""
    from bench.common import bench_camera, random_gaussians
    from core.render.raster import rasterize

    cam = bench_camera(48)
    base = random_gaussians(1500, channels=4)
    out = {}
    for n in (1, 3):
        kernel_pool.set_kernel_threads(n)
        params = [t.clone().requires_grad_(True) for t in base]
        r = rasterize(*params, cam, backend="cpu", antialiased=True)
        (r.features.sum() + r.alpha.sum()).backward()
        out[n] = (r.features.detach(), [p.grad for p in params])
    torch.testing.assert_close(out[1][0], out[3][0], rtol=0, atol=0)
    for a, b in zip(out[1][1], out[3][1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)


def test_scratch_buffers_are_zeroed_reused_and_never_shared():
    import numpy as np

    with kernel_pool.scratch_zeros((3, 1000)) as a:
        assert a.shape == (3, 1000) and a.dtype == np.float64 and not a.any()
        a += 7.0
        base = a.base if a.base is not None else a
        with kernel_pool.scratch_zeros((2, 500)) as b:  # nested: a different buffer
            assert not np.shares_memory(a, b) and not b.any()
    with kernel_pool.scratch_zeros((2, 1000)) as c:  # reuses a's memory, zeroed again
        assert np.shares_memory(c, base) and not c.any()
    with kernel_pool.scratch_zeros((4,), np.float32) as d:
        assert d.dtype == np.float32 and not d.any()
    assert len(kernel_pool._SCRATCH.idle) <= kernel_pool._SCRATCH.keep


def test_a_buffer_pool_hands_out_the_smallest_fit_and_keeps_the_largest():
    import numpy as np

    pool = kernel_pool.BufferPool(keep=2)
    a, b = pool.take(100, np.int32), pool.take(50, np.int32)
    assert a.size >= 100 and b.size >= 50 and not np.shares_memory(a, b)
    for buf in (a, b, pool.take(10, np.int32)):
        pool.give(buf)
    assert [x.size for x in pool.idle] == [100, 50]  # the smallest went
    assert pool.take(40, np.int32) is b  # the smallest that holds 40
    assert pool.take(40, np.float64).dtype == np.float64  # never another dtype's
    assert pool.take(80, np.int32) is a
    assert pool.idle == []
