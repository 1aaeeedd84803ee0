"""The app factory: settings → database (migrated), store, queue, routers under ``/v1``."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import UTC, datetime, timedelta
from typing import Any

import anyio
from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from sqlalchemy import update

import viewer_web
from api.deps import READ_THREADS, SCOPE_EXTRA
from api.problems import PROBLEM_JSON, install_handlers
from api.routers import (
    artifacts,
    jobs,
    keys,
    meshes,
    metrics,
    scenes,
    uploads,
    viewer,
    webhooks,
    workers,
)
from api.service.db import Database
from api.service.migrate import upgrade
from api.service.models import Scene, SceneState
from api.service.queue import CeleryQueue, JobQueue, LocalQueue, make_queue
from api.service.recovery import Reaper, requeue_orphans
from api.service.scene_records import relativise_scene_records
from api.service.settings import Settings, apply_to_core, get_settings
from api.service.store import ArtifactStore, LocalStore, StoreProbe, make_store
from api.service.sweeper import Sweeper
from api.service.webhook_dispatch import Dispatcher
from api.timing import ServerTimingMiddleware

log = logging.getLogger("glint.api")

# every router of the API, mounted under /v1 (each built with StrictJsonRoute)
ROUTERS = tuple(
    m.router
    for m in (keys, scenes, uploads, jobs, metrics, meshes, webhooks, artifacts, workers, viewer)
)


# a scene another replica has been validating this long is taken as abandoned by a dead
# process (validation writes no heartbeat; job liveness, GLINT_STALE_AFTER_S, is far shorter)
VALIDATING_STALE_S = 120.0


def _recover(database: Database, queue: JobQueue, settings: Settings) -> None:
    """Undo what a crashed process left half done (scenes mid-validation, local jobs)."""
    local = isinstance(queue, LocalQueue)
    cutoff = datetime.now(UTC) - timedelta(seconds=VALIDATING_STALE_S)
    with database.write() as s:
        q = update(Scene).where(Scene.state == SceneState.VALIDATING)
        if not local:  # other replicas may be validating right now
            q = q.where(Scene.updated_at < cutoff)
        s.execute(q.values(state=SceneState.OPEN, updated_at=datetime.now(UTC)))
    if local:  # this process is the only runner: its orphans are ours to restart
        for job_id in requeue_orphans(database, settings):
            queue.enqueue(job_id)


def _tidy_openapi(app: FastAPI) -> dict[str, Any]:
    """Errors are problem+json only; FastAPI's default 422 schema is replaced by Problem."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title,
        version=app.version,
        description=app.description,
        routes=app.routes,
        tags=app.openapi_tags,
    )
    for path_item in schema.get("paths", {}).values():
        for method, op in path_item.items():
            if op.get("security"):  # every key-guarded operation says which scope it needs
                safe = method.upper() in ("GET", "HEAD", "OPTIONS")
                scope = op.setdefault(SCOPE_EXTRA, "read" if safe else "write")
                if scope != "read":
                    op["responses"].setdefault(
                        "403", {"description": f"The key's scope is not '{scope}' or wider"}
                    )
            for code, resp in op.get("responses", {}).items():
                content = resp.get("content", {})
                if code.startswith(("4", "5")):
                    resp["content"] = {
                        PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}
                    }
                elif PROBLEM_JSON in content:
                    content.pop(PROBLEM_JSON)
    comps = schema.get("components", {}).get("schemas", {})
    comps.pop("HTTPValidationError", None)
    comps.pop("ValidationError", None)
    app.openapi_schema = schema
    return schema


def create_app(
    settings: Settings | None = None,
    *,
    queue: JobQueue | None = None,
    store: ArtifactStore | None = None,
) -> FastAPI:
    """The ASGI app; tests pass their own settings (tmp dirs) and a queue double."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        anyio.to_thread.current_default_thread_limiter().total_tokens = settings.threads
        app.state.read_threads = anyio.CapacityLimiter(READ_THREADS)
        apply_to_core(settings)  # kernel threads, native kernels (also from a .env file)
        database = Database(settings.db_url)
        if settings.auto_migrate:
            upgrade(database.engine)
        app.state.database = database
        app.state.store = store or make_store(settings, "api")
        app.state.store_probe = StoreProbe(app.state.store)
        if isinstance(app.state.store, LocalStore):
            app.state.scratch = app.state.store  # archives are spooled beside the files
            app.state.store.sweep_tmp()
            relativise_scene_records(database, app.state.store.root)
        else:  # a bucket: nothing touches it here (it may be down; health says so)
            app.state.scratch = LocalStore(settings.cache_root / "api" / "scratch")
            app.state.scratch.sweep_tmp()
        sweeper = None
        if settings.store_sweep_s > 0:
            sweeper = Sweeper(
                database,
                app.state.store,
                settings.store_sweep_s,
                upload_idle_s=settings.upload_expire_s,
                idempotency_ttl_s=settings.idempotency_ttl_s,
            ).start()
        app.state.queue = queue or make_queue(settings)
        _recover(database, app.state.queue, settings)
        reaper = None
        if isinstance(app.state.queue, CeleryQueue):
            # the workers reap too; the API's reaper requeues a job whose only worker died
            reaper = Reaper(database, settings, app.state.queue.enqueue).start()
        # sends the webhook events of job ends, wherever the jobs ended (every replica runs one)
        dispatcher = Dispatcher(database, settings).start()
        try:
            yield
        finally:
            if sweeper is not None:
                sweeper.close()
            if reaper is not None:
                reaper.close()
            dispatcher.close()
            close = getattr(app.state.queue, "close", None)
            if queue is None and callable(close):
                close()
            database.dispose()

    from core import __version__

    app = FastAPI(
        title="Glint API",
        version=__version__,
        description="PGSR-DR reconstruction as a service: upload a scene, validate it, "
        "train it, follow the job, download the artifacts. All errors are RFC 9457 "
        "problem details (application/problem+json). Authenticate with "
        "`Authorization: Bearer <API key>`.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.validation_slots = threading.BoundedSemaphore(settings.validation_concurrency)
    install_handlers(app)
    app.add_middleware(ServerTimingMiddleware)
    for router in ROUTERS:
        app.include_router(router, prefix="/v1")
    viewer_web.mount(app, viewer.make_service(app))
    app.openapi = lambda: _tidy_openapi(app)  # type: ignore[method-assign]
    return app
