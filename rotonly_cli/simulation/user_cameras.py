"""Cameras as users have them: a simulated object-centred capture whose keypoints come from a
true camera with radial distortion, written the way the front ends leave such projects —
a COLMAP database with the focal guessed (``prior_focal_length = 0``, k = 0) and pairs
verified by COLMAP's two-view geometry estimator, and an OpenMVG project with an "EXIF"
focal and no distortion (``pinhole``) — beside the same inputs with the true intrinsics.
For issue 20's tests and ``scripts/bench/intrinsics.py``.

Scene (``arc``): ``num_views`` cameras on a ~70° arc of radius 12 around a box of points
(Strecha-like converging views, with height, look-at and roll jitter), 1536 x 1024 images,
f = 1380 px, the principal point at the image centre. Parallel optical axes (the paper's
``circular`` set-up, rotonly_cli.simulation.layout_scenes) are a critical configuration of
focal self-calibration, so they are not used here.

Two captures with a known camera beside it: a tripod panorama (:func:`simulate_panorama`, every
pair a pure rotation) and a drone survey over flat or hilly ground (:func:`simulate_survey`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rotonly_cli.geometry import so3
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, View

PathLike = str | os.PathLike


@dataclass
class UserCameraProblem:
    true: Intrinsics  # SIMPLE_RADIAL f, cx, cy, k1 (COLMAP's model and pixel convention)
    guessed: Intrinsics  # SIMPLE_RADIAL f (1 + focal_error), image centre, k1 = 0
    gt_poses: dict[int, Pose]
    points_in_world: np.ndarray
    keypoints: dict[int, np.ndarray]  # distorted noisy pixels
    matches: dict[tuple[int, int], np.ndarray]  # raw matches (with wrong ones)
    seed: int
    focal_error: float
    k1: float

    @property
    def names(self) -> dict[int, str]:
        return {view_id: f"sim_{view_id:04d}.jpg" for view_id in self.keypoints}


def _look_at(center: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    z = (target - center) / np.linalg.norm(target - center)
    x = np.cross(np.array([0.0, -1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    rows = np.stack([x, np.cross(z, x), z])
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ rows


def arc_scene(rng: np.random.Generator, num_views: int = 8, num_points: int = 4000, radius: float = 12.0,
              arc_deg: float = 70.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R_cam_from_world (n, 3, 3), centres (n, 3), points (N, 3))."""
    angles = np.deg2rad(np.linspace(-arc_deg / 2, arc_deg / 2, num_views) + rng.uniform(-3, 3, num_views))
    centers = np.stack([radius * np.sin(angles), rng.uniform(-1.5, 1.5, num_views), -radius * np.cos(angles)], 1)
    rotations = np.stack([_look_at(c, rng.uniform(-1, 1, 3), np.deg2rad(rng.uniform(-5, 5))) for c in centers])
    points = np.stack([rng.uniform(-6, 6, num_points), rng.uniform(-4, 4, num_points), rng.uniform(-3, 4, num_points)],
                      axis=1)
    return rotations, centers, points


def simulate_user_cameras(seed: int, focal_error: float, k1: float, *, num_views: int = 8, num_points: int = 4000,
                          noise_px: float = 0.5, outlier_fraction: float = 0.05, width: int = 1536,
                          height: int = 1024, focal: float = 1380.0, min_shared: int = 50,
                          principal_offset: tuple[float, float] = (0.0, 0.0)) -> UserCameraProblem:
    """One problem: the true camera SIMPLE_RADIAL(focal, centre + ``principal_offset``, k1);
    the guess has the focal off by ``focal_error`` (relative), the principal point at the
    image centre and no distortion. Keypoints: projections through the
    true camera plus Gaussian noise (``noise_px`` per coordinate); ``outlier_fraction`` of
    each pair's matches point at a random keypoint."""
    rng = np.random.default_rng(seed)
    rotations, centers, points = arc_scene(rng, num_views, num_points)
    true = Intrinsics(1, "SIMPLE_RADIAL", width, height,
                      np.array([focal, width / 2 + principal_offset[0], height / 2 + principal_offset[1], k1]))
    guessed = Intrinsics(1, "SIMPLE_RADIAL", width, height,
                         np.array([focal * (1 + focal_error), width / 2, height / 2, 0.0]), prior_focal=False)
    keypoints, matches = _observe(true, rotations, centers, points, rng, noise_px, outlier_fraction, min_shared)
    gt_poses = {v + 1: Pose(rotations[v].copy(), centers[v].copy()) for v in range(num_views)}
    return UserCameraProblem(true, guessed, gt_poses, points, keypoints, matches, seed, focal_error, k1)


