"""LiGT linear global translation (geometry/ligt/) on synthetic street scenes."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry import so3
from rotonly_cli.geometry.ligt import (
    LiGTOptions,
    baseline_disagreement_deg,
    ligt_normal_matrix,
    ligt_translations,
    rigid_views,
    robust_ligt_translations,
    views_off_their_baselines,
)

from helpers import DyingPeer, make_street_scene, similarity_align_error


def test_noise_free_exact_up_to_similarity():
    scene = make_street_scene(15, 400, seed=1)
    result = ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy)
    error, scale = similarity_align_error(result.centers, scene.centers)
    assert error < 1e-8
    assert scale > 0  # the chirality vote fixed the sign (a flip is not a proper similarity)
    assert result.sign_votes[1] == 0
    assert result.has_translation.all()
    assert abs(result.smallest_eigenvalues[0]) < 1e-10 < result.smallest_eigenvalues[1]
    # documented scale: centroid 0, mean distance to it 1
    assert np.allclose(result.centers.mean(axis=0), 0.0, atol=1e-12)
    assert np.isclose(np.linalg.norm(result.centers, axis=1).mean(), 1.0)


def test_constraint_is_the_paper_form():
    # every 3-row block B t_r + C t_i + D t_l vanishes at the true centres: (t)ᵀ LᵀL t = 0
    scene = make_street_scene(6, 80, seed=2)
    LTL, extras = ligt_normal_matrix(scene.R_cam_from_world, scene.obs_point, scene.obs_view,
                                     scene.obs_xy, 6)
    t = scene.centers.ravel()
    assert t @ (LTL @ t) < 1e-13 * (t @ t) * abs(LTL).max()
    # but a perturbed solution is penalised
    t_bad = t + np.random.default_rng(0).normal(scale=0.1, size=t.size)
    assert t_bad @ (LTL @ t_bad) > 1e-6 * abs(LTL).max()
    # chirality rows are positive at the truth
    votes = np.einsum("ni,ni->n", extras["sign_row"],
                      scene.centers[extras["sign_l"]] - scene.centers[extras["sign_r"]])
    assert (votes > 0).all()



def _reference_normal_matrix(R, obs_track, obs_view, obs_xy, num_views):
    """LᵀL from L built row block by row block, track by track, with the formulas of the
    module docstring (TPAMI eq. 29 base pair, B, C, D = −(B + C))."""
    rows = []
    x = np.c_[obs_xy, np.ones(len(obs_xy))]
    for track in np.unique(obs_track):
        obs = np.flatnonzero(obs_track == track)
        best, base = -1.0, None
        for position, a in enumerate(obs):
            for b in obs[position + 1:]:
                norm = np.linalg.norm(np.cross(R[obs_view[b]].T @ x[b], R[obs_view[a]].T @ x[a]))
                if norm > best:
                    best, base = norm, (a, b)
        l, r = base
        R_l, R_r = R[obs_view[l]], R[obs_view[r]]
        R_lr = R_r @ R_l.T
        theta = so3.hat(x[r]) @ R_lr @ x[l]
        a_row = (so3.hat(R_lr @ x[l]) @ x[r]) @ so3.hat(x[r])
        for i in obs:
            if i == l:
                continue
            R_i = R[obs_view[i]]
            B = np.outer(so3.hat(x[i]) @ R_i @ R_l.T @ x[l], a_row @ R_r)
            C = (theta @ theta) * so3.hat(x[i]) @ R_i
            row = np.zeros((3, 3 * num_views))
            for view, block in ((obs_view[r], B), (obs_view[i], C), (obs_view[l], -(B + C))):
                row[:, 3 * view:3 * view + 3] += block
            rows.append(row)
    L = np.concatenate(rows)
    return L.T @ L


@pytest.mark.parametrize("chunk_size", [50_000, 37])
def test_normal_matrix_equals_explicit_LTL(chunk_size):
    # the per-triple sums of the closed-form Gram blocks (BᵀB = ‖u‖² v vᵀ, BᵀC = v wᵀ,
    # CᵀC = ‖θ‖⁴ (‖x‖² I − y yᵀ)) must give exactly LᵀL of the explicit L, also across chunks
    scene = make_street_scene(6, 60, seed=4)
    noisy = scene.obs_xy + np.random.default_rng(5).normal(scale=2e-3, size=scene.obs_xy.shape)
    LTL, extras = ligt_normal_matrix(scene.R_cam_from_world, scene.obs_point, scene.obs_view, noisy, 6,
                                     LiGTOptions(chunk_size=chunk_size))
    expected = _reference_normal_matrix(scene.R_cam_from_world, scene.obs_point, scene.obs_view, noisy, 6)
    assert np.abs(LTL.toarray() - expected).max() < 1e-12 * np.abs(expected).max()
    assert extras["constraints_per_view"].sum() == 3 * (len(scene.obs_point) - len(np.unique(scene.obs_point)))

def test_sparse_eigensolver_matches_dense():
    scene = make_street_scene(15, 400, seed=0)
    noisy = scene.obs_xy + np.random.default_rng(100).normal(scale=1e-3, size=scene.obs_xy.shape)
    dense = ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, noisy)
    sparse = ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, noisy,
                               options=LiGTOptions(max_dense_unknowns=0, chunk_size=500))
    assert np.abs(dense.centers - sparse.centers).max() < 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_pixel_noise(seed):
    # f = 1000: 1 px = 1e-3 normalized. Measured max centre error after similarity
    # alignment (seeds 0-5): 0.0068-0.019 scene units for a 14-unit camera baseline.
    scene = make_street_scene(15, 400, seed=seed)
    noisy = scene.obs_xy + np.random.default_rng(100 + seed).normal(scale=1e-3, size=scene.obs_xy.shape)
    result = ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, noisy)
    error, scale = similarity_align_error(result.centers, scene.centers)
    assert error < 0.03
    assert scale > 0


def add_pure_rotation_view(scene, rng):
    """A new view at view 0's centre, rotated 5°, sharing 40 new points with view 0 only."""
    R_new = so3.exp(np.array([0.0, np.radians(5.0), 0.0])) @ scene.R_cam_from_world[0]
    rays = np.c_[rng.uniform(-0.3, 0.3, size=(40, 2)), np.ones(40)]
    points = scene.centers[0] + (rays * rng.uniform(5, 10, size=(40, 1))) @ scene.R_cam_from_world[0]
    xy0 = rays[:, :2]
    p_new = (points - scene.centers[0]) @ R_new.T
    xy_new = p_new[:, :2] / p_new[:, 2:]
    n = scene.R_cam_from_world.shape[0]
    first_track = scene.obs_point.max() + 1
    track = np.repeat(first_track + np.arange(40), 2)
    view = np.tile([0, n], 40)
    xy = np.stack([xy0, xy_new], axis=1).reshape(-1, 2)
    R = np.concatenate([scene.R_cam_from_world, R_new[None]])
    return (R, np.r_[scene.obs_point, track], np.r_[scene.obs_view, view],
            np.r_[scene.obs_xy, xy])


