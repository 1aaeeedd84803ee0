"""The viewer service: token signing, model caches, viewer slots, one session per socket.

The API builds one :class:`ViewerService` and hands it a ``lookup`` function that maps
(job id, owner) to the job's folders and status; ``viewer_web`` itself knows nothing
about the database or the store (data flows api → viewer_web → core).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import anyio
from starlette.websockets import WebSocket, WebSocketDisconnect

from viewer_web import protocol, tokens
from viewer_web.adaptive import ResolutionGovernor

if TYPE_CHECKING:
    import torch

    from viewer_web.renderer import ModelCache

# The renderer (torch, core) is imported on first use, not here: the API process imports
# this module at start-up and must stay free of torch (fork safety, start-up time).

log = logging.getLogger("glint.viewer")

# Close codes (4000-4999 are the application's own; 1013 is the standard "try again").
CLOSE_UNAUTHORIZED = 4401
CLOSE_NOT_FOUND = 4404
CLOSE_BUSY = 1013


@dataclass(frozen=True)
class JobView:
    """What the viewer needs of a job: its run folder, scene folder and public status."""

    run_dir: Path
    scene_dir: Path | None
    status: dict[str, Any]


# (job_id, owner) -> JobView | None; blocking (database), always called on a thread.
JobLookup = Callable[[str, str], "JobView | None"]


@dataclass
class _Slots:
    """A non-blocking counting semaphore: a viewer either gets a slot now or is told no."""

    limit: int
    used: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def try_acquire(self) -> bool:
        with self.lock:
            if self.used >= self.limit:
                return False
            self.used += 1
            return True

    def release(self) -> None:
        with self.lock:
            self.used = max(self.used - 1, 0)


def training_cameras(scene_dir: Path) -> list[dict[str, Any]]:
    """The scene's cameras as ``cameras`` message entries (pose + lens, no pixels).

    The scene is loaded at 1/8 size: only poses and the field of view are needed.
    """
    import math

    from core.scene.formats import load_scene

    scene = load_scene(scene_dir, downscale=8.0)
    out = []
    for split, views in (("train", scene.train), ("test", scene.test)):
        for v in views:
            cam = v.camera
            k = cam.intrinsics
            out.append(
                {
                    "name": v.name or f"{split}-{len(out)}",
                    "split": split,
                    "w2c": [float(x) for x in cam.world_to_cam.reshape(-1)],
                    "fov_y": math.degrees(2 * math.atan(0.5 * k.height / k.fy)),
                    "aspect": k.width / k.height,
                }
            )
    return out


class ViewerService:
    """Shared state of every viewer in this process."""

    def __init__(
        self,
        lookup: JobLookup,
        *,
        secret: bytes | None = None,
        max_viewers: int = 4,
        device: torch.device | str | None = None,
        target_fps: float = 30.0,
        refine_after_s: float = 0.25,
        status_every_s: float = 1.0,
        token_ttl_s: float = tokens.DEFAULT_TTL_S,
    ) -> None:
        self.lookup = lookup
        self.secret = secret or tokens.default_secret()
        self.slots = _Slots(max_viewers)
        import torch

        from viewer_web.renderer import default_device

        self.device = torch.device(device) if device is not None else default_device()
        self.target_fps = target_fps
        self.refine_after_s = refine_after_s
        self.status_every_s = status_every_s
        self.token_ttl_s = token_ttl_s
        # Renders get threads of their own: never the API's pool, one per viewer slot.
        self.render_limiter = anyio.CapacityLimiter(max_viewers)
        self._models: OrderedDict[Path, ModelCache] = OrderedDict()
        self._cameras: OrderedDict[Path, list[dict[str, Any]]] = OrderedDict()
        self._lock = threading.Lock()
        self.frames_rendered = 0

    # -- tokens -------------------------------------------------------------
    def issue_token(self, job_id: str, owner: str) -> tuple[str, float]:
        """A viewer token for ``job_id`` and its expiry (Unix seconds)."""
        grant = tokens.issue(self.secret, job_id, owner, self.token_ttl_s)
        return tokens.encode(self.secret, grant), grant.expires

    def check_token(self, token: str | None, job_id: str) -> tokens.ViewerGrant | None:
        return tokens.verify(self.secret, token, job_id)

    # -- caches -------------------------------------------------------------
    def model_cache(self, run_dir: Path) -> ModelCache:
        """The shared model of a run folder (a few jobs are kept; the oldest goes first)."""
        with self._lock:
            cache = self._models.get(run_dir)
            if cache is None:
                from viewer_web.renderer import ModelCache

                cache = self._models[run_dir] = ModelCache(run_dir, self.device)
                while len(self._models) > 8:
                    self._models.popitem(last=False)
            self._models.move_to_end(run_dir)
            return cache

    def cameras(self, scene_dir: Path | None) -> list[dict[str, Any]]:
        """Training/test cameras of a scene folder, cached (blocking)."""
        if scene_dir is None:
            return []
        with self._lock:
            if scene_dir in self._cameras:
                return self._cameras[scene_dir]
        try:
            cams = training_cameras(scene_dir)
        except Exception:
            log.exception("viewer: cannot read the cameras of %s", scene_dir)
            cams = []
        with self._lock:
            self._cameras[scene_dir] = cams
            while len(self._cameras) > 16:
                self._cameras.popitem(last=False)
        return cams

    async def view(self, job_id: str, owner: str) -> JobView | None:
        return await anyio.to_thread.run_sync(self.lookup, job_id, owner)

    # -- sockets ------------------------------------------------------------
    async def serve(self, websocket: WebSocket, job_id: str, token: str | None) -> None:
        """Run one viewer connection from handshake to close."""
        await websocket.accept()
        grant = self.check_token(token, job_id)
        if grant is None:
            await websocket.close(CLOSE_UNAUTHORIZED, "invalid or expired viewer token")
            return
        view = await self.view(job_id, grant.owner)
        if view is None:
            await websocket.close(CLOSE_NOT_FOUND, f"job '{job_id}' not found")
            return
        if not self.slots.try_acquire():
            await websocket.close(
                CLOSE_BUSY, f"viewer limit reached ({self.slots.limit} at once); try again later"
            )
            return
        try:
            await ViewerSession(self, websocket, job_id, grant, view).run()
        except WebSocketDisconnect:
            pass
        finally:
            self.slots.release()


class ViewerSession:
    """One connected viewer: receive cameras, render the newest, push frames and status.

    The latest-wins slot is ``self.pending``: the receive task overwrites it with every
    camera message, the render task takes whatever is there when it becomes free, so a
    burst of N cameras costs at most two renders, never a queue.
    """

    def __init__(
        self,
        service: ViewerService,
        websocket: WebSocket,
        job_id: str,
        grant: tokens.ViewerGrant,
        view: JobView,
    ) -> None:
        self.service = service
        self.ws = websocket
        self.job_id = job_id
        self.grant = grant
        self.view = view
        self.models = service.model_cache(view.run_dir)
        self.governor = ResolutionGovernor(service.target_fps)
        self.pending: protocol.CameraMsg | None = None
        self.wake = asyncio.Event()
        self.last: protocol.CameraMsg | None = None
        self.last_scale = 1.0
        self.last_model_mtime: float | None = None
        self.refresh = False  # the model changed: re-render the last camera
        self.renders = 0
        self.received = 0
        self._send_lock = asyncio.Lock()

    async def send_json(self, data: dict[str, Any]) -> None:
        async with self._send_lock:
            await self.ws.send_json(data)

    async def send_bytes(self, data: bytes) -> None:
        async with self._send_lock:
            await self.ws.send_bytes(data)

    async def run(self) -> None:
        svc = self.service
        model = await anyio.to_thread.run_sync(self.models.get, limiter=svc.render_limiter)
        hello: dict[str, Any] = {
            "type": "hello",
            "protocol": protocol.PROTOCOL_VERSION,
            "job_id": self.job_id,
            "channels": list(protocol.CHANNELS),
            "device": str(svc.device),
            "target_fps": svc.target_fps,
            "token_expires": self.grant.expires,
            "job": self.view.status,
            "model": None if model is None else model.summary(),
        }
        if model is not None:
            self.last_model_mtime = model.mtime
        await self.send_json(hello)
        try:
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._render_loop)
                tg.start_soon(self._status_loop)
                await self._receive_loop()
                tg.cancel_scope.cancel()
        except* (WebSocketDisconnect, RuntimeError, OSError):
            # The client went away mid-send (or we closed): nothing left to tell anyone.
            log.debug("viewer %s: connection ended", self.job_id)

    # -- receiving ----------------------------------------------------------
    async def _receive_loop(self) -> None:
        while True:
            msg = await self.ws.receive()
            if msg["type"] == "websocket.disconnect":
                return
            text = msg.get("text")
            if text is None:
                await self._error("binary messages are not accepted; send JSON text")
                continue
            try:
                parsed = protocol.parse(text)
            except protocol.ProtocolError as exc:
                await self._error(str(exc), exc.seq)
                continue
            if isinstance(parsed, protocol.CameraMsg):
                self.received += 1
                self.pending = parsed  # latest wins: an unrendered older camera is dropped
                self.wake.set()
            elif isinstance(parsed, protocol.PingMsg):
                await self.send_json({"type": "pong", "t": parsed.t, "server_time": time.time()})
            else:
                cams = await anyio.to_thread.run_sync(self.service.cameras, self.view.scene_dir)
                await self.send_json({"type": "cameras", "cameras": cams})

    async def _error(self, message: str, seq: int | None = None) -> None:
        await self.send_json(
            {"type": "error", "code": "bad-message", "message": message, "seq": seq}
        )

    # -- rendering ----------------------------------------------------------
    async def _render_loop(self) -> None:
        svc = self.service
        while True:
            # Wait for a camera; after a reduced frame, wake up anyway to sharpen it.
            timeout = svc.refine_after_s if self.last is not None and self.last_scale < 1 else None
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.wake.wait(), timeout)
            self.wake.clear()
            req, self.pending = self.pending, None
            if req is not None:
                reason = "camera"
                scale = 1.0 if req.still else None
            elif self.last is not None and (self.last_scale < 1 or self.refresh):
                req, reason, scale = self.last, ("model" if self.refresh else "refine"), 1.0
            else:
                continue
            self.refresh = False
            await self._render(req, reason, scale)

    async def _render(self, req: protocol.CameraMsg, reason: str, scale: float | None) -> None:
        model = await anyio.to_thread.run_sync(self.models.get, limiter=self.service.render_limiter)
        if model is None:
            await self.send_json(
                {
                    "type": "waiting",
                    "seq": req.seq,
                    "message": "no checkpoint yet: the first frame comes with the first save",
                }
            )
            self.last, self.last_scale = req, 1.0
            return
        if model.mtime != self.last_model_mtime:
            self.last_model_mtime = model.mtime
            await self.send_json({"type": "model", **model.summary()})
        full_px = req.width * req.height
        if scale is None:
            scale = self.governor.next_scale(full_px)
        quality = req.quality or (90 if scale >= 1 else 75)
        try:
            from viewer_web.renderer import timed_frame

            jpeg, info = await anyio.to_thread.run_sync(
                timed_frame, model, req, scale, quality, limiter=self.service.render_limiter
            )
        except Exception as exc:  # a camera that cannot be rendered is the client's to fix
            log.exception("viewer: render failed")
            await self._error(f"render failed: {exc}", req.seq)
            self.last, self.last_scale = None, 1.0
            return
        self.governor.observe(info["width"] * info["height"], info["render_ms"] + info["encode_ms"])
        self.renders += 1
        self.service.frames_rendered += 1
        self.last, self.last_scale = req, scale
        header = {
            "type": "frame",
            "seq": req.seq,
            "channel": req.channel,
            "scale": round(scale, 3),
            "full": scale >= 1.0,
            "full_width": req.width,
            "full_height": req.height,
            "reason": reason,
            "renders": self.renders,
            "received": self.received,
            **info,
        }
        await self.send_bytes(protocol.pack_frame(header, jpeg))

    # -- job status ---------------------------------------------------------
    async def _status_loop(self) -> None:
        """Push the job's status when it changes; re-render when a new checkpoint lands."""
        version = self.view.status.get("version")
        while True:
            await anyio.sleep(self.service.status_every_s)
            if self.grant.expires < time.time():
                await self.ws.close(CLOSE_UNAUTHORIZED, "viewer token expired; reconnect")
                return
            view = await self.service.view(self.job_id, self.grant.owner)
            if view is None:
                await self.ws.close(CLOSE_NOT_FOUND, "job deleted")
                return
            if view.status.get("version") != version:
                version = view.status.get("version")
                await self.send_json({"type": "job", "job": view.status})
            mtime = self.models.mtime()
            if mtime is not None and mtime != self.last_model_mtime and self.last is not None:
                self.refresh = True
                self.wake.set()
