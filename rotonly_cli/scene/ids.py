"""View, intrinsic and landmark ids between COLMAP's and OpenMVG's conventions.

COLMAP ids start at 1, OpenMVG's at 0 (SfMInit_ImageListing). COLMAP -> OpenMVG shifts
view, intrinsic and landmark ids by -1; the COLMAP writers shift 0-based ids by +1, so a
round trip restores them. Pair orientation is unchanged (the shift is monotone).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.scene.types import SfMScene, Structure, View


def shift_ids(scene: SfMScene, view_shift: int, intrinsic_shift: int, point_shift: int = 0) -> SfMScene:
    """A copy of ``scene`` with view (= pose), intrinsic and landmark ids shifted."""
    if view_shift == 0 and intrinsic_shift == 0 and point_shift == 0:
        return scene
    views = {view_id + view_shift: View(
        view_id + view_shift, view.name, view.intrinsics_id + intrinsic_shift,
        None if view.pose_id is None else view.pose_id + view_shift, view.width, view.height)
        for view_id, view in scene.views.items()}
    intrinsics = {intrinsic_id + intrinsic_shift: replace(intrinsic, id=intrinsic_id + intrinsic_shift)
                  for intrinsic_id, intrinsic in scene.intrinsics.items()}
    pairs = {(i + view_shift, j + view_shift): replace(pair, i=i + view_shift, j=j + view_shift)
             for (i, j), pair in scene.pairs.items()}
    structure = scene.structure
    if structure is not None:
        structure = remap_observation_views(
            replace(structure, point_ids=np.asarray(structure.point_ids, dtype=np.int64) + point_shift),
            lambda view_ids: view_ids + view_shift)
    return replace(
        scene, views=views, intrinsics=intrinsics, pairs=pairs, structure=structure,
        poses={view_id + view_shift: pose for view_id, pose in scene.poses.items()},
        keypoints={view_id + view_shift: k for view_id, k in scene.keypoints.items()},
        normalized={view_id + view_shift: x for view_id, x in scene.normalized.items()})


def remap_observation_views(structure: Structure, new_view_ids) -> Structure:
    """A copy of ``structure`` whose observations' view ids are ``new_view_ids(old)`` (an
    array function), remapped on the flat observation arrays rather than per landmark
    (which the copy keeps as ``observation_arrays`` for the writers)."""
    track_lengths, view_feature = structure.flat_observations()
    views = new_view_ids(view_feature[:, 0]) if len(view_feature) else view_feature[:, 0]
    remapped = np.stack([views, view_feature[:, 1]], axis=1).astype(np.int64).reshape(-1, 2)
    return replace(structure, observations=observation_lists(track_lengths, remapped),
                   observation_arrays=(track_lengths, remapped))


def observation_lists(track_lengths: np.ndarray, view_feature: np.ndarray) -> list[list[tuple[int, int]]]:
    """``Structure.observations`` (per point a list of (view id, feature) tuples) of flat
    arrays: one zip over all observations, then one slice per point."""
    pairs = list(zip(view_feature[:, 0].tolist(), view_feature[:, 1].tolist()))
    ends = np.cumsum(track_lengths).tolist()
    return [pairs[start:end] for start, end in zip([0] + ends[:-1], ends)]


def renumber_views_by_name(scene: SfMScene) -> SfMScene:
    """View (and pose) ids 0..n-1 in file-name order, as ``openMVG_main_SfMInit_ImageListing``
    numbers them. OpenMVG's evalQuality pairs the estimate with the ground truth by pose id
    (formats.md §3.4), so an sfm_data.json numbered in COLMAP's database order would be
    compared against the wrong cameras."""
    order = sorted(scene.views, key=lambda v: (scene.views[v].name, v))
    new_id = {old: new for new, old in enumerate(order)}
    if all(old == new for old, new in new_id.items()):
        return scene
    views = {new_id[old]: replace(scene.views[old], id=new_id[old], pose_id=new_id[old]) for old in order}
    structure = scene.structure
    if structure is not None:
        old_ids = np.asarray(order, dtype=np.int64)
        sorter = np.argsort(old_ids)

        def renumber(view_ids: np.ndarray) -> np.ndarray:  # new id = position in ``order``
            position = np.minimum(np.searchsorted(old_ids, view_ids, sorter=sorter), len(order) - 1)
            if not np.array_equal(old_ids[sorter[position]], view_ids):
                raise InputError("observation of an unknown view", field="structure.observations")
            return sorter[position]

        structure = remap_observation_views(structure, renumber)
    return replace(scene, views=views, structure=structure,
                   poses={new_id[v]: p for v, p in scene.poses.items()},
                   keypoints={new_id[v]: k for v, k in scene.keypoints.items()},
                   normalized={new_id[v]: x for v, x in scene.normalized.items()},
                   pairs={})
