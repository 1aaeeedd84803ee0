"""Database tables: API keys, scenes and their files, jobs, their artifacts and webhooks.

Ownership is a plain ``owner`` name copied from the API key onto every scene and job,
so a query filters on it directly. Jobs carry their own progress fields (the database,
not the broker, is the source of truth), a ``version`` bumped on every change (the
event stream and ETags read it), and the lease of the runner that holds them.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_id(prefix: str) -> str:
    """``scn_<32 hex>``: random (unguessable), and the prefix says what it names."""
    return f"{prefix}_{uuid.uuid4().hex}"


class UTCDateTime(TypeDecorator[datetime]):
    """Aware UTC datetimes on every backend (SQLite keeps no zone: store naive UTC)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given; use datetime.now(UTC)")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    type_annotation_map: ClassVar[dict[Any, Any]] = {datetime: UTCDateTime(), dict[str, Any]: JSON}


class ApiKey(Base):
    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    owner: Mapped[str] = mapped_column(String(100), index=True)
    name: Mapped[str] = mapped_column(String(100))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))
    # 'read', 'write' or 'admin' (each includes the ones before it; see api.auth)
    scope: Mapped[str] = mapped_column(String(8))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_used_at: Mapped[datetime | None] = mapped_column(default=None)
    revoked_at: Mapped[datetime | None] = mapped_column(default=None)
    # the default webhook of jobs created with this key (PUT /v1/keys/me/webhook)
    webhook_url: Mapped[str | None] = mapped_column(String(2048), default=None)
    webhook_secret: Mapped[str | None] = mapped_column(String(300), default=None)


class SceneState:
    OPEN = "open"  # accepting uploads (also after a failed validation)
    VALIDATING = "validating"  # commit in progress; uploads refused
    READY = "ready"  # validated; jobs may use it; files are frozen


class Scene(Base):
    __tablename__ = "scenes"

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    owner: Mapped[str] = mapped_column(String(100), index=True)
    name: Mapped[str] = mapped_column(String(200))
    state: Mapped[str] = mapped_column(String(16), default=SceneState.OPEN)
    format: Mapped[str | None] = mapped_column(String(32), default=None)
    report: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    last_error: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)
    committed_at: Mapped[datetime | None] = mapped_column(default=None)

    files: Mapped[list[SceneFile]] = relationship(
        back_populates="scene", cascade="all, delete-orphan", passive_deletes=True
    )


