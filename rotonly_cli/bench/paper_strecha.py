"""Strecha benchmark (rotation_only.tex Tables strecha_results_relativeopt and
strecha_rotation_accuracy; published numbers in algorithms.md §7).

For every scene folder under ``root`` holding ``database.db`` and ``gt_dense_cameras/``, every row
of both tables is computed on the same pairs: those ``rotonly run`` keeps before GRRM
(bench/strecha_pairs.py: the load stage's re-estimated relative poses and inlier matches, scene
identification's and rotation averaging's filters applied), the protocol the paper's tables
follow with OpenMVG's front end (its AC-RANSAC poses and its global pipeline's edge filtering).
The table header states the protocol and, per scene, how many of the input's pairs are used.

* Table 1 — two-view: from each pair's initial pose (the load stage's), BA / PA / Kneip eigen /
  Kneip nonlinear / TRRM refine it on its inlier matches; error = geodesic angle to the GT
  relative rotation R_j R_iᵀ (deg), mean over the pairs.
* Table 2 — global: Chatterjee (ℓ½) on the initial relative rotations, ROBA and GRRM from
  Chatterjee's rotations on the same matches, the pycolmap global mapper (GLOMAP, K fixed) on a
  copy of the database whose verified pairs are these pairs (their initial poses and inliers),
  and ``rotonly run`` itself (the run the pairs were read from); error = mean geodesic angle
  after rotation-only L2 alignment to the GT.

The ground truth scores the rows and is read after the run. Images are matched to GT cameras
by file name. The paper's numbers come from full-resolution images with OpenMVG SIFT matches;
the data here is half resolution with COLMAP SIFT, so the published columns are context.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from rotonly_cli.bench.common import error_deg, fmt, markdown_table, parallel_map, result_dir, stats, write_json
from rotonly_cli.bench.paper_twoview import METHODS as TWOVIEW_METHODS
from rotonly_cli.bench.paper_twoview import PER_EDGE_METHODS, refine_per_edge
from rotonly_cli.bench.results_md import portable_path
from rotonly_cli.errors import InputError

GLOBAL_METHODS = ("Chatterjee", "ROBA", "GRRM", "pycolmap global mapper", "rotonly run")

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
    """The per-edge baselines (BA, PA, Kneip nonlinear) from one pair's initial pose (a pool task)."""
    R_init, t_init, x_i, x_j, methods = args
    rotations, seconds = refine_per_edge(R_init, t_init, x_i, x_j, methods)
    return dict(rotations=rotations, seconds=seconds)


def input_pairs(folder: Path, max_pairs: int | None, min_matches: int):
    """What the run is given: ``folder/database.db`` itself, or (``max_pairs``) the database read
    with only that many of its verified pairs with ``min_matches`` or more, neighbours first (by
    image-name order), which keeps the graph connected. Returns (source, kind, label)."""
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.io.detect import InputKind

    database = folder / "database.db"
    if max_pairs is None:
        return database, None, None
    scene = read_database(database)
    rank = {v: k for k, v in enumerate(sorted(scene.views, key=lambda v: (scene.views[v].name, v)))}
    keys = [k for k, pair in scene.pairs.items() if pair.verified and len(pair.matches) >= min_matches]
    keys = sorted(keys, key=lambda k: (abs(rank[k[1]] - rank[k[0]]), k))[:max_pairs]
    scene.pairs = {k: scene.pairs[k] for k in sorted(keys)}
    return scene, InputKind.COLMAP_DB, f"{database} ({len(keys)} pairs)"


