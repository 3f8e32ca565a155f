#!/usr/bin/env python
"""Probe: does `auto` calibrate wrong intrinsics on real scenes it was not tuned on? Each
Strecha scene's inputs rewritten as a user's would arrive, run (in-process) and scored
against the ground truth.

* ``guessed db``: the COLMAP database with COLMAP's own guess for an unknown camera
  (SIMPLE_RADIAL, f = 1.2 x max(w, h), principal point at the centre, k1 = 0,
  ``prior_focal_length = 0``) and its E-verified pairs marked UNCALIBRATED, as a database
  matched without camera parameters says; the matches are the scene's own.
* ``db x F``: the COLMAP database with its focal length(s) F x the given ones and still marked
  known (``prior_focal_length = 1``), as an EXIF focal that is off; found only by the
  reprojection errors.
* ``exif db x F``: the COLMAP database as COLMAP's feature extractor writes a camera whose
  EXIF gives the focal: SIMPLE_RADIAL, F x the given (mean) focal, the principal point at the
  image centre, k1 = 0, ``prior_focal_length = 1``; with ``--exif-camera-per-image`` also
  ``exif db per image x F``, the same camera given to every image on its own (COLMAP's
  default).
* ``omvg x F``: the OpenMVG project with the focal F x the given one (a wrong EXIF focal) and
  the principal point at the image centre; nothing marks it as a guess. With
  ``--omvg-intrinsic-per-view`` also ``omvg per view x F``: that intrinsic copied to every
  view, as OpenMVG's image listing writes them without grouping.
* ``lens k1=K db`` (``--k1``): the keypoints moved as a lens with radial distortion k1 = K
  would have imaged them (OPENCV around the database's own camera: its focal lengths and
  principal point, k1 = K on the normalized radius), written with COLMAP's guess as in
  ``guessed db`` (a phone user's database: the lens is there, the camera says nothing of it);
  ``lens k1=K known db``: the same keypoints with that OPENCV camera, marked known.
* ``phone db``: ``database_guessed_focal.db`` where the scene has one (COLMAP's own
  extraction and matching without camera parameters).

One table row per run: mean rotation and position error, registered views, the final focal
and principal point (COLMAP's pixel convention) against the ground truth's. ``--ba-huber-px``
sets ``IntrinsicsOptions.ba_huber_px`` (``none``: squared loss) to compare the loss.

    python scripts/research/probe_wrong_intrinsics.py --root DATA/strecha --scenes castle-P19 entry-P10
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

GUESS_FACTOR = 1.2  #: COLMAP's focal guess for a camera without parameters: 1.2 x max(w, h)


def guessed_database(scene, out: Path) -> Path:
    """``scene`` (a database as read) written to ``out`` with COLMAP's guess for an unknown
    camera (module docstring)."""
    from rotonly_cli.io.colmap import write_database
    from rotonly_cli.scene.types import Intrinsics

    intrinsics = {c: Intrinsics(c, "SIMPLE_RADIAL", k.width, k.height,
                                np.array([GUESS_FACTOR * max(k.width, k.height), k.width / 2, k.height / 2, 0.0]),
                                prior_focal=False) for c, k in scene.intrinsics.items()}
    pairs = {key: replace(pair, config="UNCALIBRATED" if pair.config == "CALIBRATED" else pair.config)
             for key, pair in scene.pairs.items()}
    write_database(out, replace(scene, intrinsics=intrinsics, pairs=pairs))
    return out


def lens_database(scene, k1: float, out: Path, known: bool = False) -> Path:
    """``scene`` (a database as read, pinhole cameras) with every keypoint where a lens with
    radial distortion ``k1`` would have put it (module docstring), written to ``out`` with
    COLMAP's guess for the camera, or with that OPENCV camera when ``known``."""
    from rotonly_cli.io.cameras import parameter_groups, project
    from rotonly_cli.io.colmap import write_database
    from rotonly_cli.scene.types import Intrinsics

    lenses = {}
    for camera_id, intrinsic in scene.intrinsics.items():
        params, groups = np.asarray(intrinsic.params, dtype=np.float64), parameter_groups(intrinsic)
        focal = np.broadcast_to(params[groups["focal"]], 2)
        lenses[camera_id] = Intrinsics(camera_id, "OPENCV", intrinsic.width, intrinsic.height,
                                       np.array([*focal, *params[groups["principal_point"]], k1, 0.0, 0.0, 0.0]),
                                       prior_focal=True)
    keypoints = {v: project(lenses[view.intrinsics_id], scene.normalized[v]) for v, view in scene.views.items()}
    distorted = replace(scene, keypoints=keypoints, intrinsics=lenses)
    if known:
        write_database(out, distorted)
        return out
    return guessed_database(distorted, out)


