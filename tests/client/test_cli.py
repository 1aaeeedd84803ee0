"""``glint remote`` end to end against a real server, and the exit codes scripts rely on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from glint_client.cli import (
    EXIT_API,
    EXIT_CANCELLED,
    EXIT_OK,
    EXIT_SERVER,
    EXIT_USAGE,
    main,
)

from tests.api.support import LiveServer, free_port
from tests.client.conftest import QUICK_CONFIG
from tests.client.support import sha256


def test_submit_wait_download(
    server: LiveServer,
    key: str,
    scene_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(QUICK_CONFIG))
    out = tmp_path / "result"
    conn = ["--server", server.url, "--key", key]
    wait = ["--wait", "--download", str(out)]
    options = ["--config", str(config), "--iterations", "20", "--set", "eval.every=5", *wait]
    code = main(["submit", str(scene_dir), *conn, *options])
    printed = capsys.readouterr()
    assert code == EXIT_OK, printed.err
    job_id = printed.out.strip()
    assert job_id.startswith("job_")
    assert "ready: blender, 8 views" in printed.err and "succeeded" in printed.err

    assert main(["status", job_id, *conn, "--json"]) == EXIT_OK
    job = json.loads(capsys.readouterr().out)
    assert job["state"] == "succeeded" and job["config"]["eval"]["every"] == 5

    assert main(["download", job_id, *conn, "--list", "--json"]) == EXIT_OK
    listed = {a["name"]: a["sha256"] for a in json.loads(capsys.readouterr().out)}
    got = {p.relative_to(out).as_posix(): sha256(p) for p in out.rglob("*") if p.is_file()}
    assert got == listed

    assert main(["list", *conn, "--json"]) == EXIT_OK
    assert [j["id"] for j in json.loads(capsys.readouterr().out)] == [job_id]
    assert main(["metrics", job_id, *conn, "--json"]) == EXIT_OK
    iterations = [r["iteration"] for r in json.loads(capsys.readouterr().out)]
    assert len(iterations) > 2 and iterations == sorted(iterations) and iterations[-1] == 20


def test_remote_is_a_glint_command(
    trained: tuple[str, str, dict], capsys: pytest.CaptureFixture[str]
) -> None:
    from core.cli import main as glint_main

    url, key, job = trained
    assert glint_main(["remote", "status", job["id"], "--server", url, "--key", key]) == EXIT_OK
    assert f"job {job['id']}: succeeded" in capsys.readouterr().out


def test_cancelled_job_exits_5(
    server: LiveServer, key: str, scene_dir: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.setenv("GLINT_SERVER", server.url)  # server and key from the environment
    monkeypatch.setenv("GLINT_KEY", key)
    assert main(["submit", str(scene_dir), "--iterations", "100000", "-q"]) == EXIT_OK
    job_id = capsys.readouterr().out.strip()
    assert main(["cancel", job_id]) == EXIT_OK
    assert main(["follow", job_id, "-q"]) == EXIT_CANCELLED
    assert "cancelled" in capsys.readouterr().out


def test_exit_codes_for_bad_key_unreachable_server_and_usage(
    server: LiveServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.delenv("GLINT_KEY", raising=False)
    monkeypatch.delenv("GLINT_SERVER", raising=False)
    assert main(["list", "--server", server.url, "--key", "glk_not_a_key"]) == EXIT_API
    assert "401 unauthorized" in capsys.readouterr().err

    nobody = f"http://127.0.0.1:{free_port()}"
    assert main(["list", "--server", nobody, "--key", "k", "--retries", "0"]) == EXIT_SERVER
    assert "no answer from" in capsys.readouterr().err

    assert main(["list", "--server", server.url]) == EXIT_USAGE  # no key anywhere
    assert "no API key" in capsys.readouterr().err
    missing = str(tmp_path / "nothing-here")
    assert main(["submit", missing, "--server", server.url, "--key", "k"]) == EXIT_USAGE
    with pytest.raises(SystemExit) as usage:
        main(["submit", "--iterations", "x"])
    assert usage.value.code == EXIT_USAGE


def test_mesh_flags_reach_the_request_only_when_given() -> None:
    """``glint remote mesh``: the grazing blend is the server's default unless a flag
    says otherwise (None is left out of the request body)."""
    from glint_client.cli import build_parser

    p = build_parser()
    assert p.parse_args(["mesh", "job_x"]).grazing_blend is None
    assert p.parse_args(["mesh", "job_x", "--no-grazing-blend"]).grazing_blend is False
    assert p.parse_args(["mesh", "job_x", "--grazing-blend"]).grazing_blend is True
