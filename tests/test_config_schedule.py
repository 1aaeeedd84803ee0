"""Training config validation and the phase schedule."""

from __future__ import annotations

import pytest

from core.config import ConfigError, config_from_dict, load_config
from core.model.schedule import Marks, phase_at


def test_defaults_are_the_papers():
    c = config_from_dict({})
    assert (c.loss.scale, c.loss.single_view, c.loss.multi_view, c.loss.l1) == (
        100.0,
        0.2,
        0.1,
        0.8,
    )
    assert c.iterations == 30_000 and c.envmap_resolution == "auto"
    m = Marks.of(c)
    assert (m.geometry_start, m.multiview_start, m.sh_full_start) == (3000, 7000, 10000)


NO_FLOORS = {"min_rgb_iterations": 0, "min_geometry_iterations": 0}


def test_marks_scale_with_run_length():
    m = Marks.of(config_from_dict({"iterations": 3000, "phases": NO_FLOORS}))
    assert (m.geometry_start, m.multiview_start, m.sh_full_start) == (300, 700, 1000)


def test_short_runs_get_floored_phases():
    # 1500 iterations: scaled marks 150/350 are raised to 500 and 500 + 250.
    m = Marks.of(config_from_dict({"iterations": 1500}))
    assert (m.geometry_start, m.multiview_start, m.sh_full_start) == (500, 750, 500)
    # The floors never take more than a third (a sixth) of the run.
    m = Marks.of(config_from_dict({"iterations": 300}))
    assert (m.geometry_start, m.multiview_start) == (100, 150)
    # Long runs: the floors do not bind.
    m = Marks.of(config_from_dict({"iterations": 60_000}))
    assert (m.geometry_start, m.multiview_start) == (6000, 14000)
    # Marks the user put at 0 (or merged) stay where they are.
    c = {"iterations": 1500, "phases": {"geometry_start": 0, "multiview_start": 0}}
    m = Marks.of(config_from_dict(c))
    assert (m.geometry_start, m.multiview_start) == (0, 0)


def test_envmap_resolution_validated():
    assert config_from_dict({"envmap_resolution": 16}).envmap_resolution == 16
    for bad in (2, 4096, "big"):
        with pytest.raises(ConfigError, match="envmap_resolution"):
            config_from_dict({"envmap_resolution": bad})


def test_phases_in_order():
    c = config_from_dict({"iterations": 3000, "phases": NO_FLOORS})
    p0, p1, p2, p3 = (phase_at(c, i) for i in (0, 300, 700, 1000))
    assert (p0.name, p0.single_view, p0.envmap, p0.multi_view, p0.sh_degree) == (
        "rgb",
        False,
        False,
        False,
        0,
    )
    assert (p1.name, p1.single_view, p1.envmap, p1.multi_view) == ("geometry", True, True, False)
    assert (p2.name, p2.multi_view, p2.sh_degree) == ("multiview", True, 0)
    assert p3.sh_degree == 3
    assert phase_at(c, 299).name == "rgb"


def test_ablations_switch_parts_off():
    off = ("deferred_shading", "single_view", "multi_view", "planar", "planar_depth")
    c = config_from_dict({"iterations": 100, "ablation": dict.fromkeys(off, False)})
    p = phase_at(c, 99)
    assert not (p.envmap or p.single_view or p.multi_view or p.scale_loss or p.planar_depth)
    assert not phase_at(config_from_dict({}), 20000, envmap_planned=False).envmap
    assert phase_at(config_from_dict({}), 20000, max_sh_degree=0).sh_degree == 0


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"iterations": 0}, "iterations"),
        ({"loss": {"scale": -1}}, "loss.scale"),
        ({"loss": {"l1": 1.5}}, "loss.l1"),
        ({"background": [1, 2]}, "background"),
        ({"background": "purple"}, "background"),
        ({"phases": {"geometry_start": 5000, "multiview_start": 1000}}, "phases"),
        ({"backend": "gpu"}, "backend"),
        ({"typo_field": 1}, "typo_field"),
        ({"densify": {"interval": 0}}, "densify.interval"),
    ],
)
def test_invalid_values_name_the_field(data, field):
    with pytest.raises(ConfigError, match=f"field '{field}"):
        config_from_dict(data)


def test_load_yaml_json_and_overrides(tmp_path):
    y = tmp_path / "c.yaml"
    y.write_text("iterations: 500\nloss:\n  scale: 50\n")
    c = load_config(y, {"loss.single_view": 0.5})
    assert (c.iterations, c.loss.scale, c.loss.single_view) == (500, 50.0, 0.5)
    j = tmp_path / "c.json"
    j.write_text('{"iterations": 7}')
    assert load_config(j).iterations == 7
    bad = tmp_path / "bad.yaml"
    bad.write_text("iterations: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: cannot parse"):
        load_config(bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(lst)


# -- geometry pause after opacity resets ------------------------------------------------
@pytest.mark.parametrize(
    "over",
    [
        {"iterations": 3000},
        {"iterations": 30000},
        {"iterations": 8000, "densify": {"opacity_reset_interval": 0}},
        {"iterations": 8000, "densify": {"enabled": False}},
    ],
)
def test_last_opacity_reset_matches_the_strategy(over):
    from core.model.schedule import last_opacity_reset
    from core.training.densify import DensifyStrategy

    cfg = config_from_dict(over)
    s = DensifyStrategy(cfg, 1.0)
    last = None
    for it in range(cfg.iterations):
        assert last_opacity_reset(cfg, it) == last, it
        if s.is_reset_step(it):
            last = it


def test_geometry_losses_pause_after_each_reset():
    from core.model.schedule import geometry_paused

    cfg = config_from_dict({"iterations": 30000})
    resets = [3000, 6000, 9000, 12000]
    paused = [it for it in range(30000) if geometry_paused(cfg, it)]
    assert paused == [it for r in resets for it in range(r + 1, r + 101)]
    p = phase_at(cfg, 9050)
    assert p.name == "multiview" and not p.single_view and not p.multi_view and p.envmap
    assert phase_at(cfg, 9101).multi_view and phase_at(cfg, 9101).single_view
    off = config_from_dict({"iterations": 30000, "phases": {"geometry_pause_after_reset": 0}})
    assert not any(geometry_paused(off, it) for it in range(30000))


def test_the_silhouette_term_stops_at_its_fraction_of_the_run():
    """phases.silhouette_until ends the silhouette loss; 1.0 keeps it to the last step."""
    cfg = config_from_dict({"iterations": 3000, "phases": {"silhouette_until": 0.8}})
    on = [it for it in range(3000) if phase_at(cfg, it).silhouette]
    assert on and on[-1] == 2399 and phase_at(cfg, 2400).single_view
    full = config_from_dict({"iterations": 3000})
    assert phase_at(full, 2999).silhouette
    assert not phase_at(full, 2999, silhouette_planned=False).silhouette
    with pytest.raises(ConfigError, match=r"phases\.silhouette_until"):
        config_from_dict({"phases": {"silhouette_until": 0}})
