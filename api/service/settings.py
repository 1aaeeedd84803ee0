"""Every knob of the service in one pydantic-settings class, read from ``GLINT_*``.

The API, the worker and the docker images all build their configuration from
:class:`Settings`, so a deployment is described by environment variables alone
(``GLINT_DATABASE_URL``, ``GLINT_STORE_DIR``, ...). Paths default to a data dir
(``$XDG_DATA_HOME/glint`` or ``~/.local/share/glint``) so ``glint serve`` works on a
bare machine: SQLite database and artifact store side by side.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Literal, get_args, get_origin

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

GiB = 1 << 30
MiB = 1 << 20
DAY_S = 24 * 3600.0


def _default_data_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "glint"


class Settings(BaseSettings):
    """Service configuration; every field can be set as ``GLINT_<FIELD>`` (upper case)."""

    model_config = SettingsConfigDict(env_prefix="GLINT_", env_file=".env", extra="ignore")

    # --- where things live ---------------------------------------------------------
    data_dir: Path = Field(
        default_factory=_default_data_dir,
        description="root for the default SQLite database and artifact store",
    )
    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL, e.g. postgresql+psycopg://user@host/db; "
        "default sqlite:///{data_dir}/glint.db",
    )
    store_dir: Path | None = Field(
        None,
        description="artifact store root (scene files, run folders); a volume shared by "
        "API and workers; default {data_dir}/store",
    )
    store_url: str | None = Field(
        None,
        description="s3://BUCKET[/PREFIX]: keep artifacts in an S3-compatible bucket (API and "
        "workers on different hosts share nothing else but the database and Redis); unset: "
        "the directory store_dir",
    )
    s3_endpoint_url: str | None = Field(
        None,
        description="S3 endpoint, e.g. http://minio:9000 (MinIO, Ceph RGW, R2); unset: "
        "AWS_ENDPOINT_URL_S3 / AWS_ENDPOINT_URL, else AWS S3 itself",
    )
    s3_region: str | None = Field(
        None, description="bucket region; unset: AWS_REGION / AWS_DEFAULT_REGION / AWS config"
    )
    s3_access_key_id: str | None = Field(
        None,
        description="access key; unset: the standard AWS chain (AWS_ACCESS_KEY_ID and "
        "AWS_SECRET_ACCESS_KEY, AWS_PROFILE, an instance or task role)",
    )
    s3_secret_access_key: str | None = Field(
        None,
        description="secret key going with s3_access_key_id (both set, or the AWS chain is used)",
    )
    s3_addressing_style: Literal["auto", "path", "virtual"] = Field(
        "auto",
        description="bucket in the path (http://host/bucket/key) or the host name; 'auto': "
        "path with a custom endpoint (MinIO), virtual hosts on AWS",
    )
    store_timeout_s: float = Field(
        10.0,
        gt=0,
        description="connect and read timeout of one store request (the health check and "
        "job submission wait at most min(3, this) on an unreachable store)",
    )
    store_part_bytes: int = Field(
        8 * MiB,
        ge=5 * MiB,
        le=512 * MiB,
        description="multipart upload part size: the memory one upload holds in the API; "
        "objects up to 10,000 parts",
    )
    store_retry_s: float = Field(
        600.0,
        ge=0,
        description="a runner that loses the store keeps retrying (exponential backoff) this "
        "long, then fails the job (resume it later); 0: no retry",
    )
    store_sweep_s: float = Field(
        3600.0,
        ge=0,
        description="period of the API's sweep for orphans: objects of deleted scenes and "
        "jobs, multipart uploads abandoned for a day; 0: off",
    )
    cache_dir: Path | None = Field(
        None,
        description="local copies of bucket objects (scenes and run folders a worker trains "
        "on, checkpoints the viewer shows); default {data_dir}/cache",
    )
    redis_url: str | None = Field(None, description="broker URL for the Celery queue")
    queue_backend: Literal["auto", "local", "celery"] = Field(
        "auto",
        description="'auto': 'celery' when redis_url is set, else 'local'; 'local': jobs "
        "run in child processes of the API (embedded, no external service); 'celery': "
        "Celery workers on the Redis broker",
    )
    auto_migrate: bool = Field(True, description="run Alembic migrations when the app starts")

    # --- HTTP server -------------------------------------------------------------
    host: str = Field("127.0.0.1", description="address `glint serve` binds")
    port: int = Field(8000, ge=0, le=65535, description="port `glint serve` listens on")
    log_level: str = Field("info", description="uvicorn and service log level")
    threads: int = Field(
        40, ge=1, description="worker threads for blocking route code (database, files)"
    )
    kernel_threads: int | None = Field(
        None,
        ge=1,
        description="threads of the compiled CPU rasteriser kernels (training, viewer "
        "renders); torch's own ops run on one. None: every CPU the process may use",
    )
    # Applied to core by apply_to_core() when the API or a worker starts.
    native: bool = Field(
        True,
        description="use the SIMD C compositing kernel where it builds or is prebuilt; "
        "false keeps the numba kernels",
    )
    native_cache: Path | None = Field(
        None,
        description="where kernels built at first use are cached; None: "
        "$XDG_CACHE_HOME/glint/native or ~/.cache/glint/native",
    )
    native_prebuilt: Path | None = Field(
        None,
        description="directory of kernels prebuilt by `python -m core.kernels.native_build "
        "--prebuild DIR` (the API image sets it); tried before compiling",
    )

    key_last_used_s: float = Field(
        60.0,
        ge=0,
        description="an API key's last_used_at is written at most this often (keys are "
        "looked up on every request, so a revocation takes effect at once); 0 = every request",
    )

    # --- uploads -------------------------------------------------------------------
    max_file_bytes: int = Field(2 * GiB, ge=1, description="largest single scene file")
    max_scene_bytes: int = Field(20 * GiB, ge=1, description="all files of one scene")
    max_scene_files: int = Field(10_000, ge=1, description="files in one scene")
    max_archive_bytes: int = Field(20 * GiB, ge=1, description="largest uploaded archive")
    max_archive_ratio: float = Field(
        200.0, gt=1, description="uncompressed/compressed bound (zip bombs)"
    )
    upload_chunk_bytes: int = Field(1 * MiB, ge=4096, description="write granularity")
    upload_chunk_max_bytes: int = Field(
        64 * MiB,
        ge=4096,
        description="largest chunk of a resumable upload (PATCH /v1/scenes/{id}/uploads/{id}); "
        "a chunk cut off midway is sent again whole, so this bounds what a dropped connection "
        "costs",
    )
    upload_expire_s: float = Field(
        7 * 24 * 3600.0,
        gt=0,
        description="an unfinished resumable upload that received no chunk for this long is "
        "removed by the store sweep",
    )
    idempotency_ttl_s: float = Field(
        24 * 3600.0,
        gt=0,
        description="how long a POST's Idempotency-Key is remembered (a retry within it "
        "answers the object the first request made)",
    )
    max_path_length: int = Field(255, ge=16, description="longest relative file path")

    # --- validation and jobs -------------------------------------------------------
    validation_concurrency: int = Field(1, ge=1, description="scenes loaded at once")
    local_workers: int = Field(1, ge=1, description="jobs run at once by the local queue")
    embedded_job_nice: int = Field(
        10,
        ge=0,
        le=19,
        description="niceness added to the local queue's job processes (0 = as the API): "
        "training yields the CPU to the API's requests",
    )
    progress_interval_s: float = Field(0.5, gt=0, description="min seconds between DB writes")
    cancel_poll_s: float = Field(0.5, gt=0, description="min seconds between cancel checks")
    heartbeat_s: float = Field(
        5.0, gt=0, description="period of a running job's liveness update (its heartbeat)"
    )
    stale_after_s: float = Field(
        20.0,
        gt=0,
        description="a running job without heartbeat this long has lost its runner: the "
        "reaper puts it back in the queue (at least 2 x heartbeat_s)",
    )
    max_attempts: int = Field(
        3,
        ge=1,
        description="runs a job gets when its runner dies (killed, crashed, lost its "
        "machine): the job that lost this many runners ends failed, saying so",
    )

    mesh_max_resolution: int = Field(
        512,
        ge=16,
        le=2048,
        description="longest side of a mesh extraction's voxel grid a job may ask for; "
        "memory grows with the narrow band around the surface (see docs/benchmarks.md)",
    )

    # --- workers (glint worker) ------------------------------------------------------
    worker_device: str = Field(
        "cpu", description="torch device a worker trains on (cpu, cuda:N); set by --device"
    )
    visibility_timeout_s: float = Field(
        DAY_S,
        gt=0,
        description="Redis redelivers an unacknowledged message after this long; above "
        "typical job length (a redelivery of a live job is a no-op, but costs a message)",
    )
    worker_heartbeat_s: float = Field(5.0, gt=0, description="workers-table upsert period")
    reaper_interval_s: float = Field(
        5.0,
        gt=0,
        description="period of the scan for stale / lost jobs (workers and, with the "
        "celery queue, the API)",
    )
    queued_grace_s: float = Field(
        60.0,
        gt=0,
        description="a queued job untouched this long and absent from the broker is re-sent",
    )

    # --- viewer ----------------------------------------------------------------------
    viewer_max: int = Field(4, ge=1, description="concurrent viewer sessions per API process")
    viewer_secret: str | None = Field(
        None,
        description="key that signs viewer tokens; set the same value on every API replica "
        "behind one load balancer. None: a random key per process",
    )

    # --- reading -------------------------------------------------------------------
    sse_poll_s: float = Field(0.5, gt=0, description="job event stream DB poll period")
    sse_keepalive_s: float = Field(15.0, gt=0, description="comment line when nothing changed")
    page_size_max: int = Field(200, ge=1, description="largest page a list endpoint returns")

    # --- webhooks (POSTed when a job ends; api.service.webhooks) -------------------
    webhook_allow_private: bool = Field(
        False,
        description="let webhooks go to loopback, private, link-local (cloud metadata), CGNAT, "
        "multicast and reserved addresses and to 'localhost'; off: such a URL is refused when "
        "it is set (422) and a host name resolving to one fails its delivery",
    )
    webhook_timeout_s: float = Field(
        10.0,
        gt=0,
        le=300,
        description="connect and read timeout of one webhook delivery attempt",
    )
    webhook_max_attempts: int = Field(
        6, ge=1, le=100, description="attempts a webhook delivery gets; then it is failed"
    )
    webhook_backoff_s: float = Field(
        5.0,
        ge=0,
        description="wait before a failed webhook delivery's second attempt; doubled after "
        "each further failure",
    )
    webhook_backoff_max_s: float = Field(
        600.0, ge=0, description="longest wait between two attempts of a webhook delivery"
    )
    webhook_poll_s: float = Field(
        1.0,
        gt=0,
        le=3600,
        description="how often the API's webhook dispatcher looks for deliveries that are due",
    )

    @model_validator(mode="after")
    def _liveness_periods(self) -> Settings:
        # a runner that beats every heartbeat_s must be able to miss one beat unnoticed
        if self.stale_after_s < 2 * self.heartbeat_s:
            raise ValueError(
                f"stale_after_s ({self.stale_after_s}) must be at least twice heartbeat_s "
                f"({self.heartbeat_s}): a live runner would be taken for dead"
            )
        return self

    @model_validator(mode="after")
    def _store_url(self) -> Settings:
        if self.store_url is not None:
            from urllib.parse import urlsplit

            parts = urlsplit(self.store_url)
            if parts.scheme != "s3" or not parts.netloc or parts.query or parts.fragment:
                raise ValueError(
                    f"store_url {self.store_url!r} is not s3://BUCKET[/PREFIX]; "
                    "leave it unset for the directory store"
                )
        return self

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.data_dir / 'glint.db'}"

    @property
    def store_root(self) -> Path:
        return self.store_dir if self.store_dir is not None else self.data_dir / "store"

    @property
    def cache_root(self) -> Path:
        return self.cache_dir if self.cache_dir is not None else self.data_dir / "cache"


@lru_cache
def get_settings() -> Settings:
    """Process-wide settings from the environment (the app factory can be given others)."""
    return Settings()


def apply_to_core(settings: Settings) -> None:
    """Hand the fields ``core`` reads to it: the compiled kernels' thread count and
    where the SIMD kernel comes from. Called once when the API or a worker starts."""
    from core.kernels import native_build

    native_build.configure(
        # on is the default: only a switch-off needs saying (None keeps the environment's)
        enabled=None if settings.native else False,
        cache=settings.native_cache,
        prebuilt=settings.native_prebuilt,
    )
    if settings.kernel_threads is not None:
        from core.kernels.threads import configure_cpu_threads

        configure_cpu_threads(settings.kernel_threads)


def settings_markdown() -> str:
    """Every ``GLINT_*`` variable as a Markdown table, generated from :class:`Settings`."""
    lines = [
        "# Settings",
        "",
        "Generated from `api.service.settings.Settings` by "
        "`python -m api.service.settings --markdown > docs/settings.md`; a test fails when "
        "this file and the model differ. Every field is read from `GLINT_<FIELD>` (or a "
        "`.env` file) by the API and the workers alike.",
        "",
        "| variable | type | default | meaning |",
        "|---|---|---|---|",
    ]
    for name, f in Settings.model_fields.items():
        if f.default_factory is not None:
            default = "(see meaning)"
        else:
            default = "unset" if f.default is None else f"`{f.default}`"
        if get_origin(f.annotation) is Literal:
            kind = " or ".join(repr(a) for a in get_args(f.annotation))
        else:
            kind = getattr(f.annotation, "__name__", None) or str(f.annotation)
        kind = kind.replace("pathlib.", "").replace("typing.", "").replace("|", "\\|")
        desc = (f.description or "").replace("|", "\\|")
        lines.append(f"| `GLINT_{name.upper()}` | {kind} | {default} | {desc} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--markdown"]:
        sys.exit("usage: python -m api.service.settings --markdown")
    sys.stdout.write(settings_markdown())
