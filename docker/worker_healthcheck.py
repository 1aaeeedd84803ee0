"""Container health check of a Glint worker: is this host's worker alive?

``glint worker`` (Celery, solo pool) upserts a row in the ``workers`` table from a
housekeeping thread every GLINT_WORKER_HEARTBEAT_S seconds, with an ``expires_at`` a
few periods ahead; the thread keeps beating while a long job runs. A row for this
hostname (the container's) that has not expired means the worker is up, registered
and reaches the database. (``celery inspect ping`` is no liveness check here: with
the solo pool, control messages wait until the running job ends, for hours.)

Reads the same GLINT_* settings as the worker; exit 0 healthy, 1 not. Installed in the
images as /opt/glint/worker_healthcheck.py (see docker/*.Dockerfile, deploy/compose.yaml).
"""

from __future__ import annotations

import socket
import sys
from datetime import UTC, datetime


def main() -> int:
    from sqlalchemy import select

    from api.service.db import Database
    from api.service.models import Worker
    from api.service.settings import Settings

    host = socket.gethostname()
    database = Database(Settings().db_url)
    try:
        with database.read() as s:
            row = s.execute(
                select(Worker.id, Worker.device, Worker.current_job)
                .where(Worker.host == host, Worker.expires_at > datetime.now(UTC))
                .limit(1)
            ).first()
    except Exception as exc:
        print(f"unhealthy: database: {type(exc).__name__}: {exc}")
        return 1
    finally:
        database.dispose()
    if row is None:
        print(f"unhealthy: no live worker registered for host {host}")
        return 1
    print(f"ok: {row.id} on {row.device}, job {row.current_job or '-'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
