"""The API's JSON objects as TypedDicts: what the client returns is the server's JSON,
unchanged (new server fields pass through), with types for editors and checkers.

Field meanings are in docs/api.md; only the fields the client itself relies on are
required here, the rest are ``NotRequired`` so an older or newer server still type-checks.
"""

from __future__ import annotations

from typing import Any, Literal, NotRequired, TypedDict

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
SceneState = Literal["open", "validating", "ready"]
TERMINAL_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


class FieldError(TypedDict):
    field: str | None
    message: str
    file: NotRequired[str | None]


class SceneReport(TypedDict):
    """What commit's validation found (``needs_sfm``: photos without poses)."""

    format: str
    views: int
    train_views: int
    test_views: int
    resolution: list[int]
    resolutions: NotRequired[list[list[int]]]
    intrinsics: NotRequired[dict[str, float] | None]
    masks: NotRequired[bool]
    points: NotRequired[int]
    center: NotRequired[list[float] | None]
    radius: NotRequired[float | None]
    warnings: list[str]
    needs_sfm: NotRequired[bool]


class Scene(TypedDict):
    id: str
    name: str
    state: SceneState
    format: str | None
    file_count: int
    total_bytes: int
    report: SceneReport | None
    last_error: NotRequired[dict[str, Any] | None]
    created_at: str
    updated_at: NotRequired[str]
    committed_at: NotRequired[str | None]


class SceneFile(TypedDict):
    path: str
    size: int
    sha256: str


class Upload(TypedDict):
    """A resumable upload of one file: ``offset`` bytes have arrived; ``state`` is
    ``complete`` (and ``file`` set, ``id`` null) once the file is in the scene."""

    id: str | None
    scene_id: str
    path: str
    size: int
    sha256: str
    offset: int
    state: Literal["open", "complete"]
    chunk_max_bytes: NotRequired[int]
    file: NotRequired[SceneFile | None]
    created_at: NotRequired[str]
    updated_at: NotRequired[str]


class Job(TypedDict):
    id: str
    kind: NotRequired[Literal["train", "mesh"]]
    parent_id: NotRequired[str | None]
    scene_id: str
    state: JobState
    cancel_requested: NotRequired[bool]
    phase: str | None
    iteration: int
    total_iterations: int
    progress: float
    n_gaussians: NotRequired[int | None]
    loss: NotRequired[float | None]
    metrics: dict[str, Any] | None
    elapsed_s: NotRequired[float | None]
    eta_s: NotRequired[float | None]
    time_budget_s: NotRequired[float | None]
    time_left_s: NotRequired[float | None]
    error: str | None
    attempts: NotRequired[int]
    version: int
    config: NotRequired[dict[str, Any]]
    plan: NotRequired[dict[str, Any] | None]
    stage: NotRequired[dict[str, Any] | None]
    sfm: NotRequired[dict[str, Any] | None]
    webhook: NotRequired[dict[str, Any] | None]
    created_at: str
    updated_at: NotRequired[str]
    started_at: NotRequired[str | None]
    finished_at: NotRequired[str | None]


class Artifact(TypedDict):
    name: str
    size: int
    content_type: str
    sha256: str
    url: NotRequired[str]


class MetricRow(TypedDict):
    """One evaluation of a run (``wall_time``: training seconds so far)."""

    iteration: int
    wall_time: float
    phase: NotRequired[str]
    psnr: NotRequired[float | None]
    ssim: NotRequired[float | None]
    n_gaussians: NotRequired[int]


class Metrics(TypedDict):
    items: list[MetricRow]
    total: int
    geometry: NotRequired[str | None]
    time_budget_s: NotRequired[float | None]


class Me(TypedDict):
    owner: str
    key_id: str
    name: str
    scope: Literal["read", "write", "admin"]
