"""Worker-only knobs, on top of the service's :class:`api.settings.Settings` (``GLINT_*``)."""

from __future__ import annotations

from pydantic import Field

from api.settings import Settings

DAY_S = 24 * 3600.0


class WorkerSettings(Settings):
    """Everything a worker reads; ``GLINT_<FIELD>`` like the rest of the service."""

    worker_device: str = Field(
        "cpu", description="torch device this worker trains on (cpu, cuda:N); set by --device"
    )
    visibility_timeout_s: float = Field(
        DAY_S,
        gt=0,
        description="Redis redelivers an unacknowledged message after this long; above "
        "typical job length (a redelivery of a live job is a no-op, but costs a message)",
    )
    worker_heartbeat_s: float = Field(5.0, gt=0, description="workers-table upsert period")
    reaper_interval_s: float = Field(15.0, gt=0, description="stale/lost job scan period")
    queued_grace_s: float = Field(
        60.0,
        gt=0,
        description="a queued job untouched this long and absent from the broker is re-sent",
    )
