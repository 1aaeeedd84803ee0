"""Request and response bodies (kept apart from the database models in api.service.models)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydantic_core import PydanticCustomError

from api.problems import Problem
from api.service.webhook_guard import MAX_URL_LENGTH, split_url
from core.config import TrainConfig

T = TypeVar("T")
JobStateName = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JobKindName = Literal["train", "mesh"]
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
    store: Literal["ok"]
    version: str


ScopeName = Literal["read", "write", "admin"]
SCOPE_HELP = (
    "'read': GET requests and viewer tokens; 'write': also everything that changes "
    "scenes and jobs; 'admin': also creating keys and revoking other keys"
)


class Me(BaseModel):
    owner: str
    key_id: str
    name: str
    scope: ScopeName = Field(description=SCOPE_HELP)
    webhook_url: str | None = Field(
        None,
        description="the key's default webhook: jobs created with this key and no webhook "
        "of their own POST their end there (PUT /v1/keys/me/webhook)",
    )


class KeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=100, pattern=NAME_PATTERN)
    scope: ScopeName = Field("write", description=SCOPE_HELP)


class KeyOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: str
    owner: str
    name: str
    prefix: str = Field(description="first characters of the key, to recognise it")
    scope: ScopeName = Field(description=SCOPE_HELP)
    created_at: datetime
    last_used_at: datetime | None = Field(
        description="last request made with the key (to within GLINT_KEY_LAST_USED_S)"
    )
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
    intrinsics: Intrinsics | None = Field(
        description="of the first view, in pixels; null for photos without poses (needs_sfm)"
    )
    masks: bool = Field(description="views carry alpha or mask files")
    points: int = Field(description="sparse points shipped with the scene (COLMAP)")
    center: list[float] | None = Field(description="null until SfM for photos without poses")
    radius: float | None = Field(description="null until SfM for photos without poses")
    warnings: list[str]
    needs_sfm: bool = Field(
        False,
        description="plain photos without poses (format 'images'): every training job on "
        "the scene starts with an 'sfm' phase that recovers the cameras",
    )


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


class UploadCreate(BaseModel):
    """One file announced for a resumable upload: where it goes, its size, its checksum."""

    model_config = ConfigDict(extra="forbid")
    path: str = Field(
        min_length=1, max_length=1024, description="its path inside the scene, e.g. train/r_0.png"
    )
    size: int = Field(ge=0, le=2**62, description="the file's size in bytes")
    sha256: str = Field(
        pattern="^[0-9a-fA-F]{64}$", description="the file's SHA-256 (hex); checked at the end"
    )


UploadStateName = Literal["open", "complete"]


class UploadOut(BaseModel):
    id: str | None = Field(description="upl_...; null once the file is complete")
    scene_id: str
    path: str
    size: int
    sha256: str
    offset: int = Field(description="bytes the server holds: send the next chunk from here")
    state: UploadStateName
    chunk_max_bytes: int = Field(description="the largest chunk a PATCH may carry")
    file: SceneFileOut | None = Field(description="the scene file, once complete")
    created_at: datetime | None
    updated_at: datetime | None


# --- jobs ----------------------------------------------------------------------------


class SfmConfig(BaseModel):
    """Structure-from-motion options of a job on an images-only scene (the defaults are
    ``core.scene.sfm.SfmOptions``'s; tests/api/test_sfm_jobs.py holds them equal)."""

    model_config = ConfigDict(extra="forbid")
    matching: Literal["auto", "exhaustive", "retrieval"] = Field(
        "auto",
        description="'auto': every pair up to 40 photos, each photo with its most similar "
        "ones above; or force one",
    )
    mapper: Literal["incremental", "global"] = Field(
        "incremental", description="COLMAP's incremental mapper, or GLOMAP's global one"
    )
    feature_masks: bool = Field(
        False,
        description="keep SIFT features off the object (needs masks; measure it first: on "
        "the Gold Cape capture it registered 2 of 119 photos instead of 119)",
    )
    min_registered: float = Field(
        0.8,
        ge=0,
        le=1,
        allow_inf_nan=False,
        description="fraction of the photos that must register, else the job fails naming "
        "the ones that did not",
    )
    seed: int = Field(0, ge=0, le=2**31 - 1, description="random seed of the mapper")


# --- webhooks ------------------------------------------------------------------------

WebhookEventName = Literal["job.succeeded", "job.failed", "job.cancelled"]
DeliveryStateName = Literal["pending", "delivered", "failed"]
SECRET_HELP = (
    "the HMAC-SHA256 key that signs every event (Glint-Signature); omitted: the server "
    "makes one (whsec_...) and answers it once, in this response"
)


class WebhookIn(BaseModel):
    """Where to POST a job's end, and the key its events are signed with."""

    model_config = ConfigDict(extra="forbid")
    url: str = Field(
        min_length=1,
        max_length=MAX_URL_LENGTH,
        description="http(s) URL; a loopback, private or link-local address (or localhost) "
        "is refused unless the server allows it (GLINT_WEBHOOK_ALLOW_PRIVATE)",
        examples=["https://example.com/hooks/glint"],
    )
    secret: str | None = Field(None, min_length=16, max_length=256, description=SECRET_HELP)

    @field_validator("url")
    @classmethod
    def _http_url(cls, url: str) -> str:
        split_url(url)  # ValueError: scheme, host, port, white space
        return url


class DeliverySummary(BaseModel):
    id: str = Field(description="whd_...; the Glint-Delivery header of its requests")
    event: WebhookEventName
    state: DeliveryStateName
    attempts: int
    last_status: int | None = Field(description="HTTP status of the last attempt")
    created_at: datetime
    delivered_at: datetime | None


class JobWebhookOut(BaseModel):
    url: str
    deliveries: list[DeliverySummary] = Field(
        description="the latest deliveries (at most 10), newest first: one per end of the job"
    )
    secret: str | None = Field(
        None,
        exclude_if=lambda secret: secret is None,  # absent, not null, where it is not shown
        description="only in the 201 response of the request that set it, when the server "
        "made it; never shown again",
    )


class KeyWebhookOut(BaseModel):
    url: str
    secret: str = Field(description="the signing key; shown only in this response")


class WebhookDeliveryOut(DeliverySummary):
    url: str = Field(description="where it is sent (the job's webhook when the job ended)")
    last_error: str | None = Field(description="why the last attempt failed")
    next_attempt_at: datetime | None = Field(
        description="when a pending delivery is tried next; null once delivered or failed"
    )


# --- jobs (continued) ----------------------------------------------------------------


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene_id: str = Field(min_length=1, max_length=40)
    config: TrainConfig = Field(
        default_factory=TrainConfig, description="training config; omitted fields default"
    )
    sfm: SfmConfig | None = Field(
        None,
        description="structure-from-motion options; only for scenes of photos without poses "
        "(report.needs_sfm), which get the defaults when this is omitted",
    )
    webhook: WebhookIn | None = Field(
        None,
        description="POST the job's end here (signed); omitted: the key's default webhook, if any",
    )


ASSET_TEXTURE_SIZES = tuple(2**k for k in range(6, 13))  # 64 .. 4096


class AssetCreate(BaseModel):
    """A relightable asset baked from the mesh (core.asset's AssetOptions, same bounds).

    The bounds live here as well as in core.asset so a bad request is a 422 naming the
    field, before a job is queued (the API process does not import the baker)."""

    model_config = ConfigDict(extra="forbid")
    faces: int = Field(
        100_000,
        ge=1000,
        le=2_000_000,
        description="face budget of the simplified, UV-unwrapped mesh of the asset",
    )
    texture_size: int = Field(
        1024,
        ge=64,
        le=4096,
        description="side of the baked textures in texels: a power of two, 64 to 4096",
    )
    views: int = Field(32, ge=1, le=256, description="how many training views are baked")
    occlusion: bool = Field(True, description="bake ambient occlusion (the ORM texture's R)")

    @field_validator("texture_size")
    @classmethod
    def _power_of_two(cls, size: int) -> int:
        if size not in ASSET_TEXTURE_SIZES:  # the message as is, no "Value error, " prefix
            raise PydanticCustomError(
                "power_of_two",
                "texture_size must be a power of two: one of {sizes}; got {size}",
                {"sizes": ", ".join(str(s) for s in ASSET_TEXTURE_SIZES), "size": size},
            )
        return size


class MeshCreate(BaseModel):
    """Parameters of a mesh extraction from a finished training job's checkpoint."""

    model_config = ConfigDict(extra="forbid")
    resolution: int = Field(
        256,
        ge=16,
        description="voxels along the longest side of the surface's box (the grid is fitted "
        "to the surface); at most GLINT_MESH_MAX_RESOLUTION",
    )
    voxel: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="voxel size in scene units; replaces resolution",
    )
    trunc: float | None = Field(
        None, gt=0, allow_inf_nan=False, description="truncation distance; default 4 voxels"
    )
    color: Literal["base", "radiance"] = Field(
        "base",
        description="vertex colour: 'base', the material without reflections (Eq. 9's base "
        "colour), or 'radiance', the rendered colour with the environment baked in",
    )
    keep_fraction: float = Field(
        0.1,
        ge=0,
        le=1,
        description="keep connected components with at least this fraction of the largest "
        "one's faces (0 keeps every component)",
    )
    simplify: int | None = Field(
        None, ge=4, le=100_000_000, description="quadric decimation to about this many faces"
    )
    grazing_blend: bool = Field(
        True,
        description="fuse the splats' centre depth (Eq. 5) where a view sees the surface "
        "obliquely (cos 0.6 to 0.3 ramp), the planar depth (Eq. 8) elsewhere; false: the "
        "planar depth at every angle",
    )
    asset: AssetCreate | None = Field(
        None,
        description="also bake a relightable asset from this mesh: asset.glb (glTF 2.0, +Y "
        "up, metallic-roughness textures), asset_env.hdr / asset_env.exr (the environment, "
        "absent for a diffuse scene), asset.json and asset_preview.png become this job's "
        "artifacts too; omitted: the mesh only. `{}` takes the defaults",
        examples=[{"faces": 100_000, "texture_size": 1024, "views": 32, "occlusion": True}],
    )
    webhook: WebhookIn | None = Field(
        None,
        description="POST the mesh job's end here (signed); omitted: the key's default webhook",
    )


