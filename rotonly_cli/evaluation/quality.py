"""Compare an estimated reconstruction to ground truth, the way ``openMVG_main_evalQuality`` does,
plus the rotation metrics of the paper.

Two families of numbers (formats.md §3; the Strecha README, "What the references reach"):

* ``evalquality``: OpenMVG's own numbers, reproduced digit for digit: Umeyama similarity of the
  estimated centres onto the GT centres (§3.5), distance residuals in GT units and the
  *trace/3* "angular residual" of ``R_gt_i R R_est_iᵀ`` (§3.6, not a geodesic angle), with
  OpenMVG's statistics (§3.7: upper median).
* the paper's metric (``rotation_error_deg``): the geodesic angle of ``R_gt_iᵀ R_est_i Sᵀ`` after
  the best single global rotation S (chordal L2 mean projected to SO(3)); GT rotations are
  projected onto SO(3) first (Strecha's are not exactly orthonormal). Plus the gauge-free
  relative-rotation error over all pairs and the centre error after the similarity.
"""

from __future__ import annotations

import posixpath
from dataclasses import asdict, dataclass, field

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.geometry import alignment, so3
from rotonly_cli.scene.types import SfMScene

MEDIAN_CONVENTION = "upper median: element n//2 of the sorted values (OpenMVG minMaxMeanMedian, formats.md §3.7)"


