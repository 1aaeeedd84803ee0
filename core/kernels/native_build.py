"""Build a bundled C source into a shared library at first use, cached per machine.

Why at first use: the fastest CPU kernels need the host's vector width
(``-march=native``), which a wheel built elsewhere cannot know, and a plain
``pip install`` must keep working without a compiler. So a kernel is compiled the
first time a process asks for it, with ``$CC``, else ``cc``, ``gcc`` or ``clang``
(about 1 s), and loaded with ctypes. The library is cached under
``$GLINT_NATIVE_CACHE`` (default ``$XDG_CACHE_HOME/glint/native`` or
``~/.cache/glint/native``), keyed by the source, the flags, the compiler's version
and the CPU's model and feature flags, so a cache copied to another machine, or a
container image built on one, is rebuilt rather than run with the wrong
instructions. Setting ``GLINT_NATIVE=0`` turns native kernels off.

Images without a compiler ship prebuilt variants instead: ``python -m
core.kernels.native_build --prebuild DIR`` (in an image's build stage) compiles every kernel
for each x86-64 micro-architecture level (v4: AVX-512, v3: AVX2, v2, baseline) or
the baseline of other machines, and ``GLINT_NATIVE_PREBUILT=DIR`` at run time loads
the best level this CPU supports, before any compiling is tried.

When neither works, :func:`load` returns None and :func:`why_unavailable` says
why; callers fall back to their numba kernels.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

__all__ = ["SOURCES", "cache_dir", "configure", "load", "prebuild", "why_unavailable"]

log = logging.getLogger(__name__)

# -O3 and the host's vector units; errno-free, trap-free maths lets the compiler keep
# the vector code branch-free. No -ffast-math (NaN tests must keep their meaning) and
# no multiply-add the compiler fuses on its own: where a value decides something (which
# pixels a splat reaches) kernels reproduce the numba kernels' float32 rounding; they
# fuse explicitly only where nothing depends on the last bit.
_FLAGS = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-shared", "-fPIC"]
_ARCH_FLAGS = ["-march=native"]
_COMPILE_TIMEOUT_S = 120

# The bundled kernel sources (what --prebuild builds).
SOURCES = tuple(sorted((Path(__file__).parent / "native").glob("*.c")))

# x86-64 micro-architecture levels of prebuilt kernels, best first, with the
# /proc/cpuinfo flags each needs.
_X86_LEVELS: tuple[tuple[str, frozenset[str]], ...] = (
    ("x86-64-v4", frozenset({"avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"})),
    ("x86-64-v3", frozenset({"avx", "avx2", "fma", "bmi1", "bmi2", "f16c", "movbe"})),
    ("x86-64-v2", frozenset({"sse4_1", "sse4_2", "ssse3", "popcnt"})),
    ("x86-64", frozenset()),
)

_LOCK = threading.Lock()
_LOADED: dict[str, ctypes.CDLL] = {}
_FAILED: dict[str, str] = {}
# Values a service configured (its Settings); each replaces its environment variable.
_CONFIGURED: dict[str, str] = {}


def configure(
    *, enabled: bool | None = None, cache: Path | None = None, prebuilt: Path | None = None
) -> None:
    """Set what ``GLINT_NATIVE``, ``GLINT_NATIVE_CACHE`` and ``GLINT_NATIVE_PREBUILT``
    would (None leaves the environment's value). A service calls this with its
    Settings at start-up, so values from a ``.env`` file apply too."""
    with _LOCK:
        for key, value in (
            ("GLINT_NATIVE", None if enabled is None else ("1" if enabled else "0")),
            ("GLINT_NATIVE_CACHE", None if cache is None else str(cache)),
            ("GLINT_NATIVE_PREBUILT", None if prebuilt is None else str(prebuilt)),
        ):
            if value is None:
                _CONFIGURED.pop(key, None)
            else:
                _CONFIGURED[key] = value
        _FAILED.clear()  # a new source or switch may succeed where the old one failed


def _setting(name: str, default: str | None = None) -> str | None:
    return _CONFIGURED.get(name, os.environ.get(name, default))


def cache_dir() -> Path:
    """Where built libraries are kept (see the module docstring)."""
    env = _setting("GLINT_NATIVE_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "glint" / "native"


def _compiler() -> str | None:
    cc = os.environ.get("CC")
    if cc:
        return shutil.which(cc) or (cc if Path(cc).is_file() else None)
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _cpu_signature() -> str:
    """The CPU model and feature flags (Linux), else the platform's processor string."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    keep = [ln for ln in lines if ln.split(":")[0].strip() in ("model name", "flags", "Features")]
    return "\n".join(sorted(set(keep)))


def _cpu_flags() -> frozenset[str]:
    """The CPU's feature flags as /proc/cpuinfo spells them (empty where unknown)."""
    for line in _cpu_signature().splitlines():
        if line.split(":")[0].strip() in ("flags", "Features"):
            return frozenset(line.split(":", 1)[1].split())
    return frozenset()


def _levels() -> tuple[tuple[str, frozenset[str]], ...]:
    """Prebuilt variants for this kind of machine: (-march value, flags it needs)."""
    machine = platform.machine().lower()
    if machine in ("x86_64", "amd64"):
        return _X86_LEVELS
    if machine in ("aarch64", "arm64"):
        return (("armv8-a", frozenset()),)
    return ()


def _prebuilt_name(source: Path, level: str) -> str:
    digest = hashlib.sha256(source.read_bytes()).hexdigest()[:16]
    return f"{source.stem}-{digest}-{level}.so"


def prebuild(out_dir: Path, sources: tuple[Path, ...] = SOURCES) -> list[Path]:
    """Compile every source for every level of this kind of machine into ``out_dir``."""
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC, or install gcc or clang)")
    if not _levels():
        raise RuntimeError(f"no prebuilt levels are defined for {platform.machine()}")
    built = []
    for source in sources:
        for level, _ in _levels():
            target = Path(out_dir) / _prebuilt_name(source, level)
            why = _compile(cc, source, target, [f"-march={level}"], fallback=False)
            if why is not None:
                raise RuntimeError(why)
            built.append(target)
    return built


