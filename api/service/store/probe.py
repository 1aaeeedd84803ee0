"""Is the store usable right now? One cheap request, its answer kept a moment.

Job submission asks before it creates anything (a job whose scene cannot be read would
only fail on a worker), so a dead bucket answers 503 within the check's timeout
(``CHECK_TIMEOUT_S``) instead of queueing doomed work. A success is kept for
``ok_ttl_s`` so that a burst of submissions costs one request; a failure is not kept.
"""

from __future__ import annotations

import threading
import time

from api.service.store.base import ArtifactStore


class StoreProbe:
    """Wraps ``store.check()`` with a short memory of success."""

    def __init__(self, store: ArtifactStore, ok_ttl_s: float = 2.0) -> None:
        self.store = store
        self.ok_ttl_s = ok_ttl_s
        self._ok_until = 0.0
        self._lock = threading.Lock()

    def require(self, fresh: bool = False) -> None:
        """Return if the store answered lately (or now); raise StoreUnavailableError."""
        if not fresh and time.monotonic() < self._ok_until:
            return
        with self._lock:
            if not fresh and time.monotonic() < self._ok_until:
                return
            self._ok_until = 0.0
            self.store.check()
            self._ok_until = time.monotonic() + self.ok_ttl_s