class SceneFile(Base):
    __tablename__ = "scene_files"
    __table_args__ = (UniqueConstraint("scene_id", "path", name="uq_scene_files_path"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    scene_id: Mapped[str] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    path: Mapped[str] = mapped_column(String(1024))
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    scene: Mapped[Scene] = relationship(back_populates="files")


class JobState:
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    TERMINAL = frozenset({SUCCEEDED, FAILED, CANCELLED})
    ALL = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED)


class JobKind:
    TRAIN = "train"  # trains a scene (and, unless its config says otherwise, meshes it)
    MESH = "mesh"  # extracts a mesh from a finished training job's checkpoint
    ALL = (TRAIN, MESH)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_owner_created", "owner", "created_at"),)

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    owner: Mapped[str] = mapped_column(String(100), index=True)
    scene_id: Mapped[str] = mapped_column(ForeignKey("scenes.id", ondelete="RESTRICT"), index=True)
    kind: Mapped[str] = mapped_column(String(16), default=JobKind.TRAIN, server_default="train")
    parent_id: Mapped[str | None] = mapped_column(
        ForeignKey("jobs.id", ondelete="CASCADE", name="fk_jobs_parent_id_jobs"),
        default=None,
        index=True,
    )
    state: Mapped[str] = mapped_column(String(16), default=JobState.QUEUED, index=True)
    config: Mapped[dict[str, Any]] = mapped_column()
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    # progress, written by the runner
    phase: Mapped[str | None] = mapped_column(String(32), default=None)
    # a post-training step (e.g. {"name": "mesh", "step": "integrate", "done": 3, "total": 24})
    stage: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    total_iterations: Mapped[int] = mapped_column(Integer)
    n_gaussians: Mapped[int | None] = mapped_column(Integer, default=None)
    loss: Mapped[float | None] = mapped_column(Float, default=None)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    plan: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    # jobs on an images-only scene: {"options": SfmConfig, "result": None until the sfm
    # phase's scene is whole in the store, then its summary} (api.service.sfm_phase)
    sfm: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    elapsed_s: Mapped[float | None] = mapped_column(Float, default=None)
    eta_s: Mapped[float | None] = mapped_column(Float, default=None)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    # bookkeeping
    version: Mapped[int] = mapped_column(Integer, default=1)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    # runners this job lost (stopped heartbeating while running it); the reaper fails
    # the job at Settings.max_attempts, and a resume starts the count again
    runner_deaths: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    lease: Mapped[str | None] = mapped_column(String(40), default=None)
    worker: Mapped[str | None] = mapped_column(String(200), default=None)
    heartbeat_at: Mapped[datetime | None] = mapped_column(default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    # where the job's end is POSTed (api.service.webhooks), and the key that signs it
    webhook_url: Mapped[str | None] = mapped_column(String(2048), default=None)
    webhook_secret: Mapped[str | None] = mapped_column(String(300), default=None)

    artifacts: Mapped[list[Artifact]] = relationship(
        back_populates="job",
        cascade="all, delete-orphan",
        passive_deletes=True,
        order_by="Artifact.name",
    )
    webhook_deliveries: Mapped[list[WebhookDelivery]] = relationship(
        back_populates="job",
        cascade="all, delete-orphan",
        passive_deletes=True,
        order_by="WebhookDelivery.created_at",
    )


class Artifact(Base):
    __tablename__ = "artifacts"
    __table_args__ = (UniqueConstraint("job_id", "name", name="uq_artifacts_name"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(1024))
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    content_type: Mapped[str] = mapped_column(String(100))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    job: Mapped[Job] = relationship(back_populates="artifacts")


class DeliveryState:
    PENDING = "pending"  # waiting for its next attempt (or being sent now)
    DELIVERED = "delivered"  # the receiver answered 2xx
    FAILED = "failed"  # out of attempts, or refused (a forbidden address)
    ALL = (PENDING, DELIVERED, FAILED)


class WebhookDelivery(Base):
    """One POST of a job's end to its webhook, with its delivery state.

    Created in the transaction that writes the job's terminal state (so a job end is
    never lost or announced twice) and sent by the API's dispatcher
    (:mod:`api.service.webhook_dispatch`), which claims it by moving ``next_attempt_at``
    forward in a conditional ``UPDATE``: replicas never send one attempt twice.
    """

    __tablename__ = "webhook_deliveries"
    __table_args__ = (Index("ix_webhook_deliveries_due", "state", "next_attempt_at"),)

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    owner: Mapped[str] = mapped_column(String(100))
    url: Mapped[str] = mapped_column(String(2048))
    event: Mapped[str] = mapped_column(String(32))  # job.succeeded, job.failed, job.cancelled
    payload: Mapped[dict[str, Any]] = mapped_column()  # the JSON body, as signed and sent
    state: Mapped[str] = mapped_column(String(16), default=DeliveryState.PENDING)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime | None] = mapped_column(default=None)
    last_status: Mapped[int | None] = mapped_column(Integer, default=None)
    last_error: Mapped[str | None] = mapped_column(Text, default=None)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    delivered_at: Mapped[datetime | None] = mapped_column(default=None)

    job: Mapped[Job] = relationship(back_populates="webhook_deliveries")


class Worker(Base):
    """A training worker's liveness row, upserted by the worker every few seconds.

    ``expires_at`` is written by the worker (now + a few of its own heartbeat periods),
    so the API needs no knowledge of worker settings to tell the living from the dead.
    """

    __tablename__ = "workers"

    id: Mapped[str] = mapped_column(String(200), primary_key=True)  # Celery node name
    host: Mapped[str] = mapped_column(String(200))
    pid: Mapped[int] = mapped_column(Integer)
    device: Mapped[str] = mapped_column(String(32))
    current_job: Mapped[str | None] = mapped_column(String(40), default=None)
    started_at: Mapped[datetime] = mapped_column(default=utcnow)
    heartbeat_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    expires_at: Mapped[datetime] = mapped_column(default=utcnow)


class Upload(Base):
    """One file arriving in chunks (``POST /v1/scenes/{id}/uploads``), resumable.

    Each chunk that arrived whole is an object of its own under the scene
    (``scenes/{id}/uploads/{upload id}/...``, listed in ``chunks`` in offset order), so
    ``offset`` is exactly what the server holds and a client that lost its connection,
    or its process, sends only the rest. When ``offset`` reaches ``size`` the chunks are
    joined into the scene file, checked against ``sha256``, and the row goes away.
    """

    __tablename__ = "uploads"
    __table_args__ = (Index("ix_uploads_scene_path", "scene_id", "path"),)

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    scene_id: Mapped[str] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    path: Mapped[str] = mapped_column(String(1024))
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    offset: Mapped[int] = mapped_column(BigInteger, default=0)
    # [[start offset, store key], ...] of the chunks received, in offset order
    chunks: Mapped[list[Any]] = mapped_column(JSON, default=list)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)


class IdempotencyRecord(Base):
    """What a ``POST`` sent with an ``Idempotency-Key`` header created.

    A retry with the same key (same owner, same route) and the same body answers the
    object the first request made instead of making another; the same key with another
    body is refused. Records older than ``Settings.idempotency_ttl_s`` are swept.
    """

    __tablename__ = "idempotency_keys"
    __table_args__ = (
        UniqueConstraint("owner", "route", "key", name="uq_idempotency_owner_route_key"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    owner: Mapped[str] = mapped_column(String(100))
    route: Mapped[str] = mapped_column(String(100))  # e.g. "POST /v1/jobs"
    key: Mapped[str] = mapped_column(String(255))
    request_sha256: Mapped[str] = mapped_column(String(64))
    resource_id: Mapped[str] = mapped_column(String(40))
    created_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
