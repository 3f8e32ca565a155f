"""Stage `load`: INPUT (COLMAP database or OpenMVG project) -> SfMScene -> ViewGraph.

Relative poses: every edge is re-estimated from its matches by default (``--reestimate``:
``auto`` keeps COLMAP's E-based stored poses, ``none`` keeps every stored pose). Poses
decomposed from a homography or a fundamental matrix are several times less accurate
(data/strecha/README.md), OpenMVG stores none, and COLMAP verifies at 4 px, loose enough for
repeated-structure matches to pull its E.

The estimate is pycolmap's calibrated LO-RANSAC (``estimate_relative_pose``, formats.md §4.7)
on normalized coordinates at a threshold measured on the input: ``inlier_threshold_sigmas``
x the noise sigma of the matches (Sampson errors of a loose RANSAC on the largest pairs).
Each edge runs ``consensus_runs`` seeded RANSACs and keeps the stable consensus: the matches
that every run accepts (:func:`stable_consensus`); an edge whose first run falls short of
``min_inliers`` gets no further runs (it would be filtered anyway), and no run goes on beyond
the trials an inlier ratio of ``min_inliers`` / its matches needs (a consensus run: beyond
those its first run's inlier ratio needs). An edge whose first two runs, on a smaller subset,
agree keep them (``consensus_agreement``; on edges of more than ``agreement_min_matches`` matches, in a
load of at least ``agreement_min_edges`` edges (--consensus auto, the default): :func:`_consensus_runs`).
Dropped matches are counted per edge and reason. It is per-edge C++ work, so a loop over edges is fine here.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry import so3
from rotonly_cli.io import cameras
from rotonly_cli.io.detect import InputKind, detect_input
from rotonly_cli.io.readers import READERS
from rotonly_cli.options import LoadOptions, Reestimate
from rotonly_cli.runtime import cluster, heartbeat
from rotonly_cli.scene.types import Intrinsics, SfMScene
from rotonly_cli.scene.view_graph import Edge, ViewGraph, largest_component

logger = logging.getLogger(__name__)

#: configurations whose stored cam2_from_cam1 comes from an essential matrix (formats.md §4.5)
ESSENTIAL_CONFIGS = ("CALIBRATED", "E")
#: matches per sample of the five-point essential-matrix solver
ESSENTIAL_SAMPLE_SIZE = 5


def read_input(input_path: str | Path, matches_dir: str | Path | None = None,
               matches_file: str | Path | None = None, scratch_dir: str | Path | None = None,
               kind: InputKind | None = None) -> tuple[SfMScene, str]:
    """(scene, kind) for a COLMAP database or an OpenMVG sfm_data.json (+ features, matches;
    ``matches_file``: the matches file, -M, else the first of matches.e/f/putative), read as
    io/readers.READERS reads its kind. ``scratch_dir``: where a database's private copy is made
    (default: a temporary folder); ``kind``: the input's kind, when detected already."""
    input_path = Path(input_path)
    kind = kind or detect_input(input_path)
    return READERS[kind].read(input_path, matches_dir, matches_file, scratch_dir), kind


def without_unprojectable_keypoints(scene: SfMScene) -> tuple[SfMScene, dict]:
    """``scene`` (not changed) with the matches of keypoints its cameras cannot undistort
    left out (io.cameras.undistortion_failures: a fisheye's rays 90° or more off its axis,
    which normalized z = 1 coordinates cannot hold), and a report: those keypoints per view,
    the matches left out. The same scene when there are none."""
    failed = {}
    for view_id, view in scene.views.items():
        if view_id in scene.normalized and view_id in scene.keypoints:
            bad = cameras.undistortion_failures(scene.intrinsics[view.intrinsics_id], scene.keypoints[view_id],
                                                scene.normalized[view_id])
            if bad.any():
                failed[view_id] = bad
    if not failed:
        return scene, {}
    out = copy.copy(scene)
    out.normalized, out.pairs = dict(scene.normalized), dict(scene.pairs)
    for view_id, bad in failed.items():
        out.normalized[view_id] = np.where(bad[:, None], np.nan, scene.normalized[view_id])
    dropped = 0
    for key, pair in scene.pairs.items():
        matches = np.asarray(pair.matches, dtype=np.int64).reshape(-1, 2)
        keep = np.ones(len(matches), dtype=bool)
        for column, view_id in ((0, pair.i), (1, pair.j)):
            if view_id in failed:
                keep &= ~failed[view_id][matches[:, column]]
        if not keep.all():
            out.pairs[key] = replace(pair, matches=matches[keep])
            dropped += int((~keep).sum())
    report = {"keypoints_not_undistorted": {str(v): int(bad.sum()) for v, bad in sorted(failed.items())},
              "matches_of_them_left_out": dropped}
    logger.info("load: %d keypoints in %d view(s) lie where the camera model cannot be inverted (a fisheye's rays "
                "90 deg or more off its axis): their %d matches are left out",
                sum(int(b.sum()) for b in failed.values()), len(failed), dropped)
    return out, report