@dataclass
class Stats:
    """min / max / mean / median (OpenMVG's upper median) of n values."""

    min: float
    max: float
    mean: float
    median: float
    count: int

    @classmethod
    def of(cls, values: np.ndarray) -> Stats | None:
        values = np.asarray(values, dtype=float)
        if values.size == 0:
            return None
        # OpenMVG: nth_element at n/2, no averaging for even n (formats.md §3.7)
        median = float(np.partition(values, values.size // 2)[values.size // 2])
        return cls(min=float(values.min()), max=float(values.max()), mean=float(values.mean()),
                   median=median, count=int(values.size))


@dataclass
class CameraResult:
    """Per matched camera. Errors are ``None`` when the metric is undefined (see the report notes)."""

    name: str
    gt_view_id: int
    estimate_view_id: int
    rotation_error_deg: float  # geodesic, after the global L2 rotation alignment
    position_error: float | None  # GT units, after the Umeyama similarity
    evalquality_angular_residual_deg: float | None  # trace/3 angle, as OpenMVG
    evalquality_distance_residual: float | None  # GT units, as OpenMVG
    center_gt: list[float]
    center_estimate_aligned: list[float] | None


@dataclass
class Similarity:
    """``c_gt ≈ scale * rotation @ c_est + translation``."""

    scale: float
    rotation: list[list[float]]
    translation: list[float]


@dataclass
class EvalQualityResult:
    """What ``openMVG_main_evalQuality`` reports (``gt_eval_stats_blob.json`` + its statistics)."""

    angular_residual_deg: Stats
    distance_residual: Stats
    rotation_angular_residuals: list[float]  # blob order: matched cameras, ascending GT view id
    distance_residuals: list[float]
    similarity: Similarity


@dataclass
class QualityReport:
    num_gt: int
    num_estimated: int
    num_matched: int
    missing_in_estimate: list[str]  # GT images without an estimated pose
    not_in_gt: list[str]  # estimated images the GT does not know
    rotation_error_deg: Stats  # geodesic after global L2 rotation alignment (the paper's metric)
    relative_rotation_error_deg: Stats | None  # geodesic of R_j R_iᵀ over all matched pairs
    position_error: Stats | None  # GT units, after the similarity (None if undefined)
    rotation_alignment: list[list[float]]  # S with R_est_i ≈ R_gt_i S
    similarity: Similarity | None
    evalquality: EvalQualityResult | None
    per_camera: list[CameraResult]
    worst_pairs: list[dict] = field(default_factory=list)  # largest relative-rotation errors
    notes: list[str] = field(default_factory=list)
    median_convention: str = MEDIAN_CONVENTION
    gt_path: str = ""
    estimate_path: str = ""

    def to_dict(self) -> dict:
        """Plain JSON-serialisable dict (report.json)."""
        return asdict(self)


def _pose_arrays(scene: SfMScene, view_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    R = np.array([scene.poses[v].R_cam_from_world for v in view_ids], dtype=float).reshape(-1, 3, 3)
    c = np.array([scene.poses[v].center for v in view_ids], dtype=float).reshape(-1, 3)
    return R, c


def _posed_names(scene: SfMScene) -> dict[str, int]:
    return {view.name: view_id for view_id, view in scene.views.items() if view_id in scene.poses}


def match_views(gt: SfMScene, estimate: SfMScene) -> tuple[list[tuple[str, int, int]], list[str], list[str]]:
    """Pair GT and estimated posed views by image file name.

    evalQuality pairs them by pose id (formats.md §3.4); rotonly pairs by name (architecture.md "CLI contract").
    On Strecha both agree, because OpenMVG's pose ids are the indices of the sorted names on both
    sides. Exact names first; if none match (e.g. ``images/0000.jpg`` vs ``0000.jpg``), base
    names. Returns ``([(name, gt_view_id, estimate_view_id)] sorted by GT view id, missing, extra)``.
    """
    gt_names = _posed_names(gt)
    est_names = _posed_names(estimate)
    common = set(gt_names) & set(est_names)
    if not common:
        gt_base = {posixpath.basename(n.replace("\\", "/")): v for n, v in gt_names.items()}
        est_base = {posixpath.basename(n.replace("\\", "/")): v for n, v in est_names.items()}
        if len(gt_base) == len(gt_names) and len(est_base) == len(est_names):
            gt_names, est_names = gt_base, est_base
            common = set(gt_names) & set(est_names)
    matched = sorted(((n, gt_names[n], est_names[n]) for n in common), key=lambda m: (m[1], m[0]))
    missing = sorted(set(gt_names) - common)
    extra = sorted(set(est_names) - common)
    return matched, missing, extra


#: the share of GT cameras, or of posed images, that may find no partner by name before the
#: comparison warns (and at least two must not): a ground truth of another scene with the same
#: file names (0000.jpg, ...) matches some cameras and gives errors of tens of degrees
UNMATCHED_SHARE_WARNING = 0.1


def unmatched_warning(report: dict, input_names=None) -> str | None:
    """A warning when two or more, and more than :data:`UNMATCHED_SHARE_WARNING`, of the GT
    cameras or of the posed images are not matched by name (``report``:
    :meth:`QualityReport.to_dict`), else None. ``input_names``: the names of every image of the
    input (`rotonly run`), so that a GT camera whose image was given but not registered is not
    counted (a warning of its own says so)."""
    missing, extra = report["missing_in_estimate"], report["not_in_gt"]
    if input_names is not None:
        given = set(input_names) | {posixpath.basename(str(n).replace("\\", "/")) for n in input_names}
        missing = [name for name in missing if name not in given]
    matched, num_gt = report["num_matched"], report["num_gt"]
    found = []
    if len(missing) >= 2 and len(missing) > UNMATCHED_SHARE_WARNING * num_gt:
        where = "name none of the input's images" if input_names is not None else "have no estimated pose"
        found.append(f"{len(missing)} of the {num_gt} GT cameras {where}")
    if len(extra) >= 2 and len(extra) > UNMATCHED_SHARE_WARNING * (matched + len(extra)):
        found.append(f"{len(extra)} of the {matched + len(extra)} posed images are not in the GT")
    if not found:
        return None
    return (f"{' and '.join(found)}: is the GT this scene's? The errors cover the {matched} images matched by name")


def _openmvg_strecha_centres(R_gt_raw: np.ndarray, c_gt: np.ndarray) -> np.ndarray:
    """GT centres as evalQuality holds them for a Strecha folder: ``R_fileR_fileᵀ C``.

    io_readGTStrecha builds ``PinholeCamera(K, R_fileᵀ, t = −R_fileᵀ C)`` whose centre is
    ``−R t = R_file R_fileᵀ C`` (PinholeCamera.hpp), not C, because R_file is not exactly
    orthonormal. This moves centres by ~1e-5 GT units and was the whole gap between a plain
    Umeyama port and the real tool (fountain-P11: 2 % → 4e-7 relative), not Refine_RTS.
    With R_gt_raw = R_fileᵀ (world->camera as read), R_file R_fileᵀ = R_gt_rawᵀ R_gt_raw.
    """
    return np.einsum("nji,njk,nk->ni", R_gt_raw, R_gt_raw, c_gt)


def evaluate(gt: SfMScene, estimate: SfMScene) -> QualityReport:
    """Compare ``estimate`` to ``gt`` (both SfMScene with poses); see the module docstring.

    Raises InputError when no posed image is common to both.
    """
    matched, missing, extra = match_views(gt, estimate)
    if not matched:
        raise InputError(f"no common posed images between GT ({len(_posed_names(gt))} posed) and "
                         f"estimate ({len(_posed_names(estimate))} posed); images are matched by file name",
                         field="views")
    names = [m[0] for m in matched]
    R_gt_raw, c_gt = _pose_arrays(gt, [m[1] for m in matched])
    R_est, c_est = _pose_arrays(estimate, [m[2] for m in matched])
    if not (np.all(np.isfinite(R_gt_raw)) and np.all(np.isfinite(c_gt))):
        raise InputError("ground-truth poses contain non-finite values", field="poses")
    if not (np.all(np.isfinite(R_est)) and np.all(np.isfinite(c_est))):
        raise InputError("estimated poses contain non-finite values", field="poses")
    notes: list[str] = []

    # --- the paper's metric: geodesic after the best global rotation (GT projected onto SO(3))
    R_gt = so3.project_to_so3(R_gt_raw)
    R_est_rot = so3.project_to_so3(R_est)
    rotation_errors, S = alignment.rotation_errors_after_alignment(R_est_rot, R_gt)
    relative_errors = alignment.relative_rotation_errors(R_est_rot, R_gt)
    num_worst = min(20, relative_errors.size)
    worst = np.argpartition(-relative_errors, num_worst - 1)[:num_worst] if num_worst else np.zeros(0, int)
    worst = worst[np.argsort(-relative_errors[worst], kind="stable")]
    worst_pairs = [{"i": names[i], "j": names[j], "error_deg": float(relative_errors[k])}
                   for k, (i, j) in zip(worst, alignment.pair_from_flat_index(len(names), worst))]

    # --- similarity on centres: the paper-style position error (GT centres as given) ...
    n = len(matched)
    similarity = None
    position_errors = None
    centers_aligned = None
    evalq = None
    est_spread = np.sqrt(np.sum((c_est - c_est.mean(0)) ** 2) / n)
    gt_spread = np.sqrt(np.sum((c_gt - c_gt.mean(0)) ** 2) / n)
    if n < 3:
        notes.append(f"only {n} matched camera(s): the centre similarity needs 3 (OpenMVG FindRTS); "
                     "position and evalQuality metrics are omitted")
    elif est_spread <= 1e-12 * max(gt_spread, 1.0) or gt_spread == 0.0:
        notes.append("estimated (or GT) camera centres all coincide (rotation-only output?): the centre "
                     "similarity is undefined; position and evalQuality metrics are omitted")
    else:
        s, R_sim, t_sim = alignment.umeyama(c_est, c_gt, with_scale=True)
        centers_aligned = alignment.apply_similarity(c_est, s, R_sim, t_sim)
        position_errors = np.linalg.norm(c_gt - centers_aligned, axis=1)
        similarity = Similarity(float(s), R_sim.tolist(), t_sim.tolist())

        # ... and evalQuality's own numbers (formats.md §3.5-3.6), raw GT rotations as read
        c_gt_openmvg = _openmvg_strecha_centres(R_gt_raw, c_gt) if gt.source == "strecha" else c_gt
        s_q, R_q, t_q = alignment.umeyama(c_est, c_gt_openmvg, with_scale=True)
        distance_residuals = np.linalg.norm(c_gt_openmvg - alignment.apply_similarity(c_est, s_q, R_q, t_q), axis=1)
        # R2T = R_est_i Rᵀ; angle of R_gt_i R2Tᵀ = R_gt_i R R_est_iᵀ by trace/3
        angular_residuals = alignment.trace_over_3_angle_deg(R_gt_raw @ R_q @ np.swapaxes(R_est, -1, -2))
        evalq = EvalQualityResult(
            angular_residual_deg=Stats.of(angular_residuals),
            distance_residual=Stats.of(distance_residuals),
            rotation_angular_residuals=angular_residuals.tolist(),
            distance_residuals=distance_residuals.tolist(),
            similarity=Similarity(float(s_q), R_q.tolist(), t_q.tolist()),
        )
    if gt.source == "strecha":
        notes.append("evalquality.* uses Strecha's raw (non-orthonormal) GT rotations and OpenMVG's GT "
                     "centres R R^T C, as openMVG_main_evalQuality does; rotation_error_deg projects "
                     "the GT rotations onto SO(3)")

    per_camera = []
    for k, (name, gt_id, est_id) in enumerate(matched):
        per_camera.append(CameraResult(
            name=name, gt_view_id=int(gt_id), estimate_view_id=int(est_id),
            rotation_error_deg=float(rotation_errors[k]),
            position_error=None if position_errors is None else float(position_errors[k]),
            evalquality_angular_residual_deg=None if evalq is None else evalq.rotation_angular_residuals[k],
            evalquality_distance_residual=None if evalq is None else evalq.distance_residuals[k],
            center_gt=c_gt[k].tolist(),
            center_estimate_aligned=None if centers_aligned is None else centers_aligned[k].tolist(),
        ))

    return QualityReport(
        num_gt=len(_posed_names(gt)),
        num_estimated=len(_posed_names(estimate)),
        num_matched=n,
        missing_in_estimate=missing,
        not_in_gt=extra,
        rotation_error_deg=Stats.of(rotation_errors),
        relative_rotation_error_deg=Stats.of(relative_errors),
        position_error=None if position_errors is None else Stats.of(position_errors),
        rotation_alignment=S.tolist(),
        similarity=similarity,
        evalquality=evalq,
        per_camera=per_camera,
        worst_pairs=worst_pairs,
        notes=notes,
    )