class JobOut(BaseModel):
    id: str
    kind: JobKindName = Field(
        description="'train' (a training job) or 'mesh' (a mesh extracted from one)"
    )
    parent_id: str | None = Field(description="for a mesh job: the training job it meshes")
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
    eta_s: float | None = Field(
        description="estimated seconds of training left (within the time budget, if any)"
    )
    time_budget_s: float | None = Field(
        description="the job's time budget in seconds (config.time_budget), or null"
    )
    time_left_s: float | None = Field(
        description="seconds of the time budget left (training, evaluation, checkpoints)"
    )
    error: str | None
    attempts: int
    version: int = Field(description="bumped on every change")
    config: dict[str, Any]
    plan: dict[str, Any] | None = Field(description="what parts of the method the scene needs")
    stage: dict[str, Any] | None = Field(
        description="the step outside the training loop that runs now, e.g. {'name': 'mesh', "
        "'step': 'integrate', 'done': 3, 'total': 24} or {'name': 'sfm', 'step': 'matching', "
        "'done': 40, 'total': 66, 'elapsed_s': 12.5}"
    )
    sfm: dict[str, Any] | None = Field(
        description="jobs on photos without poses: {'options': {...}, 'result': null until "
        "the sfm phase recovered the cameras, then {'images', 'registered', 'unregistered', "
        "...}}; null for scenes with poses"
    )
    webhook: JobWebhookOut | None = Field(
        None, description="where the job's end is POSTed, and the deliveries so far; or null"
    )
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
