"""The client installs without the server's dependencies: it declares httpx and tqdm only,
and its modules import nothing else outside the standard library."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

CLIENT = Path(__file__).resolve().parents[2] / "client"
ALLOWED = {"httpx", "tqdm", "glint_client"}


def test_declares_only_httpx_and_tqdm() -> None:
    project = tomllib.loads((CLIENT / "pyproject.toml").read_text())["project"]
    names = {re.split(r"[<>=!~\[ ;]", d, maxsplit=1)[0].lower() for d in project["dependencies"]}
    assert names == {"httpx", "tqdm"}
    assert project["scripts"]["glint-remote"] == "glint_client.cli:main"
    assert project["entry-points"]["glint.commands"]["remote"] == "glint_client.cli:register"


def test_imports_only_the_standard_library_httpx_and_tqdm() -> None:
    foreign = []
    for path in sorted((CLIENT / "glint_client").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                tops = [a.name.split(".")[0] for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                tops = [(node.module or "").split(".")[0]]
            else:
                continue
            foreign += [
                f"{path.name}:{node.lineno} {t}"
                for t in tops
                if t not in ALLOWED and t not in sys.stdlib_module_names and t != "__future__"
            ]
    assert not foreign, foreign
