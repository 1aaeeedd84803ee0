"""Python client for the Glint REST API: HTTP only, no torch (``pip install ./client``).

    from glint_client import Client

    with Client("http://127.0.0.1:8000", "glk_...") as glint:
        scene = glint.create_scene_from("captures/teapot")      # upload (resumable) + commit
        job = glint.create_job(scene["id"], time_budget="5m")
        job = glint.wait(job["id"])                               # follows the event stream
        glint.download(job["id"], "out/teapot")                   # parallel, checksums verified

docs/client.md is the walk-through; ``glint remote --help`` the command line.
"""

from glint_client._version import __version__
from glint_client.client import Client, new_idempotency_key
from glint_client.errors import (
    BadRequest,
    ChecksumMismatch,
    Conflict,
    FieldProblem,
    Forbidden,
    GlintAPIError,
    GlintClientError,
    IdempotencyKeyReused,
    IntegrityError,
    JobCancelled,
    JobFailed,
    NotFound,
    OffsetMismatch,
    ServerError,
    ServerUnreachable,
    ServiceUnavailable,
    TooLarge,
    Unauthorized,
    ValidationError,
)

__all__ = [
    "BadRequest",
    "ChecksumMismatch",
    "Client",
    "Conflict",
    "FieldProblem",
    "Forbidden",
    "GlintAPIError",
    "GlintClientError",
    "IdempotencyKeyReused",
    "IntegrityError",
    "JobCancelled",
    "JobFailed",
    "NotFound",
    "OffsetMismatch",
    "ServerError",
    "ServerUnreachable",
    "ServiceUnavailable",
    "TooLarge",
    "Unauthorized",
    "ValidationError",
    "__version__",
    "new_idempotency_key",
]
