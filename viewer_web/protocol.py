"""The viewer's WebSocket protocol: message shapes, validation and frame packing.

Client → server messages are JSON text; server → client messages are JSON text,
except frames, which are one binary message each::

    uint32 big-endian N | N bytes of UTF-8 JSON header | JPEG bytes

so a frame's metadata can never be paired with the wrong image. docs/viewer.md is
the reference for every field.
"""

from __future__ import annotations

import json
import math
import struct
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from core.model.channels import CHANNELS

PROTOCOL_VERSION = 1
MAX_SIDE = 4096
MAX_PIXELS = 4096 * 2160

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid")


class IntrinsicsMsg(_Msg):
    """Pinhole intrinsics in pixels of the full ``width`` × ``height`` image."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float


class CameraMsg(_Msg):
    """A view to render. Pose: ``w2c`` (OpenCV world-to-camera, 16 numbers row-major)
    or ``eye``/``target``/``up``; lens: ``fov_y`` (degrees) or ``intrinsics``."""

    type: Literal["camera"]
    seq: int = Field(ge=0, le=2**53)
    width: int = Field(ge=8, le=MAX_SIDE)
    height: int = Field(ge=8, le=MAX_SIDE)
    channel: str = "final"
    still: bool = False
    eye: Vec3 | None = None
    target: Vec3 | None = None
    up: Vec3 | None = None
    w2c: Annotated[list[float], Field(min_length=16, max_length=16)] | None = None
    fov_y: float | None = Field(None, gt=1, lt=170)
    intrinsics: IntrinsicsMsg | None = None
    quality: int | None = Field(None, ge=30, le=95)

    @model_validator(mode="after")
    def _check(self) -> CameraMsg:
        if self.channel not in CHANNELS:
            raise ValueError(f"channel must be one of {', '.join(CHANNELS)}")
        if self.width * self.height > MAX_PIXELS:
            raise ValueError(f"width × height must be at most {MAX_PIXELS} pixels")
        look = (self.eye, self.target, self.up)
        if self.w2c is None and any(v is None for v in look):
            raise ValueError("give a pose: 'w2c', or all of 'eye', 'target' and 'up'")
        if self.w2c is not None and any(v is not None for v in look):
            raise ValueError("give either 'w2c' or 'eye'/'target'/'up', not both")
        if (self.fov_y is None) == (self.intrinsics is None):
            raise ValueError("give exactly one of 'fov_y' and 'intrinsics'")
        nums = [*(self.w2c or []), *(v for vec in look if vec for v in vec)]
        if not all(math.isfinite(v) for v in nums):
            raise ValueError("pose numbers must be finite")
        if self.eye is not None and self.target is not None and self.up is not None:
            fwd = [t - e for t, e in zip(self.target, self.eye, strict=True)]
            cross = [
                fwd[1] * self.up[2] - fwd[2] * self.up[1],
                fwd[2] * self.up[0] - fwd[0] * self.up[2],
                fwd[0] * self.up[1] - fwd[1] * self.up[0],
            ]
            if math.hypot(*cross) < 1e-9 * max(math.hypot(*fwd) * math.hypot(*self.up), 1e-30):
                raise ValueError("'eye' and 'target' must differ and 'up' must not be parallel")
        return self


class PingMsg(_Msg):
    type: Literal["ping"]
    t: float | None = None


class CamerasMsg(_Msg):
    """Ask for the job's training cameras (answered with a ``cameras`` message)."""

    type: Literal["cameras"]


ClientMsg = CameraMsg | PingMsg | CamerasMsg
_KINDS: dict[str, type[_Msg]] = {"camera": CameraMsg, "ping": PingMsg, "cameras": CamerasMsg}


class ProtocolError(ValueError):
    """A client message that cannot be used; ``seq`` echoes the message's, if any."""

    def __init__(self, message: str, seq: int | None = None) -> None:
        super().__init__(message)
        self.seq = seq


def parse(text: str) -> ClientMsg:
    """Validate one client text message; raises :class:`ProtocolError` saying why not."""
    if len(text) > 64 * 1024:
        raise ProtocolError("message too large (64 KiB at most)")
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ProtocolError(f"not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ProtocolError("a message is a JSON object with a 'type'")
    seq = data.get("seq") if isinstance(data.get("seq"), int) else None
    kind = _KINDS.get(data.get("type"))  # type: ignore[arg-type]
    if kind is None:
        raise ProtocolError(
            f"unknown message type {data.get('type')!r}; expected one of {', '.join(_KINDS)}", seq
        )
    try:
        return kind.model_validate(data)  # type: ignore[return-value]
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "message"
        raise ProtocolError(f"{where}: {first['msg']}", seq) from None


def pack_frame(header: dict[str, Any], jpeg: bytes) -> bytes:
    """One binary frame message: length-prefixed JSON header, then the JPEG."""
    head = json.dumps(header, separators=(",", ":")).encode("utf-8")
    return struct.pack(">I", len(head)) + head + jpeg


def unpack_frame(data: bytes) -> tuple[dict[str, Any], bytes]:
    """Inverse of :func:`pack_frame` (for Python clients and tests)."""
    (n,) = struct.unpack(">I", data[:4])
    return json.loads(data[4 : 4 + n].decode("utf-8")), data[4 + n :]