def wrong_focal_database(scene, factor: float, out: Path) -> Path:
    """``scene`` (a database as read) written to ``out`` with every camera's focal length(s)
    x ``factor``, still marked known."""
    from rotonly_cli.io.cameras import parameter_groups
    from rotonly_cli.io.colmap import write_database

    intrinsics = {}
    for camera_id, intrinsic in scene.intrinsics.items():
        params = np.array(intrinsic.params, dtype=np.float64)
        params[parameter_groups(intrinsic)["focal"]] *= factor
        intrinsics[camera_id] = replace(intrinsic, params=params, prior_focal=True)
    write_database(out, replace(scene, intrinsics=intrinsics))
    return out


def exif_database(scene, factor: float, out: Path, per_image: bool = False) -> Path:
    """``scene`` (a database as read, one camera) written to ``out`` as COLMAP writes an EXIF
    camera (module docstring); ``per_image``: a copy of it for every image."""
    from rotonly_cli.io.colmap import write_database
    from rotonly_cli.scene.types import Intrinsics
    from rotonly_cli.simulation.user_cameras import camera_per_view

    (k,) = scene.intrinsics.values()
    exif = replace(scene, intrinsics={k.id: Intrinsics(k.id, "SIMPLE_RADIAL", k.width, k.height, np.array(
        [factor * k.focal_px, k.width / 2, k.height / 2, 0.0]), prior_focal=True)})
    write_database(out, camera_per_view(exif) if per_image else exif)
    return out


def wrong_focal_project(sfm_data: Path, factor: float, out: Path, per_view: bool = False) -> Path:
    """``sfm_data`` with every intrinsic's focal x ``factor`` and its principal point at the
    image centre, image root made absolute (the features stay where they are); ``per_view``:
    a copy of the (first) intrinsic for every view, as OpenMVG's image listing writes them
    without grouping (``-g 0``)."""
    from rotonly_cli.io.openmvg import read_sfm_data, write_sfm_data
    from rotonly_cli.simulation.user_cameras import camera_per_view

    data = json.loads(sfm_data.read_text())
    for intrinsic in data["intrinsics"]:
        camera = intrinsic["value"]["ptr_wrapper"]["data"]
        camera["focal_length"] *= factor
        camera["principal_point"] = [camera["width"] / 2, camera["height"] / 2]
    data["root_path"] = str((sfm_data.parent / data["root_path"]).resolve())
    out.write_text(json.dumps(data))
    if per_view:
        write_sfm_data(out, camera_per_view(read_sfm_data(out)), include_structure=False)
    return out


def focal_and_principal_point(intrinsic) -> np.ndarray:
    """(mean focal, cx, cy) of a camera, in COLMAP's pixel convention."""
    from rotonly_cli.io.cameras import parameter_groups, to_colmap_intrinsics

    colmap = to_colmap_intrinsics(intrinsic)
    params, groups = np.asarray(colmap.params, dtype=np.float64), parameter_groups(colmap)
    return np.array([params[groups["focal"]].mean(), *params[groups["principal_point"]]])


def run_row(label: str, input_path: Path, gt: Path, true: np.ndarray, options, matches_dir: Path | None) -> dict:
    """One run scored against the ground truth ``gt`` and its camera ``true``
    (:func:`focal_and_principal_point`, averaged over the GT's cameras)."""
    import rotonly_cli

    result = rotonly_cli.run(input_path, gt=gt, matches_dir=matches_dir, options=options)
    evaluation = result.evaluation
    # the Strecha scenes have one camera; with a camera per image, the worst of them
    ends = np.array([focal_and_principal_point(camera) for camera in result.scene.intrinsics.values()])
    focal_errors = 100 * (ends[:, 0] / true[0] - 1)
    return {"input": label, "rotation_deg": evaluation["rotation_error_deg"]["mean"],
            "position": (evaluation.get("position_error") or {}).get("mean", float("nan")),
            "registered": f"{len(result.rotations)}/{result.summary['num_views']}",
            "focal_error_pct": float(focal_errors[np.argmax(np.abs(focal_errors))]),
            "principal_point_error_px": float(np.hypot(*(ends[:, 1:3] - true[1:3]).T).max()),
            # the zoom check's warning (calibration/focals.per_image_focals): none of these inputs has a zoom
            "zoom_warned": any("disagree on the focal length" in w for w in result.summary.get("warnings", []))}


