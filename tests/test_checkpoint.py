"""Checkpoints: round trip, NaN refusal, atomic replacement, validation on load."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
import torch

import core.model.checkpoint as ckpt_mod
from core.model.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    CheckpointError,
    NonFiniteError,
    load_checkpoint,
    save_checkpoint,
)
from core.render.gaussians import PARAM_SHAPES, Gaussians


def random_gaussians(n: int = 16, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(n, *s, generator=g) for k, s in PARAM_SHAPES.items()}
    return Gaussians(params, sh_degree=2)


def trained_state(g: Gaussians) -> dict:
    """One real Adam step so the optimizer state holds tensors, as in training."""
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in g.params.items()}
    loss = sum(p.square().sum() for p in g.params.values())
    loss.backward()
    for o in opts.values():
        o.step()
    return {
        "iteration": 1234,
        "optimizers": {k: o.state_dict() for k, o in opts.items()},
        "rng": {
            "torch": torch.get_rng_state(),
            "numpy": np.random.default_rng(5).bit_generator.state,
            "python": random.Random(3).getstate(),
        },
        "config": {"lambda_scale": 100.0, "phases": [3000, 7000], "name": "ball", "x": None},
        "env_map": torch.rand(6, 8, 8, 3),
    }


def test_round_trip(tmp_path: Path) -> None:
    g = random_gaussians()
    extra = trained_state(g)
    path = save_checkpoint(tmp_path / "ckpt.pt", g, extra)
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]
    ck = load_checkpoint(path, "cpu")
    assert ck.version == CHECKPOINT_VERSION and ck.path == path
    assert ck.gaussians.sh_degree == 2
    for k in g.params:
        assert torch.equal(ck.gaussians.params[k], g.params[k].detach()), k
    assert isinstance(ck.gaussians.params, torch.nn.ParameterDict)
    assert ck.extra["iteration"] == 1234
    assert ck.extra["config"] == extra["config"]
    assert torch.equal(ck.extra["rng"]["torch"], extra["rng"]["torch"])
    assert ck.extra["rng"]["numpy"] == extra["rng"]["numpy"]
    assert tuple(ck.extra["rng"]["python"]) == extra["rng"]["python"]
    assert torch.equal(ck.extra["env_map"], extra["env_map"])
    # Optimizer state restores into fresh optimizers on the loaded parameters.
    for k, p in ck.gaussians.params.items():
        opt = torch.optim.Adam([p], lr=1e-3)
        opt.load_state_dict(ck.extra["optimizers"][k])
        state = opt.state[p]
        ref = extra["optimizers"][k]["state"][0]
        assert torch.equal(state["exp_avg"], ref["exp_avg"])


def test_nan_or_inf_parameter_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "ckpt.pt"
    good = random_gaussians()
    save_checkpoint(path, good, {"iteration": 1})
    before = path.read_bytes()
    for name, value in (("quats", float("nan")), ("refl_logits", float("inf"))):
        bad = good.clone()
        with torch.no_grad():
            bad.params[name].view(-1)[3] = value
        with pytest.raises(NonFiniteError) as err:
            save_checkpoint(path, bad, {"iteration": 2})
        assert err.value.field == f"gaussians.params.{name}"
        assert name in str(err.value) and str(path) in str(err.value)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]
    assert load_checkpoint(path).extra["iteration"] == 1


def test_nan_in_extra_tensor_is_refused(tmp_path: Path) -> None:
    env = torch.zeros(6, 4, 4, 3)
    env[1, 2, 3, 0] = float("nan")
    with pytest.raises(NonFiniteError) as err:
        save_checkpoint(tmp_path / "c.pt", random_gaussians(), {"env": {"texels": env}})
    assert err.value.field == "extra.env.texels"
    assert not list(tmp_path.iterdir())
    # Integer tensors (RNG state) are not checked; opting out allows NaN in extra.
    save_checkpoint(tmp_path / "c.pt", random_gaussians(), {"env": env}, check_extra_finite=False)


def test_unsupported_extra_type_is_refused_before_writing(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError) as err:
        save_checkpoint(tmp_path / "c.pt", random_gaussians(), {"config": {"obj": object()}})
    assert err.value.field == "extra.config.obj"
    assert not list(tmp_path.iterdir())


def test_failed_save_leaves_existing_checkpoint_intact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, random_gaussians(seed=1), {"iteration": 10})
    before = path.read_bytes()

    real_save = torch.save

    def torn_save(obj: object, f: object) -> None:
        real_save(obj, f)
        f.truncate(100)  # type: ignore[attr-defined]
        raise OSError("disk full")

    monkeypatch.setattr(ckpt_mod.torch, "save", torn_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, random_gaussians(seed=2), {"iteration": 20})
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # temp file removed
    ck = load_checkpoint(path)
    assert ck.extra["iteration"] == 10
    # A later good save replaces it.
    save_checkpoint(path, random_gaussians(seed=2), {"iteration": 20})
    assert load_checkpoint(path).extra["iteration"] == 20


def test_save_creates_directories(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "a" / "b" / "ckpt.pt", random_gaussians())
    assert path.is_file()


def _raw(path: Path, data: object) -> Path:
    torch.save(data, path)
    return path


def test_load_validates_format_version_and_keys(tmp_path: Path) -> None:
    g = random_gaussians()
    good = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "gaussians": g.state_dict(),
        "extra": {},
    }
    cases = {
        "format": dict(good, format="something-else"),
        "version": dict(good, version=CHECKPOINT_VERSION + 1),
        "gaussians": {k: v for k, v in good.items() if k != "gaussians"},
        "extra": dict(good, extra=None),
        "gaussians.params.quats": dict(
            good,
            gaussians={
                "params": {k: v for k, v in g.state_dict()["params"].items() if k != "quats"},
                "sh_degree": 3,
            },
        ),
        "gaussians.params": dict(
            good,
            gaussians={
                "params": dict(g.state_dict()["params"], sh_rest=torch.zeros(16, 3, 3)),
                "sh_degree": 3,
            },
        ),
    }
    for field, data in cases.items():
        path = _raw(tmp_path / f"{field}.pt", data)
        with pytest.raises(CheckpointError) as err:
            load_checkpoint(path)
        assert err.value.field == field, field
        assert str(path) in str(err.value)
    assert load_checkpoint(_raw(tmp_path / "ok.pt", good)).gaussians.num == 16


def test_load_garbage_and_missing(tmp_path: Path) -> None:
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00garbage" * 10)
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(junk)
    assert err.value.file == str(junk)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "absent.pt")
    with pytest.raises(CheckpointError):
        load_checkpoint(_raw(tmp_path / "list.pt", [1, 2, 3]))
