"""The store :class:`Settings` describe: a bucket when ``store_url`` is set, else a directory."""

from __future__ import annotations

from typing import Literal

from api.service.settings import Settings
from api.service.store.base import ArtifactStore
from api.service.store.local import LocalStore

CHECK_TIMEOUT_S = 3.0  # the health check and job submission wait at most this on the store

Role = Literal["api", "runner"]


def make_store(settings: Settings, role: Role = "api") -> ArtifactStore:
    """The configured store. ``role`` separates local copies on a shared data folder: the
    API's (validation, viewer) never touch a runner's run folders, which it trains in."""
    if not settings.store_url:
        return LocalStore(settings.store_root)
    from api.service.store.s3 import S3Store
    from api.service.store.s3_client import S3Location, endpoint_url, make_client

    endpoint = endpoint_url(settings.s3_endpoint_url)
    common = {
        "endpoint": endpoint,
        "region": settings.s3_region,
        "access_key_id": settings.s3_access_key_id,
        "secret_access_key": settings.s3_secret_access_key,
        "addressing_style": settings.s3_addressing_style,
    }
    client = make_client(**common, timeout_s=settings.store_timeout_s, attempts=3)
    check_timeout = min(CHECK_TIMEOUT_S, settings.store_timeout_s)
    check_client = make_client(**common, timeout_s=check_timeout, attempts=1, pool=2)
    return S3Store(
        S3Location.parse(settings.store_url),
        client,
        check_client,
        settings.cache_root / role,
        part_bytes=settings.store_part_bytes,
        endpoint=endpoint,
    )