def unprojectable_warning(report: dict | None) -> str | None:
    """The run summary's warning for keypoints the cameras cannot undistort (load report)."""
    counts = (report or {}).get("keypoints_not_undistorted")
    if not counts:
        return None
    return (f"{sum(counts.values())} keypoints in {len(counts)} view(s) lie where the camera model cannot be "
            f"inverted (rays 90 deg or more off the axis: a fisheye wider than 180 deg, or a distortion model "
            f"beyond its range): their {report['matches_of_them_left_out']} matches are left out "
            f"(reports/load.json)")


def input_files(input_path: str | Path, kind: str, scene: SfMScene, matches_dir: str | Path | None = None,
                matches_file: str | Path | None = None) -> dict:
    """What :func:`read_input` read, for reports/load.json: ``input_files`` (the database, or
    the sfm_data.json, each view's ``.feat`` and the matches file) and, for OpenMVG input,
    ``matches_file``."""
    return READERS[kind].files(Path(input_path), scene, matches_dir, matches_file)


def focal_length(intrinsics: Intrinsics) -> float:
    """Focal length in pixels (mean of fx, fy for two-focal COLMAP models)."""
    return intrinsics.focal_px


def ransac_trials(num_matches: int, options: LoadOptions, inlier_ratio: float | None = None) -> tuple[int, int]:
    """(min, max) RANSAC trials of an edge of ``num_matches`` matches.

    An edge needs min_inliers of its matches to survive: a RANSAC that has not drawn a model
    with that many after the trials such an inlier ratio needs has, at this confidence, an
    edge that is filtered anyway (weak pairs are the ones that run to the trial limit). With
    the edge's ``inlier_ratio`` known (its first run's), a consensus run stops at the trials
    that ratio needs, but not below the ``ransac_min_trials`` floor: without it (4 trials at
    0.99) the 1000-view recipe's consensus runs settled on worse models, dropping 7x more
    matches as unstable and 3 of its 10 000 edges (docs/tuning.md)."""
    ceiling = max(options.ransac_max_trials, options.ransac_min_trials)
    needed = pg.ransac_trials_needed(options.min_inliers / max(num_matches, 1), ESSENTIAL_SAMPLE_SIZE,
                                     options.ransac_confidence)
    max_trials = int(np.clip(needed, options.ransac_min_trials, ceiling))
    if inlier_ratio is not None:
        known = pg.ransac_trials_needed(inlier_ratio, ESSENTIAL_SAMPLE_SIZE, options.ransac_confidence)
        max_trials = int(np.clip(known, options.ransac_min_trials, max_trials))
    return options.ransac_min_trials, max_trials


