"""Tests of the research code (not run by the product's test suite):

    python -m pytest -q -p no:cacheprovider scripts/research

GRRM with every t_ij held fixed (grrm_fixed_translations.py) and the probes on the bundled
Herz-Jesus-P8 fixture. These moved here from tests/ with the diagnostics they test."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli import multiview
from rotonly_cli.geometry import alignment, averaging, grrm, so3
from rotonly_cli.scene.view_graph import Edge
from rotonly_cli.simulation.layout_scenes import simulate_multiview

import grrm_fixed_translations as fixed
from research_scripts import FIXTURES, digest, load_script

probe = load_script("probe_grrm_residuals")
probe_structure = load_script("probe_grrm_structure")


def _problem(setup="circular", noise=1.0, seed=1, views=10, points=400, window=3, init="ransac"):
    p = simulate_multiview(setup, num_views=views, num_points=points, noise_px=noise, rng=seed, window=window,
                           init=init)
    vids = sorted(p.scene.views)
    keys = sorted(p.scene.pairs)
    prob = multiview.build_problem(p.scene.normalized, {k: p.scene.pairs[k].matches for k in keys}, vids)
    return p, prob, np.stack([p.gt_poses[v].R_cam_from_world for v in vids])


def _l1_irls_start(p, prob) -> np.ndarray:
    R_rel = np.stack([p.scene.pairs[k].R_j_from_i for k in prob.pair_keys])
    weights = np.array([len(p.scene.pairs[k].matches) for k in prob.pair_keys], dtype=float)
    return averaging.average_rotations(len(prob.view_ids), prob.edge_views[:, 0], prob.edge_views[:, 1], R_rel,
                                       weights).R_cam_from_world


def _mean_err_deg(R, R_gt):
    return float(alignment.rotation_errors_after_alignment(R, R_gt)[0].mean())


def test_jacobian_with_held_translations_matches_central_differences():
    """With every edge's t_ij held fixed (dt/dδ = 0), in both residual forms."""
    p, prob, R_gt = _problem(noise=2.0, seed=4, views=6, window=2)
    t = _true_translations(p, prob)
    R = so3.exp(np.random.default_rng(1).normal(scale=0.005, size=(6, 3))) @ R_gt
    for residual in ("bearing", "image"):
        def residuals(R_at, with_jacobian=False, residual=residual):
            return fixed.residuals_with_translations(R_at, prob.edge_views, prob.batch, prob.obs_ids, t,
                                                     with_jacobian, residual)

        V, J = residuals(R, True)
        J = J.toarray()
        h = 1e-6
        J_fd = np.zeros_like(J)
        for col in range(3 * len(R)):
            d = np.zeros((len(R), 3))
            d.flat[col] = h
            J_fd[:, col] = (residuals(so3.exp(d) @ R)[0] - residuals(so3.exp(-d) @ R)[0]).ravel() / (2 * h)
        assert np.max(np.abs(J - J_fd)) / np.max(np.abs(J)) < 1e-6


# ============================================================================ translations held fixed

def _true_translations(p, prob) -> np.ndarray:
    """t_ij = R_j (c_i - c_j) per edge of the problem (camera j, x_j ~ R_ij x_i + t_ij)."""
    vids = sorted(p.scene.views)
    R = np.stack([p.gt_poses[v].R_cam_from_world for v in vids])
    C = np.stack([p.gt_poses[v].center for v in vids])
    i, j = prob.edge_views[:, 0], prob.edge_views[:, 1]
    return np.einsum("eab,eb->ea", R[j], C[i] - C[j])


def test_fixed_true_translations_equal_the_null_vector_on_exact_data():
    """Noise-free, at the true rotations Pˢ's null vector is the true t_ij (Theorem 1), so
    holding t_ij fixed gives the same residuals (all zero) as the paper's t_ij(R_ij); away
    from the truth the two differ (the fixed t has no dt/dδ)."""
    p, prob, R_gt = _problem(noise=0.0, seed=6, views=6, window=2, init="truth")
    t = 3.0 * _true_translations(p, prob)  # any positive length
    V_free, _ = grrm.grrm_residuals(R_gt, prob.edge_views, prob.batch, prob.obs_ids)
    V_fixed, _ = fixed.residuals_with_translations(R_gt, prob.edge_views, prob.batch, prob.obs_ids, t)
    assert np.abs(V_free).max() < 1e-10 and np.abs(V_fixed).max() < 1e-10
    R = so3.exp(np.random.default_rng(2).normal(scale=0.003, size=(6, 3))) @ R_gt
    V_free, _ = grrm.grrm_residuals(R, prob.edge_views, prob.batch, prob.obs_ids)
    V_fixed, _ = fixed.residuals_with_translations(R, prob.edge_views, prob.batch, prob.obs_ids, t)
    assert np.abs(V_free - V_fixed).max() > 1e-5


