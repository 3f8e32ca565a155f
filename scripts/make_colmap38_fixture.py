#!/usr/bin/env python3
"""Regenerate data_fixtures/colmap38_herzjesu4/database.db: a database written by COLMAP 3.8
itself (Debian's ``colmap`` package), in its own schema (``images.prior_*``,
``two_view_geometries.qvec/tvec``, no rigs/frames tables), so the tests check that rotonly
reads what users of that COLMAP produce.

Steps: ``colmap feature_extractor`` (one shared PINHOLE camera fixed to the ground-truth K in
COLMAP's pixel convention, CPU SIFT) and ``colmap exhaustive_matcher`` on the Strecha images,
then the database is cut to the first ``--num-images`` images by name with sqlite3 (the
descriptors dropped, as in the shared Strecha databases; every other row kept byte for byte).

Usage: python scripts/make_colmap38_fixture.py [--scene /work/shared/data/strecha/Herz-Jesus-P8]
       [--out data_fixtures/colmap38_herzjesu4] [--num-images 4]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import subprocess
import tempfile
from contextlib import closing
from pathlib import Path

import numpy as np

PAIR_ID_BASE = 2147483647  # COLMAP's pair_id = i * 2147483647 + j (i < j)


def ground_truth_pinhole(scene: Path) -> str:
    """fx,fy,cx,cy of the scene's first GT camera, principal point shifted +0.5 px (COLMAP)."""
    first = sorted((scene / "gt_dense_cameras").glob("*.camera"))[0]
    K = np.array(first.read_text().split()[:9], dtype=float).reshape(3, 3)
    return ",".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5))


def cut_database(path: Path, names: list[str]) -> None:
    """Keep the images called ``names``, their keypoints and the pairs among them; drop descriptors."""
    with closing(sqlite3.connect(path)) as db, db:  # closed (not only committed) before VACUUM
        keep = {row[0] for row in db.execute(
            f"SELECT image_id FROM images WHERE name IN ({','.join('?' * len(names))})", names)}
        ids = ",".join(str(i) for i in sorted(keep))
        db.execute("DELETE FROM descriptors")
        db.execute(f"DELETE FROM keypoints WHERE image_id NOT IN ({ids})")
        db.execute(f"DELETE FROM images WHERE image_id NOT IN ({ids})")
        for table in ("matches", "two_view_geometries"):
            drop = [(pair_id,) for (pair_id,) in db.execute(f"SELECT pair_id FROM {table}")
                    if not {pair_id // PAIR_ID_BASE, pair_id % PAIR_ID_BASE} <= keep]
            db.executemany(f"DELETE FROM {table} WHERE pair_id = ?", drop)
    with closing(sqlite3.connect(path)) as db:
        db.execute("VACUUM")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=Path("/work/shared/data/strecha/Herz-Jesus-P8"))
    parser.add_argument("--out", type=Path, default=Path("data_fixtures/colmap38_herzjesu4"))
    parser.add_argument("--num-images", type=int, default=4)
    args = parser.parse_args()
    colmap = shutil.which("colmap")
    if colmap is None:
        raise SystemExit("needs the colmap command (Debian: apt-get install colmap)")
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    with tempfile.TemporaryDirectory() as tmp:
        database = Path(tmp) / "database.db"
        subprocess.run([colmap, "feature_extractor", "--database_path", str(database),
                        "--image_path", str(args.scene / "images"), "--ImageReader.camera_model", "PINHOLE",
                        "--ImageReader.single_camera", "1",
                        "--ImageReader.camera_params", ground_truth_pinhole(args.scene),
                        "--SiftExtraction.use_gpu", "0"], check=True, env=env, capture_output=True)
        subprocess.run([colmap, "exhaustive_matcher", "--database_path", str(database),
                        "--SiftMatching.use_gpu", "0"], check=True, env=env, capture_output=True)
        names = sorted(p.name for p in (args.scene / "images").glob("*.jpg"))[:args.num_images]
        cut_database(database, names)
        args.out.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(database, args.out / "database.db")
    print(f"wrote {args.out / 'database.db'} ({(args.out / 'database.db').stat().st_size} bytes)")


if __name__ == "__main__":
    main()
