"""bench.splat_order_view: a trained model's G-buffer timed in every compositing order."""

from pathlib import Path

import pytest

from bench.splat_order_view import ORDERS, main
from core.config import config_from_dict
from core.scene.synthetic import write_synthetic_scene
from core.training.run import train_scene


def test_times_every_order_forward_and_backward_against_centre(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scene = write_synthetic_scene(tmp_path / "scene", "sphere", "glossy", n_train=4, n_test=1,
                                  size=24)  # fmt: skip
    cfg = config_from_dict(
        {"iterations": 5, "init_points": 300, "envmap_resolution": 8,
         "densify": {"enabled": False}, "outputs": {"mesh": False}}
    )  # fmt: skip
    train_scene(scene, tmp_path / "run", cfg)
    main([str(tmp_path / "run" / "checkpoint.pt"), str(scene), "--repeat", "1", "--warmup", "0"])
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("| ") and "ms" not in r]
    assert [r.split(" | ")[0][2:] for r in rows] == [
        f"{o}: {w}" for o in ORDERS for w in ("forward", "forward+backward")
    ]
    ratios = {r.split(" | ")[0][2:]: float(r.split(" | ")[2].rstrip(" |")) for r in rows}
    assert ratios["centre: forward"] == ratios["centre: forward+backward"] == 1.0
    assert all(v > 0 for v in ratios.values())
