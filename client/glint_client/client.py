"""``Client``: the Glint REST API as Python calls (docs/client.md is the walk-through).

Every create (scene, job, mesh) sends a fresh ``Idempotency-Key`` and reuses it on its
own retries, so a create that timed out after the server made it is not made twice.
Lists follow their pages; errors are the typed exceptions of :mod:`glint_client.errors`.
"""

from __future__ import annotations

import fnmatch
import secrets
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, cast
from urllib.parse import quote

import httpx

from glint_client.downloads import Downloader
from glint_client.errors import GlintClientError, JobCancelled, JobFailed
from glint_client.events import JobFollower
from glint_client.files import ARCHIVE_SUFFIXES, LocalFile, scene_files
from glint_client.http import Http
from glint_client.models import (
    TERMINAL_STATES,
    Artifact,
    Job,
    Me,
    MetricRow,
    Metrics,
    Scene,
    SceneFile,
    Upload,
)
from glint_client.uploads import DEFAULT_CHUNK_BYTES, ByteCallback, Uploader

PAGE = 200


def new_idempotency_key() -> str:
    return str(uuid.uuid4())


class Client:
    """A connection to one Glint server with one API key.

    ``url`` is the server (``http://host:8000``, with or without ``/v1``). ``retries``
    bounds how often a call that may safely be repeated is tried again after a
    connection failure or a 502/503/504 (with backoff); ``transport`` replaces httpx's
    transport (tests, proxies). Use it as a context manager, or call :meth:`close`.
    Methods are safe to call from several threads.
    """

    def __init__(
        self,
        url: str,
        key: str | None,
        *,
        timeout: float = 60.0,
        retries: int = 4,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.http = Http(url, key, timeout=timeout, retries=retries, transport=transport)

    @property
    def url(self) -> str:
        return self.http.base_url

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- plumbing -----------------------------------------------------------------------

    def _json(self, method: str, path: str, **kw: Any) -> Any:
        return self.http.request(method, path, **kw).json()

    def _create(self, path: str, body: Mapping[str, Any], idempotency_key: str | None) -> Any:
        headers = {"Idempotency-Key": idempotency_key or new_idempotency_key()}
        return self._json("POST", path, json=dict(body), headers=headers)

    def _pages(self, path: str, params: Mapping[str, Any] | None = None) -> Iterator[Any]:
        offset = 0
        while True:
            page = self._json(
                "GET", path, params={**(params or {}), "limit": PAGE, "offset": offset}
            )
            yield from page["items"]
            offset += int(page["limit"])
            if not page["items"] or offset >= int(page["total"]):
                return

    # --- server -------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """The server's liveness (needs no key); raises ServiceUnavailable when it is down."""
        return cast(dict[str, Any], self._json("GET", "/v1/health"))

    def me(self) -> Me:
        """Who the key belongs to and its scope (a cheap way to check a key)."""
        return cast(Me, self._json("GET", "/v1/keys/me"))

    # --- scenes -------------------------------------------------------------------------

    def create_scene(self, name: str, *, idempotency_key: str | None = None) -> Scene:
        """An empty, open scene. Pass ``idempotency_key`` to make a retried create (from
        another process, say) return the scene the first one made."""
        return cast(Scene, self._create("/v1/scenes", {"name": name}, idempotency_key))

    def get_scene(self, scene_id: str) -> Scene:
        return cast(Scene, self._json("GET", f"/v1/scenes/{scene_id}"))

    def list_scenes(self, state: str | None = None) -> Iterator[Scene]:
        """Every scene of the key's owner, newest first."""
        return self._pages("/v1/scenes", {"state": state} if state else None)

    def delete_scene(self, scene_id: str) -> None:
        self.http.request("DELETE", f"/v1/scenes/{scene_id}")

    def scene_files(self, scene_id: str) -> Iterator[SceneFile]:
        return self._pages(f"/v1/scenes/{scene_id}/files")

    def upload(
        self,
        scene_id: str,
        source: str | Path | Sequence[str | Path],
        *,
        parallel: int = 4,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        on_bytes: ByteCallback | None = None,
        on_files: Callable[[list[LocalFile]], None] | None = None,
    ) -> list[Upload]:
        """Upload a folder, an archive (unpacked here first) or photos into an open
        scene, resumably (see :mod:`glint_client.uploads`): calling this again after an
        interruption, from any process, sends only what has not arrived.

        ``on_files`` is told the file list before any byte is sent (for a progress
        bar's total), ``on_bytes`` the bytes as they are on the server.
        """
        sources = [Path(source)] if isinstance(source, str | Path) else [Path(s) for s in source]
        with scene_files(sources) as files:
            if on_files:
                on_files(files)
            uploader = Uploader(
                self.http, chunk_bytes=chunk_bytes, parallel=parallel, on_bytes=on_bytes
            )
            return uploader.upload_all(scene_id, files)

    def upload_archive(self, scene_id: str, archive: str | Path) -> dict[str, Any]:
        """Send a zip/tar archive as one request (the server unpacks it). Not resumable:
        for large archives :meth:`upload` (which unpacks locally) is the better way."""
        path = Path(archive)
        kind = "application/zip" if path.name.lower().endswith(".zip") else "application/x-tar"
        with path.open("rb") as body:  # streamed from disk, with its Content-Length
            r = self.http.request(
                "POST",
                f"/v1/scenes/{scene_id}/archive",
                content=body,
                headers={"Content-Type": kind, "Content-Length": str(path.stat().st_size)},
                retry=False,
            )
        return cast(dict[str, Any], r.json())

    def uploads(self, scene_id: str) -> Iterator[Upload]:
        """The scene's unfinished uploads (what a crashed client left)."""
        return self._pages(f"/v1/scenes/{scene_id}/uploads")

    def cancel_upload(self, scene_id: str, upload_id: str) -> None:
        self.http.request("DELETE", f"/v1/scenes/{scene_id}/uploads/{upload_id}")

    def commit(self, scene_id: str) -> Scene:
        """Freeze and validate the scene; a 422 ValidationError names the file and field.
        ``report.needs_sfm`` says the photos have no poses (jobs then start with SfM)."""
        return cast(Scene, self._json("POST", f"/v1/scenes/{scene_id}/commit", retry=False))

    def create_scene_from(
        self,
        source: str | Path | Sequence[str | Path],
        *,
        name: str | None = None,
        scene_id: str | None = None,
        parallel: int = 4,
        on_bytes: ByteCallback | None = None,
        on_files: Callable[[list[LocalFile]], None] | None = None,
        on_scene: Callable[[Scene], None] | None = None,
    ) -> Scene:
        """Create a scene, upload ``source`` into it and commit it: the ready scene.

        With ``scene_id``, continue that (open) scene instead of creating one: this is
        how an upload interrupted by a crash is finished. ``on_scene`` hears of the
        scene before the upload starts (to print its id for such a restart).
        """
        if scene_id is None:
            first = Path(source if isinstance(source, str | Path) else source[0])
            scene = self.create_scene(name or _scene_name(first))
        else:
            scene = self.get_scene(scene_id)
        if on_scene:
            on_scene(scene)
        if scene["state"] == "open":
            self.upload(
                scene["id"], source, parallel=parallel, on_bytes=on_bytes, on_files=on_files
            )
            scene = self.commit(scene["id"])
        return scene

    # --- jobs ---------------------------------------------------------------------------

    def create_job(
        self,
        scene_id: str,
        config: Mapping[str, Any] | None = None,
        *,
        iterations: int | None = None,
        time_budget: str | float | None = None,
        sfm: Mapping[str, Any] | None = None,
        webhook: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> Job:
        """Start training on a ready scene. ``config`` is a TrainConfig (any fields);
        ``iterations`` and ``time_budget`` (``"5m"``, seconds) are set on top of it.

        ``webhook`` ``{"url": ..., "secret": ...}`` has the server POST the job's end
        there, signed with ``secret``; without one a secret is made here (not by the
        server, whose secret a retried create would not repeat) and returned in the
        job's ``webhook["secret"]``, as the server's answer would."""
        cfg = dict(config or {})
        if iterations is not None:
            cfg["iterations"] = iterations
        if time_budget is not None:
            cfg["time_budget"] = time_budget
        body: dict[str, Any] = {"scene_id": scene_id, "config": cfg}
        if sfm is not None:
            body["sfm"] = dict(sfm)
        hook = _with_secret(webhook)
        if hook is not None:
            body["webhook"] = hook
        return _show_secret(cast(Job, self._create("/v1/jobs", body, idempotency_key)), hook)

    def get_job(self, job_id: str) -> Job:
        return cast(Job, self._json("GET", f"/v1/jobs/{job_id}"))

    def list_jobs(
        self,
        state: str | Sequence[str] | None = None,
        *,
        scene_id: str | None = None,
        kind: str | None = None,
    ) -> Iterator[Job]:
        """The owner's jobs, newest first, filtered by state(s), scene and kind."""
        params: dict[str, Any] = {}
        if state:
            params["state"] = [state] if isinstance(state, str) else list(state)
        if scene_id:
            params["scene_id"] = scene_id
        if kind:
            params["kind"] = kind
        return self._pages("/v1/jobs", params)

    def follow(self, job_id: str, *, give_up_s: float = 120.0) -> JobFollower:
        """Iterate over the job's states as they change (server-sent events; a dropped
        stream is reopened with Last-Event-ID) until it ends."""
        return JobFollower(self.http, job_id, give_up_s=give_up_s)

    def wait(
        self, job_id: str, *, on_update: Callable[[Job], None] | None = None, check: bool = True
    ) -> Job:
        """Follow the job to its end and return it. With ``check``, a failed job raises
        JobFailed and a cancelled one JobCancelled."""
        job: Job | None = None
        for job in self.follow(job_id):
            if on_update:
                on_update(job)
        if job is None or job["state"] not in TERMINAL_STATES:
            job = self.get_job(job_id)  # deleted meanwhile: raises NotFound
        if check and job["state"] == "failed":
            raise JobFailed(dict(job))
        if check and job["state"] == "cancelled":
            raise JobCancelled(dict(job))
        return job

    def metrics(self, job_id: str, *, points: int | None = None) -> list[MetricRow]:
        """The run's evaluation rows (error against training time), oldest first.
        ``points`` thins the series evenly to that many rows on the server."""
        if points is not None:
            page: Metrics = self._json(
                "GET", f"/v1/jobs/{job_id}/metrics", params={"points": points}
            )
            return page["items"]
        return list(self._pages(f"/v1/jobs/{job_id}/metrics"))

    def cancel(self, job_id: str) -> Job:
        """Stop the job (a running one stops at its next check, after a checkpoint)."""
        return cast(Job, self._json("POST", f"/v1/jobs/{job_id}/cancel", retry=False))

    def resume(self, job_id: str) -> Job:
        """Queue a cancelled or failed job again; it continues from its checkpoint."""
        return cast(Job, self._json("POST", f"/v1/jobs/{job_id}/resume", retry=False))

    def delete_job(self, job_id: str) -> None:
        """Delete a finished job with its files (and its mesh jobs)."""
        self.http.request("DELETE", f"/v1/jobs/{job_id}")

    # --- artifacts and meshes -----------------------------------------------------------

    def artifacts(self, job_id: str) -> list[Artifact]:
        """The files the run produced (name, size, content type, SHA-256), by name."""
        return list(self._pages(f"/v1/jobs/{job_id}/artifacts"))

    def download(
        self,
        job_id: str,
        dest: str | Path,
        names: Sequence[str] | None = None,
        *,
        parallel: int = 4,
        on_bytes: ByteCallback | None = None,
        on_artifacts: Callable[[list[Artifact]], None] | None = None,
    ) -> list[Path]:
        """Download the job's artifacts into ``dest``: all, or those matching ``names``
        (exact names or glob patterns such as ``renders/*.png``). Parallel, resumed with
        Range requests, each verified against its listed SHA-256; files already there
        with the right checksum are skipped."""
        arts = self.artifacts(job_id)
        if names:

            def matches(name: str, pattern: str) -> bool:
                return name == pattern or fnmatch.fnmatchcase(name, pattern)

            chosen = [a for a in arts if any(matches(a["name"], n) for n in names)]
            missing = [n for n in names if not any(matches(a["name"], n) for a in arts)]
            if missing:
                raise GlintClientError(
                    f"job {job_id} has no artifact matching {', '.join(missing)} "
                    f"(it has {len(arts)}: list them with `glint remote download --list`)"
                )
            arts = chosen
        if on_artifacts:
            on_artifacts(arts)
        downloader = Downloader(self.http, parallel=parallel, on_bytes=on_bytes)
        return downloader.download_all(job_id, arts, Path(dest))

    def read_artifact(self, job_id: str, name: str) -> bytes:
        """One artifact's bytes in memory (small files: reports, JSON)."""
        return self.http.request(
            "GET", f"/v1/jobs/{job_id}/artifacts/{quote(name, safe='/')}"
        ).content

    def create_mesh(
        self,
        job_id: str,
        *,
        webhook: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
        **params: Any,
    ) -> Job:
        """Extract another mesh from a succeeded training job (``resolution``, ``voxel``,
        ``trunc``, ``color``, ``keep_fraction``, ``simplify``, ``grazing_blend``;
        ``asset={...}`` also bakes a relightable asset: ``faces``, ``texture_size``,
        ``views``, ``occlusion``); a job of its own. ``webhook`` as for :meth:`create_job`."""
        hook = _with_secret(webhook)
        body = {**params, **({"webhook": hook} if hook is not None else {})}
        job = cast(Job, self._create(f"/v1/jobs/{job_id}/meshes", body, idempotency_key))
        return _show_secret(job, hook)

    def meshes(self, job_id: str) -> Iterator[Job]:
        return self._pages(f"/v1/jobs/{job_id}/meshes")


def _with_secret(webhook: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The webhook with a secret of its own: a secret the server made is answered once,
    in the 201 of the first try, so a create whose answer was lost would lose it."""
    if webhook is None:
        return None
    hook = dict(webhook)
    if not hook.get("secret"):
        hook["secret"] = "whsec_" + secrets.token_hex(16)
    return hook


def _show_secret(job: Job, hook: Mapping[str, Any] | None) -> Job:
    shown = job.get("webhook")
    if hook is not None and isinstance(shown, dict):
        shown["secret"] = hook["secret"]
    return job


def _scene_name(path: Path) -> str:
    """A scene name the API accepts (letters, digits, space, ``._-``): the folder's or
    the archive's name, or for photos the name of the folder they are in."""
    stem = path.name
    lower = stem.lower()
    if path.is_file():
        archive = next((s for s in ARCHIVE_SUFFIXES if lower.endswith(s)), None)
        stem = stem[: -len(archive)] if archive else path.resolve().parent.name
    clean = "".join(c if c.isalnum() or c in " ._-" else "_" for c in stem).lstrip(" ._-")
    return (clean or "scene")[:200]