def _relative_pose_ransac(x_i: np.ndarray, x_j: np.ndarray, focal_i: float, focal_j: float, max_error_px: float,
                          seed: int, options: LoadOptions, inlier_ratio: float | None = None):
    """pycolmap LO-RANSAC on normalized points through SIMPLE_PINHOLE(f, 0, 0) cameras, so
    the threshold is in pixels. Returns (R_j_from_i, unit t, inlier mask) or None.
    ``inlier_ratio``: the edge's, when known (:func:`ransac_trials`).

    Beyond ``options.ransac_max_matches`` matches RANSAC runs on a seeded random subset of
    that size, and the inliers are every match within the threshold of its model (Sampson)."""
    import pycolmap

    min_trials, max_trials = ransac_trials(len(x_i), options, inlier_ratio)
    subset = None
    if options.ransac_max_matches is not None and len(x_i) > options.ransac_max_matches:
        subset = np.sort(np.random.default_rng(seed).choice(len(x_i), options.ransac_max_matches, replace=False))
        all_i, all_j, x_i, x_j = x_i, x_j, x_i[subset], x_j[subset]

    cameras = [pycolmap.Camera(model=pycolmap.CameraModelId.SIMPLE_PINHOLE, width=2, height=2,
                               params=np.array([f, 0.0, 0.0])) for f in (focal_i, focal_j)]
    ransac = pycolmap.RANSACOptions(max_error=max_error_px, random_seed=seed, min_num_trials=min_trials,
                                    max_num_trials=max_trials,
                                    confidence=options.ransac_confidence,
                                    dyn_num_trials_multiplier=options.ransac_trials_multiplier)
    result = pycolmap.estimate_relative_pose(cameras[0], np.ascontiguousarray(x_i * focal_i), cameras[1],
                                             np.ascontiguousarray(x_j * focal_j), ransac)
    if result is None:
        return None
    pose = result["cam2_from_cam1"]
    t = np.array(pose.translation, dtype=float)
    norm = np.linalg.norm(t)
    R, t = np.array(pose.rotation.matrix(), dtype=float), t / norm if norm > 0 else t
    if subset is None:
        return R, t, np.asarray(result["inlier_mask"], dtype=bool).ravel()
    return R, t, pg.sampson_errors(R, t, all_i, all_j) * 0.5 * (focal_i + focal_j) <= max_error_px


def _pool_map(function, items: list, progress: bool, desc: str, threads: int = 0) -> list:
    """``function`` over ``items`` on ``threads`` threads (0: one per usable CPU; pycolmap
    releases the GIL inside RANSAC; every call is seeded, so the results do not depend on the
    scheduling). In a pipe the runs are counted for the progress lines (runtime/heartbeat)."""
    from concurrent.futures import ThreadPoolExecutor

    from rotonly_cli.runtime.parallel import usable_cpus

    with ThreadPoolExecutor(max_workers=threads or usable_cpus()) as pool:
        results = pool.map(function, items)
        if progress:
            from rotonly_cli.runtime.progress import progress_bar

            return list(progress_bar(results, total=len(items), desc=desc, unit="run", leave=False))
        # in a pipe: counted for the progress lines ("relative poses (RANSAC)" -> load/RANSAC)
        with heartbeat.task(desc[desc.find("(") + 1:].rstrip(")") or "runs", len(items)) as advance:
            done = []
            for result in results:
                done.append(result)
                advance()
            return done


#: matches per --cluster task of RANSAC runs: a run takes ~7 us per match (the 200-view recipe:
#: 8000 runs of ~2200 matches, 15 ms each), so 2^17 matches are ~1 s of work
CLUSTER_TASK_MATCHES = 1 << 17
#: the noise sigma needs this many inlier residuals to be trusted; below, the loose threshold is used
MIN_NOISE_SAMPLES = 50
#: the measured threshold never goes below this (px): noise-free input would otherwise ask
#: RANSAC for a zero threshold
MIN_THRESHOLD_PX = 0.05


def noise_sigma_px(pairs: EdgeCoordinates, options: LoadOptions) -> float | None:
    """Noise sigma (px) of the matches under the essential-matrix model: 1.4826 x the median
    Sampson error of the inliers of a loose RANSAC (``options.noise_ransac_max_error_px``) on
    the largest ``noise_sample_edges`` pairs; None with too few inliers."""
    order = sorted(range(len(pairs)), key=lambda k: -pairs.num_matches(k))[:options.noise_sample_edges]

    def residuals(k: int) -> np.ndarray:
        x_i, x_j, focal_i, focal_j = pairs[k]
        estimate = _relative_pose_ransac(x_i, x_j, focal_i, focal_j, options.noise_ransac_max_error_px,
                                         options.seed, options)
        if estimate is None:
            return np.zeros(0)
        R, t, inliers = estimate
        return pg.sampson_errors(R, t, x_i[inliers], x_j[inliers]) * 0.5 * (focal_i + focal_j)

    errors = np.concatenate([np.zeros(0)] + _pool_map(residuals, order, False, "", options.jobs))
    return 1.4826 * float(np.median(errors)) if errors.size >= MIN_NOISE_SAMPLES else None


