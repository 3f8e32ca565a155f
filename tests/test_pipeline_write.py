"""run's OpenMVG output scene (convert's colmap_to_openmvg + renumber_views_by_name): the
array remap of the landmarks equals the obvious per-landmark remap."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import openmvg
from rotonly_cli.io.colmap import colmap_to_openmvg
from rotonly_cli.scene.ids import renumber_views_by_name
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View


def _openmvg_ids_scene(scene: SfMScene) -> SfMScene:
    """What `rotonly run` writes for a COLMAP database (pipeline.write_outputs)."""
    return renumber_views_by_name(colmap_to_openmvg(scene))


def _per_landmark_reference(scene: SfMScene) -> SfMScene:
    """The same ids remapped one landmark at a time: views 0.. in (file name, id) order,
    point ids shifted down by one when they start at 1."""
    order = sorted(scene.views, key=lambda v: (scene.views[v].name, v))
    new_id = {old: new for new, old in enumerate(order)}
    expected = renumber_views_by_name(colmap_to_openmvg(replace(scene, structure=None)))
    point_ids = np.asarray(scene.structure.point_ids, dtype=np.int64)
    expected.structure = replace(scene.structure, point_ids=point_ids - (1 if point_ids.min() >= 1 else 0),
                                 observations=[[(new_id[v], k) for v, k in track]
                                               for track in scene.structure.observations])
    return expected


def _colmap_like_scene(rng: np.random.Generator, first_point_id: int) -> SfMScene:
    """COLMAP ids from 1, file names not in id order (a duplicate name too), one unposed
    view, points with empty and unsorted tracks."""
    scene = SfMScene(source="colmap-db")
    scene.intrinsics[1] = Intrinsics(1, "SIMPLE_RADIAL", 640, 480, np.array([500.0, 320.5, 240.5, 0.0]))
    names = ["c.jpg", "a.jpg", "b.jpg", "a.jpg", "e.jpg", "d.jpg"]
    for view_id, name in enumerate(names, start=1):
        scene.views[view_id] = View(view_id, name, 1)
        scene.keypoints[view_id] = rng.uniform(0, 600, (40, 2))
        scene.normalized[view_id] = rng.normal(size=(40, 2))
        if view_id != 5:
            scene.poses[view_id] = Pose(np.eye(3), rng.normal(size=3))
    observations = []
    for _ in range(200):
        views = rng.permutation(np.arange(1, 7))[:rng.integers(0, 5)]
        observations.append([(int(v), int(rng.integers(0, 40))) for v in views])
    scene.structure = Structure(np.arange(200, dtype=np.int64) + first_point_id, rng.normal(size=(200, 3)),
                                rng.integers(0, 256, (200, 3)).astype(np.uint8), observations)
    return scene


@pytest.mark.parametrize("first_point_id", [0, 1])
def test_openmvg_ids_scene_equals_convert_path(first_point_id):
    scene = _colmap_like_scene(np.random.default_rng(first_point_id), first_point_id)
    expected = _per_landmark_reference(scene)
    fast = _openmvg_ids_scene(scene)
    assert fast.views == expected.views and sorted(fast.poses) == sorted(expected.poses)
    assert [view.name for _, view in sorted(fast.views.items())] == ["a.jpg", "a.jpg", "b.jpg", "c.jpg", "d.jpg",
                                                                     "e.jpg"]
    assert fast.structure.observations == expected.structure.observations
    np.testing.assert_array_equal(fast.structure.point_ids, expected.structure.point_ids)
    assert fast.structure.point_ids[0] == 0
    np.testing.assert_array_equal(fast.structure.points, expected.structure.points)
    assert openmvg.sfm_data_bytes(fast) == openmvg.sfm_data_bytes(expected)
    assert scene.structure.observations[0] != fast.structure.observations[0] or not scene.structure.observations[0]
    assert scene.structure.point_ids[0] == first_point_id  # the input scene is not modified


def test_openmvg_ids_scene_rejects_unknown_view():
    scene = _colmap_like_scene(np.random.default_rng(3), 1)
    scene.structure.observations[4] = [(99, 0)]
    with pytest.raises(InputError, match="unknown view"):
        _openmvg_ids_scene(scene)