def test_fixed_true_translations_exact_recovery_and_noisy_gain():
    """Noise-free: exact rotations from 1 deg off with the true t held. At 1 px the true t
    makes GRRM more accurate than the paper's per-edge t (the diagnostic's premise)."""
    p, prob, R_gt = _problem("circular", noise=0.0, seed=2, views=8, window=3, init="truth")
    R0 = so3.exp(np.random.default_rng(4).normal(scale=np.deg2rad(1.0), size=(8, 3))) @ R_gt
    R0[0] = R_gt[0]
    res = fixed.optimize_with_translations(R0, prob.edge_views, prob.batch, prob.obs_ids,
                                           _true_translations(p, prob), fixed_view=0,
                                           options=grrm.GRRMOptions(loss="none", step_tolerance=1e-12,
                                                                    function_tolerance=0.0))
    assert np.max(so3.geodesic_angle(res.R_cam_from_world, R_gt)) < 1e-8
    gains = []
    for seed in range(5):
        p, prob, R_gt = _problem("circular", noise=1.0, seed=300 + seed, views=10, window=3)
        R0 = _l1_irls_start(p, prob)
        free = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids)
        held = fixed.optimize_with_translations(R0, prob.edge_views, prob.batch, prob.obs_ids,
                                                _true_translations(p, prob))
        gains.append(_mean_err_deg(free.R_cam_from_world, R_gt) - _mean_err_deg(held.R_cam_from_world, R_gt))
    assert np.mean(gains) > 0, gains


def test_fixed_translations_bad_input():
    p, prob, R_gt = _problem(noise=1.0, seed=8, views=6, window=2)
    t = _true_translations(p, prob)
    with pytest.raises(ValueError, match="translations: expected shape"):
        fixed.optimize_with_translations(R_gt, prob.edge_views, prob.batch, prob.obs_ids, t[:-1])
    t[1] = 0.0
    with pytest.raises(ValueError, match="translations: every edge"):
        fixed.residuals_with_translations(R_gt, prob.edge_views, prob.batch, prob.obs_ids, t)


# ============================================================================ probe_grrm_residuals

