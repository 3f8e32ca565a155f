"""Public two-view API (architecture.md "Python API contract", stable).

    from rotonly_cli import twoview
    twoview.identify_scene(R_j_from_i, x_i, x_j)  -> SceneIdentification(kind, detection_value, ...)
    twoview.refine_rotation(R_j_from_i, x_i, x_j) -> TwoViewRefinement(rotation, translation_direction,
                                                                       cost, iterations, kind)
    twoview.identify_scenes(R_j_from_i, xs_i, xs_j) / twoview.refine_rotations(...)   # many edges at once

``x_i``, ``x_j``: (m, 2) or (m, 3) normalized coordinates of matched points (at least 6).
``R_j_from_i``: the relative rotation R_ij = R_j R_i^T (maps camera-i coordinates into camera j).
Bad input raises ``ValueError`` naming the argument; so do coordinates that are evidently
pixels (most of an edge's coordinates beyond ``PIXEL_LIKE``: normalized ones that large lie
more than 84 degrees off the optical axis).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from rotonly_cli.geometry import pairwise as _pg
from rotonly_cli.geometry.identification import IdentificationOptions, SceneKind, identify
from rotonly_cli.geometry.trrm import TRRMOptions, refine
from rotonly_cli.runtime.parallel import map_edges, plan

__all__ = [
    "SceneKind", "SceneIdentification", "TwoViewRefinement", "BatchRefinement", "IdentificationOptions",
    "TRRMOptions", "identify_scene", "identify_scenes", "refine_rotation", "refine_rotations", "PIXEL_LIKE",
]

#: |x|/|z| beyond this for most of an edge's coordinates: pixels, not normalized coordinates
#: (tan 84.3 deg = 10)
PIXEL_LIKE = 10.0
#: matches per edge looked at for that test (the first ones)
PIXEL_SAMPLE = 8


def refuse_pixels(x: np.ndarray, offsets: np.ndarray, name: str, single: bool = False) -> None:
    """ValueError naming ``name`` (``name[e]`` for edge e unless ``single``) when most of the
    first PIXEL_SAMPLE matches of an edge have coordinates beyond PIXEL_LIKE: pixels passed
    where normalized image coordinates are expected would give a silently wrong answer."""
    starts, ends = np.asarray(offsets[:-1]), np.asarray(offsets[1:])
    if not len(starts):
        return
    rows = starts[:, None] + np.arange(PIXEL_SAMPLE)[None, :]
    present = rows < ends[:, None]
    sample = x[np.minimum(rows, len(x) - 1)]  # (E, k, 3)
    beyond = (np.abs(sample[..., :2]) > PIXEL_LIKE * np.abs(sample[..., 2:3])).sum(axis=2)
    votes = np.where(present, beyond, 0).sum(axis=1)
    flagged = np.flatnonzero(votes > present.sum(axis=1))  # more than half of the 2k coordinates
    if flagged.size:
        e = int(flagged[0])
        block = sample[e][present[e]]
        with np.errstate(all="ignore"):
            median = float(np.median(np.abs(block[:, :2] / block[:, 2:3])))
        raise ValueError(f"{name if single else f'{name}[{e}]'}: these look like pixel coordinates (median |x| = "
                         f"{median:.4g}); pass normalized image coordinates K^-1 (u, v, 1) with lens distortion "
                         "removed, e.g. pycolmap's Camera.cam_from_img(pixels)")


@dataclass(frozen=True)
class SceneIdentification:
    kind: SceneKind
    detection_value: float  #: v_rs of the paper (RotationSingular when < threshold)
    pure_rotation_ratio: float  #: ρ = f_pure / f_TRRM (PR/B/I when < threshold)
    ps_eigenvalues: tuple[float, float, float]  #: eigenvalues of Pˢ at the given rotation, ascending


@dataclass(frozen=True)
class TwoViewRefinement:
    rotation: np.ndarray  #: refined R_j_from_i (3, 3)
    translation_direction: np.ndarray  #: unit t_ij (chirality sign); zeros for PURE_ROTATION
    cost: float  #: final eq:ROMerr
    iterations: int
    kind: SceneKind
    initial_cost: float = float("nan")
    converged: bool = True
    detection_value: float = float("nan")


@dataclass(frozen=True)
class BatchRefinement:
    rotations: np.ndarray  #: (E, 3, 3)
    translation_directions: np.ndarray  #: (E, 3)
    costs: np.ndarray  #: (E,)
    initial_costs: np.ndarray  #: (E,)
    iterations: np.ndarray  #: (E,)
    converged: np.ndarray  #: (E,)
    kinds: np.ndarray  #: (E,) SceneKind
    detection_values: np.ndarray  #: (E,)
    pure_rotation_ratios: np.ndarray  #: (E,)

    def __len__(self) -> int:
        return len(self.costs)

    def __getitem__(self, e: int) -> TwoViewRefinement:
        return TwoViewRefinement(rotation=self.rotations[e], translation_direction=self.translation_directions[e],
                                 cost=float(self.costs[e]), iterations=int(self.iterations[e]), kind=self.kinds[e],
                                 initial_cost=float(self.initial_costs[e]), converged=bool(self.converged[e]),
                                 detection_value=float(self.detection_values[e]))


def _pack(xs_i: Sequence, xs_j: Sequence) -> _pg.EdgeBatch:
    """geometry.pairwise.pack_edges, checked in bulk: when every edge is a pair of float64
    (m, 2) or (m, 3) arrays with m >= MIN_MATCHES, they are concatenated and checked for
    NaN/inf once; anything else goes through pack_edges, which names the bad edge."""
    def plain(a, b) -> tuple | None:
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.ndim == 2 and b.ndim == 2
                and a.dtype == np.float64 and b.dtype == np.float64 and a.shape[0] == b.shape[0] >= _pg.MIN_MATCHES):
            return None
        return a.shape[1], b.shape[1]

    if len(xs_i) == 0 or len(xs_i) != len(xs_j):
        return _pg.pack_edges(xs_i, xs_j)
    shapes = {plain(a, b) for a, b in zip(xs_i, xs_j)}
    if len(shapes) != 1 or next(iter(shapes)) not in ((2, 2), (3, 3)):
        return _pg.pack_edges(xs_i, xs_j)
    counts = np.fromiter((a.shape[0] for a in xs_i), dtype=np.int64, count=len(xs_i))
    cols = next(iter(shapes))[0]
    x_i = np.empty((counts.sum(), 3))
    x_j = np.empty((counts.sum(), 3))
    for x, xs in ((x_i, xs_i), (x_j, xs_j)):  # straight into the (M, 3) arrays, z = 1 for 2 columns
        np.concatenate(xs, axis=0, out=x[:, :cols])
        if cols == 2:
            x[:, 2] = 1.0
    if not (np.isfinite(x_i).all() and np.isfinite(x_j).all()):
        return _pg.pack_edges(xs_i, xs_j)
    return _pg.EdgeBatch(x_i, x_j, np.concatenate([[0], np.cumsum(counts)]))


def _prepare(R_j_from_i, xs_i: Sequence, xs_j: Sequence) -> tuple[np.ndarray, _pg.EdgeBatch]:
    batch = _pack(xs_i, xs_j)
    refuse_pixels(batch.x_i, batch.offsets, "xs_i")
    refuse_pixels(batch.x_j, batch.offsets, "xs_j")
    R = _pg.as_rotations(R_j_from_i, "R_j_from_i", batch=batch.num_edges).reshape(-1, 3, 3)
    return R, batch


def _check_one_edge(x_i, x_j) -> None:
    """The checks of ``_prepare`` with the single-edge functions' argument names."""
    batch = _pg.pack_edges([x_i], [x_j])
    refuse_pixels(batch.x_i, batch.offsets, "x_i", single=True)
    refuse_pixels(batch.x_j, batch.offsets, "x_j", single=True)


