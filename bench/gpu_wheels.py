"""The wheels the GPU acceptance kit carries to a bare GPU machine, and their check.

The GPU machines this project borrows have Python 3.12, a CUDA torch, nvcc and a long
list of packages (``scripts/gpu/image_packages.txt``), but no package index. The kit
carries what is missing as x86-64 cp312 wheels, at most 64 MiB, pinned to the versions
the tests here run with. This module

* works out that set: every third-party module the kit's code imports (AST scan of
  ``core``, ``api``, ``worker``, ``viewer_web``, ``bench`` and the CUDA tests), mapped to
  its distribution, closed over runtime requirements, minus the standard library, the
  GPU image's packages and torch;
* ``--lock``: downloads them here and writes ``scripts/gpu/wheels.lock.json`` (file,
  size, SHA-256 of each);
* ``--fetch DIR``: downloads the locked wheels into DIR (what ``scripts/gpu_wheels.sh``
  makes for a GPU session to carry) and checks their hashes;
* :func:`check_lock`: the dry run's check, without network or GPU: the lock covers every
  import, pins this environment's versions, and fits the size limit.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import importlib.metadata as md
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
KIT = ROOT / "scripts" / "gpu"
LOCK = KIT / "wheels.lock.json"
IMAGE = KIT / "image_packages.txt"
LIMIT_BYTES = 64 * 1024 * 1024
# code the kit runs on the GPU machine
SCANNED = ("core", "api", "worker", "viewer_web", "bench")
KIT_TESTS = (
    "tests/conftest.py",
    "tests/helpers.py",
    "tests/gsplat_twin.py",
    "tests/test_raster_cuda.py",
    "tests/test_envmap.py",
    "tests/test_cuda_paths_twin.py",
)
# the repository's own HTTP client (client/glint_client, on the kit's PYTHONPATH): its
# dependencies (httpx, tqdm) are the service's too
CLIENT_MODULE = "glint_client"
# needed at run time but never imported by name in the scanned code
INDIRECT = ("fast-simplification", "httptools", "watchfiles")  # trimesh.simplify, uvicorn
# imported where present, with a stated fallback where not (LPIPS: "unavailable"; SfM:
# a clear error, it runs on the CPU before training and pycolmap's wheel alone is
# 36 MiB; obstore: only bench/store_io.py compares it, skipped when absent)
# Not carried either: the relightable asset's UV atlas (xatlas, imported only when an
# asset is exported, which the kit does not do) and Blender's modules (bpy, mathutils:
# bench/blender_render.py runs in its own venv, scripts/blender_venv.sh), nor Mitsuba
# (bench/render_unseen.py renders held-out scenes on a development machine, not in the kit).
OPTIONAL_MODULES = frozenset(
    {"lpips", "pycolmap", "obstore", "xatlas", "bpy", "mathutils", "mitsuba"}
)
# provided with the CUDA torch, never carried
TORCH_SIDE = re.compile(r"^(torch|triton|nvidia-.*|cuda-.*)$")
# the target: CPython 3.12 on x86-64 Linux
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")
TARGET_ENV = {
    **default_environment(),
    "python_version": "3.12",
    "python_full_version": "3.12.3",
    "implementation_name": "cpython",
    "platform_python_implementation": "CPython",
    "sys_platform": "linux",
    "platform_system": "Linux",
    "platform_machine": "x86_64",
    "os_name": "posix",
}


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def image_packages() -> set[str]:
    """The GPU image's packages (one name a line; # comments)."""
    lines = IMAGE.read_text().splitlines()
    return {norm(x.split("#")[0].strip()) for x in lines if x.split("#")[0].strip()}


def kit_files() -> list[Path]:
    files = [p for top in SCANNED for p in sorted((ROOT / top).rglob("*.py"))]
    return files + [ROOT / t for t in KIT_TESTS]


def imported_modules(files: list[Path]) -> dict[str, str]:
    """Top-level module -> the first file importing it (lazy imports included)."""
    out: dict[str, str] = {}
    for f in files:
        tree = ast.parse(f.read_text(), str(f))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            else:
                continue
            for n in names:
                out.setdefault(n.split(".")[0], str(f.relative_to(ROOT)))
    return out