def runs_agree(estimates: list, agreement: float) -> bool:
    """Whether an edge's RANSAC runs (R, t, inlier mask) keep the same matches: those that
    some but not all of them accept are at most ``agreement`` x the matches any accepts."""
    masks = [estimate[2] for estimate in estimates]
    union, common = np.logical_or.reduce(masks), np.logical_and.reduce(masks)
    return int(union.sum() - common.sum()) <= agreement * int(union.sum())


def stable_consensus(estimates: list) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One edge's seeded RANSAC results (R, t, inlier mask) -> (R, t, stable mask): the
    matches that are inliers of every run, with the pose of the run whose rotation is closest
    to the others' (least sum of geodesic angles). None if a run failed.

    Near-degenerate pairs (a dominant plane, repeated structure) let RANSAC settle on
    different models from different samples; matches near the threshold then swing in and out
    of the inlier set, and the ones that swing pull the rotation (docs/tuning.md "Load").
    Those that every run accepts do not."""
    if not estimates or any(estimate is None for estimate in estimates):
        return None
    stable = np.logical_and.reduce([estimate[2] for estimate in estimates])
    if len(estimates) <= 2:  # the two sums of angles are equal: the first run's pose, as argmin takes it
        return estimates[0][0], estimates[0][1], stable
    R = np.stack([estimate[0] for estimate in estimates])
    spread = so3.geodesic_angle(R[:, None], R[None, :]).sum(axis=1)
    best = estimates[int(np.argmin(spread))]
    return best[0], best[1], stable


def _edges_to_estimate(scene: SfMScene, options: LoadOptions) -> tuple[ViewGraph, list[int], EdgeCoordinates]:
    """The view graph of every pair (edges filtered where the input rules them out), the
    edges whose pose is re-estimated and their (x_i, x_j, focal_i, focal_j)."""
    graph = ViewGraph(views=dict(scene.views))
    to_estimate: list[int] = []
    for (i, j) in sorted(scene.pairs):
        pair = scene.pairs[(i, j)]
        matches = np.asarray(pair.matches, dtype=np.int64).reshape(-1, 2)
        has_pose = pair.R_j_from_i is not None and pair.verified
        essential = pair.config in ESSENTIAL_CONFIGS
        edge = Edge(i, j, np.asarray(pair.R_j_from_i, dtype=float) if has_pose else np.eye(3),
                    np.zeros(3) if pair.t_j_from_i is None else np.asarray(pair.t_j_from_i, dtype=float),
                    matches, pose_source="stored" if has_pose else "", config=pair.config)
        graph.edges.append(edge)
        if i not in scene.normalized or j not in scene.normalized:
            edge.filter("view without calibration")
        elif len(matches) < options.min_inliers:
            edge.filter("too few inliers")
        elif options.reestimate == Reestimate.ALL or (options.reestimate == Reestimate.AUTO
                                                      and not (has_pose and essential)):
            to_estimate.append(len(graph.edges) - 1)
        elif not has_pose:
            edge.filter("no relative pose")

    return graph, to_estimate, EdgeCoordinates(scene, graph, to_estimate)


class EdgeCoordinates:
    """The ``(x_i, x_j, focal_i, focal_j)`` of the edges ``to_estimate`` (indices into
    ``graph.edges``), gathered when a RANSAC run asks for them: all of them at once would hold
    32 bytes per match (0.7 GB for 21 M matches) for the whole stage."""

    def __init__(self, scene: SfMScene, graph: ViewGraph, to_estimate: list[int]):
        self._scene, self._edges = scene, [graph.edges[k] for k in to_estimate]

    def __len__(self) -> int:
        return len(self._edges)

    def num_matches(self, n: int) -> int:
        return len(self._edges[n].matches)

    @property
    def normalized(self) -> dict[int, np.ndarray]:
        return self._scene.normalized

    def arrays(self, ns: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Edges ``ns`` as plain arrays (a cluster task's): views (k, 2), match counts (k,),
        matches (M, 2) concatenated, focal lengths (k, 2)."""
        scene, edges = self._scene, [self._edges[n] for n in ns]
        focal = [[focal_length(scene.intrinsics[scene.views[v].intrinsics_id]) for v in (edge.i, edge.j)]
                 for edge in edges]
        return (np.array([(edge.i, edge.j) for edge in edges], dtype=np.int64).reshape(-1, 2),
                np.array([len(edge.matches) for edge in edges], dtype=np.int64),
                np.concatenate([edge.matches for edge in edges]).astype(np.int32) if edges  # keypoint indices
                else np.zeros((0, 2), dtype=np.int32),
                np.array(focal, dtype=np.float64).reshape(-1, 2))

    def __getitem__(self, n: int) -> tuple[np.ndarray, np.ndarray, float, float]:
        edge, scene = self._edges[n], self._scene
        return (scene.normalized[edge.i][edge.matches[:, 0]], scene.normalized[edge.j][edge.matches[:, 1]],
                focal_length(scene.intrinsics[scene.views[edge.i].intrinsics_id]),
                focal_length(scene.intrinsics[scene.views[edge.j].intrinsics_id]))


