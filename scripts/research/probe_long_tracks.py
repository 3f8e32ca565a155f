"""Why rotonly's error grows over the global mapper's on long tracks (issue 51, item 2).

Measures, on a simulated COLMAP database (``rotonly simulate multiview --format colmap``)
and its ground truth, where the rotation and position error of ``rotonly run`` come from,
one thing changed per row (mean errors after the best global rotation / similarity):

* ``start``: the L1-IRLS average of the TRRM edges (GRRM's start);
* ``grrm``: GRRM as in the product, and GRRM started from the GT rotations, with both costs
  under the default run's loss scale (is the start or the objective's optimum to blame?);
* ``loss``: GRRM without a robust loss, and with a wider one (``loss_scale_factor`` 3);
* ``held``: every edge's t_ij held at its GT direction (grrm_fixed_translations: an oracle);
* ``ligt``: LiGT's positions from GRRM's rotations and from the GT rotations (what LiGT
  costs by itself; no BA; ``ligt_gt``: from the GT rotations only);
* ``weights``: GRRM with the per-observation sum of its pair residuals weighted otherwise
  (``--weightings``; see :func:`weighted_system`);
* ``track_edges``: GRRM on the graph completed with the view pairs that were never matched
  but share tracks (:func:`with_track_edges`: the pairs a BA links through its points; the
  matcher's window leaves them out), from the same averaged start (``--track-edges-combined``:
  without a robust loss and with V_g x k instead: the three levers together).

The run after the average stage is pickled in ``--cache`` (the load stage alone is a minute
at 200 views), and the GT poses by name beside it.

    python scripts/research/probe_long_tracks.py --database /work/scale/v200/database.db \\
        --gt /work/scale/v200/gt/sfm_data.json --cache /tmp/lt/v200 --rows start grrm loss held ligt
"""

from __future__ import annotations

import argparse
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from probe_grrm_simulation import edge_directions

import grrm_fixed_translations as fixed


def cached_run(database: Path, cache: Path):
    """The run after load, identify, refine and average (pickled in ``cache``)."""
    path = cache / "average.pkl"
    if path.exists():
        with open(path, "rb") as f:
            return pickle.load(f)
    from rotonly_cli.options import RunOptions
    from rotonly_cli.pipeline import run_in_memory

    run = run_in_memory(database, RunOptions(jobs=1, progress=False), stages=("load", "identify", "refine", "average"))
    cache.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump(run, f, protocol=5)
    return run


