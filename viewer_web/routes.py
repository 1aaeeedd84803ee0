"""HTTP and WebSocket routes of the viewer; the API mounts them (see ``mount``).

- ``GET /viewer/{job_id}``: the page (static HTML/JS/CSS under ``/viewer/static``).
- ``GET /viewer/{job_id}/mesh``: the mesh view, the job's relightable asset (asset.glb
  lit by asset_env.hdr) drawn in the browser with three.js (vendored under
  ``/viewer/static/vendor/three``); it reads the files through the artifacts API.
- ``WS /v1/jobs/{job_id}/viewer/ws?token=…``: the frame stream (docs/viewer.md).
- ``GET /v1/jobs/{job_id}/viewer/envmap.png?token=…``: the env map, lat-long PNG.
- ``GET /app``: the dashboard (static HTML/JS/CSS under ``/app/static``), which talks to
  the public REST API only, with the key the user pastes (docs/dashboard.md).

These authenticate with a viewer token (query parameter: browsers cannot set headers
on WebSockets or <img> requests), which the API issues for the job's owner. They are
left out of the OpenAPI document, which describes the Bearer-key API.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import anyio
from fastapi import APIRouter, FastAPI, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.types import Scope
from starlette.websockets import WebSocket

from viewer_web.service import ViewerService

PathLike = str | os.PathLike[str]
STATIC = Path(__file__).resolve().parent / "static"
APP_STATIC = STATIC / "app"

JobId = Annotated[str, PathParam(max_length=40)]
Token = Annotated[str | None, Query(max_length=1024)]

api_router = APIRouter(prefix="/jobs/{job_id}/viewer", include_in_schema=False)
page_router = APIRouter(include_in_schema=False)


class RevalidatedFiles(StaticFiles):
    """Static files that browsers re-check (ETag) before each use: the dashboard's modules
    import one another, so a cached old module must never meet a new one."""

    def file_response(
        self, full_path: PathLike, stat_result: os.stat_result, scope: Scope, status_code: int = 200
    ) -> Response:
        response = super().file_response(full_path, stat_result, scope, status_code)
        response.headers.setdefault("Cache-Control", "no-cache")
        return response


def _service(app: FastAPI) -> ViewerService:
    return app.state.viewer


@page_router.get("/viewer/{job_id}")
def viewer_page(job_id: JobId) -> FileResponse:
    """The viewer page; it reads the job id from its own URL and the key from the fragment."""
    return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})


@page_router.get("/viewer/{job_id}/mesh")
def mesh_page(job_id: JobId) -> FileResponse:
    """The mesh view; like the viewer it reads the job id from its URL, the key from the
    fragment, and renders in the browser (no frames from the server)."""
    return FileResponse(STATIC / "mesh.html", headers={"Cache-Control": "no-cache"})


@page_router.get("/app")
@page_router.get("/app/")
def dashboard_page() -> FileResponse:
    """The dashboard: static, it calls the public ``/v1`` API with the key it is given."""
    return FileResponse(APP_STATIC / "index.html", headers={"Cache-Control": "no-cache"})


@api_router.websocket("/ws")
async def viewer_socket(websocket: WebSocket, job_id: str, token: str | None = None) -> None:
    await _service(websocket.app).serve(websocket, job_id, token)


@api_router.get("/envmap.png")
async def viewer_envmap(request: Request, job_id: JobId, token: Token = None) -> Response:
    """The current env map as an 8-bit lat-long PNG (2:1), re-read with each checkpoint."""
    svc = _service(request.app)
    grant = svc.check_token(token, job_id)
    if grant is None:
        raise HTTPException(401, "invalid or expired viewer token")
    view = await svc.view(job_id, grant.owner)
    if view is None:
        raise HTTPException(404, f"job '{job_id}' not found")
    cache = svc.model_cache(view.run_dir)
    png = await anyio.to_thread.run_sync(cache.envmap_png, limiter=svc.render_limiter)
    if png is None:
        raise HTTPException(404, "this job has no environment map (yet, or the scene is diffuse)")
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})


def mount(app: FastAPI, service: ViewerService, api_prefix: str = "/v1") -> None:
    """Attach the viewer to an app: its service, routes and static files."""
    app.state.viewer = service
    app.include_router(api_router, prefix=api_prefix)
    app.include_router(page_router)
    app.mount("/viewer/static", StaticFiles(directory=STATIC), name="viewer-static")
    app.mount("/app/static", RevalidatedFiles(directory=APP_STATIC), name="app-static")