def _load_prebuilt(source: Path) -> ctypes.CDLL | None:
    """The best prebuilt variant of ``source`` for this CPU, if GLINT_NATIVE_PREBUILT
    points at a directory holding one."""
    root = _setting("GLINT_NATIVE_PREBUILT")
    if not root:
        return None
    flags = _cpu_flags()
    for level, needs in _levels():
        path = Path(root) / _prebuilt_name(source, level)
        if needs <= flags and path.is_file():
            try:
                return ctypes.CDLL(str(path))
            except OSError as exc:
                log.warning("cannot load prebuilt %s: %s", path, exc)
    return None


def _version(cc: str) -> str:
    out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
    return out.stdout.strip()


def _compile(
    cc: str, source: Path, target: Path, extra: list[str], fallback: bool = True
) -> str | None:
    """Compile ``source`` into ``target`` (atomically); None on success, else why not.
    With ``fallback`` a compiler that rejects -march=native builds without it."""
    target.parent.mkdir(parents=True, exist_ok=True)
    errors = []
    for arch in (_ARCH_FLAGS, []) if fallback else ([],):
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
        os.close(fd)
        cmd = [cc, *_FLAGS, *arch, *extra, "-o", tmp, str(source), "-lm"]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=_COMPILE_TIMEOUT_S)
        except (OSError, subprocess.TimeoutExpired) as exc:
            res = None
            errors.append(f"{' '.join(cmd)}: {exc}")
        if res is not None and res.returncode == 0:
            os.replace(tmp, target)  # atomic: concurrent workers never load a partial file
            return None
        if res is not None:
            errors.append(f"{' '.join(cmd)} exited {res.returncode}: {res.stderr.strip()[:400]}")
        Path(tmp).unlink(missing_ok=True)
    return "; ".join(errors)


_FALSE = ("0", "f", "false", "n", "no", "off")  # as pydantic reads GLINT_NATIVE


def _disabled() -> bool:
    return (_setting("GLINT_NATIVE", "1") or "1").strip().lower() in _FALSE


def load(source: Path, extra_flags: tuple[str, ...] = ()) -> ctypes.CDLL | None:
    """The built library of ``source`` (compiled on first use), or None if it cannot be.

    ``extra_flags`` go after the default ones (tests build other vector widths).
    """
    if _disabled():
        return None
    key = f"{source}\0{' '.join(extra_flags)}"
    with _LOCK:
        if key in _LOADED:
            return _LOADED[key]
        if key in _FAILED:
            return None
        lib, why = _build_and_load(source, tuple(extra_flags))
        if lib is None:
            _FAILED[key] = why
            log.warning("native kernel %s unavailable (%s); numba kernels stay", source.name, why)
        else:
            _LOADED[key] = lib
        return lib


def why_unavailable(source: Path, extra_flags: tuple[str, ...] = ()) -> str | None:
    """None when ``source`` builds and loads here, otherwise the reason."""
    if _disabled():
        return "GLINT_NATIVE=0 turns native kernels off"
    if load(source, extra_flags) is not None:
        return None
    return _FAILED.get(f"{source}\0{' '.join(extra_flags)}", "not built")


def _build_and_load(source: Path, extra: tuple[str, ...]) -> tuple[ctypes.CDLL | None, str]:
    if not source.is_file():
        return None, f"{source} is missing from the installation"
    if not extra:
        lib = _load_prebuilt(source)
        if lib is not None:
            return lib, ""
    cc = _compiler()
    if cc is None:
        return None, "no C compiler found (set CC, or install gcc or clang)"
    try:
        version = _version(cc)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return None, f"{cc} --version failed: {exc}"
    h = hashlib.sha256()
    for part in (source.read_bytes(), " ".join([*_FLAGS, *_ARCH_FLAGS, *extra]).encode(),
                 cc.encode(), version.encode(), _cpu_signature().encode(),
                 platform.machine().encode()):  # fmt: skip
        h.update(part)
        h.update(b"\0")
    target = cache_dir() / f"{source.stem}-{h.hexdigest()[:20]}.so"
    if not target.is_file():
        try:
            why = _compile(cc, source, target, list(extra))
        except OSError as exc:  # e.g. the cache directory is not writable
            why = f"cannot write {target.parent}: {exc}"
        if why is not None:
            return None, why
    try:
        return ctypes.CDLL(str(target)), ""
    except OSError as exc:
        return None, f"cannot load {target}: {exc}"


def main(argv: list[str] | None = None) -> None:
    """``python -m core.kernels.native_build --prebuild DIR``: the image build step."""
    import argparse

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--prebuild", type=Path, required=True, metavar="DIR")
    args = ap.parse_args(argv)
    for path in prebuild(args.prebuild):
        print(path)


if __name__ == "__main__":
    main()
