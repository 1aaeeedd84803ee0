"""``glint serve`` and ``glint keys create|list|revoke``: the service's commands in the glint CLI.

Loaded by ``core.cli`` through the ``glint.commands`` entry point, so ``core`` never
imports ``api``. Heavy imports happen inside the handlers: ``glint --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from datetime import datetime

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


def _keys_database(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from api.service.db import Database
    from api.service.migrate import upgrade

    database = Database(_settings(args).db_url)
    upgrade(database.engine)
    return database


def _cmd_keys_create(args: argparse.Namespace) -> int:
    from api.auth import create_key

    database = _keys_database(args)
    try:
        with database.write() as s:
            row, key = create_key(s, owner=args.name, name=args.label, scope=args.scope)
    finally:
        database.dispose()
    print(key)
    print(
        f"(key {row.id}, scope {row.scope}, for owner '{row.owner}'; it is shown only now: "
        "store it safely)",
        file=sys.stderr,
    )
    return 0


def _when(value: datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M:%S") if value is not None else "-"


def _cmd_keys_list(args: argparse.Namespace) -> int:
    from sqlalchemy import select

    from api.service.models import ApiKey

    database = _keys_database(args)
    try:
        with database.read() as s:
            q = select(ApiKey).order_by(ApiKey.owner, ApiKey.created_at, ApiKey.id)
            if args.owner:
                q = q.where(ApiKey.owner == args.owner)
            if not args.all:
                q = q.where(ApiKey.revoked_at.is_(None))
            rows = list(s.scalars(q))
    finally:
        database.dispose()
    head = ("id", "owner", "name", "scope", "prefix", "created", "last used", "revoked")
    table = [head] + [
        (
            r.id,
            r.owner,
            r.name,
            r.scope,
            r.prefix,
            _when(r.created_at),
            _when(r.last_used_at),
            _when(r.revoked_at),
        )
        for r in rows
    ]
    widths = [max(len(str(row[i])) for row in table) for i in range(len(head))]
    for row in table:
        print("  ".join(str(v).ljust(w) for v, w in zip(row, widths, strict=True)).rstrip())
    return 0


def _cmd_keys_revoke(args: argparse.Namespace) -> int:
    from datetime import UTC, datetime

    from api.service.models import ApiKey
    from core.errors import GlintError

    database = _keys_database(args)
    try:
        with database.write() as s:
            row = s.get(ApiKey, args.key_id)
            if row is None:
                raise GlintError(f"no key '{args.key_id}' (see glint keys list)")
            already = row.revoked_at is not None
            if not already:
                row.revoked_at = datetime.now(UTC)
            owner = row.owner
    finally:
        database.dispose()
    what = "was already revoked" if already else "revoked: it fails from the next request on"
    print(f"key {args.key_id} of owner '{owner}' {what}")
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
    k.add_argument(
        "--scope",
        choices=["read", "write", "admin"],
        default="admin",
        help="what the key may do: read (GET only), write (also change scenes and jobs), "
        "admin (also create and revoke keys through the API); default admin",
    )
    _add_common(k)
    k.set_defaults(func=_cmd_keys_create, compute=False)  # no torch: see core.cli.main

    k = keys_sub.add_parser(
        "list",
        help="list API keys (id, owner, name, scope, created, last used)",
        description="Lists live keys (--all: revoked ones too), of every owner or of OWNER. "
        "The keys themselves are not stored and cannot be shown.",
    )
    k.add_argument("owner", metavar="OWNER", nargs="?", help="only this owner's keys")
    k.add_argument("--all", action="store_true", help="revoked keys too")
    _add_common(k)
    k.set_defaults(func=_cmd_keys_list, compute=False)  # no torch: see core.cli.main

    k = keys_sub.add_parser(
        "revoke",
        help="revoke an API key by id (it fails from the next request on)",
        description="Revokes key KEY_ID (key_..., see glint keys list) of any owner; "
        "the API refuses it from the next request on, on every replica.",
    )
    k.add_argument("key_id", metavar="KEY_ID", help="the key's id (key_...)")
    _add_common(k)
    k.set_defaults(func=_cmd_keys_revoke, compute=False)  # no torch: see core.cli.main
