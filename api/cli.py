"""``glint serve`` and ``glint keys create``: the service's commands in the glint CLI.

Loaded by ``core.cli`` through the ``glint.commands`` entry point, so ``core`` never
imports ``api``. Heavy imports happen inside the handlers: ``glint --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from api.service.settings import Settings


def _settings(args: argparse.Namespace) -> Settings:
    from api.service.settings import Settings

    overrides = {}
    if getattr(args, "data_dir", None):
        overrides["data_dir"] = args.data_dir
    if getattr(args, "database_url", None):
        overrides["database_url"] = args.database_url
    return Settings(**overrides)


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from api.main import create_app

    settings = _settings(args)
    host = args.host or settings.host
    port = args.port if args.port is not None else settings.port
    print(f"glint api on http://{host}:{port}/v1 (docs at /docs); database {settings.db_url}")
    uvicorn.run(
        create_app(settings),
        host=host,
        port=port,
        log_level=args.log_level or settings.log_level,
        timeout_graceful_shutdown=10,
    )
    return 0


def _cmd_keys_create(args: argparse.Namespace) -> int:
    from api.auth import create_key
    from api.service.db import Database
    from api.service.migrate import upgrade

    settings = _settings(args)
    database = Database(settings.db_url)
    try:
        upgrade(database.engine)
        with database.write() as s:
            row, key = create_key(s, owner=args.name, name=args.label)
    finally:
        database.dispose()
    print(key)
    print(
        f"(key {row.id} for owner '{row.owner}'; it is shown only now: store it safely)",
        file=sys.stderr,
    )
    return 0


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data-dir", help="data folder (default: GLINT_DATA_DIR or ~/.local/share/glint)"
    )
    p.add_argument("--database-url", help="SQLAlchemy URL (default: GLINT_DATABASE_URL or SQLite)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``serve`` and ``keys`` to the ``glint`` command line."""
    p = sub.add_parser(
        "serve",
        help="run the REST API (uvicorn); migrates the database on start",
        description="Serve the Glint REST API under /v1. With the defaults it needs no "
        "Redis, PostgreSQL or GPU: SQLite and the artifact store live in the data folder "
        "and jobs run in this process. Every option also reads GLINT_* variables.",
    )
    p.add_argument("--host", help="bind address (default: GLINT_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default: GLINT_PORT or 8000)")
    p.add_argument("--log-level", choices=["critical", "error", "warning", "info", "debug"])
    _add_common(p)
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("keys", help="manage API keys")
    keys_sub = p.add_subparsers(dest="keys_command", metavar="ACTION", required=True)
    k = keys_sub.add_parser(
        "create",
        help="create an API key for owner NAME and print it (once)",
        description="Prints a new API key on stdout. Only its SHA-256 is stored: the key "
        "cannot be shown again. Scenes and jobs belong to NAME; every key of NAME sees them.",
    )
    k.add_argument("name", metavar="NAME", help="owner name")
    k.add_argument("--label", help="label of this key (default: NAME)")
    _add_common(k)
    k.set_defaults(func=_cmd_keys_create)