def _cluster_runs(session, pairs: EdgeCoordinates, runs: list[tuple], threshold: float,
                  run_options: LoadOptions) -> list:
    """The RANSAC ``runs`` (edge, seed, inlier ratio or None, options) on the cluster
    (--cluster), in order: tasks of consecutive runs of CLUSTER_TASK_MATCHES matches or more,
    each with its edges' matches and focal lengths; the keypoints scattered once. Every run is
    seeded: the same estimates as on this machine's threads."""
    from rotonly_cli.runtime.cluster import group_ranges

    edges = [run[0] for run in runs]
    counts = np.array([pairs.num_matches(n) for n in edges], dtype=np.int64)
    groups = group_ranges([(k, k + 1) for k in range(len(runs))], counts, CLUSTER_TASK_MATCHES)
    normalized = session.scatter(pairs.normalized, "load")

    def tasks():
        for group in groups:
            a, b = group[0][0], group[-1][1]
            seeds = np.array([run[1] for run in runs[a:b]], dtype=np.int64)
            ratios = np.array([np.nan if run[2] is None else run[2] for run in runs[a:b]])
            yield normalized, pairs.arrays(edges[a:b]), seeds, ratios, threshold, run_options

    return [estimate for part in session.map("load", _ransac_task, tasks(), len(groups)) for estimate in part]


def _ransac_task(normalized: dict, arrays: tuple, seeds: np.ndarray, ratios: np.ndarray, threshold: float,
                 options: LoadOptions) -> list:
    """On a cluster worker: the RANSAC runs of :func:`_cluster_runs`' task, their coordinates
    gathered from the keypoints as EdgeCoordinates gathers them."""
    views, counts, matches, focals = arrays
    bounds = np.concatenate([[0], np.cumsum(counts)])
    estimates = []
    for k in range(len(views)):
        pair = matches[bounds[k]:bounds[k + 1]]
        x_i, x_j = normalized[int(views[k, 0])][pair[:, 0]], normalized[int(views[k, 1])][pair[:, 1]]
        ratio = None if np.isnan(ratios[k]) else float(ratios[k])
        estimates.append(_relative_pose_ransac(x_i, x_j, float(focals[k, 0]), float(focals[k, 1]), threshold,
                                               int(seeds[k]), options, ratio))
    return estimates


def uses_agreement(options: LoadOptions, num_edges: int) -> bool:
    """Whether a load that re-estimates ``num_edges`` edges takes the agreeing runs' front end
    (``consensus_agreement`` set, and at least ``agreement_min_edges`` edges)."""
    return options.consensus_agreement is not None and num_edges >= options.agreement_min_edges


