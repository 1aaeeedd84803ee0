"""One embedded job in a process of its own: ``python -m api.service.job_process JOB_ID``.

The local queue (:class:`api.service.queue.LocalQueue`) starts this module for each job
it runs, so training never competes with the API's event loop for the GIL, and runs at
a lowered CPU priority (``Settings.embedded_job_nice``) so the API's requests go first
on a busy machine. The settings come as JSON on stdin (the API's own, which tests build
in memory); the job is run by the same :func:`api.service.runner.run_job` as everywhere.

* **Shutdown**: ``SIGTERM`` (or ``SIGINT``, as from a terminal's Ctrl-C) sets the
  runner's stop event: the trainer checkpoints at its next iteration and the job goes
  back to ``queued``, exactly as the thread version did on the API's shutdown.
* **Parent gone**: this process dies with the API (``PR_SET_PDEATHSIG`` on Linux, and
  a watcher thread anywhere), so a ``kill -9`` of ``glint serve`` still kills its job's
  runner, and the next start settles the job like any crash.
* **Crash**: the runner heartbeats the database itself; the local queue settles the job
  of a child that died (``api.service.recovery.settle_dead_runners``).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
from types import FrameType

log = logging.getLogger("glint.job_process")


def _die_with_parent(parent: int) -> None:
    """Be killed when the API process goes away, whatever way it goes."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while True:
            if os.getppid() != parent:
                os._exit(1)
            threading.Event().wait(1.0)

    if os.getppid() != parent:  # it died before we could ask
        os._exit(1)
    threading.Thread(target=watch, name="glint-parent-watch", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (1, 3):
        sys.exit("usage: python -m api.service.job_process JOB_ID [PARENT_PID LOG_LEVEL]")
    job_id = args[0]
    stop = threading.Event()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    level = logging.INFO
    if len(args) == 3:
        _die_with_parent(int(args[1]))
        level = int(args[2])
    logging.basicConfig(
        level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stderr
    )

    from api.service.runner import run_job
    from api.service.settings import Settings, apply_to_core

    settings = Settings(**json.loads(sys.stdin.read() or "{}"))
    if settings.embedded_job_nice:
        try:
            os.nice(settings.embedded_job_nice)
        except OSError:
            log.warning("job %s: cannot lower this process's CPU priority", job_id)
    apply_to_core(settings)
    try:
        run_job(job_id, settings, stop=stop)
    except Exception:  # the runner records failures itself; this is a last resort
        log.exception("job %s: runner crashed", job_id)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