def run_scene(folder: Path, jobs: int, progress: bool, with_mapper: bool, max_pairs: int | None, seed: int,
              methods: tuple[str, ...] = TWOVIEW_METHODS) -> dict:
    """Both tables of one scene, every row on the pairs ``rotonly run`` keeps before GRRM
    (bench/strecha_pairs.py); the ground truth only scores the rows. ``methods``: Table 1's
    (the initial poses always)."""
    from rotonly_cli import twoview
    from rotonly_cli.baselines.kneip import refine_kneip_eigen
    from rotonly_cli.baselines.references import pycolmap_global_mapper
    from rotonly_cli.bench.paper_multiview import aligned_errors, global_methods
    from rotonly_cli.bench.strecha_pairs import kept_pairs
    from rotonly_cli.geometry import pairwise as pg
    from rotonly_cli.io.strecha import read_strecha_dir
    from rotonly_cli.options import RunOptions

    defaults = RunOptions()
    options = replace(defaults, jobs=jobs, progress=False, load=replace(defaults.load, seed=seed))
    source, kind, label = input_pairs(folder, max_pairs, options.load.min_inliers)
    front = kept_pairs(source, options, kind, label)  # the product: no ground truth read before this
    if not front.keys:
        raise InputError("rotonly kept no pair of this scene", path=str(folder), field="--root")
    gt = read_strecha_dir(folder)
    gt_by_name = {v.name: gt.poses[v.id].R_cam_from_world for v in gt.views.values()}
    index = {v: k for k, v in enumerate(front.view_ids)}
    scored = np.array([front.names[v] in gt_by_name for v in front.view_ids])  # views the GT has
    R_gt = np.stack([gt_by_name.get(front.names[v], np.eye(3)) for v in front.view_ids])
    ii = np.array([index[i] for i, _ in front.keys])
    jj = np.array([index[j] for _, j in front.keys])

    # Table 1: every kept pair's initial pose refined by each method on its inlier matches
    methods = ("initial",) + tuple(m for m in TWOVIEW_METHODS[1:] if m in methods)
    per_edge = tuple(m for m in PER_EDGE_METHODS if m in methods)
    rotations = {"initial": front.R_init}
    seconds = {"initial": 0.0}
    if per_edge:
        results = parallel_map(_pair_task, [(*pair, per_edge) for pair in zip(front.R_init, front.t_init, front.x_i,
                                                                               front.x_j)],
                               jobs, f"{folder.name} pairs", progress)
        for name in per_edge:
            rotations[name] = np.stack([r["rotations"][name] for r in results])
            seconds[name] = float(np.mean([r["seconds"][name] for r in results]))
    if "Kneip eigen" in methods:
        start = time.perf_counter()
        with np.errstate(all="ignore"):
            rotations["Kneip eigen"] = refine_kneip_eigen(front.R_init,
                                                          pg.pack_edges(front.x_i, front.x_j)).rotations
        seconds["Kneip eigen"] = (time.perf_counter() - start) / len(front.keys)
    if "TRRM" in methods:
        start = time.perf_counter()
        rotations["TRRM"] = np.asarray(twoview.refine_rotations(front.R_init, front.x_i, front.x_j).rotations)
        seconds["TRRM"] = (time.perf_counter() - start) / len(front.keys)
    pair_scored = scored[ii] & scored[jj]
    R_pair_gt = R_gt[jj] @ np.swapaxes(R_gt[ii], 1, 2)
    twoview_rows = {m: {**stats(error_deg(rotations[m], R_pair_gt)[pair_scored]), "ms_per_edge": 1e3 * seconds[m]}
                    for m in methods}

    # Table 2: observation ids = view offset + keypoint index
    offset = np.concatenate([[0], np.cumsum(front.num_keypoints)])
    obs_ids = np.concatenate([np.column_stack([offset[index[i]] + m[:, 0], offset[index[j]] + m[:, 1]])
                              for (i, j), m in zip(front.keys, front.matches)])
    batch = pg.pack_edges(front.x_i, front.x_j)
    with np.errstate(all="ignore"):
        global_R, global_s = global_methods(len(front.view_ids), np.column_stack([ii, jj]), batch, obs_ids,
                                            front.R_init, batch.counts, methods=("Chatterjee", "ROBA", "GRRM"))
    if with_mapper:
        start = time.perf_counter()
        mapped = pycolmap_global_mapper(folder / "database.db", seed=seed, pairs=front.named_pairs())
        global_R["pycolmap global mapper"] = np.stack([mapped.get(front.names[v], np.full((3, 3), np.nan))
                                                       for v in front.view_ids])
        global_s["pycolmap global mapper"] = time.perf_counter() - start
    global_R["rotonly run"], global_s["rotonly run"] = front.run_rotations, front.run_seconds
    global_rows = {m: {**stats(aligned_errors(R[scored], R_gt[scored])), "seconds": global_s[m]}
                   for m, R in global_R.items()}
    return dict(scene=folder.name, published_key=published_key(folder.name), views=int(scored.sum()),
                input_views=len(front.view_ids), pairs=len(front.keys), input_pairs=front.num_input_pairs,
                scored_pairs=int(pair_scored.sum()), filtered=front.filtered, matches=int(batch.counts.sum()),
                keys=[[front.names[i], front.names[j]] for i, j in front.keys],
                twoview=twoview_rows, global_=global_rows)


def _with_published(value: float, published: float | None) -> str:
    return fmt(value) + (f" ({published:.4f})" if published is not None else "")


