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

When no compiler works, :func:`load` returns None and :func:`why_unavailable`
says why; callers fall back to their numba kernels.
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

__all__ = ["cache_dir", "load", "why_unavailable"]

log = logging.getLogger(__name__)

# -O3 and the host's vector units; errno-free, trap-free maths lets the compiler keep
# the vector code branch-free. No -ffast-math (NaN tests must keep their meaning) and
# no fused multiply-add: kernels reproduce the numba kernels' float32 rounding.
_FLAGS = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-shared", "-fPIC"]
_ARCH_FLAGS = ["-march=native"]
_COMPILE_TIMEOUT_S = 120

_LOCK = threading.Lock()
_LOADED: dict[str, ctypes.CDLL] = {}
_FAILED: dict[str, str] = {}


def cache_dir() -> Path:
    """Where built libraries are kept (see the module docstring)."""
    env = os.environ.get("GLINT_NATIVE_CACHE")
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


def _version(cc: str) -> str:
    out = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
    return out.stdout.strip()


def _compile(cc: str, source: Path, target: Path, extra: tuple[str, ...]) -> str | None:
    """Compile ``source`` into ``target`` (atomically); None on success, else why not."""
    target.parent.mkdir(parents=True, exist_ok=True)
    errors = []
    for arch in (_ARCH_FLAGS, []):  # a compiler without -march=native still builds
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


def _disabled() -> bool:
    return os.environ.get("GLINT_NATIVE", "1").strip().lower() in ("0", "false", "no", "off")


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
            why = _compile(cc, source, target, extra)
        except OSError as exc:  # e.g. the cache directory is not writable
            why = f"cannot write {target.parent}: {exc}"
        if why is not None:
            return None, why
    try:
        return ctypes.CDLL(str(target)), ""
    except OSError as exc:
        return None, f"cannot load {target}: {exc}"
