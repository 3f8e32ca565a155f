"""Time and peak memory of the multi-view geometry blocks on a large synthetic scene.

Usage: python scripts/bench/multiview_blocks.py [--views 1000] [--points 100000] [--noise-px 1]

Prints one row per stage: wall time, peak Python-heap memory (tracemalloc; numpy buffers are
traced) and the process max RSS (resource). The scene is the "street" of rotonly_cli/simulation/street.py
(f = 1000, 1000×1000 px). Accuracy columns compare with the generating ground truth.
"""

from __future__ import annotations

import argparse
import resource
import time
import tracemalloc
from pathlib import Path

import numpy as np

from rotonly_cli.bench import results_md
from rotonly_cli.geometry import so3
from rotonly_cli.geometry.averaging import average_rotations
from rotonly_cli.geometry.ligt import ligt_translations
from rotonly_cli.geometry.tracks import build_tracks, pairs_within_tracks
from rotonly_cli.geometry.triangulation import triangulate_tracks
from rotonly_cli.simulation.street import make_street_scene, similarity_align_error


def measure(fn):
    tracemalloc.start()
    start = time.perf_counter()
    out = fn()
    elapsed = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, elapsed, peak / 2**20


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=1000)
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--noise-px", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--results-md", type=Path, default=None,
                        help="also write the table into this file's `multiview-blocks` section (docs/results.md)")
    args = parser.parse_args(argv)

    scene = make_street_scene(args.views, args.points, seed=args.seed)
    rng = np.random.default_rng(args.seed + 1)
    xy = scene.obs_xy + rng.normal(scale=args.noise_px * 1e-3, size=scene.obs_xy.shape)
    n = args.views
    header = (f"scene: {n} views, {len(scene.points)} points, {scene.obs_point.size} observations, "
              f"mean track length {scene.obs_point.size / len(scene.points):.2f}, noise {args.noise_px} px")
    print(header)

    # pairwise matches of every pair of track members -> tracks (feature = observation index)
    a, b = pairs_within_tracks(np.r_[0, np.flatnonzero(np.diff(scene.obs_point)) + 1, scene.obs_point.size])
    va, vb = scene.obs_view[a], scene.obs_view[b]
    order = np.lexsort((vb, va))
    a, b, va, vb = a[order], b[order], va[order], vb[order]
    pair_key = va * n + vb
    starts = np.flatnonzero(np.r_[True, pair_key[1:] != pair_key[:-1]])
    ends = np.r_[starts[1:], pair_key.size]
    keys = [(int(va[s]), int(vb[s])) for s in starts]  # loop over view pairs, not matches
    matches = [np.stack([a[s:e], b[s:e]], axis=1) for s, e in zip(starts, ends)]
    rows = []
    tracks, t, m = measure(lambda: build_tracks(keys, matches))
    rows.append(("build_tracks", t, m, f"{tracks.num_tracks} tracks from {len(keys)} pairs"))

    # rotation averaging on the covisibility graph (0.5° edge noise)
    R_gt = scene.R_cam_from_world
    ki, kj = np.array([k[0] for k in keys]), np.array([k[1] for k in keys])
    R_ij = so3.exp(rng.normal(scale=np.radians(0.5), size=(ki.size, 3))) @ R_gt[kj] @ np.transpose(R_gt[ki], (0, 2, 1))
    weights = np.array([len(mm) for mm in matches], dtype=float)
    ra, t, m = measure(lambda: average_rotations(n, ki, kj, R_ij, weights))
    S = so3.project_to_so3(np.einsum("nji,njk->ik", ra.R_cam_from_world, R_gt))
    err = np.degrees(so3.geodesic_angle(ra.R_cam_from_world @ S, R_gt))
    rows.append(("average_rotations", t, m, f"{ki.size} edges, mean err {err.mean():.4f} deg"))

    obs_xy = xy[tracks.feature]  # feature index = original observation index
    ligt, t, m = measure(lambda: ligt_translations(R_gt, tracks.track_id, tracks.view, obs_xy))
    error, _ = similarity_align_error(ligt.centers, scene.centers)
    rows.append(("ligt_translations (GT R)", t, m, f"max centre err {error:.4f} (scene span {n - 1})"))

    tri, t, m = measure(lambda: triangulate_tracks(R_gt, scene.centers, scene.obs_point, scene.obs_view, xy))
    point_error = np.linalg.norm(tri.points_in_world - scene.points, axis=1)
    rows.append(("triangulate_tracks (GT poses)", t, m,
                 f"valid {tri.valid.mean():.3f}, median err {np.median(point_error):.4f}"))

    lines = [header, "", "| stage | time (s) | peak traced (MiB) | notes |", "|---|---|---|---|"]
    lines += [f"| {name} | {seconds:.2f} | {mib:.1f} | {note} |" for name, seconds, mib, note in rows]
    lines += ["", f"process max RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB"]
    print("\n".join(lines[2:]))
    results_md.record(args.results_md, "multiview-blocks", "Multi-view geometry blocks on a large street scene",
                      results_md.command_line("python scripts/bench/multiview_blocks.py", argv), "\n".join(lines))


if __name__ == "__main__":
    main()