def add_leaf_view(scene, rng, num_points: int = 60, shared_tracks: int = 0):
    """A new view 1.5 units beside view 3, sharing ``num_points`` new points with view 3 only
    (two-view tracks: they fix the direction of its baseline, not its length) and, with
    ``shared_tracks``, also seeing that many of the scene's own points. The new view is
    view 0 (the scene's views move up by one): the first view, which LiGT's references fix."""
    n = scene.R_cam_from_world.shape[0]
    R_new = so3.exp(np.array([0.0, np.radians(10.0), 0.0])) @ scene.R_cam_from_world[3]
    c_new = scene.centers[3] + np.array([0.0, 1.5, 0.0])
    rays = np.c_[rng.uniform(-0.3, 0.3, size=(num_points, 2)), np.ones(num_points)]
    points = scene.centers[3] + (rays * rng.uniform(8, 12, size=(num_points, 1))) @ scene.R_cam_from_world[3]
    p_new = (points - c_new) @ R_new.T
    track = np.r_[scene.obs_point, np.repeat(scene.obs_point.max() + 1 + np.arange(num_points), 2)]
    view = np.r_[scene.obs_view, np.tile([3, n], num_points)]
    xy = np.r_[scene.obs_xy, np.stack([rays[:, :2], p_new[:, :2] / p_new[:, 2:]], axis=1).reshape(-1, 2)]
    if shared_tracks:
        seen_by_3 = np.unique(scene.obs_point[scene.obs_view == 3])[:shared_tracks]
        p_shared = (scene.points[seen_by_3] - c_new) @ R_new.T
        track, view = np.r_[track, seen_by_3], np.r_[view, np.full(shared_tracks, n)]
        xy = np.r_[xy, p_shared[:, :2] / p_shared[:, 2:]]
    order = np.argsort(track, kind="stable")
    return (np.concatenate([R_new[None], scene.R_cam_from_world]), np.concatenate([c_new[None], scene.centers]),
            track[order], (view[order] + 1) % (n + 1), xy[order])


