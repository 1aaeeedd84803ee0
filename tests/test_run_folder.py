"""scene.json: a run remembers its scene relative to itself, never as a server path."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from core.errors import GlintError
from core.model.run_folder import SCENE_RECORD, find_run_scene, record_scene


def test_the_scene_is_recorded_relative_to_the_run(tmp_path: Path) -> None:
    scene = tmp_path / "store" / "scenes" / "scn_1" / "files"
    run = tmp_path / "store" / "jobs" / "job_1" / "run"
    scene.mkdir(parents=True)
    record_scene(run, scene)
    text = (run / SCENE_RECORD).read_text()
    assert str(tmp_path) not in text
    assert json.loads(text) == {"scene": "../../../scenes/scn_1/files"}
    assert find_run_scene(run) == scene.resolve()


def test_a_run_moved_with_its_scene_still_finds_it(tmp_path: Path) -> None:
    (tmp_path / "a" / "data" / "teapot").mkdir(parents=True)
    record_scene(tmp_path / "a" / "out" / "run", tmp_path / "a" / "data" / "teapot")
    shutil.move(tmp_path / "a", tmp_path / "b")
    assert find_run_scene(tmp_path / "b" / "out" / "run") == (tmp_path / "b/data/teapot").resolve()


def test_older_absolute_records_still_work(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / SCENE_RECORD).write_text(json.dumps({"scene": str(tmp_path / "elsewhere")}))
    assert find_run_scene(run) == (tmp_path / "elsewhere").resolve()


def test_an_explicit_scene_wins_and_no_record_is_an_error(tmp_path: Path) -> None:
    assert find_run_scene(tmp_path, tmp_path / "given") == tmp_path / "given"
    with pytest.raises(GlintError, match=r"no scene\.json"):
        find_run_scene(tmp_path / "empty")
