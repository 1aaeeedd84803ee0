"""bench.viewer serves a small sphere through the real stack and reports its still frames."""

from __future__ import annotations

import sys

import pytest

from bench import viewer


def test_viewer_bench_reports_each_still_frame_and_its_parts():
    res = viewer.run(3000, 64, 0.5, one_sided=True, stills=4)
    still = res["still_full_res"]
    assert still["frames"] == 4
    lo, hi = still["render_plus_encode_ms_range"]
    assert 0 < lo <= still["render_plus_encode_ms_median"] <= hi
    # render and encode are the two parts of each frame's time: each part's median is
    # at most the whole's (frame by frame, each part is at most the whole)
    total = still["render_plus_encode_ms_median"]
    assert 0 < still["render_ms_median"] <= total + 0.05
    assert 0 < still["encode_ms_median"] <= total + 0.05
    assert res["moving"]["frames"] > 0 and res["moving"]["fps"] > 0


def test_viewer_bench_refuses_no_still_frame(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench.viewer", "--stills", "0"])
    with pytest.raises(SystemExit) as exc:
        viewer.main()
    assert exc.value.code == 2
    assert "--stills" in capsys.readouterr().err