# pair ids by lookup table / by sort; the pairs inside tracks in one piece / a track or two at a time
@pytest.mark.parametrize("max_dense_keys", [4_000_000, 0])
@pytest.mark.parametrize("pairs_per_chunk", [1 << 19, 1, 4])
def test_rigid_views_follow_shared_baselines(monkeypatch, max_dense_keys, pairs_per_chunk):
    monkeypatch.setattr("rotonly_cli.geometry.ligt.rigid.MAX_DENSE_KEYS", max_dense_keys)
    monkeypatch.setattr("rotonly_cli.geometry.tracks.PAIRS_PER_CHUNK", pairs_per_chunk)

    def rigid(tracks, num_views):
        track = np.repeat(np.arange(len(tracks)), [len(t) for t in tracks])
        return rigid_views(track, np.concatenate(tracks), num_views).tolist()

    # (0,1,2) and (1,2,3) share the baseline 1-2; view 4 is reached by a two-view track only
    assert rigid([[0, 1, 2], [1, 2, 3], [3, 4]], 5) == [True, True, True, True, False]
    # two bodies hinged on view 3 alone scale freely about it: the larger one is kept
    assert rigid([[0, 1, 2], [1, 2, 3], [3, 4, 5], [4, 5, 6], [5, 6, 7]], 8) == [False] * 3 + [True] * 5
    # (0,1,2) and (0,2,3) make one body that holds 1 and 3; (1,3,4) shares that baseline
    # though no track holds 1, 3 and another of the first body's views
    assert rigid([[0, 1, 2], [0, 2, 3], [1, 3, 4]], 5) == [True] * 5
    # ... and merged bodies can make a new shared baseline: (5,6,7) shares 3-6 only with the
    # union of the first bodies and (3,4,6)
    assert rigid([[0, 1, 2], [0, 2, 3], [1, 3, 4], [1, 4, 6], [3, 6, 5], [5, 6, 7], [7, 8]], 9) == [True] * 8 + [False]
    # two-view tracks only: their one baseline is the scale of everything; of several pairs,
    # the one with the most tracks (a lone observation counts for nothing)
    assert rigid([[0, 1], [0, 1]], 2) == [True, True]
    assert rigid([[0, 1], [1, 2], [1, 2], [3]], 4) == [False, True, True, False]
    # a masked view takes its pairs with it: without view 2 nothing ties 3 to 0-1
    track = np.repeat(np.arange(3), 3)
    assert rigid_views(track, np.array([0, 1, 2, 1, 2, 3, 0, 1, 3]), 4,
                       view_mask=np.array([True, True, False, True])).tolist() == [True, True, False, True]


@pytest.mark.parametrize("robust", [False, True])
def test_leaf_view_without_multiview_tracks_gets_no_centre(robust):
    # the leaf's distance from view 3 is free (an exact null vector besides the gauge): before
    # rigid_views LiGT put it anywhere and shrank the others (castle-P19 subsets, algorithms.md §1.2)
    scene = make_street_scene(8, 300, seed=12)
    R, _, track, view, xy = add_leaf_view(scene, np.random.default_rng(13))
    if robust:
        result = robust_ligt_translations(R, track, view, xy, 1000.0).result
    else:
        result = ligt_translations(R, track, view, xy)
    assert result.has_translation.tolist() == [False] + [True] * 8
    error, _ = similarity_align_error(result.centers[1:], scene.centers)
    assert error < 1e-8


def test_centroid_gauge_keeps_a_weakly_linked_view_in_place():
    # the leaf sees 3 of the scene's points besides its 60 two-view ones: rigid, but its
    # distance rests on 3 tracks. With view 0's centre fixed at 0 and a unit norm, the smallest
    # eigenvector of such a system can pull the others together away from a weak gauge view;
    # the centroid gauge has no preferred view. Noise 1 px (f = 1000).
    scene = make_street_scene(8, 300, seed=14)
    R, centers, track, view, xy = add_leaf_view(scene, np.random.default_rng(15), shared_tracks=3)
    noisy = xy + np.random.default_rng(16).normal(scale=1e-3, size=xy.shape)
    result = ligt_translations(R, track, view, noisy)
    assert result.has_translation.all()
    error, scale = similarity_align_error(result.centers, centers)
    assert error < 0.05 and scale > 0


