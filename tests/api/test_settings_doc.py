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
