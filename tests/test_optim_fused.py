"""Glint's Adam (fused kernel or plain update) against torch.optim.Adam: same parameters
after steps, densification's state surgery, checkpoints written by either class."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from core.config import TrainConfig
from core.render.gaussians import Gaussians
from core.training.adam import Adam
from core.training.optim import (
    append_zero_rows,
    make_optimizers,
    replace_param,
    select_rows,
    set_lr,
)


def _model(seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(300, 3, generator=g)
    return Gaussians.from_points(pts, torch.rand(300, 3, generator=g), sh_degree=3, radius=1.0)


def _plain(model: Gaussians, fused: dict[str, Adam]) -> dict[str, torch.optim.Adam]:
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
        o.load_state_dict(saved[k])
        assert o.param_groups[0]["fused"] is True  # the old groups said fused: None
    for i in range(1, 4):
        _step([a, b], [old, resumed], i)
    _close(a, b)


def test_adam_falls_back_where_no_fused_kernel_applies() -> None:
    p = torch.nn.Parameter(torch.zeros(3, dtype=torch.complex64))
    opt = Adam([p], lr=0.1)
    assert not opt.param_groups[0]["fused"]
    p.grad = torch.ones_like(p)
    opt.step()  # the plain implementation takes what the fused kernel refuses
    assert torch.isfinite(torch.view_as_real(p.detach())).all()


# --- core.training.adam.Adam against torch.optim.Adam (the reference) -----------------


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _pair(fused: bool, dtype: torch.dtype, seed: int = 3, device: str = "cpu"):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(40, 3, generator=g, dtype=dtype).to(device)
    mine = torch.nn.Parameter(x.clone())
    ref = torch.nn.Parameter(x.clone())
    ours = Adam([mine], lr=0.05, eps=1e-15, fused=fused)
    theirs = torch.optim.Adam([ref], lr=0.05, eps=1e-15, fused=fused or None)
    return mine, ref, ours, theirs


def _grad_steps(pairs, steps: range, seed: int = 7) -> None:
    g = torch.Generator().manual_seed(seed)
    for i in steps:
        grad = None
        for p, opt in pairs:
            if grad is None:
                grad = torch.randn(p.shape, generator=g, dtype=p.dtype).to(p.device) * (1 + i)
            p.grad = grad.clone()
            opt.step()
            if i == 3:
                set_lr(opt, 0.01)  # a schedule changes the rate between steps


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_adam_matches_torch_optim_adam(fused: bool, dtype: torch.dtype, device: str) -> None:
    mine, ref, ours, theirs = _pair(fused, dtype, device=device)
    _grad_steps([(mine, ours), (ref, theirs)], range(8))
    tol = {"rtol": 1e-6, "atol": 1e-7} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 0}
    torch.testing.assert_close(mine.detach(), ref.detach(), **tol)
    for name in ("exp_avg", "exp_avg_sq", "step"):
        torch.testing.assert_close(ours.state[mine][name], theirs.state[ref][name], **tol)
        assert ours.state[mine][name].device == theirs.state[ref][name].device


def test_fused_and_plain_updates_agree() -> None:
    a, _, fused, _ = _pair(True, torch.float32)
    b, _, plain, _ = _pair(False, torch.float32)
    _grad_steps([(a, fused), (b, plain)], range(12))
    torch.testing.assert_close(a.detach(), b.detach(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("fused", [True, False])
def test_state_dicts_load_across_both_classes_and_resume_equal(fused: bool) -> None:
    mine, ref, ours, theirs = _pair(fused, torch.float32)
    _grad_steps([(mine, ours), (ref, theirs)], range(3))
    from_ours = copy.deepcopy(ours.state_dict())  # as torch.save would
    from_theirs = copy.deepcopy(theirs.state_dict())
    assert from_ours["param_groups"][0].keys() == from_theirs["param_groups"][0].keys()
    # swap: torch.optim.Adam resumes our state, ours resumes torch's
    p1 = torch.nn.Parameter(mine.detach().clone())
    p2 = torch.nn.Parameter(ref.detach().clone())
    t_opt = torch.optim.Adam([p1], lr=1.0, fused=fused or None)
    t_opt.load_state_dict(from_ours)
    o_opt = Adam([p2], lr=1.0, fused=fused)
    o_opt.load_state_dict(from_theirs)
    assert o_opt.param_groups[0]["lr"] == 0.05  # the saved rate, as torch.optim loads it
    assert bool(o_opt.param_groups[0]["fused"]) is fused
    _grad_steps([(p1, t_opt), (p2, o_opt), (mine, ours)], range(3, 7), seed=11)
    torch.testing.assert_close(p1.detach(), mine.detach(), rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(p2.detach(), mine.detach(), rtol=1e-6, atol=1e-7)


def test_a_state_for_other_parameters_is_refused() -> None:
    p, q = torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(3))
    two = torch.optim.Adam([p, q], lr=0.1)
    with pytest.raises(ValueError, match="group of 2 parameters, expected 1"):
        Adam([torch.nn.Parameter(torch.zeros(3))], lr=0.1).load_state_dict(two.state_dict())
    with pytest.raises(ValueError, match="out of range"):
        Adam([p], lr=-1.0)
    with pytest.raises(ValueError, match="fused kernel"):
        Adam([torch.nn.Parameter(torch.zeros(3, dtype=torch.complex64))], lr=0.1, fused=True)


def test_a_training_step_does_not_import_torch_dynamo() -> None:
    """The reason for the class: torch.optim imports torch._dynamo (1.6-2 s) on first use."""
    code = (
        "import sys, torch\n"
        "from core.config import TrainConfig\n"
        "from core.render.gaussians import Gaussians\n"
        "from core.training.optim import make_optimizers\n"
        "x = torch.randn(50, 3)\n"
        "g = Gaussians.from_points(x, x.abs() % 1, sh_degree=3, radius=1.0)\n"
        "opts = make_optimizers(g, TrainConfig(), 1.0)\n"
        "for p in g.params.values(): p.grad = torch.ones_like(p)\n"
        "for o in opts.values(): o.step(); o.zero_grad()\n"
        "assert 'torch._dynamo' not in sys.modules, 'torch._dynamo was imported'\n"
    )
    root = Path(__file__).resolve().parents[1]
    res = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
