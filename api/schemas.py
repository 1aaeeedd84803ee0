"""Request and response bodies (kept apart from the database models in api.service.models)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from api.problems import Problem
from core.config import TrainConfig

T = TypeVar("T")
JobStateName = Literal["queued", "running", "succeeded", "failed", "cancelled"]
SceneStateName = Literal["open", "validating", "ready"]
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9 ._\-]*$"


class Page(BaseModel, Generic[T]):
    items: list[T]
    total: int = Field(description="items matching the filters, over all pages")
    limit: int
    offset: int


# --- health and keys -----------------------------------------------------------------


class Health(BaseModel):
    status: Literal["ok"]
    database: Literal["ok"]
    version: str


class Me(BaseModel):
    owner: str
    key_id: str


class KeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=100, pattern=NAME_PATTERN)


class KeyOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: str
    owner: str
    name: str
    prefix: str = Field(description="first characters of the key, to recognise it")
    created_at: datetime
    revoked_at: datetime | None


class KeyCreated(KeyOut):
    key: str = Field(description="the API key; shown only in this response")


# --- scenes --------------------------------------------------------------------------


class SceneCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=200, pattern=NAME_PATTERN)


class Intrinsics(BaseModel):
    fx: float
    fy: float
    cx: float
    cy: float


class ValidationReport(BaseModel):
    """What the loaders found: enough to check a capture before paying for training."""

    format: str
    views: int
    train_views: int
    test_views: int
    resolution: list[int] = Field(description="[width, height] of the first view")
    resolutions: list[list[int]] = Field(description="every distinct [width, height]")
    intrinsics: Intrinsics = Field(description="of the first view, in pixels")
    masks: bool = Field(description="views carry alpha or mask files")
    points: int = Field(description="sparse points shipped with the scene (COLMAP)")
    center: list[float]
    radius: float
    warnings: list[str]


class SceneFileOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    path: str
    size: int
    sha256: str


class SceneOut(BaseModel):
    id: str
    name: str
    state: SceneStateName
    format: str | None
    file_count: int
    total_bytes: int
    report: ValidationReport | None
    last_error: Problem | None = Field(description="why the last commit failed, if it did")
    created_at: datetime
    updated_at: datetime
    committed_at: datetime | None


class UploadResult(BaseModel):
    scene: SceneOut
    files: list[SceneFileOut] = Field(description="files written by this request")


# --- jobs ----------------------------------------------------------------------------


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene_id: str = Field(min_length=1, max_length=40)
    config: TrainConfig = Field(
        default_factory=TrainConfig, description="training config; omitted fields default"
    )


class JobOut(BaseModel):
    id: str
    scene_id: str
    state: JobStateName
    cancel_requested: bool
    phase: str | None
    iteration: int
    total_iterations: int
    progress: float = Field(ge=0, le=1)
    n_gaussians: int | None
    loss: float | None
    metrics: dict[str, Any] | None = Field(description="latest held-out evaluation")
    elapsed_s: float | None = Field(description="training seconds so far")
    eta_s: float | None = Field(description="estimated training seconds left")
    error: str | None
    attempts: int
    version: int = Field(description="bumped on every change")
    config: dict[str, Any]
    plan: dict[str, Any] | None = Field(description="what parts of the method the scene needs")
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class ArtifactOut(BaseModel):
    name: str = Field(description="path inside the run folder, e.g. renders/test_r_0_final.png")
    size: int
    content_type: str
    sha256: str
    url: str


# --- workers -------------------------------------------------------------------------


class WorkerOut(BaseModel):
    id: str = Field(description="worker node name, e.g. glint-cuda0@gpu-host-1")
    host: str
    pid: int
    device: str = Field(description="torch device the worker trains on: cpu, cuda:N")
    busy: bool = Field(description="whether it is running a job now")
    current_job: str | None = Field(
        description="the job it runs, when that job is the caller's (others' ids are hidden)"
    )
    started_at: datetime
    heartbeat_at: datetime = Field(description="last liveness update")
