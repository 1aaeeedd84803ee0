"""docs/settings.md is generated from Settings: every GLINT_* variable, none stale."""

from __future__ import annotations

import re
from pathlib import Path

from api.service.settings import Settings, settings_markdown

DOC = Path(__file__).resolve().parents[2] / "docs" / "settings.md"


def test_settings_doc_is_generated_from_the_model() -> None:
    assert DOC.read_text() == settings_markdown(), (
        "docs/settings.md is stale: python -m api.service.settings --markdown > docs/settings.md"
    )


def test_every_field_is_listed_with_its_variable() -> None:
    listed = set(re.findall(r"`GLINT_([A-Z0-9_]+)`", settings_markdown()))
    assert listed == {n.upper() for n in Settings.model_fields}
    assert {"VIEWER_MAX", "VIEWER_SECRET", "WORKER_DEVICE", "NATIVE"} <= listed


def test_every_glint_variable_the_code_reads_is_a_field() -> None:
    """No GLINT_* variable read around Settings: code, scripts, images and compose."""
    root = DOC.parents[1]
    fields = {f"GLINT_{n.upper()}" for n in Settings.model_fields}
    seen: dict[str, str] = {}
    for top in ("core", "api", "worker", "viewer_web", "scripts", "docker", "deploy"):
        for p in (root / top).rglob("*"):
            if p.is_file() and p.suffix in {".py", ".sh", ".yaml", ".yml", ".Dockerfile", ""}:
                for name in re.findall(r"GLINT_[A-Z0-9_]+", p.read_text(errors="ignore")):
                    seen.setdefault(name, str(p.relative_to(root)))
    assert {"GLINT_NATIVE", "GLINT_KERNEL_THREADS", "GLINT_REDIS_URL"} <= set(seen)  # it looked
    stray = {n: where for n, where in seen.items() if n not in fields}
    assert not stray, f"GLINT_* names that are not Settings fields: {stray}"