def test_view_without_translation_constraint_reported():
    scene = make_street_scene(10, 250, seed=5)
    R, obs_track, obs_view, obs_xy = add_pure_rotation_view(scene, np.random.default_rng(6))
    result = ligt_translations(R, obs_track, obs_view, obs_xy)
    assert not result.has_translation[10] and np.isnan(result.centers[10]).all()
    assert result.has_translation[:10].all()
    assert result.num_constraints_per_view[10] == 0
    error, _ = similarity_align_error(result.centers[:10], scene.centers)
    assert error < 1e-8


def test_view_mask_excludes_view():
    scene = make_street_scene(10, 250, seed=8)
    mask = np.ones(10, dtype=bool)
    mask[4] = False
    result = ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy,
                               view_mask=mask)
    assert result.has_translation.tolist() == mask.tolist()
    error, _ = similarity_align_error(result.centers[mask], scene.centers[mask])
    assert error < 1e-8


def test_too_few_constrained_views_is_an_error():
    scene = make_street_scene(4, 50, seed=9)
    with pytest.raises(AlgorithmError):
        ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy,
                          view_mask=np.array([True, False, False, False]))


def test_base_views_are_the_max_parallax_pair():
    from rotonly_cli.geometry.ligt.linear import _select_base_views

    # track 0: rays at 0°, 10°, 30°, 5° -> pair (0, 2); track 1: single ray; track 2: two rays
    def ray(deg):
        return [np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))]

    rays = np.array([ray(0), ray(10), ray(30), ray(5), ray(0), ray(0), ray(20)])
    base_l, base_r, norm = _select_base_views(rays, np.array([0, 4, 5, 7]), max_views=64)
    assert base_l.tolist() == [0, -1, 5] and base_r.tolist() == [2, -1, 6]
    assert np.allclose(norm, [np.sin(np.radians(30)), 0.0, np.sin(np.radians(20))])


def _with_wrong_observations(scene, fraction: float, rng):
    """Every track's last observation replaced, for ``fraction`` of the tracks, by a point 30 px
    (f = 1000) away in a random direction: wrong matches that tie a track to another point."""
    obs = scene.obs_xy.copy()
    last = np.flatnonzero(np.r_[scene.obs_point[1:] != scene.obs_point[:-1], True])
    wrong = rng.choice(last, size=int(fraction * last.size), replace=False)
    direction = rng.normal(size=(wrong.size, 2))
    obs[wrong] += 0.03 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    return obs, wrong


def test_robust_rounds_remove_wrong_observations():
    """3 % of the tracks with one wrong observation: the plain solve is off by several times the
    noise level, the robust rounds drop those observations (and few others) and match the
    solve on the clean tracks."""
    rng = np.random.default_rng(7)
    scene = make_street_scene(12, 600, seed=7)
    clean = scene.obs_xy + rng.normal(scale=3e-4, size=scene.obs_xy.shape)  # 0.3 px
    corrupted, wrong = _with_wrong_observations(type("S", (), {"obs_xy": clean, "obs_point": scene.obs_point})(),
                                                0.03, rng)
    R, tracks, views = scene.R_cam_from_world, scene.obs_point, scene.obs_view
    reference, _ = similarity_align_error(ligt_translations(R, tracks, views, clean).centers, scene.centers)
    plain, _ = similarity_align_error(ligt_translations(R, tracks, views, corrupted).centers, scene.centers)
    robust = robust_ligt_translations(R, tracks, views, corrupted, 1000.0)
    error, _ = similarity_align_error(robust.result.centers, scene.centers)
    assert plain > 3 * reference
    assert error < 1.5 * reference + 1e-3
    assert robust.keep[wrong].mean() < 0.1  # a wrong ray in a two-view track can pass off as depth
    assert robust.keep.sum() > 0.97 * (tracks.size - wrong.size)
    assert robust.rounds and all(r["threshold_px"] >= 1.0 for r in robust.rounds)


def test_robust_rounds_keep_clean_data_whole():
    scene = make_street_scene(10, 300, seed=3)
    robust = robust_ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy, 1000.0)
    plain = ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy)
    assert robust.keep.all() and len(robust.rounds) == 1
    assert np.abs(robust.result.centers - plain.centers).max() < 1e-12