def _jobs(jobs) -> int:
    if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or jobs < 1:
        raise ValueError(f"jobs: must be an integer >= 1, got {jobs!r}")
    return int(jobs)


def _quiet():
    """Numerical corner cases are handled explicitly; no numpy warning may escape."""
    ctx = np.errstate(all="ignore")
    return ctx


def identify_scenes(R_j_from_i, xs_i: Sequence, xs_j: Sequence,
                    options: IdentificationOptions = IdentificationOptions(),
                    jobs: int = 1) -> list[SceneIdentification]:
    """Identify many edges at once (batched), each at the rotation given for it. ``jobs`` > 1
    splits the edges over that many forked processes (rotonly_cli.runtime.parallel: Linux, large
    batches; same numbers).

    ROTATION_SINGULAR does not depend on the rotation; the PR/B/I ratio does (geometry/identification.py):
    from a poor rotation a regular edge can read as PURE_ROTATION (Standard scene, 1 px, starts
    1 deg off: 5 of 1000 edges). ``refine_rotations`` decides PR/B/I again at the refined
    rotation, which is what ``rotonly run`` uses."""
    R, batch = _prepare(R_j_from_i, xs_i, xs_j)
    with _quiet(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ident = map_edges(partial(identify, options=options), R, batch, plan(batch, _jobs(jobs)))
    return [SceneIdentification(kind=ident.kinds[e], detection_value=float(ident.detection_value[e]),
                                pure_rotation_ratio=float(ident.pure_rotation_ratio[e]),
                                ps_eigenvalues=tuple(float(v) for v in ident.ps_eigenvalues[e]))
            for e in range(batch.num_edges)]


def identify_scene(R_j_from_i, x_i, x_j,
                   options: IdentificationOptions = IdentificationOptions()) -> SceneIdentification:
    """Scene kind of one edge: REGULAR, PURE_ROTATION (PR/B/I) or ROTATION_SINGULAR, at the
    given rotation (see ``identify_scenes``)."""
    R = _pg.as_rotations(R_j_from_i, "R_j_from_i")
    if R.ndim != 2:
        raise ValueError(f"R_j_from_i: expected one (3, 3) rotation, got shape {R.shape}")
    _check_one_edge(x_i, x_j)
    return identify_scenes(R[None], [x_i], [x_j], options)[0]


def refine_rotations(R_j_from_i, xs_i: Sequence, xs_j: Sequence, options: TRRMOptions = TRRMOptions(),
                     identification_options: IdentificationOptions = IdentificationOptions(),
                     jobs: int = 1) -> BatchRefinement:
    """TRRM (Alg. 2) on many edges at once, in lock-step. ``jobs`` > 1 splits the edges over
    that many forked processes (rotonly_cli.runtime.parallel: Linux, large batches; same numbers)."""
    R, batch = _prepare(R_j_from_i, xs_i, xs_j)
    ranges = plan(batch, _jobs(jobs))
    with _quiet(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = map_edges(partial(refine, options=options, identification_options=identification_options),
                        R, batch, ranges)
    return BatchRefinement(rotations=res.rotations, translation_directions=res.translation_directions, costs=res.cost,
                           initial_costs=res.initial_cost, iterations=res.iterations, converged=res.converged,
                           kinds=res.kinds, detection_values=res.identification.detection_value,
                           pure_rotation_ratios=res.identification.pure_rotation_ratio)


def refine_rotation(R_j_from_i, x_i, x_j, options: TRRMOptions = TRRMOptions(),
                    identification_options: IdentificationOptions = IdentificationOptions()) -> TwoViewRefinement:
    """TRRM (Alg. 2) on one edge: the refined R_j_from_i and the closed-form t_ij."""
    R = _pg.as_rotations(R_j_from_i, "R_j_from_i")
    if R.ndim != 2:
        raise ValueError(f"R_j_from_i: expected one (3, 3) rotation, got shape {R.shape}")
    _check_one_edge(x_i, x_j)
    return refine_rotations(R[None], [x_i], [x_j], options, identification_options)[0]
