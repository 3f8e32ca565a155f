"""The paper's multi-view simulation set-ups (rotation_only.tex §"Multi-view Rotation
Estimation", Fig. GRRM_scene): ``circular``, ``square``, ``linear`` and ``outward``.

* n cameras (default 100) with a fixed distance (10 m) between adjacent centres, centred at
  the world origin, in the plane z = 0.
* ``circular`` / ``square`` / ``linear``: cameras look straight up (+z, heading along the
  trajectory) with a small random tilt (``max_tilt_deg``); points are "directly above the
  cameras within a range of 0 to 400 m": uniform in z ∈ (0, 400] over the cameras' xy
  bounding box grown by ``0.3 · 400`` m (the footprint of the 62° field of view).
* ``outward``: cameras on the circle look horizontally outwards; points fill the cylindrical
  ring r ∈ [200, 3000] m, z ∈ [-200, 200] m (uniform in area).
* ``num_points`` (10 000) points are kept that are in front of and inside the 960×960 image
  (focal 800 px, algorithms.md §6) of at least two cameras. Which camera sees which point is
  held sparse (rotonly_cli.simulation.sparse_visibility): memory grows with the observations,
  not with views x points.
* Every observation gets one pixel-noise draw (same models as the two-view simulation, default
  magnitude U(0, n) px), shared by all pairs, so tracks are consistent.
* Pairs: cameras at most ``window`` apart along the trajectory (cyclic for the closed ones)
  that share at least ``min_shared`` points; matches index the per-view keypoints.
* Initial relative poses (``init``): ``"ransac"`` = OpenCV 5-point RANSAC on the noisy
  matches (rotonly_cli.simulation.fivepoint; the paper's initialiser), ``"perturbed"`` = the
  ground truth rotated by ``init_noise_deg`` about a random axis, ``"truth"`` = exact.
* ``corrupt_fraction`` of the pairs get a uniformly random rotation and direction instead
  (repeated-structure outliers); they are listed in ``MultiViewProblem.corrupted_pairs``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.geometry import so3
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, Structure, View
from rotonly_cli.simulation.fivepoint import five_point_ransac, perturbed_rotation
from rotonly_cli.simulation.pair_scenes import NOISE_MODELS, add_pixel_noise, bounded_rotation, normalized_to_pixels
from rotonly_cli.simulation.sparse_visibility import (
    SparseVisibility,
    TrackLists,
    shared_keypoints,
    visible_observations,
)

SETUPS: tuple[str, ...] = ("circular", "square", "linear", "outward")
INITS: tuple[str, ...] = ("ransac", "perturbed", "truth")


@dataclass
class MultiViewProblem:
    scene: SfMScene  # views, intrinsics, keypoints, normalized (noisy), pairs with initial R_j_from_i; no poses
    gt_poses: dict[int, Pose]
    points_in_world: np.ndarray  # (N, 3)
    sparse_visibility: SparseVisibility  # per view the points it sees; keypoint k = its k-th
    corrupted_pairs: list[tuple[int, int]]
    setup: str
    noise_px: float
    focal: float
    image_size: tuple[int, int]
    parameters: dict = field(default_factory=dict)

    @property
    def visibility(self) -> np.ndarray:
        """(n_views, N) bool, which view sees which point: O(views x points), for small problems."""
        return self.sparse_visibility.dense()

    def gt_scene(self) -> SfMScene:
        """The scene with ground-truth poses and the true points as structure (for sfm_data.json)."""
        gt = copy.copy(self.scene)
        gt.poses = {k: Pose(p.R_cam_from_world.copy(), p.center.copy()) for k, p in self.gt_poses.items()}
        track_lengths, view_feature = self.sparse_visibility.tracks()
        gt.structure = Structure(point_ids=np.arange(len(self.points_in_world), dtype=np.int64),
                                 points=self.points_in_world.copy(),
                                 observations=TrackLists(track_lengths, view_feature),
                                 observation_arrays=(track_lengths, view_feature))
        gt.pairs = {key: copy.copy(pair) for key, pair in self.scene.pairs.items()}
        for (i, j), pair in gt.pairs.items():  # GT relative poses in the GT scene
            R_i, R_j = self.gt_poses[i].R_cam_from_world, self.gt_poses[j].R_cam_from_world
            pair.R_j_from_i = R_j @ R_i.T
            t = R_j @ (self.gt_poses[i].center - self.gt_poses[j].center)
            pair.t_j_from_i = t / np.linalg.norm(t)
        gt.source = "simulation-gt"
        return gt

    def gt_relative_rotation(self, i: int, j: int) -> np.ndarray:
        return self.gt_poses[j].R_cam_from_world @ self.gt_poses[i].R_cam_from_world.T


# ----------------------------------------------------------------------------- cameras
def _look_up(heading: np.ndarray) -> np.ndarray:
    """R_cam_from_world of a camera looking along +z world, image x-axis along ``heading``."""
    z = np.array([0.0, 0.0, 1.0])
    x = np.array([heading[0], heading[1], 0.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])  # rows are the camera axes in world coordinates


def _look_out(direction: np.ndarray) -> np.ndarray:
    """R_cam_from_world of a camera looking horizontally along ``direction``, image y down."""
    z = np.array([direction[0], direction[1], 0.0])
    z /= np.linalg.norm(z)
    y = np.array([0.0, 0.0, -1.0])
    return np.stack([np.cross(y, z), y, z])


def camera_layout(setup: str, num_views: int, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 3) and headings (n, 3): tangent of the trajectory, or the outward radial."""
    k = np.arange(num_views)
    if setup in ("circular", "outward"):
        radius = spacing / (2.0 * np.sin(np.pi / num_views))  # chord between neighbours = spacing
        phi = 2.0 * np.pi * k / num_views
        centers = np.column_stack([radius * np.cos(phi), radius * np.sin(phi), np.zeros(num_views)])
        radial = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(num_views)])
        tangent = np.column_stack([-np.sin(phi), np.cos(phi), np.zeros(num_views)])
        return centers, (radial if setup == "outward" else tangent)
    if setup == "square":
        side = num_views * spacing / 4.0
        s = k * spacing  # arc length along the perimeter, counter-clockwise from (-side/2, -side/2)
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], dtype=float) * side / 2
        edge = np.minimum((s // side).astype(int), 3)
        frac = (s - edge * side) / side
        xy = corners[edge] + frac[:, None] * (corners[edge + 1] - corners[edge])
        headings = corners[edge + 1] - corners[edge]
        return (np.column_stack([xy, np.zeros(num_views)]),
                np.column_stack([headings / side, np.zeros(num_views)]))
    if setup == "linear":
        x = (k - (num_views - 1) / 2.0) * spacing
        return (np.column_stack([x, np.zeros(num_views), np.zeros(num_views)]),
                np.tile([1.0, 0.0, 0.0], (num_views, 1)))
    raise InputError(f"unknown set-up {setup!r} (choose from {', '.join(SETUPS)})", field="setup")


def _point_sampler(setup: str, centers: np.ndarray, rng: np.random.Generator, max_height: float,
                   ring: tuple[float, float], ring_height: float):
    if setup == "outward":
        r_in, r_out = ring

        def sample(n: int) -> np.ndarray:
            r = np.sqrt(rng.uniform(r_in**2, r_out**2, size=n))  # uniform in area
            phi = rng.uniform(0.0, 2.0 * np.pi, size=n)
            return np.column_stack([r * np.cos(phi), r * np.sin(phi), rng.uniform(-ring_height, ring_height, n)])
        return sample
    margin = 0.3 * max_height
    lo = centers[:, :2].min(axis=0) - margin
    hi = centers[:, :2].max(axis=0) + margin

    def sample(n: int) -> np.ndarray:
        return np.column_stack([rng.uniform(lo, hi, size=(n, 2)), rng.uniform(0.0, max_height, n)])
    return sample


def _window_pairs(num_views: int, window: int, cyclic: bool) -> np.ndarray:
    """(pairs, 2) rows i < j at most ``window`` steps apart (cyclic: either way round), sorted,
    made from every view's next ``window`` views (O(views x window), not all pairs)."""
    steps = min(window, num_views)
    first = np.repeat(np.arange(num_views, dtype=np.int64), steps)
    second = first + np.tile(np.arange(1, steps + 1, dtype=np.int64), num_views)
    if cyclic:
        second %= num_views
    keep = (second < num_views) & (second != first)
    low, high = np.minimum(first, second)[keep], np.maximum(first, second)[keep]
    key = np.unique(low * num_views + high)
    return np.column_stack([key // num_views, key % num_views])


# ----------------------------------------------------------------------------- main entry
def simulate_multiview(setup: str = "circular", *, num_views: int = 100, num_points: int = 10_000,
                       noise_px: float = 1.0, focal: float = 800.0, image_size: tuple[int, int] | int = (960, 960),
                       rng: np.random.Generator | int | None = None, spacing: float = 10.0,
                       window: int = 10, min_shared: int = 30, init: str = "ransac",
                       init_noise_deg: float = 0.5, corrupt_fraction: float = 0.0,
                       noise_model: str = "uniform", max_tilt_deg: float = 5.0, max_height: float = 400.0,
                       ring: tuple[float, float] = (200.0, 3000.0), ring_height: float = 200.0,
                       ransac_threshold_px: float | None = None, epipolar_outlier_fraction: float = 0.0,
                       epipolar_shift_px: tuple[float, float] = (10.0, 80.0),
                       swapped_fraction: float = 0.0, look_alike_px: float = 40.0) -> MultiViewProblem:
    """Draw one multi-view problem (module docstring)."""
    if setup not in SETUPS:
        raise InputError(f"unknown set-up {setup!r} (choose from {', '.join(SETUPS)})", field="setup")
    if init not in INITS:
        raise InputError(f"unknown init {init!r} (choose from {', '.join(INITS)})", field="init")
    if noise_model not in NOISE_MODELS:
        raise InputError(f"unknown noise model {noise_model!r}", field="noise_model")
    if num_views < 3 or num_points < 1 or window < 1:
        raise InputError("need num_views >= 3, num_points >= 1, window >= 1", field="num_views/num_points/window")
    fractions = {"corrupt_fraction": corrupt_fraction, "epipolar_outlier_fraction": epipolar_outlier_fraction,
                 "swapped_fraction": swapped_fraction}
    for name, value in fractions.items():
        if not 0.0 <= value <= 1.0:
            raise InputError("must be in [0, 1]", field=name)
    if isinstance(image_size, (int, np.integer)):
        image_size = (int(image_size), int(image_size))
    image_size = (int(image_size[0]), int(image_size[1]))
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

    centers, headings = camera_layout(setup, num_views, spacing)
    orient = _look_out if setup == "outward" else _look_up
    tilt = np.deg2rad(max_tilt_deg)
    R_cam_from_world = np.stack([bounded_rotation(rng, tilt) @ orient(h) for h in headings])

    # --- points seen by >= 2 cameras, in batches (visibility kept sparse: sparse_visibility.py)
    sample = _point_sampler(setup, centers, rng, max_height, ring, ring_height)
    half = 0.5 * np.asarray(image_size, dtype=float) / focal
    kept_points, kept_views, kept_ids, have = [], [], [], 0
    batch = max(2 * num_points, 2000)
    for _ in range(200):
        X = sample(batch)
        views_seen, points_seen = visible_observations(X, R_cam_from_world, centers, half)
        ok = np.bincount(points_seen, minlength=len(X)) >= 2
        new_id = np.cumsum(ok) - 1 + have
        kept = ok[points_seen]
        kept_points.append(X[ok])
        kept_views.append(views_seen[kept])
        kept_ids.append(new_id[points_seen[kept]])
        have += int(ok.sum())
        if have >= num_points:
            break
    if have < num_points:
        raise AlgorithmError(f"could only place {have} of {num_points} points seen by two cameras ({setup})")
    points = np.concatenate(kept_points)[:num_points]
    observation_views, observation_ids = np.concatenate(kept_views), np.concatenate(kept_ids)
    first_points = observation_ids < num_points
    visibility = SparseVisibility.from_observations(observation_views[first_points], observation_ids[first_points],
                                                    num_views, num_points)
    del kept_points, kept_views, kept_ids, observation_views, observation_ids, first_points

    # --- per-view keypoints (noise drawn once per observation)
    x_true = _true_image_points(points, R_cam_from_world, centers, visibility)
    swapped = _swap_look_alikes(x_true, visibility, swapped_fraction, look_alike_px / focal, rng)
    scene = SfMScene(source="simulation")
    scene.intrinsics[0] = Intrinsics(id=0, model="PINHOLE", width=image_size[0], height=image_size[1],
                                     params=np.array([focal, focal, image_size[0] / 2, image_size[1] / 2]))
    gt_poses: dict[int, Pose] = {}
    for v in range(num_views):
        scene.views[v] = View(id=v, name=f"sim_{v:04d}.jpg", intrinsics_id=0)
        x_noisy = add_pixel_noise(x_true[visibility.offsets[v]:visibility.offsets[v + 1]], noise_px, focal, rng,
                                  noise_model)
        scene.normalized[v] = x_noisy
        scene.keypoints[v] = normalized_to_pixels(x_noisy, focal, image_size)
        gt_poses[v] = Pose(R_cam_from_world[v].copy(), centers[v].copy())

    # --- pairs, matches and initial relative poses
    candidates = _window_pairs(num_views, window, cyclic=setup != "linear")
    threshold = ransac_threshold_px if ransac_threshold_px is not None else max(1.0, 2.0 * noise_px)
    for i, j in candidates:
        keypoints_i, keypoints_j = shared_keypoints(visibility, i, j)  # the shared points, by point id
        if len(keypoints_i) < min_shared:
            continue
        matches = np.column_stack([keypoints_i, keypoints_j]).astype(np.int64)
        R_true = R_cam_from_world[j] @ R_cam_from_world[i].T
        t_true = R_cam_from_world[j] @ (centers[i] - centers[j])
        t_true /= np.linalg.norm(t_true)
        if epipolar_outlier_fraction > 0:
            x_j_true = x_true[visibility.offsets[j]:visibility.offsets[j + 1]]
            matches = _move_along_epipolar_lines(scene, matches, x_j_true, R_true, t_true, focal, image_size,
                                                 int(j), epipolar_outlier_fraction, epipolar_shift_px, noise_px,
                                                 noise_model, rng)
        pair = PairMatches(i=int(i), j=int(j), matches=matches, config="CALIBRATED")
        if init == "ransac":
            est = five_point_ransac(scene.normalized[i][matches[:, 0]], scene.normalized[j][matches[:, 1]],
                                    focal, threshold_px=threshold, seed=int(rng.integers(2**31)))
            if est.success:
                pair.R_j_from_i, pair.t_j_from_i = est.R_j_from_i, est.t_direction
            else:
                pair.config = "DEGENERATE"
        elif init == "perturbed":
            pair.R_j_from_i, pair.t_j_from_i = perturbed_rotation(R_true, init_noise_deg, rng), t_true
        else:
            pair.R_j_from_i, pair.t_j_from_i = R_true.copy(), t_true
        scene.pairs[(int(i), int(j))] = pair

    # --- repeated-structure outliers: random rotations on a fraction of the edges
    keys = sorted(scene.pairs)
    num_corrupt = int(round(corrupt_fraction * len(keys)))
    corrupted = [keys[k] for k in sorted(rng.choice(len(keys), size=num_corrupt, replace=False))] if num_corrupt else []
    if corrupted:
        random_R = so3.random_rotations(len(corrupted), rng)
        random_t = rng.normal(size=(len(corrupted), 3))
        random_t /= np.linalg.norm(random_t, axis=1, keepdims=True)
        for key, R, t in zip(corrupted, random_R, random_t):
            scene.pairs[key].R_j_from_i, scene.pairs[key].t_j_from_i = R, t
            scene.pairs[key].config = "CALIBRATED"

    parameters = dict(num_views=num_views, num_points=num_points, spacing=spacing, window=window,
                      min_shared=min_shared, init=init, init_noise_deg=init_noise_deg,
                      corrupt_fraction=corrupt_fraction, noise_model=noise_model, max_tilt_deg=max_tilt_deg,
                      epipolar_outlier_fraction=epipolar_outlier_fraction, epipolar_shift_px=list(epipolar_shift_px),
                      swapped_fraction=swapped_fraction, look_alike_px=look_alike_px,
                      num_swapped_observations=swapped)
    return MultiViewProblem(scene=scene, gt_poses=gt_poses, points_in_world=points, sparse_visibility=visibility,
                            corrupted_pairs=corrupted, setup=setup, noise_px=float(noise_px), focal=float(focal),
                            image_size=image_size, parameters=parameters)


def _true_image_points(points: np.ndarray, R_cam_from_world: np.ndarray, centers: np.ndarray,
                       visibility: SparseVisibility) -> np.ndarray:
    """(observations, 2) normalized image position of every observation, view by view in
    keypoint order (the same einsum per view as for all views at once, so the same bits)."""
    x_true = np.empty((len(visibility.point_ids), 2))
    for v in range(visibility.num_views):
        rows = slice(visibility.offsets[v], visibility.offsets[v + 1])
        X_cam = np.einsum("vab,vnb->vna", R_cam_from_world[v:v + 1],
                          points[visibility.point_ids[rows]][None] - centers[v:v + 1, None])[0]
        x_true[rows] = X_cam[:, :2] / X_cam[:, 2:3]
    return x_true


def _swap_look_alikes(x_true: np.ndarray, visibility: SparseVisibility, fraction: float, radius: float,
                      rng: np.random.Generator) -> int:
    """Repeated structure seen by one camera: in each view, about ``fraction`` of the visible
    points trade their image positions (``x_true``, per observation) with a look-alike point
    within ``radius`` (normalized units) of them, in place, so every match of that view through
    them is wrong the same way and the wrong matches form whole consistent tracks. Returns the
    number of observations moved."""
    if fraction <= 0:
        return 0
    moved = 0
    for v in range(visibility.num_views):
        first = int(visibility.offsets[v])
        seen = np.arange(first, visibility.offsets[v + 1])  # the view's rows of x_true
        if seen.size < 2:
            continue
        pts = x_true[seen]
        order = rng.permutation(seen.size)
        taken = np.zeros(seen.size, dtype=bool)
        budget = int(round(fraction * seen.size / 2))
        for a in order:
            if budget == 0:
                break
            if taken[a]:
                continue
            distance = np.linalg.norm(pts - pts[a], axis=1)
            near = np.flatnonzero((distance < radius) & (distance > 0) & ~taken)
            if near.size == 0:
                continue
            b = near[rng.integers(near.size)]
            ka, kb = seen[a], seen[b]
            x_true[[ka, kb]] = x_true[[kb, ka]]
            taken[[a, b]] = True
            budget -= 1
            moved += 2
    return moved


def _move_along_epipolar_lines(scene: SfMScene, matches: np.ndarray, x_j_true: np.ndarray,
                               R_true: np.ndarray, t_true: np.ndarray, focal: float, image_size: tuple[int, int],
                               j: int, fraction: float, shift_px: tuple[float, float], noise_px: float,
                               noise_model: str, rng: np.random.Generator) -> np.ndarray:
    """Wrong matches that pass any two-view check: ``fraction`` of the pair's matches get a
    new keypoint in view j, the true one (``x_j_true``: view j's true positions by keypoint)
    moved by U(shift_px) pixels (either way) along its epipolar line (x_jᵀ E x_i = 0 still
    holds), with its own pixel noise. Returns the matches."""
    count = int(round(fraction * len(matches)))
    if count == 0:
        return matches
    rows = rng.choice(len(matches), size=count, replace=False)
    x_j = np.c_[x_j_true[matches[rows, 1]], np.ones(count)]
    epipole = t_true / t_true[2] if abs(t_true[2]) > 1e-12 else None
    # the epipolar line through x_j runs towards the epipole (or along t for a far epipole)
    direction = (x_j - epipole)[:, :2] if epipole is not None else np.broadcast_to(t_true[:2], (count, 2))
    direction = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    step = rng.uniform(*shift_px, size=count) * rng.choice([-1.0, 1.0], size=count) / focal
    moved = add_pixel_noise(x_j[:, :2] + step[:, None] * direction, noise_px, focal, rng, noise_model)
    first = len(scene.normalized[j])
    scene.normalized[j] = np.concatenate([scene.normalized[j], moved])
    scene.keypoints[j] = np.concatenate([scene.keypoints[j], normalized_to_pixels(moved, focal, image_size)])
    matches = matches.copy()
    matches[rows, 1] = first + np.arange(count)
    return matches


# ----------------------------------------------------------------------------- files
def _writer(module: str, name: str):
    """The COLMAP / OpenMVG writers of ``rotonly_cli.io``, imported lazily."""
    import importlib

    return getattr(importlib.import_module(f"rotonly_cli.io.{module}"), name)


def as_openmvg_camera(scene: SfMScene) -> SfMScene:
    """Shallow copy of ``scene`` whose COLMAP ``PINHOLE`` (fx = fy) cameras become OpenMVG
    ``pinhole`` [focal, ppx, ppy] (both in COLMAP's pixel convention, scene/types.py)."""
    out = copy.copy(scene)
    out.intrinsics = {}
    for key, intr in scene.intrinsics.items():
        fx, fy, cx, cy = np.asarray(intr.params, dtype=float)
        if intr.model != "PINHOLE" or fx != fy:
            raise InputError(f"cannot express {intr.model} {intr.params} as an OpenMVG pinhole",
                             field=f"intrinsics[{key}]")
        out.intrinsics[key] = Intrinsics(id=intr.id, model="pinhole", width=intr.width, height=intr.height,
                                         params=np.array([fx, cx, cy]))
    return out


def save_multiview(out_dir, problem: MultiViewProblem, formats: tuple[str, ...] = ("colmap", "openmvg")):
    """Write ``problem`` into ``out_dir`` atomically (temp folder next to it, renamed at the end).

    Layout: ``database.db`` (COLMAP: cameras, images, keypoints, matches and two-view
    geometries with the initial relative poses), ``openmvg/sfm_data.json`` + ``openmvg/matches``
    (OpenMVG project without poses), ``gt/sfm_data.json`` (OpenMVG, ground-truth poses and
    points), and ``simulation.json`` (set-up parameters and the corrupted pairs).
    """
    import json
    from pathlib import Path

    from rotonly_cli.io import atomic

    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError("exists and is not an empty folder", path=out_dir, field="-o")
    with atomic.staging_dir(out_dir) as tmp:
        if "colmap" in formats:
            _writer("colmap", "write_database")(tmp / "database.db", problem.scene)
        if "openmvg" in formats:
            _writer("openmvg", "write_project")(tmp / "openmvg", as_openmvg_camera(problem.scene))
        (tmp / "gt").mkdir()
        _writer("openmvg", "write_sfm_data")(tmp / "gt" / "sfm_data.json", as_openmvg_camera(problem.gt_scene()))
        info = dict(setup=problem.setup, noise_px=problem.noise_px, focal=problem.focal,
                    image_size=list(problem.image_size), num_pairs=len(problem.scene.pairs),
                    corrupted_pairs=[list(map(int, key)) for key in problem.corrupted_pairs],
                    **{k: (v if not isinstance(v, tuple) else list(v)) for k, v in problem.parameters.items()})
        (tmp / "simulation.json").write_text(json.dumps(info, indent=2))
    return out_dir