def _noisy_street_with_wrong_observations():
    """(R, tracks, views, observations, view mask without view 5): a 12-view street, 0.3 px
    noise, 3 % of the tracks with one wrong observation (:func:`_with_wrong_observations`)."""
    rng = np.random.default_rng(11)
    scene = make_street_scene(12, 600, seed=7)
    noisy = scene.obs_xy + rng.normal(scale=3e-4, size=scene.obs_xy.shape)
    corrupted, _ = _with_wrong_observations(type("S", (), {"obs_xy": noisy, "obs_point": scene.obs_point})(),
                                            0.03, rng)
    mask = np.ones(len(scene.R_cam_from_world), dtype=bool)
    mask[5] = False
    return scene.R_cam_from_world, scene.obs_point, scene.obs_view, corrupted, mask


def test_a_helper_process_leaves_the_robust_rounds_unchanged_bit_for_bit():
    """The robust rounds work on two parts of the tracks, cut at a track boundary, whether this
    process evaluates both or a forked helper the second: centres, kept observations, errors
    and rounds are the same bits, with a view masked out too."""
    from rotonly_cli.geometry.ligt.robust import _TrackParts
    from rotonly_cli.runtime import parallel

    R, tracks, views, corrupted, mask = _noisy_street_with_wrong_observations()
    for view_mask in (None, mask):
        parts = _TrackParts(R, tracks, views, corrupted, view_mask, LiGTOptions())
        (a0, b0), (a1, b1) = parts.ranges
        assert (a0, b1) == (0, tracks.size) and b0 == a1 and tracks[a1] != tracks[a1 - 1]
        assert abs((b0 - a0) - (b1 - a1)) < 0.05 * tracks.size
        one = robust_ligt_translations(R, tracks, views, corrupted, 1000.0, view_mask=view_mask)
        two = robust_ligt_translations(R, tracks, views, corrupted, 1000.0, view_mask=view_mask,
                                       peer_class=parallel.ForkedPeer)
        dead = robust_ligt_translations(R, tracks, views, corrupted, 1000.0, view_mask=view_mask,
                                        peer_class=DyingPeer)  # its child dies: this process takes over
        assert len(one.rounds) >= 2 and one.rounds == two.rounds == dead.rounds
        for other in (two, dead):
            assert np.array_equal(one.result.centers, other.result.centers, equal_nan=True)
            assert np.array_equal(one.keep, other.keep) and np.array_equal(one.error_px, other.error_px)
        assert one.result.has_translation.sum() == (11 if view_mask is not None else 12)


def _edges_with_true_directions(scene, num_edges: int, seed: int):
    """Random view pairs of ``scene`` with their exact t_ij = R_j (c_i - c_j), normalized."""
    rng = np.random.default_rng(seed)
    n = len(scene.centers)
    ends = np.array([rng.choice(n, 2, replace=False) for _ in range(num_edges)])
    R, C = scene.R_cam_from_world, scene.centers
    t = np.einsum("eab,eb->ea", R[ends[:, 1]], C[ends[:, 0]] - C[ends[:, 1]])
    return ends, t / np.linalg.norm(t, axis=1, keepdims=True)


def test_baseline_check_agrees_with_true_centres_and_ignores_the_sign():
    scene = make_street_scene(12, 50, seed=4)
    ends, t_dirs = _edges_with_true_directions(scene, 40, seed=0)
    t_dirs[::3] *= -1.0  # the two-view sign (chirality) is not the check's business
    angles = baseline_disagreement_deg(scene.R_cam_from_world, scene.centers, ends, t_dirs)
    assert np.nanmax(angles) < 1e-5
    # a similarity of the centres changes no baseline direction
    shrunk = 0.01 * scene.centers + np.array([3.0, -2.0, 1.0])
    assert np.nanmax(baseline_disagreement_deg(scene.R_cam_from_world, shrunk, ends, t_dirs)) < 1e-5
    medians, off = views_off_their_baselines(angles, ends, 12, 10.0)
    assert off.size == 0 and np.nanmax(medians) < 1e-5


def test_baseline_check_finds_the_view_a_collapse_throws_out():
    # LiGT's collapse on castle-P19 (OpenMVG matches, 5 consensus runs, seed 3): one view far
    # out, the others shrunk around a point; the baselines among the shrunk ones keep their
    # directions, those of the far view do not
    scene = make_street_scene(12, 50, seed=5)
    ends, t_dirs = _edges_with_true_directions(scene, 60, seed=1)
    collapsed = scene.centers.mean(axis=0) + 0.05 * (scene.centers - scene.centers.mean(axis=0))
    collapsed[7] = scene.centers[7] + np.array([0.0, 40.0, 25.0])
    angles = baseline_disagreement_deg(scene.R_cam_from_world, collapsed, ends, t_dirs)
    touches_7 = (ends == 7).any(axis=1)
    assert np.all(angles[touches_7] > 10.0) and np.nanmax(angles[~touches_7]) < 1e-5
    medians, off = views_off_their_baselines(angles, ends, 12, 10.0)
    assert off.tolist() == [7]
    assert medians[7] > 10.0


