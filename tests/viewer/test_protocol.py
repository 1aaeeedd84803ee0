"""The viewer's WebSocket protocol against a real uvicorn, with a Python client."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from core.model.channels import CHANNELS
from tests.viewer.conftest import TrainedJob
from viewer_web.protocol import unpack_frame


@contextlib.contextmanager
def open_ws(job: TrainedJob) -> Iterator[tuple[ClientConnection, dict]]:
    """A connected viewer socket and its ``hello`` message."""
    with connect(f"{job.ws_base}?token={job.token()}", open_timeout=20, max_size=None) as ws:
        hello = json.loads(ws.recv(timeout=60))
        assert hello["type"] == "hello", hello
        yield ws, hello


def camera(hello: dict, seq: int, yaw: float = 0.6, **kw: Any) -> str:
    model = hello["model"]
    c, r = model["center"], model["radius"]
    eye = [c[0] + 3.2 * r * math.cos(yaw), c[1] + 3.2 * r * math.sin(yaw), c[2] + 1.2 * r]
    msg = {"type": "camera", "seq": seq, "width": 96, "height": 80, "channel": "final"}
    msg.update(eye=eye, target=c, up=[0, 0, 1], fov_y=40.0, still=True)
    msg.update(kw)
    return json.dumps(msg)


def next_frame(ws: ClientConnection, timeout: float = 60) -> tuple[dict, bytes]:
    """The next binary frame, skipping (but checking) text messages on the way."""
    deadline = time.monotonic() + timeout
    while True:
        msg = ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
        if isinstance(msg, bytes):
            return unpack_frame(msg)
        assert json.loads(msg)["type"] in ("job", "model", "pong", "cameras"), msg


def decode(jpeg: bytes) -> Image.Image:
    assert jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9", "not a complete JPEG"
    img = Image.open(io.BytesIO(jpeg))
    img.load()
    return img


def test_hello_describes_job_and_model(trained_job: TrainedJob) -> None:
    with open_ws(trained_job) as (_ws, hello):
        assert hello["protocol"] == 1
        assert hello["channels"] == [
            "final", "base", "specular", "normal", "depth", "w_r", "roughness", "alpha"
        ]  # fmt: skip
        assert hello["job"]["state"] == "succeeded" and hello["job"]["iteration"] == 12
        assert hello["model"]["n_gaussians"] > 0 and hello["model"]["iteration"] == 12
        assert hello["model"]["radius"] > 0


def test_every_channel_has_a_label_in_the_viewer() -> None:
    """viewer.js names each channel the server announces (else its button shows the raw
    key); the labels map is one line of literal ``key: "Label"`` pairs."""
    js = (Path(__file__).resolve().parents[2] / "viewer_web" / "static" / "viewer.js").read_text()
    line = next(ln for ln in js.splitlines() if "const labels = {" in ln)
    labels = dict(re.findall(r'(\w+): "([^"]+)"', line))
    assert set(CHANNELS) <= set(labels), set(CHANNELS) - set(labels)
    assert labels["roughness"] == "Roughness"


def test_frame_for_camera(trained_job: TrainedJob) -> None:
    with open_ws(trained_job) as (ws, hello):
        ws.send(camera(hello, seq=7))
        head, jpeg = next_frame(ws)
        assert head["type"] == "frame" and head["seq"] == 7 and head["full"] is True
        assert (head["width"], head["height"]) == (96, 80)
        assert head["render_ms"] > 0 and head["channel"] == "final"
        img = decode(jpeg)
        assert img.size == (96, 80)
        gray = np.asarray(img.convert("L"), dtype=np.float64)
        assert gray.std() > 5, f"blank frame (mean {gray.mean():.1f}, std {gray.std():.1f})"


def test_channels_differ(trained_job: TrainedJob) -> None:
    seen: dict[str, bytes] = {}
    with open_ws(trained_job) as (ws, hello):
        for i, ch in enumerate(hello["channels"]):
            ws.send(camera(hello, seq=i, channel=ch))
            head, jpeg = next_frame(ws)
            assert head["channel"] == ch and head["seq"] == i
            seen[ch] = decode(jpeg).tobytes()
    assert len(set(seen.values())) == len(seen), "some channels rendered identical images"


def test_burst_renders_only_the_newest(trained_job: TrainedJob) -> None:
    with open_ws(trained_job) as (ws, hello):
        for seq in range(1, 51):  # a fast drag: 50 cameras, nobody waits for frames
            ws.send(camera(hello, seq, yaw=seq * 0.05, still=False, width=160, height=120))
        frames = []
        while not frames or frames[-1]["seq"] != 50:
            frames.append(next_frame(ws)[0])
        seqs = [f["seq"] for f in frames]
        assert seqs == sorted(seqs), "frames out of order"
        assert len(frames) <= 8, f"{len(frames)} renders for 50 cameras: {seqs}"
        assert frames[-1]["received"] == 50
        # The camera rests now: the server sharpens the last view to full resolution.
        last = frames[-1]
        while not last["full"]:
            last = next_frame(ws, timeout=20)[0]
            assert last["seq"] == 50 and last["reason"] == "refine"
        assert (last["width"], last["height"]) == (160, 120)


def test_moving_frames_are_reduced_then_refined(trained_job: TrainedJob) -> None:
    with open_ws(trained_job) as (ws, hello):
        ws.send(camera(hello, 1, still=False, width=400, height=300))
        first, _ = next_frame(ws)
        assert first["seq"] == 1 and first["full"] is False and first["width"] < 400
        refined, jpeg = next_frame(ws, timeout=20)
        assert refined["seq"] == 1 and refined["full"] is True and refined["reason"] == "refine"
        assert decode(jpeg).size == (400, 300)


def test_bad_messages_get_errors_and_the_connection_stays(trained_job: TrainedJob) -> None:
    with open_ws(trained_job) as (ws, hello):
        bad = [
            "{not json",
            json.dumps([1, 2]),
            json.dumps({"type": "teleport"}),
            json.dumps({"type": "camera", "seq": 3, "width": 64, "height": 64}),  # no pose
            camera(hello, 4, channel="x-ray"),
            camera(hello, 5, width=100000),
            camera(hello, 6, eye=[0, 0, 0], target=[0, 0, 0]),
            camera(hello, 7, fov_y=float("nan")),
        ]
        for text in bad:
            ws.send(text)
            err = json.loads(ws.recv(timeout=20))
            assert err["type"] == "error" and err["code"] == "bad-message", (text, err)
            assert err["message"]
        assert err["seq"] == 7
        ws.send(b"\x00\x01binary")
        assert json.loads(ws.recv(timeout=20))["type"] == "error"
        ws.send(json.dumps({"type": "ping", "t": 1.5}))
        pong = json.loads(ws.recv(timeout=20))
        assert pong["type"] == "pong" and pong["t"] == 1.5
        ws.send(camera(hello, 99))
        head, jpeg = next_frame(ws)
        assert head["seq"] == 99
        decode(jpeg)


@pytest.mark.parametrize("token", ["", "nonsense", "gvt_e30.AAAA"])
def test_bad_token_is_refused(trained_job: TrainedJob, token: str) -> None:
    url = f"{trained_job.ws_base}?token={token}"
    with connect(url, open_timeout=20) as ws, pytest.raises(ConnectionClosed) as info:
        ws.recv(timeout=20)
    assert info.value.rcvd is not None and info.value.rcvd.code == 4401
    assert "token" in info.value.rcvd.reason


def test_token_of_another_job_is_refused(trained_job: TrainedJob) -> None:
    other = trained_job.ws_base.replace(trained_job.job_id, "job_" + "0" * 32)
    url = f"{other}?token={trained_job.token()}"
    with connect(url, open_timeout=20) as ws, pytest.raises(ConnectionClosed) as info:
        ws.recv(timeout=20)
    assert info.value.rcvd is not None and info.value.rcvd.code == 4401


def test_viewer_token_endpoint_is_owner_scoped(trained_job: TrainedJob) -> None:
    srv, path = trained_job.server, f"/v1/jobs/{trained_job.job_id}/viewer-token"
    with srv.client(None) as anon:
        assert anon.post(path).status_code == 401
    with srv.client(srv.new_key("someone-else")) as stranger:
        r = stranger.post(path)
        assert r.status_code == 404
        assert r.headers["content-type"].startswith("application/problem+json")
    with srv.client(trained_job.key) as c:
        body = c.post(path).json()
        assert body["token"].startswith("gvt_") and body["expires_in"] > 60
        assert body["websocket"].endswith(body["token"]) and body["page"].startswith("/viewer/")


def test_envmap_png(trained_job: TrainedJob, http) -> None:  # type: ignore[no-untyped-def]
    base = f"/v1/jobs/{trained_job.job_id}/viewer/envmap.png"
    r = http.get(base, params={"token": trained_job.token()})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = Image.open(io.BytesIO(r.content))
    assert img.size[0] == 2 * img.size[1]
    r = http.get(base, params={"token": "gvt_bad.bad"})
    assert r.status_code == 401
    assert r.headers["content-type"].startswith("application/problem+json")


def test_page_and_assets_are_served(trained_job: TrainedJob, http) -> None:  # type: ignore[no-untyped-def]
    r = http.get(f"/viewer/{trained_job.job_id}")
    assert r.status_code == 200 and "<canvas" in r.text
    assert http.get("/viewer/static/viewer.js").status_code == 200
    assert http.get("/viewer/static/viewer.css").status_code == 200


def test_new_checkpoint_is_picked_up(trained_job: TrainedJob) -> None:
    with open_ws(trained_job) as (ws, hello):
        ws.send(camera(hello, 1))
        assert next_frame(ws)[0]["reason"] == "camera"
        ckpt = trained_job.run_dir / "checkpoint.pt"
        st = ckpt.stat()
        os.utime(ckpt, (st.st_atime, st.st_mtime + 5))  # as if training saved again
        deadline = time.monotonic() + 30
        got_model = False
        while True:
            msg = ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
            if isinstance(msg, str):
                got_model |= json.loads(msg)["type"] == "model"
                continue
            head, _ = unpack_frame(msg)
            if head["reason"] == "model":
                break
        assert got_model and head["seq"] == 1


def test_concurrent_viewers_are_bounded(trained_job: TrainedJob) -> None:
    slots = trained_job.server.app.state.viewer.slots
    deadline = time.monotonic() + 15  # earlier tests' sockets may still be closing
    while slots.used and time.monotonic() < deadline:
        time.sleep(0.05)
    assert slots.used == 0, "a viewer of an earlier test never released its slot"
    old, slots.limit = slots.limit, 1
    try:
        url = f"{trained_job.ws_base}?token={trained_job.token()}"
        with open_ws(trained_job), connect(url) as second:
            with pytest.raises(ConnectionClosed) as info:
                second.recv(timeout=20)
            assert info.value.rcvd is not None and info.value.rcvd.code == 1013
            assert "limit" in info.value.rcvd.reason
        deadline = time.monotonic() + 10  # the slot is released when the first one closes
        while slots.used >= slots.limit and time.monotonic() < deadline:
            time.sleep(0.05)
        with open_ws(trained_job) as (_ws, hello):
            assert hello["model"] is not None
    finally:
        slots.limit = old
