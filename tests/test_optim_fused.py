"""The fused Adam kernel against the plain loop it replaced: same parameters after steps,
densification's state surgery and a checkpoint written by the plain one."""

from __future__ import annotations

import copy

import torch

from core.config import TrainConfig
from core.render.gaussians import Gaussians
from core.training.optim import (
    adam,
    append_zero_rows,
    load_adam_state,
    make_optimizers,
    replace_param,
    select_rows,
)


def _model(seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(300, 3, generator=g)
    return Gaussians.from_points(pts, torch.rand(300, 3, generator=g), sh_degree=3, radius=1.0)


def _plain(model: Gaussians, fused: dict[str, torch.optim.Adam]) -> dict[str, torch.optim.Adam]:
    out = {}
    for k, o in fused.items():
        group = o.param_groups[0]
        out[k] = torch.optim.Adam(
            [model.params[k]], lr=group["lr"], eps=group["eps"], betas=group["betas"]
        )
    return out


def _step(models: list[Gaussians], opts: list[dict], seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    grads = {k: torch.randn(p.shape, generator=g) for k, p in models[0].params.items()}
    for model, o in zip(models, opts, strict=True):
        for k in o:
            model.params[k].grad = grads[k].clone()
        for opt in o.values():
            opt.step()


def _close(a: Gaussians, b: Gaussians) -> None:
    for k in a.params:
        torch.testing.assert_close(a.params[k], b.params[k], rtol=1e-5, atol=1e-6)


def test_fused_adam_matches_the_plain_loop_through_densification() -> None:
    fast, slow = _model(), _model()
    fused = make_optimizers(fast, TrainConfig(), 1.0)
    assert all(o.param_groups[0]["fused"] for o in fused.values())
    plain = _plain(slow, fused)
    for i in range(5):
        _step([fast, slow], [fused, plain], i)
    _close(fast, slow)
    keep = torch.arange(0, 300, 2)  # prune half, then add rows, as densification does
    for model, opts in ((fast, fused), (slow, plain)):
        for k, o in opts.items():
            p = torch.nn.Parameter(model.params[k].detach()[keep])
            replace_param(o, p, select_rows(keep))
            q = torch.nn.Parameter(torch.cat([p.detach(), p.detach()[:10]]))
            replace_param(o, q, append_zero_rows(10))
            model.params[k] = q
    for i in range(5, 10):
        _step([fast, slow], [fused, plain], i)
    _close(fast, slow)


def test_a_plain_checkpoint_resumes_fused_and_stays_equal() -> None:
    a, b = _model(1), _model(1)
    old = _plain(a, make_optimizers(_model(1), TrainConfig(), 1.0))
    _step([a], [old], 0)
    saved = copy.deepcopy({k: o.state_dict() for k, o in old.items()})  # as torch.save would
    b.params = {k: torch.nn.Parameter(v.detach().clone()) for k, v in a.params.items()}
    resumed = make_optimizers(b, TrainConfig(), 1.0)
    for k, o in resumed.items():
        load_adam_state(o, saved[k])
        assert o.param_groups[0]["fused"] is True  # the old groups said fused: None
    for i in range(1, 4):
        _step([a, b], [old, resumed], i)
    _close(a, b)


def test_adam_falls_back_where_no_fused_kernel_applies() -> None:
    p = torch.nn.Parameter(torch.zeros(3, dtype=torch.complex64))
    opt = adam([p], lr=0.1)
    assert not opt.param_groups[0]["fused"]
    p.grad = torch.ones_like(p)
    opt.step()  # the plain implementation takes what the fused kernel refuses
    assert torch.isfinite(torch.view_as_real(p.detach())).all()
