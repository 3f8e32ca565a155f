#!/usr/bin/env python
"""Probe: does GRRM's error on a Strecha input come from one edge, from the matches it leaves
out, from the keypoints' scale, or from the per-edge translations?

Runs rotonly's chain in-process on one Strecha scene (database or OpenMVG input) up to the
averaged rotations (load, identify, refine, average), then prints four tables:

* ``edges``: per REGULAR edge that enters GRRM, its TRRM and its GRRM relative-rotation
  error against the GT (deg), and GRRM's mean error with that edge left out;
* ``tracks``: GRRM from the same start with every edge's matches completed from the tracks of
  all GRRM edges. eq:GRRMRes1 sums over E_ik, the edges through view i that *match*
  observation k; with tracks, every edge whose two views both see the track counts. Rows:
  the edges as loaded, completed, completed and filtered (added matches at most the edge's own
  90 % epipolar-angle quantile at its TRRM pose), and completed plus new edges for view pairs
  that share at least 30 tracks but have no edge;
* ``scale`` (OpenMVG input): the keypoints' residuals against the GT (tracks triangulated with
  the GT cameras) by SIFT scale (the third column of the ``.feat`` files): mean offset and RMS
  in pixels. A scale-dependent offset would be a detector bias;
* ``translations``: GRRM's per-edge t_ij (Pˢ's null vector at GRRM's rotations) against the
  GT direction R_j (c_i - c_j), and GRRM from the same start with every t_ij held fixed: at
  the GT directions (an oracle: how much of the rotation error the translations carry), at
  the directions of LiGT's centres from GRRM's rotations, and at the directions of centres
  averaged from Pˢ's own directions (:func:`average_directions`), each re-computed for three
  rounds.

    python scripts/research/probe_grrm_structure.py --root DATA/strecha --scene Herz-Jesus-P8 --input openmvg
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

SCALE_BINS = (0.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 7.0, 10.0, np.inf)
TABLES = ("edges", "tracks", "scale", "translations")


def completed_graph(graph, edges: list[int], new_edge_min: int | None = None, quantile: float | None = None,
                    normalized: dict | None = None):
    """Copy of ``graph`` whose edges ``edges`` hold every match their tracks imply (consistent
    tracks of those edges' matches). ``quantile``: keep an added match only if its epipolar
    angle at the edge's pose is at most that quantile of the edge's own matches (needs
    ``normalized``). ``new_edge_min``: also add REGULAR edges for view pairs without one that
    share at least this many tracks (pose: none yet, GRRM takes it from the rotations).
    Returns (graph, matches added to existing edges, new edges)."""
    from rotonly_cli.geometry.tracks import build_tracks, pairs_within_tracks
    from rotonly_cli.scene.view_graph import Edge

    out = copy.deepcopy(graph)
    chosen = [out.edges[k] for k in edges]
    tracks = build_tracks([(e.i, e.j) for e in chosen], [e.matches for e in chosen])
    a, b = pairs_within_tracks(tracks.offsets)  # sorted by view inside a track: view[a] < view[b]
    pair = tracks.view[a] * (tracks.view.max() + 1) + tracks.view[b]
    order = np.argsort(pair, kind="stable")
    cuts = np.flatnonzero(np.diff(pair[order])) + 1
    by_views = {(e.i, e.j): e for e in chosen}
    added, new_edges = 0, []
    for part in np.split(order, cuts):
        i, j = int(tracks.view[a[part[0]]]), int(tracks.view[b[part[0]]])
        implied = np.stack([tracks.feature[a[part]], tracks.feature[b[part]]], axis=1)
        edge = by_views.get((i, j))
        if edge is None:
            if new_edge_min is not None and len(implied) >= new_edge_min:
                new = Edge(i=i, j=j, R_j_from_i=np.eye(3), t_dir=np.zeros(3), matches=implied, pose_source="tracks")
                new.scene_kind = "REGULAR"
                out.edges.append(new)
                new_edges.append((i, j, len(implied)))
            continue
        width = int(max(implied.max(), edge.matches.max())) + 1
        known = edge.matches[:, 0] * width + edge.matches[:, 1]
        extra = implied[~np.isin(implied[:, 0] * width + implied[:, 1], known)]
        if quantile is not None and len(extra):
            angle = epipolar_angles(edge, normalized, extra)
            extra = extra[angle <= np.quantile(epipolar_angles(edge, normalized, edge.matches), quantile)]
        edge.matches = np.concatenate([edge.matches, extra])
        added += len(extra)
    return out, added, new_edges


def epipolar_angles(edge, normalized: dict, matches: np.ndarray) -> np.ndarray:
    """|sin| of the angle between the bearing in view j and the epipolar plane of the bearing
    in view i at the edge's (R_j_from_i, t_dir)."""
    def bearings(view: int, rows: np.ndarray) -> np.ndarray:
        x = np.column_stack([normalized[view][rows], np.ones(len(rows))])
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    normal = np.cross(edge.t_dir, bearings(edge.i, matches[:, 0]) @ edge.R_j_from_i.T)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return np.abs(np.einsum("nk,nk->n", normal, bearings(edge.j, matches[:, 1])))


def average_directions(n: int, edge_views: np.ndarray, d_world: np.ndarray, rounds: int = 10) -> np.ndarray:
    """Centres (n, 3) whose baselines c_i - c_j follow the unit directions ``d_world`` (E, 3):
    min Σ_e w_e ‖[d_e]x (c_i - c_j)‖² with c_0 = 0 and ‖c‖ = 1 (smallest singular vector),
    reweighted by w_e = 1 / ‖c_i - c_j‖² so that the cross product measures an angle
    (Govindu's iterative linear translation averaging); dense, for scenes of a few views."""
    from rotonly_cli.geometry import so3

    hat = so3.hat(d_world)  # (E, 3, 3)
    E = len(edge_views)
    rows = np.arange(3 * E).reshape(E, 3)
    weights = np.ones(E)
    C = np.zeros((n, 3))
    for _ in range(rounds):
        A = np.zeros((3 * E, 3 * n))
        root = np.sqrt(weights)[:, None, None] * hat
        for side, sign in ((0, 1.0), (1, -1.0)):
            cols = 3 * edge_views[:, side][:, None] + np.arange(3)
            A[rows[:, :, None], cols[:, None, :]] += sign * root
        C = np.concatenate([np.zeros(3), np.linalg.svd(A[:, 3:], full_matrices=False)[2][-1]]).reshape(n, 3)
        baseline = C[edge_views[:, 0]] - C[edge_views[:, 1]]
        if np.einsum("ek,ek->", baseline, d_world) < 0:
            C, baseline = -C, -baseline
        weights = 1.0 / np.maximum(np.einsum("ek,ek->e", baseline, baseline), 1e-18)
    return C


def main(argv: list[str] | None = None) -> int:
    from strecha_gt import add_scene_arguments, averaged_run, gt_poses_for, gt_track_residuals, scene_input

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser)
    parser.add_argument("--tables", nargs="+", choices=TABLES, default=list(TABLES))
    args = parser.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING)  # the stages log at INFO; this prints tables

    from rotonly_cli.geometry import kernels, so3
    from rotonly_cli.geometry.alignment import rotation_errors_after_alignment
    from rotonly_cli.pipeline import STAGE_FUNCTIONS
    from rotonly_cli.scene.view_graph import edge_batch, regular_edges
    from rotonly_cli.stages.load import focal_length
    from rotonly_cli.stages.optimize import optimize_graph
    from rotonly_cli.stages.translate import translate_graph

    from grrm_fixed_translations import optimize_graph_with_translations

    input_path, gt = scene_input(parser, args)
    run = averaged_run(input_path)
    graph, scene = run.graph, run.scene
    view_ids = graph.view_ids()
    row = {v: r for r, v in enumerate(view_ids)}
    R_gt, C_gt = gt_poses_for(gt, scene, view_ids)
    start = run.rotations.copy()

    def grrm(g, translations: dict | None = None, R_start: np.ndarray = start) -> np.ndarray:
        if translations is not None:  # every t_ij held (grrm_fixed_translations.py)
            return optimize_graph_with_translations(g, scene.normalized, R_start, translations)
        return optimize_graph(g, scene.normalized, R_start)[0]

    def directions(R: np.ndarray, C: np.ndarray, ks: list[int]) -> dict[int, np.ndarray]:
        # t_ij = R_j (c_i - c_j): camera j's axes, x_j ~ R_ij x_i + t_ij
        return {k: R[row[graph.edges[k].j]] @ (C[row[graph.edges[k].i]] - C[row[graph.edges[k].j]]) for k in ks}

    def line(label: str, R: np.ndarray, extra: str = "") -> str:
        """A table row: label, one extra cell, GRRM's mean and per-camera errors."""
        e = errors(R)
        return f"| {label} | {extra} | {e.mean():.4f} | {' '.join(f'{x:.3f}' for x in e)} |"

    def angles_deg(unit_a: np.ndarray, unit_b: np.ndarray) -> np.ndarray:
        return np.degrees(np.arccos(np.clip(np.einsum("ek,ek->e", unit_a, unit_b), -1.0, 1.0)))

    def errors(R: np.ndarray) -> np.ndarray:
        return rotation_errors_after_alignment(R, R_gt)[0]

    def relative_error(R_j_from_i: np.ndarray, i: int, j: int) -> float:
        truth = R_gt[row[j]] @ R_gt[row[i]].T
        return float(np.degrees(so3.geodesic_angle(R_j_from_i[None], truth[None]))[0])

    R_grrm = grrm(graph)
    base = errors(R_grrm)
    print(f"{args.scene}, {args.input} input: L1-IRLS start {errors(start).mean():.4f} deg, GRRM {base.mean():.4f} "
          f"deg (per camera {' '.join(f'{e:.3f}' for e in base)})\n")
    edges = regular_edges(graph)
    if "edges" in args.tables:
        print("| edge | matches | TRRM relative error (deg) | GRRM relative error (deg) | GRRM without it (deg) |")
        print("|---|---|---|---|---|")
        for k in edges:
            edge = graph.edges[k]
            status = edge.status
            edge.status = "filtered"  # GRRM takes only active edges
            try:
                without = errors(grrm(graph)).mean()
            finally:
                edge.status = status
            R_ij = R_grrm[row[edge.j]] @ R_grrm[row[edge.i]].T
            print(f"| {edge.i}-{edge.j} | {edge.num_inliers} | {relative_error(edge.R_j_from_i, edge.i, edge.j):.4f} | "
                  f"{relative_error(R_ij, edge.i, edge.j):.4f} | {without:.4f} |", flush=True)
        print()
    if "tracks" in args.tables:
        print("| matches of the GRRM edges | matches | GRRM (deg) | GRRM per camera (deg) |")
        print("|---|---|---|---|")
        loaded = sum(graph.edges[k].num_inliers for k in edges)
        print(line("as loaded", R_grrm, str(loaded)))
        variants = {"completed from the tracks": {},
                    "completed, added matches within the edge's 90 % epipolar quantile":
                        {"quantile": 0.9, "normalized": scene.normalized},
                    "completed, plus new edges (>= 30 tracks)": {"new_edge_min": 30}}
        for label, kwargs in variants.items():
            completed, added, new_edges = completed_graph(graph, edges, **kwargs)
            if new_edges:
                label += " " + ", ".join(f"{i}-{j}" for i, j, _ in new_edges)
            total = loaded + added + sum(m for _, _, m in new_edges)
            print(line(label, grrm(completed), str(total)), flush=True)
        print()
    if "translations" in args.tables:
        t_gt = directions(R_gt, C_gt, edges)
        batch = edge_batch(graph, scene.normalized, edges)
        views = np.array([[row[graph.edges[k].i], row[graph.edges[k].j]] for k in edges])
        t_ps = kernels.trrm_normal_equations(R_grrm[views[:, 1]] @ np.swapaxes(R_grrm[views[:, 0]], 1, 2), batch,
                                             with_jacobian=False).t
        truth = np.stack([t_gt[k] / np.linalg.norm(t_gt[k]) for k in edges])
        angle = angles_deg(t_ps, truth)
        print("| per-edge t_ij in GRRM | t_ij error against the GT direction (deg): mean / median / max | GRRM (deg) "
              "| GRRM per camera (deg) |")
        print("|---|---|---|---|")
        print(line("Pˢ null vector (the paper)", R_grrm,
                   f"{angle.mean():.3f} / {np.median(angle):.3f} / {angle.max():.3f}"))
        print(line("held at the GT direction", grrm(graph, t_gt), "0"), flush=True)
        def ligt_centres(R: np.ndarray) -> np.ndarray:
            return translate_graph(graph, scene.normalized, R)[0]

        def averaged_centres(R: np.ndarray) -> np.ndarray:
            t = kernels.trrm_normal_equations(R[views[:, 1]] @ np.swapaxes(R[views[:, 0]], 1, 2), batch,
                                              with_jacobian=False).t
            return average_directions(len(view_ids), views, np.einsum("eba,eb->ea", R[views[:, 1]], t))

        for label, centres in (("LiGT's directions", ligt_centres),
                               ("directions of centres averaged from Pˢ's", averaged_centres)):
            R = R_grrm
            for round_ in range(1, 4):
                held = directions(R, centres(R), edges)
                # the centres are in GRRM's world frame: compare directions in camera axes
                unit = np.stack([held[k] / np.linalg.norm(held[k]) for k in edges])
                angle = angles_deg(unit, truth)
                R = grrm(graph, held, R)
                print(line(f"held at {label} from the rotations before, round {round_}", R,
                           f"{angle.mean():.3f} / {np.median(angle):.3f} / {angle.max():.3f}"), flush=True)
        print()
    if "scale" in args.tables and args.input == "openmvg":
        for stage in ("optimize", "translate", "triangulate"):
            STAGE_FUNCTIONS[stage](run)
        tracks = gt_track_residuals(run.structure, view_ids, scene.normalized, R_gt, C_gt)
        view_row, keypoint = tracks["view_row"], tracks["keypoint"]
        scale = np.empty(len(keypoint))
        for r, v in enumerate(view_ids):
            feat = np.loadtxt(input_path.parent / (Path(scene.views[v].name).stem + ".feat"), ndmin=2)
            rows = view_row == r
            scale[rows] = feat[keypoint[rows], 2]
        focal = np.array([focal_length(scene.intrinsics[scene.views[v].intrinsics_id]) for v in view_ids])[view_row]
        residual = (tracks["observed"] - tracks["projected"]) * focal[:, None]
        ok = np.isfinite(residual).all(axis=1) & (np.linalg.norm(residual, axis=1) < 3.0)
        print(f"| SIFT scale | observations | mean dx (px) | mean dy (px) | RMS (px) |  ({ok.sum()} of {len(ok)} "
              "observations within 3 px of the GT)")
        print("|---|---|---|---|---|")
        which = np.digitize(scale, SCALE_BINS)
        for b in range(1, len(SCALE_BINS)):
            m = ok & (which == b)
            if m.sum():
                print(f"| [{SCALE_BINS[b - 1]:g}, {SCALE_BINS[b]:g}) | {m.sum()} | {residual[m, 0].mean():+.4f} | "
                      f"{residual[m, 1].mean():+.4f} | {np.sqrt((residual[m] ** 2).sum(axis=1).mean()):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
