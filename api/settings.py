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

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

GiB = 1 << 30
MiB = 1 << 20


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
    redis_url: str | None = Field(None, description="broker URL for the Celery queue")
    queue_backend: str = Field(
        "auto",
        description="'auto': 'celery' when redis_url is set, else 'local'; 'local': jobs "
        "run in a thread of the API process (embedded, no external service); 'celery': "
        "Celery workers on the Redis broker; or 'module:factory'",
    )
    auto_migrate: bool = Field(True, description="run Alembic migrations when the app starts")

    # --- HTTP server -------------------------------------------------------------
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    log_level: str = "info"
    threads: int = Field(
        40, ge=1, description="worker threads for blocking route code (database, files)"
    )
    kernel_threads: int | None = Field(
        None,
        ge=1,
        description="threads of the compiled CPU rasteriser kernels (training, viewer "
        "renders); torch's own ops run on one. None: every CPU the process may use",
    )
    # Read by core.native_build from the environment (as kernel_threads by core.threads);
    # fields here so that a deployment's values are validated and documented.
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
        description="directory of kernels prebuilt by `python -m core.native_build "
        "--prebuild DIR` (the API image sets it); tried before compiling",
    )

    auth_cache_s: float = Field(
        5.0,
        ge=0,
        description="remember a valid key this long (revocations on other "
        "replicas take effect within it); 0 = look every key up",
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
    max_path_length: int = Field(255, ge=16, description="longest relative file path")

    # --- validation and jobs -------------------------------------------------------
    validation_concurrency: int = Field(1, ge=1, description="scenes loaded at once")
    local_workers: int = Field(1, ge=1, description="jobs run at once by the local queue")
    progress_interval_s: float = Field(0.5, gt=0, description="min seconds between DB writes")
    cancel_poll_s: float = Field(0.5, gt=0, description="min seconds between cancel checks")
    heartbeat_s: float = Field(10.0, gt=0, description="a running job's liveness update")
    stale_after_s: float = Field(
        120.0, gt=0, description="a running job without heartbeat this long may be reclaimed"
    )

    # --- reading -------------------------------------------------------------------
    sse_poll_s: float = Field(0.5, gt=0, description="job event stream DB poll period")
    sse_keepalive_s: float = Field(15.0, gt=0, description="comment line when nothing changed")
    page_size_max: int = Field(200, ge=1)

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.data_dir / 'glint.db'}"

    @property
    def store_root(self) -> Path:
        return self.store_dir if self.store_dir is not None else self.data_dir / "store"


@lru_cache
def get_settings() -> Settings:
    """Process-wide settings from the environment (the app factory can be given others)."""
    return Settings()
