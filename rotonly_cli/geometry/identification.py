"""Scene identification per edge (paper §"Scene Identification", Corollaries 1-2).

Three kinds:
- ``PURE_ROTATION``: PR/B/I (pure rotation, or all points on the baseline / at infinity):
  rank Pˢ = 0, every θ = 0 (Corollary 1, case 1). The translation is unobservable.
- ``ROTATION_SINGULAR``: Holoplane (rank Pˢ = 1) or RankRegular-line (all points on a
  line): max(rank Gⁱ, rank Gʲ) < 3 (Corollary 2), detected by
  v_rs = max(λ_min(Gⁱ)/m, λ_min(Gʲ)/m) < threshold.
- ``REGULAR``: everything else.

Noise-aware PR/B/I test. With pixel noise rank Pˢ = 0 never holds exactly, so rotonly
compares the two models the paper writes down on the same bearings: the pure-rotation
reprojection cost (eq:PureRotationReprojBearingError) at its exact minimiser (orthogonal
Procrustes) against the TRRM cost (eq:ROMerr) at the given rotation:

    ρ = f_pure(R*) / f_TRRM(R_ij).

Under PR/B/I both models explain the data to the noise level, so ρ stays O(1) whatever the
noise level; with a real baseline f_pure grows with the parallax while f_TRRM stays at the
noise level, so ρ ≈ (parallax / noise)² ≫ 1. The test is scale-free: it needs neither the
focal length nor the noise level. Both costs are per-match *medians* (robust to wrong
matches), R* is a Cauchy-reweighted Procrustes and t comes from unit-length θ.

Under PR/B/I, ρ has two modes, set by where TRRM's fit puts the unobservable t: near the
optical axis ρ ≈ 0.7-1 (the OpenGV set-up); in the image plane the TRRM residual is the one
noise component across near-parallel epipolar lines against the pure model's two, and ρ
nears the ratio of the medians of χ²₂ and χ²₁, 1.386 / 0.455 = 3.05 (a tripod panorama:
2.8-3.5 on a third of its pairs with 400-1500 matches, up to 10.6 with 35). ρ of m matches
is a ratio of two sample medians: the standard deviation of log ρ is 2.74 / √m (the
asymptotic variance of a sample median, 1 / (4 m f(median)²), of χ²₁ and of χ²₂, added).
An edge is PURE_ROTATION while ρ < 3.05 exp(z 2.74 / √m), z =
``pure_rotation_ratio_sigmas`` = 3: 3.9 at 1000 matches, 6.9 at 100, 13.7 at 30, below the
regular populations (docs/tuning.md; tests/geometry/test_pairwise.py pins the bands,
tests/test_user_captures.py the panorama).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.compat import StrEnum
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.options import IdentificationOptions


class SceneKind(StrEnum):
    REGULAR = "REGULAR"  #: translation observable, rotation well constrained
    PURE_ROTATION = "PURE_ROTATION"  #: PR/B/I: rank Pˢ = 0, no translation information
    ROTATION_SINGULAR = "ROTATION_SINGULAR"  #: Holoplane or RankRegular-line (Corollary 2)


@dataclass
class Identification:
    kinds: np.ndarray  # (E,) object array of SceneKind
    detection_value: np.ndarray  # (E,) v_rs
    pure_rotation_ratio: np.ndarray  # (E,) ρ
    ps_eigenvalues: np.ndarray  # (E, 3) eigenvalues of Pˢ at the given rotation, ascending


def kind_mask(kinds: np.ndarray, kind: SceneKind) -> np.ndarray:
    """Boolean mask of the edges of ``kind`` (object arrays of enums do not compare elementwise)."""
    return np.fromiter((k == kind for k in kinds), dtype=bool, count=len(kinds))


def detection_values(batch: pg.EdgeBatch) -> np.ndarray:
    """v_rs = max(λ_min(Gⁱ)/m, λ_min(Gʲ)/m), G = Σ X X^T of z = 1 points (eq:case2IdentifyingMatrixBasic)."""
    from rotonly_cli.geometry.kernels import point_moments  # kernels imports pairwise only

    G_i, G_j = point_moments(batch)
    m = batch.counts.astype(float)
    lam_i = pg.symmetric_eigenvalues3(G_i)[:, 0]
    lam_j = pg.symmetric_eigenvalues3(G_j)[:, 0]
    return np.maximum(lam_i / m, lam_j / m)


def pure_rotation_ratios(R_j_from_i: np.ndarray, batch: pg.EdgeBatch) -> np.ndarray:
    """ρ = f_pure(R*) / f_TRRM(R_ij) per edge (module docstring), with per-match medians in
    place of sums and a robust R*, so that a few wrong matches (large in both models) cannot
    make a regular edge look like a pure rotation."""
    return ratios_and_ps(R_j_from_i, batch)[0]


def ratios_and_ps(R_j_from_i: np.ndarray, batch: pg.EdgeBatch,
                   table=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ρ per edge and, as by-products of the same pass, the unweighted Pˢ (E, 3, 3) and its
    null vector with the chirality sign (E, 3) (pairwise.translation_directions)."""
    from rotonly_cli.geometry import kernels  # kernels imports pairwise only

    if table is None:
        table = kernels.MatchTable.from_batch(batch.with_weights(None))
    R_star = kernels.best_pure_rotation(table, robust_iterations=2)
    pure_sq = 2.0 * kernels.rotated_bearing_sq(R_star, table)  # both views (eq:PureRotationReprojBearingError)
    # t from unit-length θ (Σ θθᵀ/‖θ‖²): each match one vote, so wrong matches with large θ
    # cannot dictate t (the noise-free null vector is the same)
    trrm_sq = np.empty(table.data.shape[1])
    out = kernels.trrm_evaluate(np.asarray(R_j_from_i, dtype=float).reshape(-1, 3, 3), table, unit_theta=True,
                                sq_out=trrm_sq, plain_ps=True)
    tiny = 1e-24  # 0/0 on noise-free pure rotation -> ρ = 1
    rho = (kernels.segment_median(pure_sq, table.offsets) + tiny) / \
        (kernels.segment_median(trrm_sq, table.offsets) + tiny)
    return rho, out["ps"], out["t_plain"]


