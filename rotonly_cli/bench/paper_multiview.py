"""Multi-view Monte-Carlo benchmark (rotation_only.tex §"Multi-view Rotation Estimation",
Fig. GRRM_eval): circular / square / linear / outward set-ups × noise levels ×
(Chatterjee, ROBA, GRRM, pycolmap rotation averaging).

Per trial: :func:`rotonly_cli.simulation.layout_scenes.simulate_multiview` (initial relative poses by
5-point RANSAC on the noisy matches, the paper's initialiser); edges = pairs whose RANSAC
succeeded. Chatterjee = ℓ½ L1RA + IRLS on those relative rotations; ROBA and GRRM start from
Chatterjee's rotations, as in the paper ("following ROBA"); pycolmap rotation averaging is an
external reference on the same relative rotations. Error: mean geodesic rotation error (deg)
after the best global rotation (rotation-only L2 alignment).
"""

from __future__ import annotations

import time

import numpy as np

from rotonly_cli.bench.common import fmt, markdown_table, parallel_map, plot_curves, result_dir, stats, write_json

SETUPS = ("circular", "square", "linear", "outward")
METHODS = ("Chatterjee", "ROBA", "GRRM", "pycolmap RA")


def scene_arrays(scene, view_ids: list[int] | None = None, keys: list | None = None):
    """(view_ids, edge_views (E, 2), EdgeBatch, obs_ids (M, 2), R_j_from_i (E, 3, 3), counts (E,)) of the
    pairs of an SfMScene that carry a relative rotation (and ≥ 6 matches)."""
    from rotonly_cli.geometry import pairwise as pg

    if view_ids is None:
        view_ids = sorted(scene.views)
    index = {v: k for k, v in enumerate(view_ids)}
    sizes = np.array([len(scene.normalized.get(v, ())) for v in view_ids], dtype=np.int64)
    offset = np.concatenate([[0], np.cumsum(sizes)])
    if keys is None:
        keys = [k for k, p in sorted(scene.pairs.items()) if p.R_j_from_i is not None and len(p.matches) >= 6
                and k[0] in index and k[1] in index]
    xs_i, xs_j, ids, R_rel = [], [], [], []
    for i, j in keys:
        pair = scene.pairs[(i, j)]
        xs_i.append(scene.normalized[i][pair.matches[:, 0]])
        xs_j.append(scene.normalized[j][pair.matches[:, 1]])
        ids.append(np.column_stack([offset[index[i]] + pair.matches[:, 0], offset[index[j]] + pair.matches[:, 1]]))
        R_rel.append(pair.R_j_from_i)
    batch = pg.pack_edges(xs_i, xs_j)
    edge_views = np.array([[index[i], index[j]] for i, j in keys], dtype=np.int64).reshape(-1, 2)
    obs_ids = np.concatenate(ids) if ids else np.zeros((0, 2), dtype=np.int64)
    return (view_ids, edge_views, batch, obs_ids, np.asarray(R_rel, dtype=float).reshape(-1, 3, 3),
            batch.counts.copy())


def global_methods(num_views: int, edge_views: np.ndarray, batch, obs_ids: np.ndarray, R_rel: np.ndarray,
                   counts: np.ndarray, methods=METHODS) -> tuple[dict, dict]:
    """Run the global rotation methods; returns ({method: R (n, 3, 3)}, {method: seconds})."""
    from rotonly_cli.baselines.references import chatterjee, pycolmap_rotation_averaging
    from rotonly_cli.baselines.roba import roba
    from rotonly_cli.geometry.grrm import GRRMOptions, optimize_global_rotations

    rotations, seconds = {}, {}
    start = time.perf_counter()
    R_chat = chatterjee(num_views, edge_views, R_rel)
    seconds["Chatterjee"] = time.perf_counter() - start
    rotations["Chatterjee"] = R_chat
    registered = np.all(np.isfinite(R_chat), axis=(1, 2))
    if not np.all(registered):  # ROBA/GRRM on the component of the gauge view; others stay NaN
        keep = registered[edge_views[:, 0]] & registered[edge_views[:, 1]]
        new_index = np.cumsum(registered) - 1
        sub_views = new_index[edge_views[keep]]
        sub_batch = batch.subset(np.flatnonzero(keep))
        obs_keep = np.repeat(keep, batch.counts)
        sub, sub_s = global_methods(int(registered.sum()), sub_views, sub_batch, obs_ids[obs_keep], R_rel[keep],
                                    counts[keep], methods=methods)
        for m, R_sub in sub.items():
            full = np.full((num_views, 3, 3), np.nan)
            full[registered] = R_sub
            rotations[m] = full
        rotations["Chatterjee"] = R_chat
        seconds.update({m: v for m, v in sub_s.items() if m != "Chatterjee"})
        return rotations, seconds
    if "ROBA" in methods:
        start = time.perf_counter()
        rotations["ROBA"] = roba(R_chat, edge_views, batch).R_cam_from_world
        seconds["ROBA"] = time.perf_counter() - start
    if "GRRM" in methods:
        start = time.perf_counter()
        rotations["GRRM"] = optimize_global_rotations(R_chat, edge_views, batch, obs_ids, fixed_view=0,
                                                      options=GRRMOptions()).R_cam_from_world
        seconds["GRRM"] = time.perf_counter() - start
    if "pycolmap RA" in methods:
        start = time.perf_counter()
        rotations["pycolmap RA"] = pycolmap_rotation_averaging(num_views, edge_views, R_rel, num_matches=counts)
        seconds["pycolmap RA"] = time.perf_counter() - start
    return rotations, seconds