def print_row(row: dict) -> None:
    print(f"{row['input']:28s} {row['rotation_deg']:.4f} deg  pos {row['position']:.4f}  {row['registered']}  "
          f"f {row['focal_error_pct']:+.2f} %  pp {row['principal_point_error_px']:.1f} px"
          f"{'  ZOOM WARNED' if row.get('zoom_warned') else ''}", flush=True)


def main(argv: list[str] | None = None) -> int:
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.io.detect import read_ground_truth
    from rotonly_cli.options import IntrinsicsOptions, RunOptions
    from rotonly_cli.runtime.parallel import usable_cpus

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="folder of Strecha scenes (data/strecha layout)")
    parser.add_argument("--scenes", nargs="+", default=["Herz-Jesus-P8", "entry-P10", "castle-P19", "fountain-P11"])
    parser.add_argument("--factors", type=float, nargs="*", default=[1.2, 0.85], help="OpenMVG focal factors")
    parser.add_argument("--db-factors", type=float, nargs="*", default=[1.05, 0.97],
                        help="focal factors of the database's camera, marked known")
    parser.add_argument("--exif-factors", type=float, nargs="*", default=[1.0],
                        help="focal factors of the database written as an EXIF camera (principal point at the centre)")
    parser.add_argument("--k1", type=float, nargs="*", default=[],
                        help="radial distortions of a lens the keypoints are moved by (guessed and known camera)")
    parser.add_argument("--exif-camera-per-image", action="store_true",
                        help="the --exif-factors databases with a camera per image too")
    parser.add_argument("--omvg-intrinsic-per-view", action="store_true",
                        help="the --factors projects with an intrinsic per view too")
    parser.add_argument("--ba-huber-px", default=None, help="IntrinsicsOptions.ba_huber_px (none: squared loss)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    intrinsics = IntrinsicsOptions()
    if args.ba_huber_px is not None:
        intrinsics = replace(intrinsics, ba_huber_px=None if args.ba_huber_px == "none" else float(args.ba_huber_px))
    options = RunOptions(jobs=usable_cpus(), intrinsics=intrinsics)
    rows = []
    with tempfile.TemporaryDirectory(prefix="rotonly-probe-") as scratch:
        for scene in args.scenes:
            folder, gt = args.root / scene, args.root / scene / "gt_dense_cameras"
            work = Path(scratch) / scene
            work.mkdir()
            database = read_database(folder / "database.db")
            true = np.mean([focal_and_principal_point(k) for k in read_ground_truth(gt).intrinsics.values()], axis=0)
            runs = [(f"{scene} guessed db", guessed_database(database, work / "guessed.db"), None)]
            if (folder / "database_guessed_focal.db").exists():
                runs.insert(0, (f"{scene} phone db", folder / "database_guessed_focal.db", None))
            for k1 in args.k1:
                runs.append((f"{scene} lens k1={k1} db", lens_database(database, k1, work / f"lens{k1}.db"), None))
                runs.append((f"{scene} lens k1={k1} known db",
                             lens_database(database, k1, work / f"lens{k1}_known.db", known=True), None))
            for factor in args.db_factors:
                runs.append((f"{scene} db x{factor}",
                             wrong_focal_database(database, factor, work / f"x{factor}.db"), None))
            for factor in args.exif_factors:
                runs.append((f"{scene} exif db x{factor}", exif_database(database, factor, work / f"exif{factor}.db"),
                             None))
                if args.exif_camera_per_image:
                    runs.append((f"{scene} exif db per image x{factor}",
                                 exif_database(database, factor, work / f"exif{factor}_per_image.db", True), None))
            for factor in args.factors:
                project = wrong_focal_project(folder / "openmvg" / "sfm_data.json", factor,
                                              work / f"sfm_data_x{factor}.json")
                runs.append((f"{scene} omvg x{factor}", project, folder / "openmvg"))
                if args.omvg_intrinsic_per_view:
                    project = wrong_focal_project(folder / "openmvg" / "sfm_data.json", factor,
                                                  work / f"sfm_data_x{factor}_per_view.json", per_view=True)
                    runs.append((f"{scene} omvg per view x{factor}", project, folder / "openmvg"))
            for label, input_path, matches_dir in runs:
                rows.append(run_row(label, input_path, gt, true, options, matches_dir))
                print_row(rows[-1])
    print("\n| input | rot. mean (deg) | position mean | registered | focal error (%) | principal point error (px) |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['input']} | {row['rotation_deg']:.4f} | {row['position']:.4f} | {row['registered']} | "
              f"{row['focal_error_pct']:+.2f} | {row['principal_point_error_px']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
