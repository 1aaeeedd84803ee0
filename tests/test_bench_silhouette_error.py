"""bench.silhouette_error: the chord each silhouette point's ray cuts through the hull."""

import torch

from bench.silhouette_error import chord_lengths
from core.scene.synthetic import SPHERE_RADIUS, make_scene
from core.training.silhouette import SilhouettePoints, silhouette_points


def test_chords_are_short_at_the_rim_and_a_diameter_through_the_middle() -> None:
    scene = make_scene("sphere", "diffuse", n_train=16, n_test=0, size=48, samples=4)
    scene.radius = 1.2
    rim = silhouette_points(scene, max_points=400)
    assert rim is not None
    fp = 3.0 / scene.train[0].camera.intrinsics.fx  # cameras at distance 3
    chords = chord_lengths(rim, scene, reach=0.6, step=0.002)
    # a grazing ray cuts a sliver of a 16-view hull: a few pixels, never the sphere
    assert float(torch.tensor(chords).median()) < 10 * fp
    assert chords.max() < SPHERE_RADIUS
    # a ray through the centre crosses the whole hull: about a diameter
    centre = SilhouettePoints(
        torch.zeros(1, 3, dtype=torch.float64),
        torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64),
        torch.tensor([0]),
    )
    through = chord_lengths(centre, scene, reach=1.5, step=0.002)[0]
    assert abs(through - 2 * SPHERE_RADIUS) < 0.1 * SPHERE_RADIUS