def _observe(true: Intrinsics, rotations: np.ndarray, centers: np.ndarray, points: np.ndarray,
             rng: np.random.Generator, noise_px: float, outlier_fraction: float,
             min_shared: int) -> tuple[dict[int, np.ndarray], dict[tuple[int, int], np.ndarray]]:
    """Keypoints (view ids from 1): the points in front of each camera projected through
    ``true``, inside the image, plus Gaussian noise (``noise_px`` per coordinate); matches of
    every pair sharing ``min_shared`` points, ``outlier_fraction`` of them pointing at a
    random keypoint."""
    from rotonly_cli.io.colmap.cameras import pycolmap_camera

    camera = pycolmap_camera(true)
    num_views = len(rotations)
    visible = np.zeros((num_views, len(points)), dtype=bool)
    keypoints = {}
    for v in range(num_views):
        in_camera = (points - centers[v]) @ rotations[v].T
        front = in_camera[:, 2] > 1e-6
        pixels = np.full((len(points), 2), np.nan)
        pixels[front] = np.asarray(camera.img_from_cam(in_camera[front]), dtype=np.float64)
        inside = front & np.all((pixels > 0) & (pixels < [true.width, true.height]), axis=1)
        visible[v] = inside
        keypoints[v + 1] = pixels[inside] + rng.normal(0.0, noise_px, (int(inside.sum()), 2))
    index = np.cumsum(visible, axis=1) - 1
    matches = {}
    for i in range(num_views):
        for j in range(i + 1, num_views):
            shared = np.flatnonzero(visible[i] & visible[j])
            if len(shared) < min_shared:
                continue
            pair = np.column_stack([index[i, shared], index[j, shared]]).astype(np.int64)
            wrong = rng.choice(len(pair), int(outlier_fraction * len(pair)), replace=False)
            pair[wrong, 1] = rng.integers(0, len(keypoints[j + 1]), len(wrong))
            matches[(i + 1, j + 1)] = pair
    return keypoints, matches


def simulate_panorama(seed: int, *, num_views: int = 12, step_deg: float = 20.0, num_points: int = 8000,
                      noise_px: float = 0.3, outlier_fraction: float = 0.05, width: int = 1536,
                      height: int = 1024, focal: float = 1380.0, min_shared: int = 50) -> UserCameraProblem:
    """A panorama from a tripod: ``num_views`` cameras at one centre (the origin), turned
    about the vertical by ``step_deg`` each (a 58° wide field of view: each image overlaps the
    next two), points 5-40 m away all round. Every pair is a pure rotation (PR). The camera
    is known (``guessed`` = ``true``, a prior focal), without distortion."""
    rng = np.random.default_rng(seed)
    yaw = np.deg2rad(step_deg * np.arange(num_views))
    c, s = np.cos(yaw), np.sin(yaw)
    rotations = np.zeros((num_views, 3, 3))
    rotations[:, 0, 0], rotations[:, 0, 2], rotations[:, 1, 1] = c, -s, 1.0
    rotations[:, 2, 0], rotations[:, 2, 2] = s, c
    centers = np.zeros((num_views, 3))
    directions = rng.normal(size=(num_points, 3)) * [1.0, 0.4, 1.0]
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * rng.uniform(5, 40, (num_points, 1))
    true = Intrinsics(1, "SIMPLE_RADIAL", width, height, np.array([focal, width / 2, height / 2, 0.0]),
                      prior_focal=True)
    keypoints, matches = _observe(true, rotations, centers, points, rng, noise_px, outlier_fraction, min_shared)
    gt_poses = {v + 1: Pose(rotations[v].copy(), centers[v].copy()) for v in range(num_views)}
    return UserCameraProblem(true, true, gt_poses, points, keypoints, matches, seed, 0.0, 0.0)


