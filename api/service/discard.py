"""Deleting the objects of rows just deleted, without failing when the store is down."""

from __future__ import annotations

import logging

from api.service.store import ArtifactStore, StoreUnavailableError

log = logging.getLogger("glint.sweeper")


def discard(store: ArtifactStore, keys: list[str]) -> None:
    """Delete the objects of rows just deleted; a store that is down leaves them to the
    sweep (the rows are gone, so nothing lists them meanwhile)."""
    for key in keys:
        try:
            store.delete(key)
        except StoreUnavailableError as exc:
            log.warning("cannot delete %s now (%s); the store sweep will", key, exc)
