#!/usr/bin/env python3
"""Regenerate the COLMAP/OpenMVG/Strecha test fixtures under data_fixtures/ from the shared
Strecha data (half resolution, /work/shared/data/strecha, see its README.md).

Per scene, ``data_fixtures/<name>/`` gets
- ``database.db``: the scene's COLMAP database reduced to a seeded random subset of at most
  ``--max-matches`` inlier matches per verified pair (every image and every verified pair kept,
  with its config and ``cam2_from_cam1``), and only the keypoints those matches use;
- ``gt_dense_cameras/*.camera``: the ground truth, copied byte for byte;
- ``openmvg/``: the same subset as an OpenMVG project (``rotonly convert database.db -o openmvg``).

Usage: python scripts/make_fixtures.py [--root /work/shared/data/strecha] [--out data_fixtures]
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from rotonly_cli.io.colmap import read_database, write_database
from rotonly_cli.scene.types import PairMatches, SfMScene
from rotonly_cli.convert import convert

SCENES = {"Herz-Jesus-P8": "herzjesu_p8", "fountain-P11": "fountain_p11"}
MAX_FIXTURE_BYTES = 3 * 1024 * 1024


def subsample_scene(scene: SfMScene, max_matches: int, seed: int) -> SfMScene:
    """Keep every view and verified pair; at most ``max_matches`` random inliers per pair
    (spread over the image, not the first N); drop keypoints no kept match uses."""
    rng = np.random.default_rng(seed)
    pairs: dict[tuple[int, int], PairMatches] = {}
    for key in sorted(scene.pairs):
        pair = scene.pairs[key]
        if not pair.verified:
            continue
        matches = pair.matches
        if len(matches) > max_matches:
            keep = np.sort(rng.choice(len(matches), size=max_matches, replace=False))
            matches = matches[keep]
        pairs[key] = replace(pair, matches=matches)
    # Keypoints used by a kept match, renumbered densely per view (order preserved).
    used = {view_id: np.zeros(len(scene.keypoints[view_id]), dtype=bool) for view_id in scene.views}
    for (i, j), pair in pairs.items():
        used[i][pair.matches[:, 0]] = True
        used[j][pair.matches[:, 1]] = True
    new_index = {view_id: np.cumsum(mask) - 1 for view_id, mask in used.items()}
    for (i, j), pair in pairs.items():
        pair.matches = np.stack([new_index[i][pair.matches[:, 0]],
                                 new_index[j][pair.matches[:, 1]]], axis=1).astype(np.int64)
    return replace(scene, pairs=pairs,
                   keypoints={v: scene.keypoints[v][used[v]] for v in scene.views},
                   normalized={v: scene.normalized[v][used[v]] for v in scene.views})


def make_scene_fixture(scene_dir: Path, out_dir: Path, max_matches: int, seed: int) -> None:
    scene = subsample_scene(read_database(scene_dir / "database.db"), max_matches, seed)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        write_database(staging / "database.db", scene)
        shutil.copytree(scene_dir / "gt_dense_cameras", staging / "gt_dense_cameras")
        convert(staging / "database.db", staging / "openmvg")
        for path in staging.rglob("*"):
            if path.is_file() and path.stat().st_size > MAX_FIXTURE_BYTES:
                raise SystemExit(f"{path} is {path.stat().st_size} bytes > 3 MB")
        if out_dir.exists():
            shutil.rmtree(out_dir)
        staging.rename(out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    num_matches = sum(len(p.matches) for p in scene.pairs.values())
    num_keypoints = sum(len(k) for k in scene.keypoints.values())
    size = sum(p.stat().st_size for p in out_dir.rglob("*") if p.is_file())
    print(f"{out_dir}: {len(scene.views)} views, {len(scene.pairs)} pairs, {num_matches} matches, "
          f"{num_keypoints} keypoints, {size / 1e6:.2f} MB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path("/work/shared/data/strecha"))
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "data_fixtures")
    parser.add_argument("--max-matches", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=20240611)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    for scene_name, fixture_name in SCENES.items():
        make_scene_fixture(args.root / scene_name, args.out / fixture_name, args.max_matches,
                           args.seed)


if __name__ == "__main__":
    main()