def simulate_survey(seed: int, *, strips: int = 2, per_strip: int = 5, relief: float = 0.0, altitude: float = 60.0,
                    num_points: int = 10000, noise_px: float = 0.5, outlier_fraction: float = 0.05,
                    max_tilt_deg: float = 3.0, width: int = 1536, height: int = 1024,
                    focal: float = 1380.0, min_shared: int = 50) -> UserCameraProblem:
    """A drone survey: ``strips`` x ``per_strip`` nadir views at ``altitude`` flown back and
    forth (75 % forward, 60 % side overlap, 1 m of position and 3° of heading jitter, up to
    ``max_tilt_deg`` off nadir) over ground of height ``relief`` · (smooth hills of 9-23 m
    wavelength); ``relief = 0`` is a flat field, where every pair sees one plane (COLMAP's
    verifier says PLANAR_OR_PANORAMIC and no fundamental matrix holds). The camera is known
    (``guessed`` = ``true``, a prior focal), without distortion."""
    rng = np.random.default_rng(seed)
    footprint = np.array([width, height]) / focal * altitude
    along, across = 0.25 * footprint[1], 0.4 * footprint[0]
    nadir = np.diag([1.0, -1.0, -1.0])  # x along world x, looking down
    rotations, centers = [], []
    for strip in range(strips):
        for k in range(per_strip):
            step = k if strip % 2 == 0 else per_strip - 1 - k
            centers.append(np.array([strip * across, step * along, altitude]) + rng.normal(scale=1.0, size=3))
            yaw = (0.0 if strip % 2 == 0 else np.pi) + np.deg2rad(rng.normal(scale=3.0))
            tilt = so3.exp(_random_unit(rng) * np.deg2rad(max_tilt_deg) * rng.uniform())
            rotations.append(tilt @ nadir @ so3.exp(np.array([0.0, 0.0, yaw])).T)
    rotations, centers = np.stack(rotations), np.stack(centers)
    low = centers[:, :2].min(axis=0) - footprint / 2
    high = centers[:, :2].max(axis=0) + footprint / 2
    xy = rng.uniform(low, high, (num_points, 2))
    ground = relief * (np.sin(xy[:, 0] / 17.0) * np.cos(xy[:, 1] / 23.0) + 0.5 * np.sin(xy.sum(axis=1) / 9.0)) / 1.5
    points = np.column_stack([xy, ground])
    true = Intrinsics(1, "SIMPLE_RADIAL", width, height, np.array([focal, width / 2, height / 2, 0.0]),
                      prior_focal=True)
    keypoints, matches = _observe(true, rotations, centers, points, rng, noise_px, outlier_fraction, min_shared)
    gt_poses = {v + 1: Pose(rotations[v].copy(), centers[v].copy()) for v in range(len(rotations))}
    return UserCameraProblem(true, true, gt_poses, points, keypoints, matches, seed, 0.0, 0.0)


def simulate_plane(seed: int, *, num_views: int = 6, num_points: int = 4000, distance: float = 10.0,
                   spread: float = 3.0, noise_px: float = 0.5, outlier_fraction: float = 0.05, width: int = 1280,
                   height: int = 960, focal: float = 1000.0, min_shared: int = 50) -> UserCameraProblem:
    """A wall photographed from the front: ``num_points`` points on the plane z = 0 (a 16 x 12
    rectangle), ``num_views`` cameras ``distance`` in front of it, up to ``spread`` aside and
    ``spread`` / 2 up or down, each looking at a point of the wall within 1.5 of its centre
    (5° of roll jitter). Every pair sees one plane: no fundamental matrix holds. The camera
    is PINHOLE without distortion, ``guessed`` = ``true`` (the right focal) marked as a guess
    (``prior_focal_length = 0``): what COLMAP makes of images whose EXIF focal was read as a
    default."""
    rng = np.random.default_rng(seed)
    centers = np.column_stack([rng.uniform(-spread, spread, num_views), rng.uniform(-spread, spread, num_views) / 2,
                               -distance * rng.uniform(0.85, 1.15, num_views)])
    rotations = np.stack([_look_at(c, np.array([*rng.uniform(-1.5, 1.5, 2), 0.0]), np.deg2rad(rng.uniform(-5, 5)))
                          for c in centers])
    points = np.column_stack([rng.uniform(-8, 8, num_points), rng.uniform(-6, 6, num_points), np.zeros(num_points)])
    true = Intrinsics(1, "PINHOLE", width, height, np.array([focal, focal, width / 2, height / 2]), prior_focal=True)
    keypoints, matches = _observe(true, rotations, centers, points, rng, noise_px, outlier_fraction, min_shared)
    gt_poses = {v + 1: Pose(rotations[v].copy(), centers[v].copy()) for v in range(num_views)}
    return UserCameraProblem(true, replace(true, prior_focal=False), gt_poses, points, keypoints, matches, seed,
                             0.0, 0.0)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    axis = rng.normal(size=3)
    return axis / np.linalg.norm(axis)


def verified_pairs(problem: UserCameraProblem) -> dict[tuple[int, int], PairMatches]:
    """The matches as COLMAP's matcher verifies them with the guessed camera (no prior
    focal: a fundamental matrix, config UNCALIBRATED, or a homography): inliers and config."""
    import pycolmap

    from rotonly_cli.io.colmap.cameras import pycolmap_camera

    camera = pycolmap_camera(problem.guessed)
    camera.has_prior_focal_length = False
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = int(problem.seed)
    pairs = {}
    for (i, j), matches in problem.matches.items():
        geometry = pycolmap.estimate_two_view_geometry(camera, problem.keypoints[i], camera, problem.keypoints[j],
                                                       np.ascontiguousarray(matches, dtype=np.uint32), options)
        config = pycolmap.TwoViewGeometryConfiguration(int(geometry.config)).name
        inliers = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
        if config in ("UNDEFINED", "DEGENERATE") or len(inliers) < 30:
            continue
        pairs[(i, j)] = PairMatches(i, j, inliers, config=config)
    return pairs