def test_probe_grrm_residuals_on_fixture(tmp_path, capsys):
    """The probe's rows on the Herz-Jesu fixture: the real keypoints and the same residuals
    moved around; every rebuilt set gives a lower GRRM error than the real keypoints (the
    property README "Known limits" rests on), and the input is untouched."""
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "database.db")
    assert probe.main(["--root", str(tmp_path / "root"), "--scene", "Herz-Jesus-P8", "--input", "database"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "database.db") == before
    rows = {line.split(" | ")[0].lstrip("| "): line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| ") and not line.startswith("| keypoints")}
    assert len(rows) == 5
    start = {label: float(cells[1]) for label, cells in rows.items()}
    grrm = {label: float(cells[2]) for label, cells in rows.items()}
    real = grrm.pop("real keypoints")
    assert 0.005 < real < 0.1 and 0.005 < start.pop("real keypoints") < 0.1
    assert all(value < real for value in grrm.values()), grrm
    assert all(value < real for value in start.values()), start  # the start is rebuilt too
    assert all(len(cells[3].rstrip(" |").split()) == 8 for cells in rows.values())  # one error per camera


def test_probe_grrm_residuals_refuses_a_missing_scene(tmp_path):
    with pytest.raises(SystemExit) as exc:
        probe.main(["--root", str(tmp_path), "--scene", "nothing"])
    assert exc.value.code == 2


# ============================================================================ probe_grrm_structure

def _edge(i: int, j: int, matches) -> Edge:
    edge = Edge(i=i, j=j, R_j_from_i=np.eye(3), t_dir=np.array([1.0, 0.0, 0.0]),
                matches=np.array(matches, dtype=np.int64).reshape(-1, 2))
    edge.scene_kind = "REGULAR"
    return edge


def test_completed_graph_adds_the_matches_tracks_imply():
    """Track a: 0:5 - 1:7 - 2:9 matched only along 0-1 and 1-2; edge 0-2 lacks (5, 9) and gets
    it; track b (0:1 - 1:2 - 3:4) implies pairs 0-3 and 1-3, which have no edge: new edges only
    when asked for and with enough tracks; an inconsistent track adds nothing."""
    from rotonly_cli.scene.view_graph import ViewGraph

    graph = ViewGraph(views={v: None for v in range(4)},
                      edges=[_edge(0, 1, [[5, 7], [1, 2], [3, 3]]), _edge(1, 2, [[7, 9], [3, 4]]),
                             _edge(0, 2, [[0, 0], [3, 6]]), _edge(1, 3, [[2, 4]])])
    completed, added, new_edges = probe_structure.completed_graph(graph, [0, 1, 2, 3])
    # track 0:3-1:3-2:4-2:6 sees view 2 twice: inconsistent, dropped
    assert added == 1 and new_edges == []
    assert completed.edges[2].matches.tolist() == [[0, 0], [3, 6], [5, 9]]
    assert [e.matches.tolist() for e in completed.edges[:2]] == [[[5, 7], [1, 2], [3, 3]], [[7, 9], [3, 4]]]
    assert graph.edges[2].matches.tolist() == [[0, 0], [3, 6]]  # the input graph is untouched
    with_new, _, new_edges = probe_structure.completed_graph(graph, [0, 1, 2, 3], new_edge_min=1)
    assert new_edges == [(0, 3, 1)]
    assert with_new.edges[-1].matches.tolist() == [[1, 4]] and with_new.edges[-1].scene_kind == "REGULAR"
    assert probe_structure.completed_graph(graph, [0, 1, 2, 3], new_edge_min=2)[2] == []


def test_average_directions_recovers_centres_from_exact_directions():
    """Exact baseline directions of a random 6-view graph give the centres up to translation
    and positive scale; the sign follows the directions."""
    rng = np.random.default_rng(7)
    C = rng.normal(size=(6, 3))
    views = np.array([(i, j) for i in range(6) for j in range(i + 1, 6) if (i + j) % 4])
    d = C[views[:, 0]] - C[views[:, 1]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    est = probe_structure.average_directions(6, views, d)
    fit = (est - est[0]) / np.linalg.norm(est - est[0]) - (C - C[0]) / np.linalg.norm(C - C[0])
    assert np.abs(fit).max() < 1e-10
    flipped = probe_structure.average_directions(6, views, -d)
    assert np.abs(flipped + est).max() < 1e-10


def test_epipolar_angles_zero_on_exact_matches_and_sine_of_the_offset():
    rng = np.random.default_rng(5)
    R = so3.random_rotations(1, rng)[0]
    t = np.array([1.0, 0.2, -0.1])
    X = rng.normal(size=(20, 3)) + [0, 0, 6]
    x_i = X[:, :2] / X[:, 2:]
    Xj = X @ R.T + t
    x_j = Xj[:, :2] / Xj[:, 2:]
    edge = _edge(0, 1, np.column_stack([np.arange(20), np.arange(20)]))
    edge.R_j_from_i, edge.t_dir = R, t / np.linalg.norm(t)
    normalized = {0: x_i, 1: x_j}
    assert probe_structure.epipolar_angles(edge, normalized, edge.matches).max() < 1e-12
    moved = {0: x_i, 1: x_j + 1e-3}
    angles = probe_structure.epipolar_angles(edge, moved, edge.matches)
    # independently: |x̂_jᵀ E x̂_i| / ‖E x̂_i‖ with E = [t]x R
    b_i = np.column_stack([x_i, np.ones(20)])
    b_j = np.column_stack([moved[1], np.ones(20)])
    b_i /= np.linalg.norm(b_i, axis=1, keepdims=True)
    b_j /= np.linalg.norm(b_j, axis=1, keepdims=True)
    Ex = b_i @ (so3.hat(edge.t_dir) @ R).T
    expected = np.abs(np.einsum("nk,nk->n", b_j, Ex)) / np.linalg.norm(Ex, axis=1)
    np.testing.assert_allclose(angles, expected, rtol=1e-9, atol=1e-15)
    assert angles.mean() > 1e-5


def test_probe_grrm_structure_on_fixture(tmp_path, capsys):
    """The four tables on the Herz-Jesu fixture's OpenMVG project: one row per GRRM edge with
    finite errors, the completion rows add matches, the translation rows, the scale rows cover
    the observations, and the input is untouched."""
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "Herz-Jesus-P8").symlink_to(FIXTURES / "herzjesu_p8")
    before = digest(FIXTURES / "herzjesu_p8" / "openmvg" / "matches.e.bin")
    assert probe_structure.main(["--root", str(tmp_path / "root"), "--scene", "Herz-Jesus-P8",
                                 "--input", "openmvg"]) == 0
    assert digest(FIXTURES / "herzjesu_p8" / "openmvg" / "matches.e.bin") == before
    out = capsys.readouterr().out
    tables = [[line.strip("| ").split(" | ") for line in block.splitlines() if line.startswith("| ")
               and not line.startswith("|---")][1:] for block in out.split("\n\n")[1:]]
    edges, tracks, translations, scale = [t for t in tables if t]
    assert len(edges) >= 10 and all(len(row) == 5 for row in edges)
    # relative errors: TRRM up to ~1 deg on the 45-match edge 0-7, GRRM's below 0.1
    assert all(0.0 <= float(row[2]) < 5.0 and 0.0 <= float(row[3]) < 0.1 and 0.005 < float(row[4]) < 0.05
               for row in edges)
    loaded = int(tracks[0][1])
    assert tracks[0][0] == "as loaded" and len(tracks) == 4
    assert all(int(row[1]) > loaded for row in tracks[1:])
    assert all(0.001 < float(row[2]) < 0.2 for row in tracks)
    # per-edge translations: the paper's Pˢ, the GT oracle, three LiGT rounds, three rounds of
    # averaged centres; the oracle's t error is 0, the others within a degree of the GT
    assert [row[0].split(",")[0] for row in translations] == [
        "Pˢ null vector (the paper)", "held at the GT direction"] + [
        "held at LiGT's directions from the rotations before"] * 3 + [
        "held at directions of centres averaged from Pˢ's from the rotations before"] * 3
    assert translations[1][1] == "0"
    assert all(0.0 < float(row[1].split(" / ")[0]) < 1.0 for row in translations if row[1] != "0")
    assert all(0.001 < float(row[2]) < 0.2 for row in translations)
    # the fixture's .feat files come from the database's keypoints (scale column 1): one bin
    assert scale and sum(int(row[1]) for row in scale) > 15000
    assert all(0.05 < float(row[4]) < 2.0 and abs(float(row[2])) < 0.05 for row in scale)


# ============================================================================ probe_seed_sensitivity

probe_seeds = load_script("probe_seed_sensitivity")


def test_probe_seed_sensitivity_on_fixture(capsys):
    """On the clean fixture GRRM ends where it ends whatever the start or the loss scale (the
    castle-P19 OpenMVG rows of scripts/research/README.md part by 0.06 deg); the edge swap
    between two seeds moves nothing."""
    assert probe_seeds.main(["--root", str(FIXTURES), "--scene", "herzjesu_p8", "--input", "database",
                             "--seeds", "0", "1"]) == 0
    out = capsys.readouterr().out
    swaps = [float(line.split(" | ")[-1].rstrip(" |")) for line in out.split("## loss")[0].splitlines()
             if line.startswith("| (")]
    assert len(swaps) >= 10 and max(swaps) - min(swaps) < 0.002
    rows = [line.split(" | ") for line in out.split("## loss")[1].splitlines() if line.startswith("| 0 ")
            or line.startswith("| 1 ")]
    assert len(rows) == 2
    for cells in rows:
        averaged, default, tight, wide, cauchy, from_gt = map(float, cells[1:7])
        assert default < averaged and max(default, tight, wide, cauchy, from_gt) < 0.025
        assert abs(from_gt - default) < 0.001  # the start does not matter on clean data


# ============================================================================ probe_weak_pairs

probe_weak = load_script("probe_weak_pairs")


def test_probe_weak_pairs_on_fixture(capsys):
    """Pairs dropped only for their count (--min-inliers 300 on the clean fixture) are good
    pairs: most of their matches lie on the global and the GT epipolar geometry (castle-P19's
    database: 220 of 2552, scripts/research/README.md)."""
    assert probe_weak.main(["--root", str(FIXTURES), "--scene", "herzjesu_p8", "--input", "database",
                            "--min-inliers", "300"]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and line[2].isdigit()]
    pairs, matches, near_global, near_both, used = map(int, row[0].strip("| ").split(" | "))
    assert pairs > 0 and used > matches
    assert near_global >= 0.8 * matches and near_both >= 0.95 * near_global


# ============================================================================ probe_grrm_simulation

probe_simulation = load_script("probe_grrm_simulation")


def test_probe_grrm_simulation_on_a_small_scene(capsys):
    """Every row on a 12-view linear scene; GRRM's end does not depend on its start there (from
    the averaged and from the GT rotations), and holding t_ij at the GT directions helps."""
    assert probe_simulation.main(["--views", "12", "--points-per-view", "60", "--window", "3"]) == 0
    rows = {cells[0]: float(cells[1]) for cells in
            (line.strip("| \n").split(" | ") for line in capsys.readouterr().out.splitlines()[2:])}
    assert len(rows) == 9 and all(0.0 < value < 0.2 for value in rows.values())
    assert abs(rows["GRRM from the GT rotations"] - rows["GRRM"]) < 0.002
    assert rows["GRRM, t_ij held at the GT directions"] < rows["GRRM"]