def third_party(modules: dict[str, str]) -> tuple[dict[str, str], list[str]]:
    """(distribution -> module that needs it, modules with no distribution)."""
    own = set(SCANNED) | {"tests", CLIENT_MODULE}
    mapping = md.packages_distributions()
    dists: dict[str, str] = {}
    unknown = []
    for mod, where in sorted(modules.items()):
        if mod in sys.stdlib_module_names or mod in own or mod in OPTIONAL_MODULES:
            continue
        names = mapping.get(mod)
        if not names:
            unknown.append(f"{mod} (imported by {where})")
            continue
        dists.setdefault(norm(names[0]), mod)
    return dists, unknown


def runtime_requirements(dist: str) -> list[Requirement]:
    """What ``dist`` (as installed here) needs on CPython 3.12 / Linux, extras left out."""
    try:
        reqs = md.requires(dist) or []
    except md.PackageNotFoundError:
        return []
    env = {**TARGET_ENV, "extra": ""}
    return [
        r for r in map(Requirement, reqs) if r.marker is None or r.marker.evaluate(env)
    ]  # fmt: skip


def closure(dists: set[str]) -> set[str]:
    """The distributions and their runtime requirements, for CPython 3.12 on Linux."""
    seen: set[str] = set()
    todo = list(dists)
    while todo:
        d = todo.pop()
        if d in seen:
            continue
        seen.add(d)
        todo += [norm(r.name) for r in runtime_requirements(d)]
    return seen


def image_requirements(carried: set[str]) -> dict[str, list[str]]:
    """What the carried distributions (and Glint) require of the image's packages:
    {image package: [specifiers]}, checked against the GPU machine's versions there."""
    image = image_packages()
    out: dict[str, set[str]] = {}
    for d in sorted(carried | {"glint"}):
        for req in runtime_requirements(d):
            name = norm(req.name)
            if name in image and not TORCH_SIDE.match(name) and str(req.specifier):
                out.setdefault(name, set()).add(str(req.specifier))
    return {k: sorted(v) for k, v in sorted(out.items())}


def check_image(reqs: dict[str, list[str]]) -> list[str]:
    """Problems of this Python's packages against ``reqs`` (run on the GPU machine)."""
    from packaging.specifiers import SpecifierSet

    problems = []
    for name, specs in reqs.items():
        try:
            have = md.version(name)
        except md.PackageNotFoundError:
            problems.append(f"{name} is missing here (needed: {', '.join(specs)})")
            continue
        for spec in specs:
            if have not in SpecifierSet(spec, prereleases=True):
                problems.append(f"{name} {have} here, but {spec} is needed: add it to the lock")
    return problems


def needed() -> tuple[dict[str, str], list[str]]:
    """{distribution: version here} the kit must carry, and modules it cannot place."""
    direct, unknown = third_party(imported_modules(kit_files()))
    direct.update({d: "(indirect)" for d in INDIRECT})
    image = image_packages()
    out = {}
    for d in sorted(closure(set(direct))):
        if d in image or TORCH_SIDE.match(d):
            continue
        try:
            out[d] = md.version(d)
        except md.PackageNotFoundError:
            unknown.append(f"{d} (required, not installed here)")
    return out, unknown


def _download(specs: list[str], dest: Path) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:"]
    cmd += ["--python-version", "3.12", "--implementation", "cp", "-d", str(dest)]
    for p in PLATFORMS:
        cmd += ["--platform", p]
    subprocess.run(cmd + specs, check=True)