def user_scene(problem: UserCameraProblem, intrinsics: Intrinsics,
               pairs: dict[tuple[int, int], PairMatches], camera_per_view: bool = False) -> SfMScene:
    """The input scene: one camera ``intrinsics`` (or, with ``camera_per_view``, a copy of it
    per view, ids ``intrinsics.id`` + view - 1: what COLMAP's feature extractor makes by
    default), the keypoints, the verified ``pairs``."""
    from rotonly_cli.io.cameras import normalize

    scene = SfMScene(source="simulation")
    for view_id, name in problem.names.items():
        camera_id = intrinsics.id + (view_id - 1 if camera_per_view else 0)
        scene.intrinsics[camera_id] = replace(intrinsics, id=camera_id)
        scene.views[view_id] = View(view_id, name, camera_id, width=intrinsics.width, height=intrinsics.height)
        scene.keypoints[view_id] = problem.keypoints[view_id]
        scene.normalized[view_id] = normalize(intrinsics, problem.keypoints[view_id])
    scene.pairs = {key: replace(pair) for key, pair in sorted(pairs.items())}
    return scene


def camera_per_view(scene: SfMScene) -> SfMScene:
    """``scene`` with every view given its own copy of its camera, id = the view's id: what
    COLMAP's feature extractor makes by default and OpenMVG's image listing with ``-g 0``."""
    views = {v: replace(view, intrinsics_id=v) for v, view in scene.views.items()}
    intrinsics = {v: replace(scene.intrinsics[view.intrinsics_id], id=v) for v, view in scene.views.items()}
    return replace(scene, intrinsics=intrinsics, views=views)


def gt_scene(problem: UserCameraProblem) -> SfMScene:
    """Ground truth: the true camera and poses (``rotonly eval`` / evaluation.quality)."""
    scene = user_scene(problem, problem.true, {})
    scene.poses = {view_id: Pose(pose.R_cam_from_world.copy(), pose.center.copy())
                   for view_id, pose in problem.gt_poses.items()}
    return scene


def openmvg_intrinsics(intrinsics: Intrinsics) -> Intrinsics:
    """An OpenMVG camera of a SIMPLE_RADIAL one: ``pinhole`` without distortion (what an
    EXIF focal gives), ``pinhole_radial_k1`` with; of a PINHOLE one (fx = fy), ``pinhole``."""
    params = np.asarray(intrinsics.params, dtype=np.float64)
    # PINHOLE: fx = fy in these simulations, no distortion
    f, cx, cy, k1 = (params[0], params[2], params[3], 0.0) if intrinsics.model == "PINHOLE" else params
    if k1 == 0.0:
        return replace(intrinsics, id=0, model="pinhole", params=np.array([f, cx, cy]), prior_focal=None)
    return replace(intrinsics, id=0, model="pinhole_radial_k1", params=np.array([f, cx, cy, k1]), prior_focal=None)


def write_inputs(out_dir: PathLike, problem: UserCameraProblem, formats: tuple[str, ...] = ("colmap", "openmvg"),
                 true_intrinsics: bool = False, camera_per_view: bool = False) -> dict[str, Path]:
    """``out_dir/database.db`` (COLMAP) and ``out_dir/openmvg/sfm_data.json`` (OpenMVG, with its
    features and matches) with the guessed intrinsics (or the true ones, marked known; with
    ``camera_per_view`` a camera per view), and ``out_dir/gt/sfm_data.json``. Returns the
    paths by format (and "gt")."""
    from rotonly_cli.io import colmap, openmvg
    from rotonly_cli.scene.ids import shift_ids

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pairs = verified_pairs(problem)
    intrinsics = replace(problem.true, prior_focal=True) if true_intrinsics else problem.guessed
    paths = {}
    if "colmap" in formats:
        paths["colmap"] = out_dir / "database.db"
        colmap.write_database(paths["colmap"], user_scene(problem, intrinsics, pairs, camera_per_view))
    if "openmvg" in formats:
        openmvg.write_project(out_dir / "openmvg", shift_ids(user_scene(problem, openmvg_intrinsics(intrinsics), pairs,
                                                                        camera_per_view), -1, 0))
        paths["openmvg"] = out_dir / "openmvg" / "sfm_data.json"
    paths["gt"] = out_dir / "gt" / "sfm_data.json"
    gt = replace(gt_scene(problem), intrinsics={1: replace(openmvg_intrinsics(problem.true), id=1)})
    openmvg.write_sfm_data(paths["gt"], shift_ids(gt, -1, -1))
    return paths
