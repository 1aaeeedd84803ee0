"""run_job's claim, fencing and cancel semantics, against a real database (no HTTP)."""

from __future__ import annotations

import json
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from api.service.db import Database
from api.service.migrate import upgrade
from api.service.models import Job, JobState, Scene, SceneState, new_id
from api.service.recovery import settle_dead_runners
from api.service.runner import (
    _JobReporter,
    claim,
    json_safe,
    placed_config,
    run_job,
    skipped_steps_error,
)
from api.service.store import job_run_key, scene_files_key
from tests.api.support import TINY_CONFIG, make_settings


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request: pytest.FixtureRequest, tmp_path: Path):  # type: ignore[no-untyped-def]
    url = f"sqlite:///{tmp_path / 'runner.db'}"
    if request.param == "postgresql":
        url = request.getfixturevalue("pg_url")
    db = Database(url)
    upgrade(db.engine)
    yield db
    db.dispose()


def _job(db: Database, state: str = JobState.QUEUED, **values) -> str:
    sid, jid = new_id("scn"), new_id("job")
    with db.write() as s:
        s.add(Scene(id=sid, owner="t", name="s", state=SceneState.READY))
        s.flush()
        s.add(Job(id=jid, owner="t", scene_id=sid, config={}, total_iterations=10, state=state))
        s.flush()
        if values:
            job = s.get(Job, jid)
            for k, v in values.items():
                setattr(job, k, v)
    return jid


def _get(db: Database, jid: str) -> Job:
    with db.read() as s:
        job = s.scalar(select(Job).where(Job.id == jid))
        assert job is not None
        return job


def test_claim_once(database: Database) -> None:
    jid = _job(database)
    lease = claim(database, jid, "w1")
    assert lease
    job = _get(database, jid)
    assert (job.state, job.lease, job.worker, job.attempts) == ("running", lease, "w1", 1)
    assert claim(database, jid, "w2") is None