def _consensus_runs(pairs: EdgeCoordinates, threshold: float, options: LoadOptions) -> list[list]:
    """Every edge's seeded RANSAC runs (R, t, inlier mask; None where one failed), for
    :func:`stable_consensus`.

    The first run of every edge, then the other runs only where it found enough inliers: the
    stable consensus is a subset of every run's inliers, so an edge whose first run falls
    short of --min-inliers is filtered whatever the others find (weak pairs are also the ones
    whose RANSAC runs to its trial limit).

    With ``consensus_agreement``, the edges of more than ``agreement_min_matches`` matches
    take the fast front end: their consensus runs know the edge's inlier ratio (the first
    run's) and stop at the trials it needs (:func:`ransac_trials`; the other edges' runs all
    have the trials of the first: that bound changes noisy pairs enough to change which pairs
    the refutation filters), and their first two runs see at most ``agreement_max_matches``
    matches; an edge whose two runs agree (:func:`runs_agree`) keeps them. The others make
    their ``consensus_runs`` runs on ``ransac_max_matches``. Every run is seeded by the run's
    number alone, so an edge's runs do not depend on which path the other edges take."""
    session = cluster.active()
    runs_of_edge: list[list] = [[] for _ in range(len(pairs))]

    def estimate_run(run: tuple[int, int, float | None, LoadOptions]):
        x_i, x_j, focal_i, focal_j = pairs[run[0]]
        return _relative_pose_ransac(x_i, x_j, focal_i, focal_j, threshold, run[1], run[3], run[2])

    def make_runs(edges: list[int], r: int, ratio: dict, run_options: LoadOptions, what: str) -> None:
        if not edges:
            return
        runs = [(n, options.seed + r, ratio.get(n), run_options) for n in edges]
        estimates = _pool_map(estimate_run, runs, options.progress, what, options.jobs) if session is None \
            else _cluster_runs(session, pairs, runs, threshold, run_options)
        for (n, *_), estimate in zip(runs, estimates):
            runs_of_edge[n].append(estimate)

    def strong(edges: list[int]) -> dict[int, float]:
        """The edges whose first run found min_inliers, and their inlier ratios."""
        return {n: float(runs_of_edge[n][0][2].mean()) for n in edges if runs_of_edge[n][0] is not None
                and int(runs_of_edge[n][0][2].sum()) >= options.min_inliers}

    every = range(len(pairs))
    fast = [] if not uses_agreement(options, len(pairs)) else \
        [n for n in every if pairs.num_matches(n) > options.agreement_min_matches]
    fast_set = set(fast)
    # the edges of few matches (all of them without consensus_agreement): every run with the first's trials
    rest = [n for n in every if n not in fast_set]
    make_runs(rest, 0, {}, options, "relative poses (RANSAC)")
    pending = list(strong(rest))
    for r in range(1, options.consensus_runs):
        make_runs(pending, r, {}, options, f"relative poses (consensus run {r + 1})")
        pending = [n for n in pending if runs_of_edge[n][-1] is not None]
    if fast:
        _fast_consensus_runs(fast, pairs, options, make_runs, strong, runs_of_edge)
    return runs_of_edge


def _fast_consensus_runs(edges: list[int], pairs: EdgeCoordinates, options: LoadOptions, make_runs, strong,
                         runs_of_edge: list[list]) -> None:
    """:func:`_consensus_runs`' fast front end on ``edges`` (``make_runs``, ``strong``: its own)."""
    full = options.ransac_max_matches
    probing = options.consensus_runs > 2
    probe = replace(options, ransac_max_matches=options.agreement_max_matches if full is None
                    else min(full, options.agreement_max_matches)) if probing else options
    make_runs(edges, 0, {}, probe, "relative poses (RANSAC)")
    ratio = strong(edges)
    pending = list(ratio)
    if not probing:
        for r in range(1, options.consensus_runs):
            make_runs(pending, r, ratio, options, f"relative poses (consensus run {r + 1})")
            pending = [n for n in pending if runs_of_edge[n][-1] is not None]
        return
    make_runs(pending, 1, ratio, probe, "relative poses (second run)")
    pending = [n for n in pending if runs_of_edge[n][1] is not None
               and not runs_agree(runs_of_edge[n], options.consensus_agreement)]
    again = [n for n in pending if pairs.num_matches(n) > probe.ransac_max_matches]
    for n in again:
        runs_of_edge[n] = []
    make_runs(again, 0, {}, options, "relative poses (RANSAC, all matches)")
    ratio.update(strong(again))
    pending = [n for n in pending if n in ratio]
    for r in range(1, options.consensus_runs):
        make_runs([n for n in pending if len(runs_of_edge[n]) == r], r, ratio, options,
                  f"relative poses (consensus run {r + 1})")