def cached_gt(gt: Path, cache: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{image name: (R_cam_from_world, centre)} of the ground truth (cached as gt.npz)."""
    path = cache / "gt.npz"
    if not path.exists():
        from rotonly_cli.pipeline import load_ground_truth

        scene = load_ground_truth(gt)
        ids = list(scene.poses)
        np.savez(path, names=np.array([scene.views[v].name for v in ids]),
                 R=np.stack([scene.poses[v].R_cam_from_world for v in ids]),
                 C=np.stack([scene.poses[v].center for v in ids]))
    data = np.load(path)
    return {str(n): (R, C) for n, R, C in zip(data["names"], data["R"], data["C"])}


def rotation_error(R: np.ndarray, R_gt: np.ndarray) -> float:
    from rotonly_cli.geometry import alignment

    return float(alignment.rotation_errors_after_alignment(R, R_gt)[0].mean())


def position_error(C: np.ndarray, C_gt: np.ndarray) -> float:
    from rotonly_cli.geometry import alignment

    ok = np.all(np.isfinite(C), axis=1)
    s, R, t = alignment.umeyama(C[ok], C_gt[ok], with_scale=True)
    return float(np.linalg.norm(C_gt[ok] - alignment.apply_similarity(C[ok], s, R, t), axis=1).mean())


def weighted_system(kind: str):
    """A GRRMSystem whose per-observation residual V_g = Σ ω_c r_c / Σ ω_c is scaled by a factor of
    its contributions' count k_g (the edges through the observation): ``sqrt_k`` multiplies V_g by
    √k (each observation then weighs like k independent pair residuals would: the variance of an
    average of k terms falls as 1/k), ``k`` by k. Only the residuals' scale changes, per
    observation; the loss scale is re-measured at the start, as in the product."""
    from rotonly_cli.geometry.grrm import GRRMSystem

    power = {"sqrt_k": 0.5, "k": 1.0}[kind]

    class Weighted(GRRMSystem):
        def _block_terms(self, part, table, with_jacobian):
            for blk, V, S, B in super()._block_terms(part, table, with_jacobian):
                s0, s1, g0, g1 = blk
                f = part.sizes[g0:g1].astype(float) ** power
                V = V * f
                if B is not None:
                    B = B * np.repeat(f, part.sizes[g0:g1])
                yield blk, V, S, B

    return Weighted


def with_track_edges(run, min_shared: int = 30):
    """A copy of the run whose graph has, besides its edges, one REGULAR edge per unmatched view
    pair sharing at least ``min_shared`` tracks (tracks of the active REGULAR edges' matches),
    its matches the tracks' keypoints, its rotation from the run's (averaged) rotations.
    GT-free: only the matches' transitive closure."""
    import copy

    from rotonly_cli.geometry.tracks import build_tracks, pairs_within_tracks
    from rotonly_cli.scene.view_graph import Edge, regular_edges, view_index

    graph = run.graph.copy()
    edges = regular_edges(graph)
    tracks = build_tracks([(graph.edges[k].i, graph.edges[k].j) for k in edges],
                          [graph.edges[k].matches for k in edges])
    a, b = pairs_within_tracks(tracks.offsets)
    vi, vj = tracks.view[a], tracks.view[b]  # vi < vj (sorted by view within a track)
    fi, fj = tracks.feature[a], tracks.feature[b]
    existing = {(graph.edges[k].i, graph.edges[k].j) for k in edges}
    key = vi * (int(vj.max()) + 1) + vj
    order = np.argsort(key, kind="stable")
    key, vi, vj, fi, fj = key[order], vi[order], vj[order], fi[order], fj[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(key)]
    index = view_index(graph)
    R = run.rotations
    kind = graph.edges[edges[0]].scene_kind
    added = 0
    for s0, s1 in zip(starts, ends):
        i, j = int(vi[s0]), int(vj[s0])
        if (i, j) in existing or s1 - s0 < min_shared:
            continue
        graph.edges.append(Edge(i=i, j=j, R_j_from_i=R[index[j]] @ R[index[i]].T, t_dir=np.zeros(3),
                                matches=np.stack([fi[s0:s1], fj[s0:s1]], axis=1).astype(np.int64),
                                pose_source="tracks", scene_kind=kind))
        added += 1
    out = copy.copy(run)
    out.graph = graph
    return out, added, int(sum(graph.edges[k].num_inliers for k in edges))


def grrm(run, start: np.ndarray, options=None, system=None) -> tuple[np.ndarray, dict]:
    from rotonly_cli.geometry.grrm import solve
    from rotonly_cli.stages.optimize import optimize_graph

    options = options or run.options.optimize
    original = solve.GRRMSystem
    if system is not None:
        solve.GRRMSystem = system
    try:
        return optimize_graph(run.graph, run.scene.normalized, start, options)
    finally:
        solve.GRRMSystem = original


def cost_at(run, R: np.ndarray, scale: float, options=None, system=None) -> float:
    options = replace(options or run.options.optimize, loss_scale=scale, max_iterations=0,
                      epipolar_max_iterations=0)
    return float(grrm(run, R, options, system)[1]["cost_before"])


def loss_scale(run, R: np.ndarray, options=None, system=None) -> float:
    """The loss scale GRRM picks at ``R`` (factor x 1.4826 x median ‖V‖)."""
    from rotonly_cli.geometry.grrm import solve
    from rotonly_cli.stages.optimize import grrm_inputs

    options = options or run.options.optimize
    inputs = grrm_inputs(run.graph, run.scene.normalized, R)
    index = {v: k for k, v in enumerate(run.graph.view_ids())}
    R0 = np.stack([R[index[v]] for v in inputs.views])
    original = solve.GRRMSystem
    if system is not None:
        solve.GRRMSystem = system
    try:
        V = solve.grrm_residuals(R0, inputs.edge_views, inputs.matches, inputs.obs_ids, False, options.residual)[0]
    finally:
        solve.GRRMSystem = original
    return float(options.loss_scale_factor * 1.4826 * np.median(np.linalg.norm(V, axis=1)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--database", type=Path, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--cache", type=Path, required=True)
    parser.add_argument("--rows", nargs="+", default=["start", "grrm", "loss", "held", "ligt"],
                        choices=("start", "grrm", "loss", "held", "ligt", "ligt_gt", "weights", "track_edges"))
    parser.add_argument("--weightings", nargs="+", default=["sqrt_k"], choices=("sqrt_k", "k"))
    parser.add_argument("--track-edges-combined", action="store_true",
                        help="track_edges with no robust loss and V_g x k (the three levers together)")
    args = parser.parse_args(argv)
    from rotonly_cli.stages.translate import translate_graph

    t0 = time.perf_counter()
    run = cached_run(args.database, args.cache)
    gt = cached_gt(args.gt, args.cache)
    names = [run.graph.views[v].name for v in run.graph.view_ids()]
    R_gt = np.stack([gt[n][0] for n in names])
    C_gt = np.stack([gt[n][1] for n in names])
    print(f"# {args.database}: {len(names)} views, {len(run.graph.edges)} edges ({time.perf_counter() - t0:.0f} s)",
          flush=True)

    def row(label, value, extra=""):
        print(f"| {label} | {value} | {extra} |", flush=True)

    averaged = run.rotations
    default = None
    if "start" in args.rows:
        row("L1-IRLS average (GRRM's start)", f"{rotation_error(averaged, R_gt):.5f}")
    saved = args.cache / "grrm.npy"  # the product's GRRM rotations (the ligt rows reuse them)
    if "grrm" in args.rows or ("ligt" in args.rows and not saved.exists()):
        default, report = grrm(run, averaged)
        np.save(saved, default)
        scale = loss_scale(run, averaged)
        row("GRRM (product)", f"{rotation_error(default, R_gt):.5f}",
            f"{report['iterations']} iterations, cost {report['cost_before']:.6g} -> {report['cost_after']:.6g}, "
            f"scale {scale:.3g}")
    elif "ligt" in args.rows:
        default = np.load(saved)
    if "grrm" in args.rows:
        row("cost at the GT rotations (same scale)", f"{cost_at(run, R_gt, scale):.6g}", "")
        from_gt, report = grrm(run, R_gt, replace(run.options.optimize, loss_scale=scale))
        row("GRRM from the GT rotations (same scale)", f"{rotation_error(from_gt, R_gt):.5f}",
            f"{report['iterations']} iterations, cost {report['cost_before']:.6g} -> {report['cost_after']:.6g}")
    if "loss" in args.rows:
        for label, opts in (("no robust loss", replace(run.options.optimize, loss="none")),
                            ("loss_scale_factor 3", replace(run.options.optimize, loss_scale_factor=3.0))):
            R, report = grrm(run, averaged, opts)
            row(f"GRRM, {label}", f"{rotation_error(R, R_gt):.5f}", f"{report['iterations']} iterations")
    if "held" in args.rows:
        held = fixed.optimize_graph_with_translations(run.graph, run.scene.normalized, averaged,
                                                      edge_directions(run.graph, R_gt, C_gt))
        row("GRRM, t_ij held at the GT directions", f"{rotation_error(held, R_gt):.5f}")
    if "weights" in args.rows:
        for kind in args.weightings:
            system = weighted_system(kind)
            R, report = grrm(run, averaged, system=system)
            row(f"GRRM, V_g x k^{ {'sqrt_k': '1/2', 'k': '1'}[kind]}", f"{rotation_error(R, R_gt):.5f}",
                f"{report['iterations']} iterations")
    if "track_edges" in args.rows:
        completed, added, matched = with_track_edges(run)
        total = sum(e.num_inliers for e in completed.graph.edges if e.active)
        if args.track_edges_combined:
            R, report = grrm(completed, averaged, replace(run.options.optimize, loss="none"), weighted_system("k"))
            label = "GRRM on the edges completed from the tracks, no robust loss and V_g x k"
        else:
            R, report = grrm(completed, averaged)
            label = "GRRM on the edges completed from the tracks"
        row(label, f"{rotation_error(R, R_gt):.5f}",
            f"{added} edges added, matches {matched} -> {total}, {report['iterations']} iterations")
    if "ligt" in args.rows or "ligt_gt" in args.rows:
        for label, R in ((("GRRM's", default),) if "ligt" in args.rows else ()) + (("the GT", R_gt),):
            C, _ = translate_graph(run.graph, run.scene.normalized, R, run.options.translate,
                                   focal_px=run.scene.focal_px(run.graph.view_ids()))
            row(f"LiGT positions from {label} rotations", f"{position_error(C, C_gt):.5f}", "position, GT units")
    print(f"# {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
