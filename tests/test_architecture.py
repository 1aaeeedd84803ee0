"""The import rules of docs/architecture.md, checked on the source (lazy and
TYPE_CHECKING imports included): data flows one way and nothing loops back.

    routers (api/) ─┐
                    ├─▶ api.service ─▶ core
    worker/ ────────┘
    viewer_web ─▶ core.model (and below), never training
    glint_client (client/) ─▶ nothing of the server, and nothing of the server ─▶ it

Inside ``core`` each subpackage sits on a layer and imports only its own layer and
the ones below it, so ``core`` has no cycle between packages; a module-level cycle
check catches loops inside one package.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CODE = ("api", "worker", "core", "viewer_web", "glint_client")
SERVER_CODE = ("api", "worker", "core", "viewer_web")
# where each package's source lives: the client is a distribution of its own in client/
SOURCES = {top: ROOT / top for top in CODE} | {"glint_client": ROOT / "client" / "glint_client"}

# core's packages, lowest first; a module may import its own layer and those below
CORE_LAYERS: tuple[tuple[str, ...], ...] = (
    ("core", "core.errors", "core.config", "core.devices", "core.stages"),
    ("core.kernels",),
    ("core.scene",),
    ("core.render",),
    ("core.model",),
    ("core.meshing",),
    ("core.outputs",),
    ("core.asset",),
    ("core.evaluation",),
    ("core.training",),
    ("core.benchmark",),
    ("core.cli",),
)
TRAINING_SIDE = (
    "core.training",
    "core.evaluation",
    "core.benchmark",
    "core.meshing",
    "core.outputs",
)


def module_name(path: Path) -> str:
    base = ROOT / "client" if path.is_relative_to(ROOT / "client") else ROOT
    parts = list(path.relative_to(base).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    out = {}
    for top in CODE:
        for p in SOURCES[top].rglob("*.py"):
            out[module_name(p)] = p
    return out


MODULES = modules()


def imported(name: str, path: Path) -> Iterator[tuple[str, int]]:
    """Every project module ``name`` imports (anywhere in the file), with its line."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*up, base] if base else up)
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for t in targets:
            while t and t not in MODULES:
                t = t.rpartition(".")[0]
            if t and t != name:
                yield t, node.lineno


EDGES = {m: sorted(set(imported(m, p))) for m, p in MODULES.items()}


def under(name: str, *packages: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


def violations(rule) -> list[str]:
    return [
        f"{MODULES[m].relative_to(ROOT)}:{line} imports {t}"
        for m, targets in EDGES.items()
        for t, line in targets
        if rule(m, t)
    ]


def test_the_scan_sees_the_code() -> None:
    assert "api.service.runner" in MODULES and "core.model.trained" in MODULES
    assert any(t == "core.training.run" for t, _ in EDGES["api.service.runner"])


def test_api_never_imports_worker() -> None:
    assert not violations(lambda m, t: under(m, "api") and under(t, "worker"))


def test_worker_reaches_api_only_through_the_service_layer() -> None:
    bad = violations(
        lambda m, t: under(m, "worker") and under(t, "api") and not under(t, "api.service")
    )
    assert not bad, bad


def test_service_layer_imports_neither_routers_nor_worker_nor_viewer() -> None:
    bad = violations(
        lambda m, t: (
            under(m, "api.service")
            and (
                under(t, "worker", "viewer_web")
                or (under(t, "api") and not under(t, "api.service"))
            )
        )
    )
    assert not bad, bad


def test_core_imports_no_service_code() -> None:
    bad = violations(lambda m, t: under(m, "core") and under(t, "api", "worker", "viewer_web"))
    assert not bad, bad


def test_viewer_imports_nothing_of_training() -> None:
    bad = violations(lambda m, t: under(m, "viewer_web") and under(t, *TRAINING_SIDE, "worker"))
    assert not bad, bad


def test_client_imports_no_server_code() -> None:
    """The client installs without the server's dependencies (no torch): HTTP only."""
    assert "glint_client.client" in MODULES
    bad = violations(lambda m, t: under(m, "glint_client") and under(t, *SERVER_CODE))
    assert not bad, bad


def test_server_code_never_imports_the_client() -> None:
    bad = violations(lambda m, t: under(m, *SERVER_CODE) and under(t, "glint_client"))
    assert not bad, bad


def layer_of(name: str) -> int:
    best = -1, ""
    for i, layer in enumerate(CORE_LAYERS):
        for pkg in layer:
            if under(name, pkg) and len(pkg) > len(best[1]):
                best = i, pkg
    return best[0]


def test_every_core_module_has_a_layer() -> None:
    missing = [m for m in MODULES if under(m, "core") and m != "core" and layer_of(m) <= 0
               and not under(m, *CORE_LAYERS[0][1:])]  # fmt: skip
    assert not missing, f"add these to CORE_LAYERS: {missing}"


def test_core_imports_only_its_own_layer_and_below() -> None:
    bad = violations(
        lambda m, t: under(m, "core") and under(t, "core") and layer_of(t) > layer_of(m)
    )
    assert not bad, bad


@pytest.mark.parametrize("top", CODE)
def test_no_import_cycles(top: str) -> None:
    graph = {m: {t for t, _ in EDGES[m] if under(t, top)} for m in MODULES if under(m, top)}
    # a package's __init__ importing its own submodules is how packages re-export
    for m in graph:
        graph[m] = {t for t in graph[m] if not (MODULES[m].name == "__init__.py" and under(t, m))}
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycles.append([*stack[stack.index(t) :], t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, " ; ".join(" → ".join(c) for c in cycles)