#: :func:`measure_noise` found nothing to measure (a fixed threshold, no pair to re-estimate)
NOT_MEASURED = object()


def measure_noise(scene: SfMScene, options: LoadOptions):
    """The noise sigma (px) :func:`build_view_graph` measures on ``scene`` with ``options``
    (None: too few inliers; NOT_MEASURED: it measures none), to be looked at before the
    relative poses are estimated and handed to it."""
    if options.ransac_max_error_px is not None:
        return NOT_MEASURED
    _, _, pairs = _edges_to_estimate(scene, options)
    return noise_sigma_px(pairs, options) if pairs else NOT_MEASURED


def build_view_graph(scene: SfMScene, options: LoadOptions = LoadOptions(),
                     noise_sigma=NOT_MEASURED) -> tuple[ViewGraph, dict]:
    """ViewGraph of the scene's pairs (re-estimating poses as the module docstring says),
    with the min-inlier filter and the largest-component check applied. ``noise_sigma``: the
    :func:`measure_noise` of this scene and these options, when it was made already."""
    options.validate()
    start = time.perf_counter()
    graph, to_estimate, pairs = _edges_to_estimate(scene, options)
    sigma = None
    threshold = options.ransac_max_error_px
    if threshold is None:
        if noise_sigma is NOT_MEASURED:
            noise_sigma = noise_sigma_px(pairs, options) if pairs else None
        sigma = noise_sigma
        threshold = options.noise_ransac_max_error_px if sigma is None else \
            float(np.clip(options.inlier_threshold_sigmas * sigma, MIN_THRESHOLD_PX, options.noise_ransac_max_error_px))

    runs_of_edge = _consensus_runs(pairs, threshold, options)
    consensus_runs_made = sum(len(runs) for runs in runs_of_edge)
    num_failed = 0
    for n, k in enumerate(to_estimate):
        edge, runs = graph.edges[k], runs_of_edge[n]  # a weak edge: its one run, filtered below
        consensus = stable_consensus(runs)
        if consensus is None:
            num_failed += 1
            edge.filter("relative pose estimation failed")
            continue
        edge.R_j_from_i, edge.t_dir, stable = consensus
        inliers = np.logical_or.reduce([run[2] for run in runs])
        edge.drop_matches(inliers, "RANSAC outlier")
        edge.drop_matches(stable[inliers], "unstable consensus")
        edge.pose_source = "ransac"
    num_before = len(graph.active_edges())
    for k in graph.active_edges():
        if graph.edges[k].num_inliers < options.min_inliers:
            graph.edges[k].filter("too few inliers")
    num_few = num_before - len(graph.active_edges())
    component = largest_component(graph)
    dropped: dict[str, int] = {}
    for edge in graph.edges:
        for reason, count in edge.dropped_matches.items():
            dropped[reason] = dropped.get(reason, 0) + count
    report = {
        "num_views": len(scene.views), "num_pairs": len(scene.pairs), "num_reestimated": len(to_estimate),
        "num_ransac_failed": num_failed, "num_too_few_inliers_after_ransac": num_few,
        "num_active_edges": len(graph.active_edges()), "largest_component_views": len(component),
        "unregistered_views": list(graph.unregistered_views),
        "num_inlier_matches": int(sum(graph.edges[k].num_inliers for k in graph.active_edges())),
        "noise_sigma_px": sigma, "ransac_max_error_px": threshold, "consensus_runs": options.consensus_runs,
        "ransac_runs": consensus_runs_made, "agreeing_runs": uses_agreement(options, len(pairs)),
        "dropped_matches": dict(sorted(dropped.items())), "min_inliers": options.min_inliers,
        "time_s": time.perf_counter() - start,
    }
    logger.info("load: %d views, %d pairs, %d re-estimated at %.2f px%s, %d failed; %d active edges%s",
                len(scene.views), len(scene.pairs), len(to_estimate), threshold,
                "" if sigma is None else f" (noise sigma {sigma:.3g})", num_failed, report["num_active_edges"],
                f", {len(component)} views connected" if len(component) < len(scene.views) else "")
    return graph, report
