"""GPU acceptance kit: prove the CUDA path and measure it, in one call, on a bare GPU machine.

    bash scripts/gpu_check.sh --out gpu-report            # on the GPU machine
    bash scripts/gpu_check.sh --dry-run --out /tmp/dry    # anywhere: every stage in CPU form

Stages, each recorded in ``OUT/gpu_check.json`` and ``OUT/gpu_check.md`` as ``ok``,
``failed`` (with the error) or ``skipped`` (with the reason):

``env``     devices, driver, torch/CUDA/nvcc versions
``wheels``  the carried wheel folder installed (GPU) / the lock checked against every
            import of the kit's code (dry run: no network, no GPU)
``build``   gsplat's CUDA kernels compiled once (cached in the carried folder when set)
``tests``   every CUDA test, plus the gsplat-twin tests of the CUDA adapter
``parity``  CUDA vs compiled CPU vs the torch reference on the same scenes: forward
            features and alpha, gradients, planar depth, normals, deferred shading
``speed``   full PGSR-DR step vs plain 3DGS step (gsplat's own) at 800² / 300k; deferred
            render FPS at 800² for 100k, 300k, 1M Gaussians; peak GPU memory
``train``   a timed run of a dev scene to a fixed budget, its error-vs-time report and the
            extrapolated time of the paper's 30k iterations
``worker``  ``glint worker --device cuda:0`` on Redis against the API: one job, end to end

Every heavy stage runs in a child process with a timeout, a stage that finished is not
run again (``--force`` redoes it), and ``--budget-s`` stops starting stages before one
call's limit: run the same command again to finish. The dry run uses tiny sizes on the
CPU so CI proves, at every commit, that the kit's stages and report still work.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
GLINT = [
    sys.executable,
    "-c",
    "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))",
]
STAGES = ("env", "wheels", "build", "tests", "parity", "speed", "train", "worker")
REPORT = "gpu_check.json"
PAPER = (
    "Paper (PGSR-DR, RTX 3090): 103.5 FPS on Shiny Blender, 95.8 FPS on Glossy Synthetic, "
    "about 30 min for 30k iterations. Targets here: full step ≤ 1.3× the plain gsplat step, "
    "deferred render ≥ 200 FPS at 800² with 300k Gaussians, 30k iterations ≤ 10 min."
)


class Skip(Exception):  # noqa: N818  (a stage's outcome, not an error)
    """The stage cannot run here; the message says why."""


@dataclass
class Kit:
    out: Path
    dry: bool
    device: str
    deadline: float
    wheels: Path | None
    scene: Path | None
    state: dict[str, Any] = field(default_factory=dict)

    @property
    def cuda(self) -> bool:
        return self.device.startswith("cuda")

    def env(self) -> dict[str, str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        site = self.out / "site"
        paths = [str(ROOT), *([str(site)] if site.is_dir() else []), env.get("PYTHONPATH", "")]
        env["PYTHONPATH"] = os.pathsep.join(paths).rstrip(os.pathsep)
        if self.wheels is not None:
            env.setdefault("TORCH_EXTENSIONS_DIR", str(self.wheels / "torch_extensions"))
        return env

    def run(self, cmd: list[str], timeout: float, log: str) -> subprocess.CompletedProcess:
        """A child process, its output kept in OUT/log; raises on failure or timeout."""
        left = self.deadline - time.monotonic()
        timeout = max(10.0, min(timeout, left))
        path = self.out / log
        with open(path, "w") as fh:
            try:
                res = subprocess.run(
                    cmd, cwd=ROOT, env=self.env(), stdout=fh, stderr=subprocess.STDOUT,
                    timeout=timeout, check=False,
                )  # fmt: skip
            except subprocess.TimeoutExpired:
                raise RuntimeError(f"timed out after {timeout:.0f} s (see {log})") from None
        if res.returncode != 0:
            tail = path.read_text()[-1500:]
            raise RuntimeError(f"exit {res.returncode} (see {log}):\n{tail}")
        return res


# -- stages ------------------------------------------------------------------------------


def stage_env(kit: Kit) -> dict[str, Any]:
    import torch

    info: dict[str, Any] = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "cuda_available": torch.cuda.is_available(),
        "cpus": os.cpu_count(),
    }
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info.update(
            gpu=p.name, gpu_memory_gib=round(p.total_memory / 2**30, 1), sms=p.multi_processor_count
        )
    nvcc = shutil.which("nvcc")
    if nvcc:
        out = subprocess.run([nvcc, "--version"], capture_output=True, text=True).stdout
        info["nvcc"] = out.strip().splitlines()[-1] if out.strip() else "?"
    smi = shutil.which("nvidia-smi")
    if smi:
        q = "--query-gpu=name,driver_version,memory.total"
        info["nvidia_smi"] = subprocess.run(
            [smi, q, "--format=csv,noheader"], capture_output=True, text=True
        ).stdout.strip()
    if kit.cuda and not torch.cuda.is_available():
        raise RuntimeError("a CUDA device was asked for, but torch sees none")
    return info


def stage_wheels(kit: Kit) -> dict[str, Any]:
    from bench.gpu_wheels import check_carried, check_lock

    if kit.dry or kit.wheels is None:  # the imports are mapped through this environment
        res = check_lock()
    else:  # a bare machine: its distributions arrive with the wheels, checked by hash
        res = {"problems": check_carried(kit.wheels), "warnings": []}
    if res["problems"]:
        raise RuntimeError("; ".join(res["problems"]))
    if res["warnings"]:
        res["note_drift"] = "the lock differs from this environment; refresh: gpu_wheels --lock"
    from bench.gpu_wheels import LOCK, check_image

    reqs = json.loads(LOCK.read_text())["image_requirements"]
    if not kit.dry:  # the GPU image's own packages must satisfy what the carried ones need
        conflicts = check_image(reqs)
        if conflicts:
            raise RuntimeError("; ".join(conflicts))
    res["image_requirements_checked"] = len(reqs)
    if kit.dry or kit.wheels is None:
        res["installed"] = False
        res["note"] = "lock checked against every import of the kit's code; nothing installed"
        return res
    wheels = sorted(kit.wheels.glob("*.whl"))
    if not wheels:
        raise RuntimeError(f"no wheels in {kit.wheels}: make them with scripts/gpu_wheels.sh")
    site = kit.out / "site"
    cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps",
           "--no-compile", "--upgrade", "--target", str(site), *map(str, wheels)]  # fmt: skip
    kit.run(cmd, 300, "wheels.log")
    _register_commands(site)
    res.update(installed=True, site=str(site))
    return res


def _register_commands(site: Path) -> None:
    """Make ``glint worker`` / ``glint serve`` resolvable from the uninstalled checkout.

    The service layers add their commands through the ``glint.commands`` entry points,
    which importlib only finds in an installed distribution's metadata; the kit runs the
    repository from its folder, so it writes that metadata (from pyproject.toml) into
    the site folder already on PYTHONPATH.
    """
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    eps = project.get("entry-points", {})
    info = site / f"glint-{project['version']}.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: glint\nVersion: {project['version']}\n"
    )
    lines = [f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in items.items())
             for group, items in eps.items()]  # fmt: skip
    (info / "entry_points.txt").write_text("\n".join(lines))


def stage_build(kit: Kit) -> dict[str, Any]:
    code = (
        "import time, torch; t = time.perf_counter();"
        "from gsplat.cuda._backend import _C;"
        "assert _C is not None, 'gsplat CUDA extension did not build';"
        "print(round(time.perf_counter() - t, 1))"
    )
    if not kit.cuda:
        code = "import gsplat, gsplat.cuda._torch_impl; print(0.0)"
    kit.run([sys.executable, "-c", code], 590, "build.log")
    secs = float((kit.out / "build.log").read_text().strip().splitlines()[-1])
    if not kit.cuda:
        return {"note": "no GPU: gsplat and its torch reference imported; kernels not built"}
    return {"build_seconds": secs, "cache": kit.env().get("TORCH_EXTENSIONS_DIR")}


def stage_tests(kit: Kit) -> dict[str, Any]:
    tests = ["tests/test_raster_cuda.py", "tests/test_cuda_paths_twin.py", "tests/test_envmap.py",
             "tests/test_optim_fused.py"]  # fmt: skip
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rs", *tests]
    if kit.dry:
        # the stage's machinery on the CPU twins; the twin training run (13 s) is left
        # to the suite itself, which runs tests/test_cuda_paths_twin.py whole
        cmd += ["-k", "(twin or cuda_unavailable or adapter or camera_matrices) and not training"]
    kit.run(cmd, 590, "tests.log")
    text = (kit.out / "tests.log").read_text()
    summary = [ln for ln in text.splitlines() if " passed" in ln or " failed" in ln]
    skipped = [ln for ln in text.splitlines() if ln.startswith("SKIPPED")]
    if kit.cuda and any("CUDA" in s for s in skipped):
        raise RuntimeError("CUDA tests were skipped on a CUDA machine:\n" + "\n".join(skipped))
    return {"summary": summary[-1] if summary else "?", "skipped": skipped}


def stage_parity(kit: Kit) -> dict[str, Any]:
    out = kit.out / "parity.json"
    cmd = [sys.executable, "-m", "bench.gpu_parity", "--json", str(out)]
    cmd += ["--device", kit.device] + (["--small"] if kit.dry else [])
    kit.run(cmd, 400, "parity.log")
    res = json.loads(out.read_text())
    if res["failures"]:
        raise RuntimeError("; ".join(res["failures"]))
    return res


def _train_step(kit: Kit, size: int, n: int, repeat: int, tag: str) -> dict[str, Any]:
    out = kit.out / f"speed_{tag}.json"
    cmd = [sys.executable, "-m", "bench.train_step", "--device", kit.device, "--size", str(size),
           "--n", str(n), "--repeat", str(repeat), "--warmup", "1", "--json", str(out)]  # fmt: skip
    if not kit.cuda:
        cmd += ["--threads", "2", "--envmap", "16"]
    kit.run(cmd, 300, f"speed_{tag}.log")
    res = json.loads(out.read_text())
    by = {r["case"]: r for r in res["rows"]}
    return {
        "size": size,
        "n": n,
        "full_step_ms": round(by["full step (multi-view phase)"]["ms"], 2),
        "plain_step_ms": round(by["plain step"]["ms"], 2),
        "full_over_plain": round(res["full_over_plain_step"], 3),
        "masked_full_over_plain": round(res["masked_full_over_plain_step"], 3),
        "deferred_fps": round(res["deferred_fps"], 1),
        "peak_mib": round(max(r["peak_mib"] for r in res["rows"]), 1),
    }


def stage_speed(kit: Kit) -> dict[str, Any]:
    if kit.dry:
        cases = [(48, 1000, "dry")]
    else:
        cases = [(800, 300_000, "300k"), (800, 100_000, "100k"), (800, 1_000_000, "1m")]
    rows = [_train_step(kit, s, n, 3 if kit.dry else 10, tag) for s, n, tag in cases]
    head = rows[0]
    res: dict[str, Any] = {"rows": rows}
    if kit.cuda:
        res["targets"] = {
            "full_over_plain_le_1.3": head["full_over_plain"] <= 1.3,
            "deferred_fps_ge_200_at_300k": head["deferred_fps"] >= 200,
        }
    return res


def stage_train(kit: Kit) -> dict[str, Any]:
    run = kit.out / "train_run"
    if kit.dry:
        scene = kit.out / "train_scene"
        if not scene.is_dir():
            kit.run([sys.executable, "-c", (
                "import sys; from core.scene.synthetic import write_synthetic_scene as w;"
                f"w({str(scene)!r}, 'sphere', 'glossy', n_train=6, n_test=2, size=24)"
            )], 120, "train_scene.log")  # fmt: skip
        iters, extra = 30, ["--set", "init_points=500", "--set", "envmap_resolution=8"]
    else:
        scene = kit.scene or ROOT.parent / "shared" / "data" / "teapot_gold"
        if not scene.is_dir():
            raise Skip(f"no dev scene at {scene}: carry one and pass --scene")
        iters, extra = 3000, []
    cmd = [*GLINT, "train", str(scene), "--out", str(run), "--iterations", str(iters),
           "--device", kit.device, "--quiet", *extra]  # fmt: skip
    t0 = time.perf_counter()
    kit.run(cmd, 590, "train.log")
    wall = time.perf_counter() - t0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x]
    last = rows[-1]
    per_it = float(last["wall_time"]) / max(int(last["iteration"]), 1)
    return {
        "scene": str(scene),
        "iterations": int(last["iteration"]),
        "train_seconds": round(float(last["wall_time"]), 1),
        "wall_seconds": round(wall, 1),
        "psnr": last.get("psnr"),
        "n_gaussians": last.get("n_gaussians"),
        "extrapolated_30k_minutes": round(per_it * 30_000 / 60.0, 1),
        "report": str(run / "report.md"),
        "note": "extrapolated linearly from this run's seconds per iteration",
    }


def stage_worker(kit: Kit) -> dict[str, Any]:
    redis = shutil.which("redis-server") or (
        str(kit.wheels / "redis-server")
        if kit.wheels and (kit.wheels / "redis-server").is_file()
        else None
    )
    if redis is None:
        raise Skip(
            "no redis-server on PATH or in the carried folder (scripts/gpu_wheels.sh copies one)"
        )
    out = kit.out / "worker.json"
    cmd = [sys.executable, "-m", "bench.gpu_worker_trip", "--redis-server", redis, "--device",
           kit.device, "--json", str(out), "--root", str(kit.out / "worker")]  # fmt: skip
    kit.run(cmd, 400, "worker.log")
    return json.loads(out.read_text())


RUNNERS: dict[str, Callable[[Kit], dict[str, Any]]] = {
    "env": stage_env,
    "wheels": stage_wheels,
    "build": stage_build,
    "tests": stage_tests,
    "parity": stage_parity,
    "speed": stage_speed,
    "train": stage_train,
    "worker": stage_worker,
}


# -- report --------------------------------------------------------------------------------


def write_report(kit: Kit) -> Path:
    (kit.out / REPORT).write_text(json.dumps(kit.state, indent=2, default=str) + "\n")
    st = kit.state
    lines = [
        "# Glint GPU acceptance kit",
        "",
        f"Mode: {'dry run (CPU forms of every stage)' if kit.dry else 'GPU'}; "
        f"device `{kit.device}`; updated {st.get('updated', '?')}.",
        "",
        PAPER,
        "",
        "| stage | status | seconds | result |",
        "|---|---|---:|---|",
    ]
    for name in STAGES:
        s = st["stages"].get(name, {"status": "pending"})
        detail = (s.get("reason") or s.get("error") or "").split("\n")[0]
        if s.get("status") == "ok":
            r = s.get("result", {})
            keys = [k for k in r if not isinstance(r[k], (list, dict))][:4]
            detail = ", ".join(f"{k}={r[k]}" for k in keys)
        lines.append(f"| {name} | {s.get('status')} | {s.get('seconds', '')} | {detail} |")
    speed = st["stages"].get("speed", {}).get("result")
    if speed:
        lines += [
            "",
            "## Speed",
            "",
            "| image | Gaussians | full step ms | plain step ms | ratio | deferred FPS | MiB |",
            "|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in speed["rows"]:
            cells = [f"{r['size']}²", f"{r['n']:,}", r["full_step_ms"], r["plain_step_ms"],
                     r["full_over_plain"], r["deferred_fps"], r["peak_mib"]]  # fmt: skip
            lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    parity = st["stages"].get("parity", {}).get("result")
    if parity:
        lines += ["", "## Parity (max abs difference to the torch reference)", ""]
        for k, v in parity["errors"].items():
            lines.append(f"- {k}: {v}")
    pending = [n for n in STAGES if st["stages"].get(n, {}).get("status") in (None, "pending")]
    if pending:
        lines += ["", f"Not run yet: {', '.join(pending)}; run the same command again to continue."]
    md = kit.out / "gpu_check.md"
    md.write_text("\n".join(lines) + "\n")
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("gpu-report"))
    ap.add_argument("--dry-run", action="store_true", help="CPU forms of every stage (CI)")
    ap.add_argument("--device", default=None, help="default: cuda:0, cpu in a dry run")
    ap.add_argument("--wheels", type=Path, default=None, help="the carried wheel folder")
    ap.add_argument("--scene", type=Path, default=None, help="dev scene for the train stage")
    ap.add_argument("--stage", action="append", choices=STAGES, help="only these stages")
    ap.add_argument("--force", action="store_true", help="redo stages already recorded")
    ap.add_argument("--budget-s", type=float, default=540.0, help="start no stage after this")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    device = args.device or ("cpu" if args.dry_run else "cuda:0")
    kit = Kit(args.out.resolve(), args.dry_run, device, time.monotonic() + args.budget_s,
              args.wheels.resolve() if args.wheels else None, args.scene)  # fmt: skip
    path = kit.out / REPORT
    old = json.loads(path.read_text()) if path.is_file() else {}
    same_mode = old.get("dry_run") == args.dry_run and old.get("device") == device
    kit.state = old if same_mode else {}
    kit.state.update(dry_run=args.dry_run, device=device)
    kit.state.setdefault("stages", {})
    failed = False
    for name in args.stage or STAGES:
        prev = kit.state["stages"].get(name, {})
        if prev.get("status") in ("ok", "skipped") and not args.force:
            continue
        if time.monotonic() > kit.deadline:
            kit.state["stages"][name] = {
                "status": "pending",
                "reason": "time budget of this call used",
            }
            continue
        t0 = time.perf_counter()
        try:
            rec = {"status": "ok", "result": RUNNERS[name](kit)}
        except Skip as exc:
            rec = {"status": "skipped", "reason": str(exc)}
        except Exception as exc:  # a stage's failure is recorded; the others still run
            rec = {"status": "failed", "error": f"{type(exc).__name__}: {exc}",
                   "trace": traceback.format_exc()[-3000:]}  # fmt: skip
            failed = True
        rec["seconds"] = round(time.perf_counter() - t0, 1)
        kit.state["stages"][name] = rec
        kit.state["updated"] = time.strftime("%Y-%m-%d %H:%M:%S")
        write_report(kit)
        print(f"[{name}] {rec['status']} in {rec['seconds']} s", flush=True)
    md = write_report(kit)
    print(f"report: {md}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
