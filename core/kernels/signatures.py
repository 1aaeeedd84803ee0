"""The numba kernel signatures a test run compiles, recorded so a fresh clone compiles
them all up front, on both cores, instead of inside the tests.

Every kernel is ``@njit(cache=True)``: each distinct argument signature (float32 or
float64, C-contiguous or strided) compiles once, on first call, and is then loaded from
``__pycache__``. On a fresh clone the tests would otherwise compile ~50 signatures that a
tiny training run never reaches, in whichever worker first calls them (and in both when
both do at once). ``record`` reads the signatures out of the cache indexes a finished
test run leaves; ``compile_entries`` compiles a list of them through each kernel's own
dispatcher, which writes the same cache. A signature of a kernel that has since changed
is reported as stale and skipped (the tests then compile it as before); re-record with
``python scripts/warm_kernels.py --record`` after a test run.
"""

from __future__ import annotations

import importlib
import inspect
import pickle
from dataclasses import dataclass
from pathlib import Path

LIST = Path(__file__).resolve().parents[2] / "scripts" / "kernel_signatures.tsv"
HEADER = "# module\tfunction\tobject bytes (compile cost proxy)\tsignature (numba.types)\n"


@dataclass(frozen=True)
class Entry:
    """One compiled signature of one kernel."""

    module: str  # e.g. core.render.reflection_compiled
    function: str  # qualified name in that module
    cost: int  # size of its cached object code: a proxy for its compile time
    signature: str  # repr of the argument types, evaluable in numba.types

    def line(self) -> str:
        return f"{self.module}\t{self.function}\t{self.cost}\t{self.signature}\n"


def _index_entries(index: Path, root: Path) -> list[Entry]:
    """The signatures one ``*.nbi`` cache index holds (numba's format: a pickled version,
    then a pickled ``(source stamp, {(signature, target, ...): object file})``)."""
    # name: <module file stem>.<qualname>-<line>.py<ver>.nbi, inside <package>/__pycache__
    stem = index.name.rsplit(".py", 1)[0]
    modfile, _, rest = stem.partition(".")
    qualname = rest.rsplit("-", 1)[0]
    package = index.parent.parent.relative_to(root).parts
    module = ".".join((*package, modfile))
    with index.open("rb") as fh:
        pickle.load(fh)  # numba's version
        _stamp, overloads = pickle.loads(fh.read())
    out = []
    for key, objfile in overloads.items():
        obj = index.parent / objfile
        cost = obj.stat().st_size if obj.exists() else 0
        out.append(Entry(module, qualname, cost, repr(key[0])))
    return out


def record(root: Path, packages: tuple[str, ...] = ("core",)) -> list[Entry]:
    """Every cached signature under ``root``'s ``packages``, sorted for a stable diff."""
    entries = []
    for pkg in packages:
        for index in sorted((root / pkg).rglob("__pycache__/*.nbi")):
            entries.extend(_index_entries(index, root))
    return sorted(entries, key=lambda e: (e.module, e.function, e.signature))


def write(entries: list[Entry], path: Path = LIST) -> None:
    path.write_text(HEADER + "".join(e.line() for e in entries))


def read(path: Path = LIST) -> list[Entry]:
    """The recorded list; empty when there is none. A malformed line names itself."""
    if not path.exists():
        return []
    out = []
    for no, raw in enumerate(path.read_text().splitlines(), 1):
        if not raw.strip() or raw.startswith("#"):
            continue
        parts = raw.split("\t")
        if len(parts) != 4 or not parts[2].isdigit():
            raise ValueError(
                f"{path}:{no}: expected module, function, bytes, signature separated by tabs"
            )
        out.append(Entry(parts[0], parts[1], int(parts[2]), parts[3]))
    return out


def balance(entries: list[Entry], parts: int) -> list[list[Entry]]:
    """``entries`` split into ``parts`` lists of about equal total cost (longest first,
    each to the lightest list)."""
    groups: list[list[Entry]] = [[] for _ in range(parts)]
    load = [0] * parts
    for e in sorted(entries, key=lambda e: -e.cost):
        i = load.index(min(load))
        groups[i].append(e)
        load[i] += e.cost
    return groups


def dispatcher_of(entry: Entry):
    """The kernel's dispatcher; raises LookupError saying why when it no longer exists."""
    try:
        obj = importlib.import_module(entry.module)
    except ImportError as exc:
        raise LookupError(f"{entry.module}: {exc}") from None
    for name in entry.function.split("."):
        obj = getattr(obj, name, None)
        if obj is None:
            raise LookupError(f"{entry.module}.{entry.function}: no such function")
    if not hasattr(obj, "compile") or not hasattr(obj, "py_func"):
        raise LookupError(f"{entry.module}.{entry.function}: not a numba kernel")
    return obj


def argument_types(entry: Entry) -> tuple:
    """The signature as numba types (``Array(float32, 2, 'C', False, aligned=True)``...)."""
    import numba.types as nt

    types = eval(entry.signature, {"__builtins__": {}}, dict(vars(nt)))
    return tuple(types)


def _takes(disp, types: tuple) -> bool:
    """Whether the kernel's Python function takes as many arguments as ``types``."""
    return len(inspect.signature(disp.py_func).parameters) == len(types)


def arity_matches(entry: Entry) -> bool:
    """Whether the kernel still takes as many arguments as the recorded signature."""
    return _takes(dispatcher_of(entry), argument_types(entry))


def compile_entries(entries: list[Entry]) -> tuple[int, list[str]]:
    """Compile (or load from the cache) each signature; returns how many compiled and a
    message per stale entry."""
    done, stale = 0, []
    for e in entries:
        try:
            disp, types = dispatcher_of(e), argument_types(e)
            if not _takes(disp, types):
                raise LookupError(f"{e.module}.{e.function}: the kernel's arguments changed")
            disp.compile(types)
            done += 1
        except Exception as exc:
            stale.append(f"{e.module}.{e.function}{e.signature[:60]}...: {exc}".splitlines()[0])
    return done, stale