def _sha256(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def lock() -> dict:
    """Download the needed wheels here and write the lock file."""
    dists, unknown = needed()
    if unknown:
        raise SystemExit("cannot place: " + "; ".join(unknown))
    with tempfile.TemporaryDirectory() as tmp:
        _download([f"{d}=={v}" for d, v in dists.items()], Path(tmp))
        wheels = sorted(Path(tmp).glob("*.whl"))
        entries = []
        for w in wheels:
            name = norm(w.name.split("-")[0])
            entries.append(
                {"name": name, "version": dists.get(name, w.name.split("-")[1]),
                 "file": w.name, "size": w.stat().st_size, "sha256": _sha256(w)}
            )  # fmt: skip
    data = {
        "python": "3.12",
        "platforms": list(PLATFORMS),
        "image_requirements": image_requirements(set(dists)),
        "total_bytes": sum(e["size"] for e in entries),
        "wheels": entries,
    }
    LOCK.write_text(json.dumps(data, indent=2) + "\n")
    return data


def fetch(dest: Path) -> list[Path]:
    """Download the locked wheels into ``dest`` and check their hashes."""
    data = json.loads(LOCK.read_text())
    dest.mkdir(parents=True, exist_ok=True)
    _download([f"{e['name']}=={e['version']}" for e in data["wheels"]], dest)
    out = []
    for e in data["wheels"]:
        p = dest / e["file"]
        if not p.is_file() or _sha256(p) != e["sha256"]:
            raise SystemExit(f"{p}: missing or not the locked wheel")
        out.append(p)
    return out


def check_carried(folder: Path) -> list[str]:
    """The GPU machine's check: every locked wheel is in ``folder``, byte for byte.

    ``check_lock`` maps the kit's imports to the distributions installed *here*, which a
    bare GPU machine does not have until the carried wheels are installed; there the lock
    itself is the truth, so only the carried files are checked against it.
    """
    problems = []
    for e in json.loads(LOCK.read_text())["wheels"]:
        p = folder / e["file"]
        if not p.is_file():
            problems.append(f"{p}: missing (make the folder with scripts/gpu_wheels.sh)")
        elif _sha256(p) != e["sha256"]:
            problems.append(f"{p}: not the locked wheel (sha256 differs)")
    return problems


def check_lock() -> dict:
    """The dry run's check, without network or GPU.

    ``problems`` (the kit would break): a module the kit's code imports whose distribution
    is neither locked nor in the image, a lock over 64 MiB, a wheel not for cp312.
    ``warnings`` (the lock has drifted from this environment: refresh it with ``--lock``):
    a locked version other than the one installed here, a transitive requirement not
    locked, stale image requirements. Versions drift whenever the index moves on, so
    only ``--check --strict`` (for whoever refreshes the lock) fails on them.
    """
    problems: list[str] = []
    warnings: list[str] = []
    data = json.loads(LOCK.read_text())
    locked = {e["name"]: e["version"] for e in data["wheels"]}
    image = image_packages()
    direct, unknown = third_party(imported_modules(kit_files()))
    problems += [f"no distribution for module {u}" for u in unknown]
    for d, mod in sorted({**direct, **{i: "(indirect)" for i in INDIRECT}}.items()):
        if d not in locked and d not in image and not TORCH_SIDE.match(d):
            problems.append(f"{d} (for {mod}) is neither in {LOCK.name} nor in the GPU image")
    dists, _ = needed()
    for d, v in dists.items():
        if d not in locked:
            warnings.append(f"{d}=={v} is required here but not in {LOCK.name}")
        elif locked[d] != v:
            warnings.append(f"{d}: locked {locked[d]}, installed here {v}")
    if data.get("image_requirements") != image_requirements(set(dists)):
        warnings.append(f"the image requirements in {LOCK.name} differ from this environment's")
    total = sum(e["size"] for e in data["wheels"])
    if total > LIMIT_BYTES:
        problems.append(f"the wheels take {total / 2**20:.1f} MiB, over the 64 MiB limit")
    ok_tag = r"-(cp312-cp312|cp3\d+-abi3|py3-none|py2.py3-none)-"
    bad = [e["file"] for e in data["wheels"] if not re.search(ok_tag, e["file"])]
    problems += [f"{f}: not a cp312 / pure-Python wheel" for f in bad]
    return {
        "problems": problems,
        "warnings": warnings,
        "wheels": len(locked),
        "needed": len(dists),
        "total_mib": round(total / 2**20, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--lock", action="store_true", help="resolve, download, write the lock")
    g.add_argument("--fetch", type=Path, metavar="DIR", help="download the locked wheels")
    g.add_argument("--check", action="store_true", help="check the lock (no network)")
    ap.add_argument("--strict", action="store_true", help="with --check: fail on drift too")
    args = ap.parse_args(argv)
    if args.lock:
        data = lock()
        print(f"{len(data['wheels'])} wheels, {data['total_bytes'] / 2**20:.1f} MiB -> {LOCK}")
    elif args.fetch:
        print(f"{len(fetch(args.fetch))} wheels in {args.fetch}")
    else:
        res = check_lock()
        print(json.dumps(res, indent=2))
        return 1 if res["problems"] or (args.strict and res["warnings"]) else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
