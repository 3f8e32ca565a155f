"""Ground-truth pieces the GRRM probes share: GT poses by image file name, and rotonly's tracks
re-projected through the GT cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError


def gt_poses_for(gt, scene, view_ids) -> tuple[np.ndarray, np.ndarray]:
    """GT (R_cam_from_world projected to SO(3), centre) of ``view_ids`` of ``scene``, matched
    by image file name: ((n, 3, 3), (n, 3))."""
    from rotonly_cli.geometry import so3

    by_name = {Path(gt.views[v].name).name: pose for v, pose in gt.poses.items()}
    names = [Path(scene.views[v].name).name for v in view_ids]
    missing = [n for n in names if n not in by_name]
    if missing:
        raise InputError(f"no ground truth for {', '.join(missing[:3])}", field="--root")
    return (np.stack([so3.project_to_so3(by_name[n].R_cam_from_world) for n in names]),
            np.stack([by_name[n].center for n in names]))


def gt_track_residuals(structure, view_ids, normalized: dict, R_gt: np.ndarray, C_gt: np.ndarray) -> dict:
    """rotonly's tracks (``Structure.observations``) triangulated with the GT cameras (loose:
    1 normalized unit, no parallax limit) and reprojected: per observation its view row,
    keypoint, point, observed and GT-projected normalized coordinates (flat arrays)."""
    from rotonly_cli.geometry.triangulation import TriangulationOptions, triangulate_tracks

    observations = structure.observations
    point = np.repeat(np.arange(len(observations)), [len(o) for o in observations])
    flat = np.array([vk for o in observations for vk in o], dtype=np.int64).reshape(-1, 2)
    view_row = np.searchsorted(view_ids, flat[:, 0])  # view_ids are sorted
    keypoint = flat[:, 1]
    observed = np.empty((len(keypoint), 2))
    for r, v in enumerate(view_ids):
        rows = view_row == r
        observed[rows] = normalized[v][keypoint[rows]]
    loose = TriangulationOptions(max_reprojection_error=1.0, min_parallax_deg=0.0)
    X = triangulate_tracks(R_gt, C_gt, point, view_row, observed, options=loose).points_in_world
    cam = np.einsum("nij,nj->ni", R_gt[view_row], X[point] - C_gt[view_row])
    return {"view_row": view_row, "keypoint": keypoint, "point": point, "observed": observed,
            "projected": cam[:, :2] / cam[:, 2:3]}


#: the shared Strecha scenes, in the order the probes go through them
SCENES = ("Herz-Jesus-P8", "entry-P10", "fountain-P11", "castle-P19")


def add_scenes_arguments(parser) -> None:
    """The probes' --root and --scenes (several scenes, default all of SCENES)."""
    parser.add_argument("--root", type=Path, required=True, help="folder of Strecha scenes (data/strecha layout)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))


def scene_database(parser, root: Path, name: str) -> tuple[Path, Path]:
    """(database.db, gt_dense_cameras/) of scene ``name`` under ``root``; a usage error
    (exit 2) when the database is missing."""
    database = root / name / "database.db"
    if not database.is_file():
        parser.error(f"--root/--scenes: no {database}")
    return database, root / name / "gt_dense_cameras"


def add_scene_arguments(parser, default_scene: str = "Herz-Jesus-P8") -> None:
    """The probes' --root, --scene and --input."""
    parser.add_argument("--root", type=Path, required=True, help="folder of Strecha scenes (data/strecha layout)")
    parser.add_argument("--scene", default=default_scene)
    parser.add_argument("--input", choices=("openmvg", "database"), default="openmvg")


def scene_input(parser, args):
    """(input path, ground truth) of the probe's --root/--scene/--input; a usage error
    (exit 2) when the input is missing."""
    from rotonly_cli.io.detect import read_ground_truth

    scene_dir = args.root / args.scene
    input_path = scene_dir / ("openmvg/sfm_data.json" if args.input == "openmvg" else "database.db")
    if not input_path.is_file():
        parser.error(f"--root/--scene: no {input_path}")
    return input_path, read_ground_truth(scene_dir)


def averaged_run(input_path: Path, seed: int = 0):
    """rotonly's run after load, identify, refine and average (the GRRM start), with the load
    stage's ``seed``."""
    from rotonly_cli.options import LoadOptions
    from rotonly_cli.pipeline import STAGE_FUNCTIONS, RunOptions, load_stage

    run = load_stage(input_path, RunOptions(progress=False, load=LoadOptions(seed=seed)))
    for stage in ("identify", "refine", "average"):
        STAGE_FUNCTIONS[stage](run)
    return run
