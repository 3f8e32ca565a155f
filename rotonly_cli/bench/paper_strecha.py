"""Strecha benchmark (rotation_only.tex Tables strecha_results_relativeopt and
strecha_rotation_accuracy; published numbers in algorithms.md §7).

For every scene folder under ``root`` holding ``database.db`` and ``gt_dense_cameras/``:

* Table 1 — two-view: for every verified pair of the COLMAP database (its inlier matches), the
  initial pose is a calibrated 5-point RANSAC re-estimate (OpenCV, 1 px threshold at the scene's
  focal; its inliers kept), then BA / PA / Kneip eigen / Kneip nonlinear / TRRM refine it; error =
  geodesic angle to the GT relative rotation R_j R_iᵀ (deg), mean over pairs.
* Table 2 — global: Chatterjee (ℓ½) on the initial relative rotations, ROBA and GRRM from
  Chatterjee's rotations on the same matches, and the pycolmap global mapper (GLOMAP, K fixed)
  on the database; error = mean geodesic angle after rotation-only L2 alignment to the GT.

Images are matched to GT cameras by file name. The paper's numbers come from full-resolution
images with OpenMVG SIFT matches; the data here is half resolution with COLMAP SIFT, so the
published columns are context, not a target.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from rotonly_cli.bench.common import error_deg, fmt, markdown_table, parallel_map, result_dir, stats, write_json
from rotonly_cli.bench.paper_twoview import METHODS as TWOVIEW_METHODS
from rotonly_cli.bench.paper_twoview import refine_per_edge
from rotonly_cli.bench.results_md import portable_path
from rotonly_cli.errors import InputError

GLOBAL_METHODS = ("Chatterjee", "ROBA", "GRRM", "pycolmap global mapper")

# algorithms.md §7 (a): the paper's tables (deg), keyed by a lower-case scene name
PUBLISHED_TWOVIEW = {
    "herz-jesus-p25": dict(zip(TWOVIEW_METHODS, (0.1663, 0.0806, 0.0827, 0.0801, 0.0953, 0.0657))),
    "herz-jesus-p8": dict(zip(TWOVIEW_METHODS, (0.1641, 0.0502, 0.0525, 0.0514, 0.0680, 0.0497))),
    "castle-p19": dict(zip(TWOVIEW_METHODS, (0.5407, 0.3404, 0.3456, 0.4084, 0.4016, 0.2109))),
    "castle-p30": dict(zip(TWOVIEW_METHODS, (0.5540, 0.2883, 0.3055, 0.3118, 0.3062, 0.2321))),
    "entry-p10": dict(zip(TWOVIEW_METHODS, (0.1511, 0.0800, 0.1077, 0.0794, 0.0915, 0.0598))),
    "fountain-p11": dict(zip(TWOVIEW_METHODS, (0.1099, 0.0567, 0.0566, 0.0571, 0.0667, 0.0561))),
}
PUBLISHED_GLOBAL = {
    "herz-jesus-p25": {"Chatterjee": 0.1063, "ROBA": 0.0632, "GRRM": 0.0510},
    "herz-jesus-p8": {"Chatterjee": 0.0868, "ROBA": 0.0813, "GRRM": 0.0636},
    "castle-p19": {"Chatterjee": 0.3566, "ROBA": 0.1975, "GRRM": 0.1764},
    "castle-p30": {"Chatterjee": 0.3421, "ROBA": 0.2821, "GRRM": 0.1208},
    "entry-p10": {"Chatterjee": 0.0839, "ROBA": 0.0967, "GRRM": 0.0651},
    "fountain-p11": {"Chatterjee": 0.0422, "ROBA": 0.0402, "GRRM": 0.0262},
}


def published_key(scene_name: str) -> str | None:
    """'herzjesu_p8', 'Herz-Jesus-P8' -> 'herz-jesus-p8'."""
    def squash(name: str) -> str:
        return name.lower().replace("-", "").replace("_", "").replace("herzjesus", "herzjesu")

    for key in PUBLISHED_TWOVIEW:
        if squash(key) == squash(scene_name):
            return key
    return None


def find_scenes(root: str | Path) -> list[Path]:
    root = Path(root)
    if not root.is_dir():
        raise InputError("no such folder", path=str(root), field="--root")
    candidates = [root] + sorted(p for p in root.iterdir() if p.is_dir())
    scenes = [p for p in candidates if (p / "database.db").is_file() and (p / "gt_dense_cameras").is_dir()]
    if not scenes:
        raise InputError("no scene folder with database.db and gt_dense_cameras/", path=str(root), field="--root")
    return scenes


def _pair_task(args: tuple) -> dict:
    """5-point re-estimate + per-edge baselines for one pair (a pool task)."""
    from rotonly_cli.simulation.fivepoint import five_point_ransac

    key, x_i, x_j, focal, seed = args
    est = five_point_ransac(x_i, x_j, focal, threshold_px=1.0, seed=seed)
    if not est.success or est.num_inliers < 15:
        return dict(key=key, ok=False)
    x_i, x_j = x_i[est.inlier_mask], x_j[est.inlier_mask]
    rotations, seconds = refine_per_edge(est.R_j_from_i, est.t_direction, x_i, x_j)
    return dict(key=key, ok=True, R_init=est.R_j_from_i, t_init=est.t_direction, x_i=x_i, x_j=x_j,
                rotations=rotations, seconds=seconds, inlier_mask=est.inlier_mask)


def run_scene(folder: Path, jobs: int, progress: bool, with_mapper: bool, max_pairs: int | None, seed: int) -> dict:
    from rotonly_cli import twoview
    from rotonly_cli.baselines.kneip import refine_kneip_eigen
    from rotonly_cli.baselines.references import pycolmap_global_mapper
    from rotonly_cli.bench.paper_multiview import aligned_errors, global_methods
    from rotonly_cli.geometry import pairwise as pg
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.io.strecha import read_strecha_dir

    scene = read_database(folder / "database.db", include_unverified=False)
    gt = read_strecha_dir(folder)
    gt_by_name = {v.name: gt.poses[v.id].R_cam_from_world for v in gt.views.values()}
    view_ids = [v for v in sorted(scene.views) if scene.views[v].name in gt_by_name]
    R_gt = np.stack([gt_by_name[scene.views[v].name] for v in view_ids])
    index = {v: k for k, v in enumerate(view_ids)}
    keys = [k for k in sorted(scene.pairs) if k[0] in index and k[1] in index and len(scene.pairs[k].matches) >= 15]
    if max_pairs is not None:  # neighbours first (by view-index gap): keeps the graph connected
        keys = sorted(sorted(keys, key=lambda k: (index[k[1]] - index[k[0]], k))[:max_pairs])
    focal = float(np.mean(scene.intrinsics[scene.views[view_ids[0]].intrinsics_id].params[:2]))
    tasks = [(k, scene.normalized[k[0]][scene.pairs[k].matches[:, 0]],
              scene.normalized[k[1]][scene.pairs[k].matches[:, 1]], focal, seed + n) for n, k in enumerate(keys)]
    results = [r for r in parallel_map(_pair_task, tasks, jobs, f"{folder.name} pairs", progress) if r["ok"]]
    keys = [r["key"] for r in results]
    R_init = np.stack([r["R_init"] for r in results])
    x_i = [r["x_i"] for r in results]
    x_j = [r["x_j"] for r in results]
    rotations = {"initial": R_init}
    seconds = {"initial": 0.0}
    for name in ("BA", "PA", "Kneip nonlinear"):
        rotations[name] = np.stack([r["rotations"][name] for r in results])
        seconds[name] = float(np.mean([r["seconds"][name] for r in results]))
    start = time.perf_counter()
    with np.errstate(all="ignore"):
        rotations["Kneip eigen"] = refine_kneip_eigen(R_init, pg.pack_edges(x_i, x_j)).rotations
    seconds["Kneip eigen"] = (time.perf_counter() - start) / len(keys)
    start = time.perf_counter()
    rotations["TRRM"] = np.asarray(twoview.refine_rotations(R_init, x_i, x_j).rotations)
    seconds["TRRM"] = (time.perf_counter() - start) / len(keys)
    ii = np.array([index[i] for i, _ in keys])
    jj = np.array([index[j] for _, j in keys])
    R_pair_gt = R_gt[jj] @ np.swapaxes(R_gt[ii], 1, 2)
    twoview_rows = {m: {**stats(error_deg(rotations[m], R_pair_gt)), "ms_per_edge": 1e3 * seconds[m]}
                    for m in TWOVIEW_METHODS}

    # global: the 5-point inliers of every pair, observation ids = view offset + keypoint index
    sizes = np.array([len(scene.normalized[v]) for v in view_ids], dtype=np.int64)
    offset = np.concatenate([[0], np.cumsum(sizes)])
    obs_ids = np.concatenate([np.column_stack([offset[index[i]] + scene.pairs[(i, j)].matches[r["inlier_mask"], 0],
                                               offset[index[j]] + scene.pairs[(i, j)].matches[r["inlier_mask"], 1]])
                              for (i, j), r in zip(keys, results)])
    batch = pg.pack_edges(x_i, x_j)
    edge_views = np.column_stack([ii, jj])
    with np.errstate(all="ignore"):
        global_R, global_s = global_methods(len(view_ids), edge_views, batch, obs_ids, R_init, batch.counts,
                                            methods=("Chatterjee", "ROBA", "GRRM"))
    global_rows = {m: {**stats(aligned_errors(R, R_gt)), "seconds": global_s[m]} for m, R in global_R.items()}
    if with_mapper:
        start = time.perf_counter()
        mapped = pycolmap_global_mapper(folder / "database.db", seed=seed)
        names = [scene.views[v].name for v in view_ids]
        R_map = np.stack([mapped.get(name, np.full((3, 3), np.nan)) for name in names])
        global_rows["pycolmap global mapper"] = {**stats(aligned_errors(R_map, R_gt)),
                                                 "seconds": time.perf_counter() - start,
                                                 "registered": int(sum(n in mapped for n in names))}
    return dict(scene=folder.name, published_key=published_key(folder.name), views=len(view_ids),
                pairs=len(keys), matches=int(batch.counts.sum()), twoview=twoview_rows, global_=global_rows)


def _with_published(value: float, published: float | None) -> str:
    return fmt(value) + (f" ({published:.4f})" if published is not None else "")


def format_tables(rows: list[dict]) -> str:
    head = ["method"] + [f"{r['scene']} ({r['pairs']} pairs)" for r in rows]
    t1 = []
    for m in TWOVIEW_METHODS:
        t1.append([m] + [_with_published(r["twoview"][m]["mean"],
                                         PUBLISHED_TWOVIEW.get(r["published_key"] or "", {}).get(m)) for r in rows])
    t1.append(["best"] + [min((m for m in TWOVIEW_METHODS if m != "initial"),
                              key=lambda m: r["twoview"][m]["mean"]) for r in rows])
    t1t = [[m] + [f"{r['twoview'][m]['ms_per_edge']:.2f}" for r in rows] for m in TWOVIEW_METHODS[1:]]
    head2 = ["method"] + [f"{r['scene']} ({r['views']} views)" for r in rows]
    t2 = []
    for m in GLOBAL_METHODS:
        if not any(m in r["global_"] for r in rows):
            continue
        t2.append([m] + [_with_published(r["global_"][m]["mean"],
                                         PUBLISHED_GLOBAL.get(r["published_key"] or "", {}).get(m))
                         if m in r["global_"] else "–" for r in rows])
    t2.append(["best of Chatterjee/ROBA/GRRM"]
              + [min(("Chatterjee", "ROBA", "GRRM"), key=lambda m: r["global_"][m]["mean"]) for r in rows])
    t2t = [[m] + [f"{r['global_'][m]['seconds']:.2f}" if m in r["global_"] else "–" for r in rows]
           for m in GLOBAL_METHODS if any(m in r["global_"] for r in rows)]
    return ("## Table 1: two-view relative-rotation error (deg), mean over verified pairs "
            "(paper's published value in parentheses)\n\n" + markdown_table(head, t1)
            + "\n\nTime per edge (ms)\n\n" + markdown_table(["method"] + [r["scene"] for r in rows], t1t)
            + "\n\n## Table 2: global rotation error (deg), mean over views after rotation-only alignment "
            "(paper's published value in parentheses)\n\n" + markdown_table(head2, t2)
            + "\n\nTime (s)\n\n" + markdown_table(["method"] + [r["scene"] for r in rows], t2t) + "\n")


def run(out_dir, root, jobs: int = 1, seed: int = 0, with_mapper: bool = True, max_pairs: int | None = None,
        progress: bool = True) -> tuple[str, dict]:
    started = time.perf_counter()
    folders = find_scenes(root)
    rows = [run_scene(f, jobs, progress, with_mapper, max_pairs, seed) for f in folders]
    table = (f"# rotonly bench strecha\n\nroot: {portable_path(str(root), '--root')}; COLMAP verified pairs, "
             f"calibrated 5-point re-estimate (1 px), inliers only.\n\n" + format_tables(rows))
    payload = dict(config=dict(root=str(root), seed=seed, with_mapper=with_mapper, max_pairs=max_pairs),
                   rows=rows, seconds=time.perf_counter() - started)
    with result_dir(out_dir) as tmp:
        (tmp / "table.md").write_text(table)
        write_json(tmp / "results.json", payload)
        _bar_chart(tmp / "strecha.png", rows)
    return table, payload


def _bar_chart(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for ax, key, methods, title in ((axes[0], "twoview", TWOVIEW_METHODS, "two-view (mean deg)"),
                                    (axes[1], "global_", GLOBAL_METHODS, "global (mean deg)")):
        methods = [m for m in methods if all(m in r[key] for r in rows)]
        width = 0.8 / max(len(methods), 1)
        x = np.arange(len(rows))
        for k, m in enumerate(methods):
            ax.bar(x + k * width, [r[key][m]["mean"] for r in rows], width, label=m)
        ax.set_xticks(x + 0.4 - width / 2, [r["scene"] for r in rows])
        ax.set_title(title)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
