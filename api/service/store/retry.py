"""Retrying store operations with exponential backoff: a runner rides out a store outage.

A worker that loses the bucket mid-job (a MinIO restart, a network cut) keeps its job:
each store operation is tried again after 0.5, 1, 2, ... seconds (at most 30 s apart,
with jitter, so many workers do not return at once) until ``patience_s`` has passed.
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable
from typing import TypeVar

from api.service.store.base import StoreUnavailableError

T = TypeVar("T")
log = logging.getLogger("glint.store")

FIRST_DELAY_S = 0.5
MAX_DELAY_S = 30.0


def backoff_delays(first: float = FIRST_DELAY_S, cap: float = MAX_DELAY_S) -> Callable[[], float]:
    """The next wait each call: ``first`` doubling up to ``cap``, each scaled by 0.5–1."""
    delay = first

    def next_delay() -> float:
        nonlocal delay
        wait = delay * (0.5 + random.random() / 2)
        delay = min(delay * 2, cap)
        return wait

    return next_delay


def retrying(
    op: Callable[[], T],
    *,
    what: str,
    patience_s: float,
    give_up: Callable[[], bool] = lambda: False,
    sleep: Callable[[float], None] = time.sleep,
) -> T:
    """``op()``, tried again on :class:`StoreUnavailableError` until ``patience_s`` is
    spent or ``give_up()`` says so (then the last error is raised)."""
    deadline = time.monotonic() + patience_s
    delays = backoff_delays()
    attempt = 1
    while True:
        try:
            result = op()
        except StoreUnavailableError as exc:
            left = deadline - time.monotonic()
            if left <= 0 or give_up():
                log.error(
                    "%s: store unavailable, giving up after %d attempts: %s", what, attempt, exc
                )
                raise
            wait = min(delays(), left)
            log.warning(
                "%s: store unavailable (attempt %d): %s; retrying in %.1f s",
                what,
                attempt,
                exc,
                wait,
            )
            sleep(wait)
            attempt += 1
            continue
        if attempt > 1:
            log.info("%s: store reachable again after %d attempts", what, attempt)
        return result