def _global_cell(row: dict, method: str) -> str:
    """A Table 2 cell: the mean, the paper's value, and the views estimated when not all."""
    if method not in row["global_"]:
        return "–"
    entry = row["global_"][method]
    cell = _with_published(entry["mean"], PUBLISHED_GLOBAL.get(row["published_key"] or "", {}).get(method))
    return cell + (f" [{entry['count']}/{row['views']} views]" if entry["count"] < row["views"] else "")


def protocol_text(rows: list[dict]) -> str:
    """The table header: which pairs every row is computed on, scene by scene."""
    lines = ["Pairs: those `rotonly run` keeps before GRRM, the same for every row of both tables: the "
             "load stage's relative poses and inlier matches (RANSAC re-estimate, minimum-inlier filter), "
             "scene identification's rotation-singular filter, then TRRM and rotation averaging's "
             "outlier-edge filter. Every method starts from the load stage's relative rotation of each of "
             "these pairs (*initial*) on its inlier matches; Chatterjee, ROBA and GRRM use them all; "
             "the pycolmap global mapper gets a copy of the database whose verified pairs are exactly these "
             "(pose and inliers); *rotonly run* is the whole product on the same input (its reject stage "
             "may drop more). The ground truth only scores the results.", "",
             markdown_table(["scene", "pairs used", "of the input's", "left out before GRRM", "inlier matches"],
                            [[r["scene"], str(r["pairs"]), str(r["input_pairs"]),
                              ", ".join(f"{n} {reason}" for reason, n in sorted(r["filtered"].items())) or "none",
                              str(r["matches"])] for r in rows])]
    return "\n".join(lines)


def format_tables(rows: list[dict]) -> str:
    head = ["method"] + [f"{r['scene']} ({r['pairs']} of {r['input_pairs']} pairs)" for r in rows]
    twoview_methods = [m for m in TWOVIEW_METHODS if all(m in r["twoview"] for r in rows)]
    t1 = []
    for m in twoview_methods:
        t1.append([m] + [_with_published(r["twoview"][m]["mean"],
                                         PUBLISHED_TWOVIEW.get(r["published_key"] or "", {}).get(m)) for r in rows])
    t1.append(["best"] + [min(twoview_methods[1:] or ["initial"], key=lambda m: r["twoview"][m]["mean"])
                          for r in rows])
    t1t = [[m] + [f"{r['twoview'][m]['ms_per_edge']:.2f}" for r in rows] for m in twoview_methods[1:]]
    head2 = ["method"] + [f"{r['scene']} ({r['views']} views, {r['pairs']} of {r['input_pairs']} pairs)"
                          for r in rows]
    methods = [m for m in GLOBAL_METHODS if any(m in r["global_"] for r in rows)]
    t2 = [[m] + [_global_cell(r, m) for r in rows] for m in methods]
    t2.append(["best of Chatterjee/ROBA/GRRM"]
              + [min(("Chatterjee", "ROBA", "GRRM"), key=lambda m: r["global_"][m]["mean"]) for r in rows])
    t2t = [[m] + [f"{r['global_'][m]['seconds']:.2f}" if m in r["global_"] else "–" for r in rows] for m in methods]
    return ("## Table 1: two-view relative-rotation error (deg), mean over the pairs used "
            "(paper's published value in parentheses)\n\n" + markdown_table(head, t1)
            + "\n\nTime per edge (ms)\n\n" + markdown_table(["method"] + [r["scene"] for r in rows], t1t)
            + "\n\n## Table 2: global rotation error (deg), mean over views after rotation-only alignment, "
            "from the pairs used (paper's published value in parentheses; [k/n views]: only k estimated)\n\n"
            + markdown_table(head2, t2)
            + "\n\nTime (s; *rotonly run*: the whole run, load to triangulation)\n\n"
            + markdown_table(["method"] + [r["scene"] for r in rows], t2t) + "\n")


def run(out_dir, root, jobs: int = 1, seed: int = 0, with_mapper: bool = True, max_pairs: int | None = None,
        progress: bool = True, methods: tuple[str, ...] = TWOVIEW_METHODS) -> tuple[str, dict]:
    started = time.perf_counter()
    folders = find_scenes(root)
    rows = [run_scene(f, jobs, progress, with_mapper, max_pairs, seed, methods) for f in folders]
    given = "each COLMAP database" + (f" limited to {max_pairs} verified pairs (neighbours first)" if max_pairs else "")
    root_shown = portable_path(str(root), "--root")
    table = (f"# rotonly bench strecha\n\nroot: {root_shown}; input: {given}; seed {seed}.\n\n" + protocol_text(rows)
             + "\n\n" + format_tables(rows))
    payload = dict(config=dict(root=str(root), seed=seed, with_mapper=with_mapper, max_pairs=max_pairs,
                               methods=list(methods)),
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