def test_baseline_check_skips_unknown_directions_and_missing_centres():
    scene = make_street_scene(6, 30, seed=6)
    ends, t_dirs = _edges_with_true_directions(scene, 10, seed=2)
    t_dirs[0] = 0.0  # pure rotation: no direction
    centers = scene.centers.copy()
    centers[ends[1, 0]] = np.nan  # a view LiGT could not place
    angles = baseline_disagreement_deg(scene.R_cam_from_world, centers, ends, t_dirs)
    assert np.isnan(angles[0]) and np.isnan(angles[1])
    medians, off = views_off_their_baselines(angles, ends, 6, 10.0)
    assert off.size == 0


def test_updated_normal_matrix_is_the_fresh_assembly_up_to_rounding(monkeypatch):
    """Each robust round after the first may update LᵀL with the tracks whose observations
    changed (old terms out, new in): forced to (MAX_UPDATED_FRACTION 1), the centres, drops and
    sign votes are those of assembling every round afresh (0), with a view masked out too."""
    from rotonly_cli.geometry.ligt import robust as ligt

    R, tracks, views, corrupted, mask = _noisy_street_with_wrong_observations()
    assemblies = []
    evaluate = ligt._TrackParts.evaluate
    monkeypatch.setattr(ligt._TrackParts, "evaluate", lambda self, used, centers=None, peer=None: (
        assemblies.append(centers is None) or evaluate(self, used, centers, peer)))
    for view_mask in (None, mask):
        runs = {}
        for fraction in (1.0, 0.0):
            monkeypatch.setattr(ligt, "MAX_UPDATED_FRACTION", fraction)
            assemblies.clear()
            runs[fraction] = robust_ligt_translations(R, tracks, views, corrupted, 1000.0, view_mask=view_mask)
            assert sum(assemblies) == (1 if fraction else len(runs[fraction].rounds))  # a solve per round
        updated, fresh = runs[1.0], runs[0.0]
        assert len(updated.rounds) >= 2
        # the same decisions; the errors of ill-conditioned tracks (two Gauss-Newton steps from
        # the linear start) carry the rounding further than the centres' 1e-14
        assert len(updated.rounds) == len(fresh.rounds) and np.array_equal(updated.keep, fresh.keep)
        for ours, theirs in zip(updated.rounds, fresh.rounds):
            assert {k: ours[k] for k in ("observations", "dropped", "readmitted")} == {
                k: theirs[k] for k in ("observations", "dropped", "readmitted")}
            assert ours["sigma_px"] == pytest.approx(theirs["sigma_px"], rel=1e-6)
            assert ours["threshold_px"] == pytest.approx(theirs["threshold_px"], rel=1e-6)
        assert updated.result.sign_votes == fresh.result.sign_votes
        assert updated.result.num_tracks_used == fresh.result.num_tracks_used
        assert np.array_equal(updated.result.num_constraints_per_view, fresh.result.num_constraints_per_view)
        assert np.nanmax(np.abs(updated.result.centers - fresh.result.centers)) < 1e-12
        assert np.array_equal(np.isnan(updated.result.centers), np.isnan(fresh.result.centers))


def test_chunked_pairs_inside_tracks_give_the_same_solve(monkeypatch):
    # base views, rigid views and the error points' parallax all enumerate the pairs inside
    # tracks: a few tracks at a time gives the centres of one piece bit for bit
    scene = make_street_scene(10, 200, seed=3)
    whole = robust_ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy, 1000.0)
    monkeypatch.setattr("rotonly_cli.geometry.tracks.PAIRS_PER_CHUNK", 7)
    chunked = robust_ligt_translations(scene.R_cam_from_world, scene.obs_point, scene.obs_view, scene.obs_xy, 1000.0)
    np.testing.assert_array_equal(chunked.result.centers, whole.result.centers)
    np.testing.assert_array_equal(chunked.keep, whole.keep)
    error, _ = similarity_align_error(whole.result.centers, scene.centers)
    assert error < 1e-8