def test_concurrent_claims_have_one_winner(database: Database) -> None:
    jid = _job(database)
    leases: list[str | None] = []
    barrier = threading.Barrier(6)

    def go(i: int) -> None:
        barrier.wait()
        leases.append(claim(database, jid, f"w{i}"))

    threads = [threading.Thread(target=go, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    winners = [x for x in leases if x]
    assert len(winners) == 1
    assert _get(database, jid).lease == winners[0]


@pytest.mark.parametrize("state", [JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED])
def test_finished_jobs_are_not_claimable(database: Database, state: str, tmp_path: Path) -> None:
    jid = _job(database, state)
    settings = make_settings(tmp_path, database.url)
    assert run_job(jid, settings, database=database) is None
    job = _get(database, jid)
    assert job.state == state and job.attempts == 0 and job.version == 1


def test_stale_running_job_is_requeued_by_the_reaper_and_old_runner_fenced(
    database: Database,
) -> None:
    jid = _job(database)
    old = claim(database, jid, "dead")
    assert old
    settings = make_settings(Path("/nonexistent"), database.url)
    old_reporter = _JobReporter(database, jid, old, settings)
    assert claim(database, jid, "eager") is None  # running: hands off
    assert jid not in settle_dead_runners(database, settings).requeued  # heartbeat is fresh
    with database.write() as s:
        s.get(Job, jid).heartbeat_at = datetime.now(UTC) - timedelta(seconds=120)
    assert claim(database, jid, "eager") is None  # a dead runner's job goes through the reaper
    assert jid in settle_dead_runners(database, settings).requeued
    new = claim(database, jid, "rescuer")
    assert new and new != old
    assert _get(database, jid).attempts == 2 and _get(database, jid).runner_deaths == 1
    # the old runner wakes up: its writes do nothing and it is told to stop
    old_reporter.on_event(
        {
            "type": "progress",
            "iteration": 9,
            "total": 10,
            "phase": "rgb",
            "n_gaussians": 5,
            "loss": 1.0,
            "elapsed": 1.0,
            "eta": 0.1,
            "psnr": None,
        }
    )
    assert old_reporter.lost
    assert old_reporter.should_stop()
    job = _get(database, jid)
    assert job.iteration == 0 and job.lease == new and job.worker == "rescuer"


def test_progress_is_throttled_and_cancel_is_seen(database: Database) -> None:
    jid = _job(database)
    lease = claim(database, jid, "w")
    assert lease
    settings = make_settings(Path("/nonexistent"), database.url, progress_interval_s=60.0)
    rep = _JobReporter(database, jid, lease, settings)
    event = {
        "type": "progress",
        "total": 10,
        "phase": "rgb",
        "n_gaussians": 7,
        "loss": 0.5,
        "elapsed": 2.0,
        "eta": float("nan"),
        "psnr": None,
    }
    v0 = _get(database, jid).version
    for it in range(1, 6):
        rep.on_event({**event, "iteration": it})
    job = _get(database, jid)
    assert job.iteration == 1 and job.version == v0 + 1  # the first write, then throttled
    assert job.eta_s is None  # NaN is stored as null
    rep.on_event({**event, "iteration": 10})  # the last iteration always goes out
    assert _get(database, jid).iteration == 10
    assert not rep.should_stop()
    with database.write() as s:
        s.get(Job, jid).cancel_requested = True
    rep.last_poll = 0.0
    assert rep.should_stop() and rep.cancelled and not rep.lost


def test_json_safe() -> None:
    assert json_safe({"a": float("inf"), "b": [1.0, float("nan")], "c": (2, "x")}) == {
        "a": None,
        "b": [1.0, None],
        "c": [2, "x"],
    }


def test_the_backend_follows_the_workers_device() -> None:
    cfg = {"iterations": 5, "backend": "cuda"}
    assert placed_config(cfg, None) == (cfg, None)  # the embedded runner keeps the config
    placed, note = placed_config(cfg, "cpu")
    assert placed == {"iterations": 5, "backend": "auto", "device": "cpu"}
    assert note is not None and "'cuda' is unavailable" in note and "'auto' on cpu" in note
    assert cfg == {"iterations": 5, "backend": "cuda"}  # the stored job config is not edited
    for backend in ("auto", "reference"):
        assert placed_config({"backend": backend}, "cpu") == (
            {"backend": backend, "device": "cpu"},
            None,
        )


def test_a_cuda_job_on_a_cpu_worker_trains(tmp_path: Path, caplog) -> None:  # type: ignore[no-untyped-def]
    """A job submitted for GPU workers that a CPU worker takes trains instead of failing."""
    from core.scene.synthetic import write_synthetic_scene

    settings = make_settings(tmp_path)
    db = Database(settings.db_url)
    upgrade(db.engine)
    jid = _job(db, config={**TINY_CONFIG, "iterations": 6, "backend": "cuda"})
    scene_id = _get(db, jid).scene_id
    write_synthetic_scene(
        settings.store_root / scene_files_key(scene_id), "sphere", "glossy",
        n_train=3, n_test=1, size=16,
    )  # fmt: skip
    with caplog.at_level("WARNING", logger="glint"):
        assert run_job(jid, settings, database=db, device="cpu") == JobState.SUCCEEDED
    job = _get(db, jid)
    assert job.error is None and job.iteration == 6
    assert job.config["backend"] == "cuda"  # what was asked stays on record
    run_cfg = json.loads((settings.store_root / job_run_key(jid) / "config.json").read_text())
    assert (run_cfg["device"], run_cfg["backend"]) == ("cpu", "auto")
    assert any("this worker trains with 'auto' on cpu" in r.getMessage() for r in caplog.records)
    db.dispose()


def test_skipped_steps_threshold() -> None:
    assert skipped_steps_error(0, 500) is None
    assert skipped_steps_error(250, 500) is None  # half is not "more than half"
    assert skipped_steps_error(251, 500) is not None
    assert skipped_steps_error(0, 0) is None
    msg = skipped_steps_error(412, 500)
    assert msg is not None
    assert msg.startswith("412 of 500 steps were skipped (non-finite loss or gradients)")


def test_a_run_whose_steps_were_skipped_fails(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The trainer's NaN guard skipped every step: the job fails saying so (also when
    it is resumed, which trains no step), instead of succeeding with an untrained model."""
    import torch

    from core.scene.synthetic import write_synthetic_scene
    from core.training.trainer import Trainer

    monkeypatch.setattr(Trainer, "_gradient_ratios", lambda self: [torch.tensor(float("inf"))])
    settings = make_settings(tmp_path)
    db = Database(settings.db_url)
    upgrade(db.engine)
    config = {**TINY_CONFIG, "iterations": 6, "outputs": {"mesh": False}}
    jid = _job(db, config=config)
    write_synthetic_scene(
        settings.store_root / scene_files_key(_get(db, jid).scene_id), "sphere", "glossy",
        n_train=3, n_test=1, size=16,
    )  # fmt: skip
    assert run_job(jid, settings, database=db) == JobState.FAILED
    job = _get(db, jid)
    assert job.error.startswith("6 of 6 steps were skipped (non-finite loss or gradients)")
    assert str(settings.store_root) not in job.error
    with db.write() as s:  # what POST /v1/jobs/{id}/resume does
        row = s.get(Job, jid)
        row.state, row.error, row.finished_at = JobState.QUEUED, None, None
    assert run_job(jid, settings, database=db) == JobState.FAILED
    assert _get(db, jid).error.startswith("6 of 6 steps were skipped")
    db.dispose()