def aligned_errors(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Per-view geodesic error (deg) after rotation-only L2 alignment; NaN views left out."""
    from rotonly_cli.geometry.alignment import rotation_errors_after_alignment

    ok = np.all(np.isfinite(R_est), axis=(1, 2))
    if ok.sum() < 2:
        return np.full(len(R_est), np.nan)
    out = np.full(len(R_est), np.nan)
    out[ok] = rotation_errors_after_alignment(R_est[ok], R_gt[ok])[0]
    return out


def run_trial(args: tuple) -> dict:
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    setup, noise_px, seed, sizes = args
    problem = simulate_multiview(setup, noise_px=noise_px, rng=seed, init="ransac", **sizes)
    view_ids, edge_views, batch, obs_ids, R_rel, counts = scene_arrays(problem.scene)
    R_gt = np.stack([problem.gt_poses[v].R_cam_from_world for v in view_ids])
    with np.errstate(all="ignore"):
        rotations, seconds = global_methods(len(view_ids), edge_views, batch, obs_ids, R_rel, counts)
    R_pair_gt = R_gt[edge_views[:, 1]] @ np.swapaxes(R_gt[edge_views[:, 0]], 1, 2)
    from rotonly_cli.bench.common import error_deg

    return dict(errors={m: float(np.nanmean(aligned_errors(R, R_gt))) for m, R in rotations.items()},
                seconds=seconds, num_edges=len(edge_views), num_matches=int(batch.counts.sum()),
                relative_error_deg=float(error_deg(R_rel, R_pair_gt).mean()))


def run(out_dir, setups=SETUPS, noise_levels=(0.1, 1.0, 2.0, 5.0, 10.0), trials: int = 10, num_views: int = 30,
        num_points: int = 3000, window: int = 5, seed: int = 0, jobs: int = 1, progress: bool = True
        ) -> tuple[str, dict]:
    sizes = dict(num_views=num_views, num_points=num_points, window=window)
    started = time.perf_counter()
    tasks = [(setup, float(noise), seed + 7919 * s + 104_729 * k + int(noise * 1000), sizes)
             for s, setup in enumerate(setups) for k, noise in enumerate(noise_levels) for _ in range(1)]
    tasks = [(setup, noise, base + 1_000_003 * t, sz) for setup, noise, base, sz in tasks for t in range(trials)]
    results = parallel_map(run_trial, tasks, jobs, "multiview", progress)
    rows = []
    for _s, setup in enumerate(setups):
        for noise in noise_levels:
            cell = [r for (st, nz, _, _), r in zip(tasks, results) if st == setup and nz == float(noise)]
            rows.append(dict(setup=setup, noise_px=float(noise), trials=len(cell),
                             edges=float(np.mean([c["num_edges"] for c in cell])),
                             relative_error_deg=float(np.mean([c["relative_error_deg"] for c in cell])),
                             methods={m: {**stats([c["errors"][m] for c in cell]),
                                          "seconds": float(np.mean([c["seconds"][m] for c in cell]))}
                                      for m in METHODS}))
    head = ["set-up", "noise px", "edges", "5-pt rel. err"] + [f"{m} mean" for m in METHODS] + \
        ["best of Chatterjee/ROBA/GRRM"] + [f"{m} s" for m in METHODS]
    lines = []
    for r in rows:
        ours = {m: r["methods"][m]["mean"] for m in ("Chatterjee", "ROBA", "GRRM")}
        best = min(ours, key=lambda m: ours[m] if np.isfinite(ours[m]) else np.inf)
        lines.append([r["setup"], f"{r['noise_px']:g}", f"{r['edges']:.0f}", fmt(r["relative_error_deg"])]
                     + [fmt(r["methods"][m]["mean"]) for m in METHODS] + [best]
                     + [f"{r['methods'][m]['seconds']:.2f}" for m in METHODS])
    table = (f"# rotonly bench multiview\n\n{trials} trials per cell; {num_views} views, {num_points} points, "
             f"pairs within {window} views along the trajectory; initial relative poses by 5-point RANSAC; "
             f"mean rotation error (deg) over views after rotation-only alignment, averaged over trials; "
             f"time in seconds per problem.\n\n" + markdown_table(head, lines) + "\n")
    config = dict(setups=list(setups), noise_levels_px=list(noise_levels), trials=trials, seed=seed, **sizes,
                  noise_model="magnitude U(0, n) px", focal_px=800.0, image_size=[960, 960])
    payload = dict(config=config, rows=rows, seconds=time.perf_counter() - started)
    with result_dir(out_dir) as tmp:
        (tmp / "table.md").write_text(table)
        write_json(tmp / "results.json", payload)
        panels = {setup: {m: ([r["noise_px"] for r in rows if r["setup"] == setup],
                              [r["methods"][m]["mean"] for r in rows if r["setup"] == setup]) for m in METHODS}
                  for setup in setups}
        plot_curves(tmp / "error_vs_noise.png", panels, "noise (px)", "mean rotation error (deg)",
                    "Multi-view global rotation error vs noise")
    return table, payload
