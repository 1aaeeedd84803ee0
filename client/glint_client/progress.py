"""Progress bars for the command line (tqdm, on stderr): bytes for uploads and
downloads, iterations for training. Off with ``--quiet`` or when stderr is not a
terminal; then training still logs a line per phase change, unless quiet.
"""

from __future__ import annotations

import sys
import threading
from typing import Any, TextIO

from tqdm import tqdm

from glint_client.models import Job


def bars_enabled(quiet: bool, stream: TextIO | None = None) -> bool:
    stream = stream or sys.stderr
    return not quiet and hasattr(stream, "isatty") and stream.isatty()


def duration(seconds: float | None) -> str:
    """``75`` → ``1m15s``; ``None`` → ``?``."""
    if seconds is None:
        return "?"
    s = round(max(seconds, 0.0))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


class ByteBar:
    """A byte counter bar whose total may be set once the files are known. ``update``
    may be called from several threads (tqdm locks)."""

    def __init__(self, desc: str, *, enabled: bool) -> None:
        self.desc = desc
        self.enabled = enabled
        self.bar: tqdm[Any] | None = None  # drawn from the first total or bytes on
        self.done = 0
        self._lock = threading.Lock()

    def _open(self, total: int | None) -> tqdm[Any]:
        with self._lock:
            if self.bar is None:
                self.bar = tqdm(
                    desc=self.desc,
                    total=total,
                    initial=self.done,
                    unit="B",
                    unit_scale=True,
                    unit_divisor=1024,
                    file=sys.stderr,
                    dynamic_ncols=True,
                )
            return self.bar

    def set_total(self, total: int) -> None:
        if self.enabled:
            bar = self._open(total)
            bar.total = total
            bar.refresh()

    def update(self, n: int) -> None:
        self.done += n
        if self.enabled:
            self._open(None).update(n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> ByteBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def job_line(job: Job) -> str:
    """One line saying where a job is: state, phase, iteration, PSNR, time left."""
    parts = [f"job {job['id']}: {job['state']}"]
    if job.get("phase"):
        parts.append(f"phase {job['phase']}")
    stage = job.get("stage")
    if stage and stage.get("total"):
        parts.append(
            f"{stage.get('name')} {stage.get('step')} {stage.get('done')}/{stage['total']}"
        )
    total = job.get("total_iterations") or 0
    if total and job.get("kind") != "mesh":  # a mesh job's progress is its stage
        parts.append(f"iteration {job.get('iteration', 0)}/{total}")
    psnr = (job.get("metrics") or {}).get("psnr")
    if psnr is not None:
        parts.append(f"PSNR {psnr:.2f} dB")
    left = job.get("time_left_s")
    left = job.get("eta_s") if left is None else left
    if job["state"] == "running" and left is not None:
        parts.append(f"{duration(left)} left")
    return ", ".join(parts)


class TrainingBar:
    """Iterations done of the job's total (which follows a time budget's plan), with
    phase, PSNR and time left; without a terminal, a log line per state or phase."""

    def __init__(self, *, enabled: bool, quiet: bool) -> None:
        self.enabled = enabled
        self.quiet = quiet
        self.bar: tqdm[Any] | None = None
        self._last: tuple[Any, ...] = ()

    def update(self, job: Job) -> None:
        if self.enabled:
            self._draw(job)
        elif not self.quiet:
            key = (job["state"], job.get("phase"), (job.get("stage") or {}).get("name"))
            if key != self._last:
                self._last = key
                print(job_line(job), file=sys.stderr, flush=True)

    def _draw(self, job: Job) -> None:
        total = int(job.get("total_iterations") or 0) or None
        if self.bar is None:
            self.bar = tqdm(
                desc="training",
                total=total,
                unit="it",
                file=sys.stderr,
                dynamic_ncols=True,
                # the time left is the server's (postfix), not tqdm's guess from the rate
                bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]",
            )
        if total and self.bar.total != total:
            self.bar.total = total
        self.bar.n = int(job.get("iteration") or 0)
        post: dict[str, str] = {"state": job["state"]}
        if job.get("phase"):
            post["phase"] = str(job["phase"])
        stage = job.get("stage")
        if stage and stage.get("total"):
            post[str(stage.get("name"))] = f"{stage.get('done')}/{stage['total']}"
        psnr = (job.get("metrics") or {}).get("psnr")
        if psnr is not None:
            post["psnr"] = f"{psnr:.2f}"
        left = job.get("time_left_s")
        left = job.get("eta_s") if left is None else left
        if left is not None and job["state"] == "running":
            post["left"] = duration(left)
        self.bar.set_postfix(post, refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
