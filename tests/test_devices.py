"""Devices a run may use here; reopening a GPU worker's run on a CPU machine."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest
import torch

import core.devices as devices
from core.cli import main
from core.config import ConfigError, config_from_dict
from core.devices import DeviceUnavailableError, device_problem, require_device
from core.errors import BackendUnavailableError, GlintError
from core.model.placement import Placement, reopen_placement
from core.render.raster import resolve_backend
from core.scene.synthetic import make_sphere_scene, write_synthetic_scene
from core.training.run import train_scene

CPU_ONLY = torch.version.cuda is None and torch.version.hip is None
AUTO = resolve_backend("auto", "cpu")


@pytest.fixture
def fake_gpus(monkeypatch: pytest.MonkeyPatch):
    """A CUDA build that sees ``n`` GPUs (set ``fake_gpus.n``), without one."""

    class Fake:
        n = 0

    monkeypatch.setattr(devices.torch.version, "cuda", "12.4")
    monkeypatch.setattr(devices.torch.cuda, "device_count", lambda: Fake.n)
    return Fake


def test_cpu_is_always_usable():
    assert device_problem("cpu") is None
    assert require_device("cpu") == torch.device("cpu")


@pytest.mark.skipif(not CPU_ONLY, reason="needs a CPU-only torch build")
def test_cuda_on_a_cpu_only_build_says_so():
    assert device_problem("cuda") == "this torch build is CPU-only"
    with pytest.raises(DeviceUnavailableError) as exc:
        require_device("cuda:0")
    assert str(exc.value) == (
        "field 'device': 'cuda:0' cannot be used here: this torch build is CPU-only; use 'cpu'"
    )


def test_gpu_counts(fake_gpus):
    fake_gpus.n = 0
    assert "no CUDA device is visible" in str(device_problem("cuda"))
    fake_gpus.n = 2
    assert device_problem("cuda") is None and device_problem("cuda:1") is None
    assert device_problem("cuda:2") == "only 2 CUDA device(s) are visible (cuda:0 to cuda:1)"


@pytest.mark.parametrize("name", ["gpu", "cuda:", "CUDA", "cuda:0:1", "mps", ""])
def test_misspelt_devices_name_the_field(name: str):
    with pytest.raises(DeviceUnavailableError, match=f"option '--device': expected .*'{name}'"):
        require_device(name, "--device")
    with pytest.raises(ConfigError, match=r"field 'device'.*expected 'cpu', 'cuda' or 'cuda:N'"):
        config_from_dict({"device": name})


@pytest.mark.skipif(not CPU_ONLY, reason="needs a CPU-only torch build")
def test_training_on_a_missing_gpu_fails_before_writing(tmp_path: Path):
    scene = make_sphere_scene("glossy", n_train=2, n_test=1, size=16, samples=1)
    cfg = config_from_dict({"iterations": 2, "device": "cuda", "init_points": 50})
    with pytest.raises(DeviceUnavailableError, match="field 'device': 'cuda' cannot be used"):
        train_scene(scene, tmp_path / "run", cfg)
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(not CPU_ONLY, reason="needs a CPU-only torch build")
def test_reopening_a_gpu_run_on_this_machine():
    p = reopen_placement("cuda:1", "cuda")
    assert (p.device, p.backend) == ("cpu", AUTO)
    assert p.notes == [
        "the run trained on 'cuda:1', which this machine lacks (this torch build is "
        "CPU-only); using cpu",
        "rasteriser backend 'cuda' is unavailable: it needs a CUDA device, got 'cpu'; "
        f"rendering with '{AUTO}'",
    ]
    # what works here is kept as recorded, without notes
    for backend in ("auto", "reference", AUTO):
        assert reopen_placement("cpu", backend) == Placement("cpu", backend, [])
    # the user's explicit choice must work here, or fail loudly
    assert reopen_placement("cuda", "cuda", backend_override="reference").backend == "reference"
    with pytest.raises(DeviceUnavailableError, match="option '--device'"):
        reopen_placement("cpu", "auto", device_override="cuda")
    with pytest.raises(BackendUnavailableError, match="'cuda' is unavailable"):
        reopen_placement("cuda", "auto", backend_override="cuda")


def test_reopening_on_a_gpu_machine_keeps_the_gpu(fake_gpus):
    fake_gpus.n = 1
    p = reopen_placement("cuda:0", "reference")
    assert (p.device, p.backend, p.notes) == ("cuda:0", "reference", [])
    p = reopen_placement("cuda:3", "reference")
    assert p.device == "cpu" and "only 1 CUDA device(s)" in p.notes[0]


@pytest.mark.skipif(not CPU_ONLY, reason="needs a CPU-only torch build")
def test_glint_mesh_reopens_a_gpu_run_on_the_cpu(tmp_path: Path, capsys):
    scene_dir = write_synthetic_scene(
        tmp_path / "scene", "sphere", "glossy", n_train=3, n_test=1, size=20
    )
    run = tmp_path / "run"
    cfg = config_from_dict(
        {"iterations": 6, "device": "cpu", "init_points": 150, "envmap_resolution": 8}
    )
    train_scene(scene_dir, run, cfg, export=False)
    saved = json.loads((run / "config.json").read_text())
    saved.update(device="cuda:0", backend="cuda")  # as a GPU worker records it
    saved["densify"]["absgrad"] = True  # AbsGS needs gsplat, but reading a run does not
    (run / "config.json").write_text(json.dumps(saved))
    before = (run / "config.json").read_text()

    assert main(["mesh", str(run), "--mesh-resolution", "24"]) == 0
    err = capsys.readouterr().err
    assert "note: the run trained on 'cuda:0', which this machine lacks" in err
    assert f"rendering with '{AUTO}'" in err
    assert (run / "mesh.ply").is_file()
    assert (run / "config.json").read_text() == before  # the run's record is untouched

    assert main(["mesh", str(run), "--device", "cuda"]) == 2  # a usage error
    assert "option '--device': 'cuda' cannot be used here" in capsys.readouterr().err


@pytest.mark.skipif(not CPU_ONLY, reason="needs a CPU-only torch build")
def test_a_worker_without_its_gpu_refuses_to_start(capsys):
    from worker.cli import _cmd_worker

    assert _cmd_worker(argparse.Namespace(device="cuda:0")) == 2
    assert "option '--device': 'cuda:0' cannot be used here" in capsys.readouterr().err


@pytest.mark.skipif(not CPU_ONLY, reason="needs a CPU-only torch build")
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"backend": "cuda"}, "field 'backend': rasteriser backend 'cuda' is unavailable"),
        ({"densify": {"absgrad": True}}, "field 'densify.absgrad'"),
    ],
)
def test_a_backend_this_machine_lacks_fails_before_writing(tmp_path: Path, overrides, message):
    scene = make_sphere_scene("glossy", n_train=2, n_test=1, size=16, samples=1)
    cfg = config_from_dict({"iterations": 2, "init_points": 50, **overrides})
    with pytest.raises(GlintError, match=re.escape(message)):
        train_scene(scene, tmp_path / "run", cfg)
    assert not (tmp_path / "run").exists()


def test_glint_info_says_why_there_is_no_gpu_or_lists_them(fake_gpus, monkeypatch, capsys):
    fake_gpus.n = 0
    assert main(["info"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["devices"] == ["cpu"] and "no CUDA device is visible" in info["cuda"]
    fake_gpus.n = 2
    monkeypatch.setattr(devices.torch.cuda, "get_device_name", lambda i: f"GPU{i}")
    assert main(["info"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["devices"] == ["cpu", "cuda"]
    assert info["cuda"] == ["cuda:0 GPU0", "cuda:1 GPU1"]
    assert "CPU tensors only" in info["backends"]["cpu"]["cuda"]