#: the PR/B/I population's upper mode of ρ: median χ²₂ / median χ²₁ = 2 ln 2 / 0.45494
PURE_ROTATION_RATIO_MODE = 3.0472
#: m · variance of log ρ over one edge's m matches: 1 / (2 f m̃)² of χ²₁ (f(m̃) = 0.47113,
#: m̃ = 0.45494) plus that of χ²₂ (0.25, 1.38629), square-rooted: 2.3328² + 1.4427² -> 2.7428²
PURE_ROTATION_LOG_RATIO_SPREAD = 2.7428


def pure_rotation_ratio_thresholds(counts: np.ndarray, options: IdentificationOptions) -> np.ndarray:
    """Per edge of ``counts`` matches: the ρ below which it is PURE_ROTATION (module docstring)."""
    m = np.maximum(np.asarray(counts, dtype=float), 1.0)
    return PURE_ROTATION_RATIO_MODE * np.exp(options.pure_rotation_ratio_sigmas * PURE_ROTATION_LOG_RATIO_SPREAD
                                             / np.sqrt(m))


def classify(v_rs: np.ndarray, rho: np.ndarray, counts: np.ndarray, options: IdentificationOptions) -> np.ndarray:
    """Scene kinds from the two detection values (``counts``: each edge's matches).

    RotationSingular is decided first, from v_rs alone (it does not depend on the rotation).
    The paper tests PR/B/I first; rotonly cannot, because its noise-aware PR/B/I test uses
    the TRRM cost, whose analytic depths are not defined on a Holoplane (t is not unique,
    Corollary 1 case 2): a Holoplane would read as PR/B/I. A pure rotation whose image
    points are collinear in both views is therefore reported as ROTATION_SINGULAR; both
    kinds are kept out of TRRM and GRRM, so nothing downstream changes.
    """
    singular = v_rs < options.rotation_singular_threshold
    pure = ~singular & (rho < pure_rotation_ratio_thresholds(counts, options))
    codes = np.where(singular, 1, np.where(pure, 2, 0))
    table = (SceneKind.REGULAR, SceneKind.ROTATION_SINGULAR, SceneKind.PURE_ROTATION)
    kinds = np.empty(len(codes), dtype=object)
    kinds[:] = [table[c] for c in codes]  # slice assignment keeps the enum objects
    return kinds


def identify(R_j_from_i: np.ndarray, batch: pg.EdgeBatch,
             options: IdentificationOptions = IdentificationOptions()) -> Identification:
    """Identify every edge at the given rotations (see :func:`classify` for the order)."""
    options.validate()
    v_rs = detection_values(batch)
    rho, P, _ = ratios_and_ps(R_j_from_i, batch)
    eig = pg.symmetric_eigenvalues3(P)
    kinds = classify(v_rs, rho, batch.counts, options)
    return Identification(kinds=kinds, detection_value=v_rs, pure_rotation_ratio=rho, ps_eigenvalues=eig)
