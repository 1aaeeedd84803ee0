"""Reading deploy/compose*.yaml like Docker Compose does, closely enough for tests.

Compose files use two YAML tags PyYAML does not know: ``!reset`` (drop the value the
base file set) and ``!override`` (replace it instead of merging). :func:`load_yaml`
keeps them as markers, :func:`plain` strips them (for schema validation) and
:func:`merge` applies them when layering an override file on the base file.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
DOCKER = ROOT / "docker"
COMPOSE_FILES = sorted(DEPLOY.glob("compose*.yaml"))
ENV_EXAMPLE = DEPLOY / ".env.example"
SCHEMA = Path(__file__).with_name("compose-spec.json")

GLINT_VAR = re.compile(r"\bGLINT_[A-Z0-9_]+\b")


@dataclass
class Tagged:
    """A value carrying a Compose merge tag (``reset`` or ``override``)."""

    tag: str
    value: Any


class ComposeLoader(yaml.SafeLoader):
    pass


def _tagged(tag: str):
    def construct(loader: yaml.SafeLoader, node: yaml.Node) -> Tagged:
        if isinstance(node, yaml.MappingNode):
            value: Any = loader.construct_mapping(node, deep=True)
        elif isinstance(node, yaml.SequenceNode):
            value = loader.construct_sequence(node, deep=True)
        else:
            value = loader.construct_scalar(node) or None
        return Tagged(tag, value)

    return construct


ComposeLoader.add_constructor("!reset", _tagged("reset"))
ComposeLoader.add_constructor("!override", _tagged("override"))


def load_yaml(path: Path) -> dict:
    return yaml.load(path.read_text(), Loader=ComposeLoader)  # a SafeLoader subclass


def plain(value: Any) -> Any:
    """The document as Compose would see it alone: tags dropped, values kept."""
    if isinstance(value, Tagged):
        return plain(value.value)
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain(v) for v in value]
    return value


def merge(base: Any, over: Any) -> Any:
    """``over`` layered on ``base``: mappings merge, lists and scalars are replaced.

    (Compose appends some lists, e.g. ports; the files here only override lists whose
    Compose rule is replacement: command, healthcheck.test, device lists via !override.)
    """
    if isinstance(over, Tagged):
        return _RESET if over.tag == "reset" else plain(over.value)
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            merged = merge(base.get(k), v)
            if merged is _RESET:
                out.pop(k, None)
            else:
                out[k] = merged
        return out
    return plain(over)


_RESET = object()


def compose(*names: str) -> dict:
    """deploy/<names[0]> with the following files layered on, like ``-f a -f b``."""
    docs = [load_yaml(DEPLOY / n) for n in names]
    out = plain(docs[0])
    for d in docs[1:]:
        out = merge(out, d)
    return out


def env_example() -> dict[str, str]:
    """The uncommented ``NAME=value`` lines of deploy/.env.example."""
    out = {}
    for line in ENV_EXAMPLE.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#") and "=" in line:
            k, v = line.split("=", 1)
            out[k.strip()] = v.strip()
    return out


_INTERP = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}")


def interpolate(value: str, env: dict[str, str]) -> str:
    """Compose's ``${VAR}``, ``${VAR:-default}``, ``${VAR:?error}`` (``$$`` -> ``$``)."""

    def sub(m: re.Match) -> str:
        name, op, arg = m.group(1), m.group(2), m.group(3)
        got = env.get(name)
        if op and op.endswith("-"):
            return got if got else (arg or "")
        if op and op.endswith("?"):
            if not got:
                raise KeyError(f"{name}: {arg}")
            return got
        return got or ""

    return _INTERP.sub(sub, value).replace("$$", "$")


def service_env(service: dict, env: dict[str, str]) -> dict[str, str]:
    """A service's ``environment`` (mapping or list form), interpolated with ``env``."""
    raw = service.get("environment") or {}
    if isinstance(raw, list):
        raw = dict(item.split("=", 1) for item in raw)
    return {k: interpolate(str(v), env) for k, v in raw.items()}


def settings_fields() -> dict[str, str]:
    """``GLINT_<FIELD>`` -> owning class (the one Settings of API and workers alike)."""
    from api.service.settings import Settings

    return {f"GLINT_{n.upper()}": "Settings" for n in Settings.model_fields}
