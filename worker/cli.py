"""``glint worker``: one Celery worker per GPU on the Redis broker.

Loaded by ``core.cli`` through the ``glint.commands`` entry point. The worker uses
Celery's solo pool: the task runs in the worker process itself, so nothing forks
after (or before) CUDA is initialised, and concurrency is 1 by construction.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys


def node_name(device: str) -> str:
    """Default Celery node name: the device is part of it (``glint-cuda1@host``)."""
    return f"glint-{device.replace(':', '')}@{socket.gethostname()}"


def _cmd_worker(args: argparse.Namespace) -> int:
    from api.service.settings import Settings
    from core.devices import DeviceUnavailableError, require_device

    device = args.device or Settings().worker_device
    try:  # a worker without its GPU would claim jobs only to fail every one of them
        require_device(device, "--device")
    except DeviceUnavailableError as exc:
        print(f"glint worker: {exc}", file=sys.stderr)
        return 2
    # the app reads GLINT_* when worker.app is imported: options go through the env
    os.environ["GLINT_WORKER_DEVICE"] = device
    for opt, var in (
        ("data_dir", "GLINT_DATA_DIR"),
        ("database_url", "GLINT_DATABASE_URL"),
        ("redis_url", "GLINT_REDIS_URL"),
    ):
        if getattr(args, opt, None):
            os.environ[var] = str(getattr(args, opt))
    from api.service.broker import QUEUE
    from worker.app import app, settings

    if not settings.redis_url:
        print(
            "glint worker: no broker; set GLINT_REDIS_URL or --redis-url "
            "(without Redis, `glint serve` runs jobs itself)",
            file=sys.stderr,
        )
        return 2
    name = args.name or node_name(device)
    print(f"glint worker {name} on {device}; database {settings.db_url}", file=sys.stderr)
    app.worker_main(
        [
            "worker",
            "--pool=solo",
            "--concurrency=1",
            "--prefetch-multiplier=1",
            f"--queues={QUEUE}",
            f"--hostname={name}",
            # solo runs the task on the consumer thread: broker heartbeats and gossip
            # would stall during a long job and only produce noise
            "--without-gossip",
            "--without-mingle",
            "--without-heartbeat",
            f"--loglevel={args.log_level.upper()}",
        ]
    )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``worker`` to the ``glint`` command line."""
    p = sub.add_parser(
        "worker",
        help="run a training worker on the Redis broker (one per GPU)",
        description="Consume training jobs from Redis (GLINT_REDIS_URL) and run them one "
        "at a time on DEVICE, against the same database and store as the API. Start one "
        "per GPU. Every option also reads GLINT_* variables.",
    )
    p.add_argument("--device", help="cpu or cuda:N (default: GLINT_WORKER_DEVICE or cpu)")
    p.add_argument("--name", help="Celery node name (default: glint-<device>@<host>)")
    p.add_argument("--redis-url", help="broker URL (default: GLINT_REDIS_URL)")
    p.add_argument("--data-dir", help="data folder (default: GLINT_DATA_DIR)")
    p.add_argument("--database-url", help="SQLAlchemy URL (default: GLINT_DATABASE_URL)")
    p.add_argument(
        "--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"]
    )
    p.set_defaults(func=_cmd_worker)
