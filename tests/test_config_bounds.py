"""Every number of the training config has an upper bound, and none may be NaN or ±Inf."""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Iterator
from typing import Any, get_args, get_origin

import pytest
from pydantic import BaseModel, ValidationError

from core.config import ConfigError, TrainConfig, config_from_dict


def _numeric_fields(
    model: type[BaseModel], prefix: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], bool]]:
    """(path, is_float) of every int/float field, nested models included."""
    for name, field in model.model_fields.items():
        ann = field.annotation
        kinds = set(get_args(ann)) if get_origin(ann) in (typing.Union, types.UnionType) else {ann}
        sub = [k for k in kinds if isinstance(k, type) and issubclass(k, BaseModel)]
        if sub:
            yield from _numeric_fields(sub[0], (*prefix, name))
        elif kinds & {int, float}:
            yield (*prefix, name), float in kinds


NUMERIC = list(_numeric_fields(TrainConfig))


def _nested(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    data: dict[str, Any] = {path[-1]: value}
    for part in reversed(path[:-1]):
        data = {part: data}
    return data


def test_the_walk_finds_the_fields() -> None:
    names = {".".join(p) for p, _ in NUMERIC}
    assert {"iterations", "seed", "init_points", "densify.max_gaussians", "loss.scale"} <= names
    assert {"lr.means_init", "phases.geometry_start", "envmap_resolution"} <= names
    assert len(NUMERIC) >= 40


@pytest.mark.parametrize(("path", "is_float"), NUMERIC, ids=[".".join(p) for p, _ in NUMERIC])
def test_absurd_values_are_refused_naming_the_field(path: tuple[str, ...], is_float: bool) -> None:
    field = ".".join(path)
    for value in (10**15, 2**63, 10**30):
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            config_from_dict(_nested(path, value))
    if is_float:
        for value in (math.inf, -math.inf, math.nan, 1e300):
            with pytest.raises(ConfigError, match=f"field '{field}'"):
                config_from_dict(_nested(path, value))


def test_documented_maximums() -> None:
    """The bounds are in the JSON schema (and so in the API's OpenAPI document)."""
    schema = TrainConfig.model_json_schema()
    props, defs = schema["properties"], schema["$defs"]
    assert props["iterations"]["maximum"] == 10_000_000
    assert props["init_points"]["maximum"] == 10_000_000
    assert defs["Densification"]["properties"]["max_gaussians"]["maximum"] == 50_000_000
    assert defs["LossWeights"]["properties"]["scale"]["maximum"] == 1e6
    assert defs["LearningRates"]["properties"]["means_init"]["maximum"] == 1.0


def test_sensible_values_still_pass() -> None:
    cfg = config_from_dict(
        {
            "iterations": 10_000_000,
            "init_points": 10_000_000,
            "seed": 2**32 - 1,
            "densify": {"max_gaussians": 50_000_000},
            "loss": {"scale": 1e6, "single_view": 0.0},
            "lr": {"means_init": 1.0},
        }
    )
    assert cfg.iterations == 10_000_000 and cfg.densify.max_gaussians == 50_000_000


def test_assignment_is_checked_too() -> None:
    cfg = TrainConfig()
    with pytest.raises(ValidationError):
        cfg.loss.scale = math.inf
    with pytest.raises(ValidationError):
        cfg.iterations = 2**63
