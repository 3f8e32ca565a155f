"""Every option of rotonly, one frozen dataclass per stage composed in :class:`RunOptions`,
and every choice as a StrEnum.

A StrEnum member equals its string (``RobustLoss.CAUCHY == "cauchy"``), so callers may pass
either. This module imports nothing of rotonly but ``compat`` and ``errors``: the geometry
modules take their options from here, and each re-exports its own (``trrm.TRRMOptions``).
The measurements behind the defaults are in docs/tuning.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rotonly_cli.compat import StrEnum
from rotonly_cli.errors import InputError

__all__ = [
    "AverageOptions", "AveragingOptions", "GRRMOptions", "IdentificationOptions", "Intrinsics", "IntrinsicsOptions",
    "LiGTOptions", "LoadOptions", "Reestimate", "RejectOptions", "ResidualForm", "RobustLoss", "RobustWeight",
    "RunOptions", "TRRMOptions", "TriangulationOptions",
]


# ============================================================================ choices

class RobustLoss(StrEnum):
    """Robust loss ρ(s) of a squared residual norm s (geometry/robust.py)."""

    NONE = "none"  #: plain least squares (the paper's)
    HUBER = "huber"  #: ρ(s) = s inside the scale, linear in √s beyond
    CAUCHY = "cauchy"  #: ρ(s) = c² log(1 + s/c²)
    #: ρ(s) = c² s / (c² + s): redescending, a residual far beyond c has no pull at all
    GEMAN_MCCLURE = "geman_mcclure"


class ResidualForm(StrEnum):
    """Units of GRRM's residual V_ik."""

    IMAGE = "image"  #: normalized image coordinates (eq:GRRMRes1 with eq:PA2/PA3, BA's units)
    BEARING = "bearing"  #: unit-sphere differences (eq:PA3bearing, TRRM's form)


class RobustWeight(StrEnum):
    """IRLS kernel of rotation averaging (algorithms.md §2.1 step 5)."""

    GEMAN_MCCLURE = "geman_mcclure"  #: ICCV 2013; COLMAP default
    HALF_NORM = "half_norm"  #: ℓ½, TPAMI 2018 / ROBA / the seed's Chatterjee baseline
    L2 = "l2"  #: no robustness (for tests and ablations)


class Reestimate(StrEnum):
    """Which stored relative poses the load stage re-estimates with calibrated RANSAC."""

    AUTO = "auto"  #: edges without an E-based stored pose (PLANAR, UNCALIBRATED, ..., none stored)
    ALL = "all"  #: every edge
    NONE = "none"  #: none: edges without a usable stored pose are filtered


class Intrinsics(StrEnum):
    """What ``rotonly run`` does with the camera intrinsics it is given (stages/intrinsics.py)."""

    FIXED = "fixed"  #: used as given
    #: every camera calibrated: focal lengths from the view graph, then focal, principal point
    #: and radial terms estimated from the reconstruction
    REFINE = "refine"
    #: cameras the input marks as a guess (COLMAP ``prior_focal_length = 0``) calibrated as
    #: ``refine`` does, cameras whose reprojection error shows them wrong, and cameras whose
    #: principal point sits at the image centre (a default) where one adjustment moves it
    #: significantly; the others stay as given
    AUTO = "auto"


#: fewest matches an edge may have (five-point minimum + one to over-determine Pˢ)
MIN_MATCHES = 6
LOSSES = tuple(loss.value for loss in RobustLoss)
RESIDUALS = tuple(form.value for form in ResidualForm)
REESTIMATE_MODES = tuple(mode.value for mode in Reestimate)
INTRINSICS_MODES = tuple(mode.value for mode in Intrinsics)


# ============================================================================ geometry

def _require_non_negative(options, *names: str, none_allowed: bool = False) -> None:
    """ValueError naming the first of ``names`` that is negative (or NaN; or None unless
    ``none_allowed``)."""
    for name in names:
        value = getattr(options, name)
        if none_allowed and value is None:
            continue
        if not value >= 0:
            raise ValueError(f"{name}: must be >= 0 or None" if none_allowed else f"{name}: must be >= 0")


@dataclass(frozen=True)
class IdentificationOptions:
    """Scene identification (geometry/identification.py)."""

    #: v_rs below this -> ROTATION_SINGULAR: paper §"Scene Identification" / §7.2.1 (1e-4), on
    #: z = 1 normalized coordinates
    rotation_singular_threshold: float = 1e-4
    #: ρ = f_pure / f_TRRM of an edge with m matches up to this many standard deviations of
    #: log ρ (2.74 / √m) above the PR/B/I population's upper mode (3.05) -> PURE_ROTATION:
    #: the threshold is 3.05 exp(z 2.74 / √m), 3.95 at 1000 matches, 6.9 at 100
    #: (geometry/identification.py; docs/tuning.md "Scene identification")
    pure_rotation_ratio_sigmas: float = 3.0

    def validate(self) -> IdentificationOptions:
        if not self.rotation_singular_threshold >= 0:
            raise ValueError("rotation_singular_threshold: must be >= 0")
        if not self.pure_rotation_ratio_sigmas >= 0:
            raise ValueError("pure_rotation_ratio_sigmas: must be >= 0")
        return self


@dataclass(frozen=True)
class TRRMOptions:
    """Two-view TRRM (paper Alg. 1-2; geometry/trrm.py)."""

    max_iterations: int = 50  #: k_max of Alg. 2
    function_tolerance: float = 1e-12  #: stop when the relative cost decrease is below this (ε of Alg. 2)
    #: stop after a step shorter than this (rad), four orders below the noise-level error
    step_tolerance: float = 1e-7
    #: also stop after an accepted step shorter than this (rad) when the observed contraction
    #: predicts less than ``step_tolerance`` still to go; such a candidate needs no Jacobian.
    #: Trusted only in the Gauss-Newton regime (see trrm._lock_step_lm); 0 disables it
    contraction_stop_below: float = 1e-5
    #: after a step shorter than this (rad), keep JᵀJ one more iteration and compute only Jᵀr
    #: (reverse mode). Same fixed point, but from far off the other path can end in another
    #: minimum, so it is off (0) by default
    frozen_hessian_below: float = 0.0
    gradient_tolerance: float = 1e-14  #: stop when ‖J^T r‖ / (cost + tiny) is below this
    initial_damping: float = 1e-4  #: μ relative to the diagonal of J^T J (Marquardt scaling)
    min_damping: float = 1e-12
    max_damping: float = 1e8
    #: first phase on the smooth λ_min(Pˢ) cost (pairwise.epipolar_residuals), so that starts
    #: several degrees off still reach TRRM's basin; 0 disables it
    epipolar_max_iterations: int = 30
    #: the first phase only has to reach TRRM's basin: it stops at steps below this (rad)
    #: or at a relative decrease below ``epipolar_function_tolerance``
    epipolar_step_tolerance: float = 1e-4
    epipolar_function_tolerance: float = 1e-4
    #: "cauchy" (IRLS) or "none" (the paper's plain least squares): wrong matches and points
    #: near the epipole give O(1) residuals that would outweigh the good matches, in the cost
    #: and in Pˢ (IRLS weights enter Pˢ as Σ w θθᵀ; its noise-free null vector is unchanged)
    loss: RobustLoss = RobustLoss.CAUCHY
    #: Cauchy scale c = loss_scale_factor x 1.4826 x the edge's median per-match residual norm
    loss_scale_factor: float = 3.0
    #: floor of c (bearing units); noise-free data would otherwise get c = 0
    min_loss_scale: float = 1e-9
    #: IRLS rounds (weights re-estimated, LM re-run); one round plus the final inlier pass is
    #: as accurate as more rounds
    irls_rounds: int = 1
    #: step tolerance (rad) of every round but the last (None: ``step_tolerance``); looser
    #: values save time but move single edges, so it is off by default
    irls_step_tolerance: float | None = None
    #: robust loss only: after the IRLS rounds, one more LM on plain least squares over the
    #: matches within ``inlier_threshold_sigmas`` robust σ of the IRLS result (0/1 weights):
    #: Cauchy weights also down-weight good matches, which costs accuracy on clean data
    final_inlier_pass: bool = True
    #: k of the inlier test ‖r‖ <= k σ: 3σ keeps ~99.7 % of Gaussian inliers
    inlier_threshold_sigmas: float = 3.0
    #: edges whose refinement ended PURE_ROTATION or moved more than this (deg) from the
    #: start are refined again from the two rotations of the linear 8-point E of their
    #: matches; a restart replaces the result when its median squared residual is below half
    #: of it. TRRM (and its λ_min(Pˢ) phase) has local minima a few degrees from the truth,
    #: one near the pure-rotation fit; real edges start well inside 1°. None: no restarts
    restart_change_deg: float | None = 1.0

    def validate(self) -> TRRMOptions:
        if self.loss not in (RobustLoss.CAUCHY, RobustLoss.NONE):
            raise ValueError(f"loss: must be 'cauchy' or 'none', got {self.loss!r}")
        if self.max_iterations < 0:
            raise ValueError("max_iterations: must be >= 0")
        _require_non_negative(self, "function_tolerance", "step_tolerance", "gradient_tolerance", "initial_damping",
                              "contraction_stop_below", "frozen_hessian_below")
        if not self.inlier_threshold_sigmas > 0:
            raise ValueError("inlier_threshold_sigmas: must be > 0")
        _require_non_negative(self, "irls_step_tolerance", none_allowed=True)
        _require_non_negative(self, "restart_change_deg", none_allowed=True)
        return self


@dataclass(frozen=True, kw_only=True)
class AveragingOptions:
    """Robust rotation averaging (geometry/averaging.py); defaults follow COLMAP/Theia
    (algorithms.md §2.2)."""

    #: L1RA outer steps and stop rule: mean ‖Δω_k‖ (rad) below the threshold (§2.1 step 4)
    max_num_l1_iterations: int = 5
    l1_step_convergence_threshold: float = 1e-3
    skip_l1: bool = False
    #: ADMM for each L1 step: ρ = 1 (PoSDK/OpenMVG L1ADMM.h), iteration cap doubling from 10 up
    #: to 100 per L1 step (COLMAP), tolerances abs 1e-4 / rel 1e-2 (PoSDK, Boyd §3.3)
    admm_rho: float = 1.0
    admm_initial_iterations: int = 10
    admm_max_iterations: int = 100
    admm_absolute_tolerance: float = 1e-4
    admm_relative_tolerance: float = 1e-2
    #: IRLS (§2.1 step 5); stop rule as Theia/COLMAP ``ComputeAverageStepSize``: mean over
    #: the free views of ‖Δω_k‖ (rad) below the threshold
    weight_type: RobustWeight = RobustWeight.GEMAN_MCCLURE
    irls_loss_parameter_sigma_deg: float = 5.0  #: GM σ in degrees (COLMAP header "in degrees")
    #: None: σ is ``irls_loss_parameter_sigma_deg``; else this many robust sigmas (1.4826 x the
    #: median) of the edge residuals at the L1 solution, within [``irls_min_sigma_deg``,
    #: ``irls_loss_parameter_sigma_deg``]: 5° suits relative rotations a few degrees off, and
    #: lets a pair 1-2° off pull the rest when the others are 0.05° off (docs/tuning.md)
    irls_sigma_residual_factor: float | None = None
    irls_min_sigma_deg: float = 0.1
    max_num_irls_iterations: int = 100
    irls_step_convergence_threshold: float = 1e-3
    #: residual floor for ℓ½ weights (e^{-3/2} blows up at 0); Chatterjee caps the
    #: square-root weight, which is the same thing
    half_norm_min_residual_deg: float = 1e-4
    ridge_regularization: float = 1e-9  #: COLMAP ridge_regularization
    #: edges whose final residual exceeds this are flagged as outliers
    max_inlier_residual_deg: float = 5.0

    def validate(self) -> None:
        if self.max_num_l1_iterations < 0 or self.max_num_irls_iterations < 0:
            raise InputError("iteration counts must be >= 0", field="options")
        if self.irls_loss_parameter_sigma_deg <= 0 or self.admm_rho <= 0 or self.irls_min_sigma_deg <= 0:
            raise InputError("sigma and rho must be positive", field="options")
        if self.irls_sigma_residual_factor is not None and not self.irls_sigma_residual_factor > 0:
            raise InputError("irls_sigma_residual_factor must be positive", field="options")


@dataclass(frozen=True)
class GRRMOptions:
    """Multi-view GRRM (paper Alg. 3-4; geometry/grrm/)."""

    max_iterations: int = 30  #: k_max of Alg. 4
    function_tolerance: float = 1e-8  #: stop at a relative cost decrease below this (ε of Alg. 4)
    #: stop after an accepted step whose largest rotation update is below this (rad): what is
    #: left is far below real rotation errors, even where LM converges only linearly (castle-P19:
    #: ratio ~0.5; docs/tuning.md)
    step_tolerance: float = 1e-4
    initial_damping: float = 1e-4  #: μ relative to diag(JᵀJ)
    max_damping: float = 1e10
    #: robust loss on ‖V_ik‖ (bearing chord units ≈ radians). Redescending: the wrong
    #: correspondences that survive two-view RANSAC (repeated structure, a few px off their
    #: epipolar lines) keep pulling under Cauchy, whose influence only decays as 1/r
    loss: RobustLoss = RobustLoss.GEMAN_MCCLURE
    #: loss scale; None = loss_scale_factor x 1.4826 x median ‖V_ik‖ at the start
    loss_scale: float | None = None
    #: a tight scale: the wrong matches lie a few noise sigmas out
    loss_scale_factor: float = 1.5
    #: first phase on Σ_edges λ_min(Pˢ_ij(R_j R_i^T)) (smooth, like TRRM's first phase):
    #: brings starts a degree or more off into GRRM's basin; 0 disables it
    epipolar_max_iterations: int = 10
    epipolar_step_tolerance: float = 1e-4  #: rad; this phase only has to reach the basin
    #: run the λ_min phase only when GRRM's first LM step from the start is rejected, needs
    #: more damping, or moves a view more than this (rad); None: always run it first
    epipolar_trigger: float | None = 1e-2
    #: units of V_ik; bearing matches TRRM's residual and measured no worse
    residual: ResidualForm = ResidualForm.BEARING
    #: Hessian with the robust loss's second-order term (geometry/robust.robust_curvature):
    #: same optimum, fewer iterations than plain IRLS weights
    robust_hessian: bool = True
    #: with robust_hessian, from the start and after accepted steps below this (rad; 0 =
    #: never, inf = from the start): keep the Cauchy loss's full radial curvature whenever the
    #: damped system stays positive definite; it turns LM's linear rate quadratic near the
    #: optimum, while far from it the clamped PSD model is the better one
    exact_curvature_below: float = 1e-3
    #: per-edge t from IRLS-weighted Pˢ (weights fixed at the start; see TRRMOptions.loss)
    robust_translation: bool = True

    def validate(self) -> GRRMOptions:
        if self.residual not in RESIDUALS:
            raise ValueError(f"residual: must be one of {RESIDUALS}, got {self.residual!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss: must be one of {LOSSES}, got {self.loss!r}")
        if self.max_iterations < 0:
            raise ValueError("max_iterations: must be >= 0")
        if self.loss_scale is not None and not self.loss_scale > 0:
            raise ValueError("loss_scale: must be > 0")
        _require_non_negative(self, "exact_curvature_below")
        _require_non_negative(self, "epipolar_trigger", none_allowed=True)
        return self


@dataclass(frozen=True)
class ResectionOptions:
    """Centres of the views LiGT left out, by resection with known rotations
    (geometry/resection.py)."""

    #: a centre is kept when at least this many points agree with it ...
    min_inliers: int = 20
    #: ... and at least this fraction of the view's points that have a position
    min_inlier_fraction: float = 0.5
    #: a point agrees within the robust rounds' last threshold, and never within less than
    #: this (px): each resected centre carries its own error into the points the next is
    #: resected from (castle-P19's OpenMVG matches, sequential: 1 px stopped after two views)
    min_threshold_px: float = 2.0
    #: RANSAC samples of two points (seeded): at a 30 % inlier ratio 200 miss with
    #: probability 1e-8
    trials: int = 200
    #: least-squares refinements on the inliers (each re-selects them)
    refinements: int = 5
    seed: int = 0


@dataclass(frozen=True, kw_only=True)
class LiGTOptions:
    """LiGT camera centres (geometry/ligt.py)."""

    #: tracks whose best base pair has ‖θ_lr‖ below this carry no translation information
    #: (pure rotation / infinitely far points, seed §6.1: all θ = 0 for PR/B/I)
    min_base_theta_norm: float = 1e-10
    #: up to this many free unknowns (3(n−1)) the dense eigh is used, above it the sparse
    #: shift-invert Lanczos (algorithms.md §1.2); both agree, sparse is faster beyond
    max_dense_unknowns: int = 150
    #: constraints assembled per chunk; bounds the memory of one chunk's per-constraint terms
    chunk_size: int = 50_000
    #: tracks longer than this select their base pair among their first views only (the
    #: exhaustive pair scan costs Σ L²)
    max_base_search_views: int = 64
    #: views needing at least this many constraint rows to be solved
    min_constraints_per_view: int = 1
    #: robust LiGT (ligt.robust_ligt_translations): rounds of solve -> triangulate -> drop the
    #: observations that reproject badly; 0 = the plain linear solve over every observation.
    #: LiGT is a least-squares solve: a few wrong tracks (repeated structure) wreck it
    robust_rounds: int = 10
    #: an observation is an outlier beyond this many robust sigmas of the reprojection errors
    outlier_sigmas: float = 4.0
    #: ... and never within this many pixels (the sigma is measured, this is its floor)
    min_outlier_threshold_px: float = 1.0
    #: ... which starts at this and halves every round down to ``min_outlier_threshold_px``
    #: (None: no annealing): errors of a first solve that wrong tracks bend mark the good
    #: observations of weak links too (docs/tuning.md "Robust LiGT")
    outlier_threshold_start_px: float | None = 4.0
    #: at most this fraction of the observations is dropped per round, so that a first solve
    #: wrecked by outliers leaves most of the data to the next one
    max_drop_fraction: float = 0.3
    #: the rounds stop once fewer than this fraction of observations change status
    min_change_fraction: float = 1e-3
    #: a view whose centre's baselines to its neighbours point, in the median over its edges,
    #: further than this from the edges' own two-view translation directions is reported (and
    #: the run warns): LiGT's null vector put it somewhere its pairs do not (docs/tuning.md
    #: "Baseline check"; clean Strecha runs: every edge within 3.4 deg)
    max_baseline_disagreement_deg: float = 10.0
    #: registered views the robust rounds left without a centre are resected, their rotations
    #: known, from the points of the positioned views (None: not; docs/tuning.md "Resection of
    #: the views LiGT left out")
    resection: ResectionOptions | None = ResectionOptions()


@dataclass(frozen=True, kw_only=True)
class TriangulationOptions:
    """Triangulation of the tracks (geometry/triangulation.py)."""

    #: Gauss-Newton iterations of the reprojection error (3 is plenty from the linear start)
    num_refinement_iterations: int = 5
    #: mean reprojection error threshold in normalized units (≈ pixels / f): OpenMVG's 4th-BA
    #: outlier rule of 4 px (algorithms.md §7 (a)) at f = 1000
    max_reprojection_error: float = 4e-3
    #: minimum over-track max ray angle: OpenMVG's 4th BA drops < 2° (algorithms.md §7 (a)); 1°
    #: keeps more points, COLMAP's min_tri_angle-like default (1.5°) rounded down
    min_parallax_deg: float = 1.0
    #: points must have positive depth in every observing camera
    min_depth: float = 1e-9
    #: tracks longer than this use only their first ``max_parallax_views`` rays for the
    #: parallax test (the exact max over all pairs costs Σ L² memory)
    max_parallax_views: int = 64

    def validate(self) -> None:
        if self.num_refinement_iterations < 0 or self.max_reprojection_error <= 0:
            raise InputError("num_refinement_iterations >= 0 and max_reprojection_error > 0 needed", field="options")
        if self.min_parallax_deg < 0 or self.max_parallax_views < 2:
            raise InputError("min_parallax_deg >= 0 and max_parallax_views >= 2 needed", field="options")


# ============================================================================ stages

@dataclass(frozen=True)
class LoadOptions:
    """The load stage (stages/load.py)."""

    #: every edge by default: COLMAP's stored poses come from verification at 4 px, loose
    #: enough to let repeated-structure matches pull them (docs/tuning.md)
    reestimate: Reestimate = Reestimate.ALL
    #: RANSAC inlier threshold in pixels (Sampson error at the view's focal length); None:
    #: ``inlier_threshold_sigmas`` x the matches' noise sigma, measured on the input
    ransac_max_error_px: float | None = None
    inlier_threshold_sigmas: float = 2.5
    #: the loose threshold (px) of the RANSAC that measures the noise sigma
    noise_ransac_max_error_px: float = 2.0
    #: the largest edges whose RANSAC inliers give the noise sigma
    noise_sample_edges: int = 30
    #: seeded RANSAC runs per edge; an edge keeps the matches that are inliers of all of them
    #: (the stable consensus) and the pose of the run closest to the others. Four, not three:
    #: three runs can all settle on the same wrong model of a repeated-structure pair
    #: (docs/tuning.md, castle-P19's OpenMVG matches)
    consensus_runs: int = 4
    #: a fast front end for clean matches, off by default: an edge whose first two runs, on
    #: at most ``agreement_max_matches`` matches, keep the same matches up to this fraction of
    #: them keeps those runs; the others make ``consensus_runs`` runs on ``ransac_max_matches``.
    #: 0.01: the load stage several times cheaper, the Strecha scenes as accurate, but 10 %
    #: wrong matches along the epipolar lines 1.7x worse (docs/tuning.md)
    consensus_agreement: float | None = None
    agreement_max_matches: int = 500
    #: a RANSAC run on an edge with more matches samples and scores a seeded random subset of
    #: this size; the inliers are then all matches within the threshold of its model. Its cost
    #: grows with the matches (~15 µs each: the local optimisation), its model's accuracy hardly
    #: (TRRM refines it on the inliers). None: always all matches
    ransac_max_matches: int | None = 2000
    #: the matches are verified inliers already, so the adaptive trial count stops early;
    #: pycolmap's default floor of 1000 trials would dominate the load time
    ransac_min_trials: int = 20
    #: enough for an inlier ratio of 1/3 at the confidence below; pairs with fewer inliers
    #: (unverified raw matches) would otherwise run pycolmap's 100 000 trials
    ransac_max_trials: int = 2000
    ransac_confidence: float = 0.9999
    #: pycolmap multiplies its adaptive trial count (the count that reaches the confidence at
    #: the best model's inlier ratio) by this margin
    ransac_trials_multiplier: float = 1.0
    seed: int = 0
    min_inliers: int = 30  #: edges with fewer inlier matches are filtered
    progress: bool = False
    #: RANSAC threads (pycolmap releases the GIL; every edge is seeded on its own, so the
    #: results do not depend on it); 0 = one per usable CPU
    jobs: int = 0

    def validate(self) -> LoadOptions:
        if self.reestimate not in REESTIMATE_MODES:
            raise InputError(f"must be one of {', '.join(REESTIMATE_MODES)}", field="reestimate")
        if self.ransac_max_error_px is not None and not self.ransac_max_error_px > 0:
            raise InputError("must be > 0", field="ransac_max_error_px")
        if not (self.inlier_threshold_sigmas > 0 and self.noise_ransac_max_error_px > 0):
            raise InputError("must be > 0", field="inlier_threshold_sigmas")
        if not self.ransac_trials_multiplier > 0:
            raise InputError("must be > 0", field="ransac_trials_multiplier")
        if self.consensus_agreement is not None and not 0 <= self.consensus_agreement < 1:
            raise InputError("must be in [0, 1)", field="consensus_agreement")
        if self.consensus_runs < 1 or self.noise_sample_edges < 1 or self.agreement_max_matches < 1:
            raise InputError("must be >= 1", field="consensus_runs")
        if self.min_inliers < MIN_MATCHES:
            raise InputError(f"must be >= {MIN_MATCHES}", field="min_inliers")
        if self.jobs < 0:
            raise InputError("must be >= 0", field="jobs")
        return self


@dataclass(frozen=True)
class IntrinsicsOptions:
    """Camera calibration (stages/intrinsics.py; docs/tuning.md "Intrinsics")."""

    mode: Intrinsics = Intrinsics.AUTO
    #: auto: a camera whose reprojection errors after the first reconstruction (robust sigma
    #: over every observation, before triangulation drops any) are above ``suspect_noise_sigmas``
    #: x the matches' noise sigma (fundamental-matrix fits) and above ``suspect_reprojection_px``
    #: is a suspect, calibrated if one adjustment on that reconstruction moves it significantly
    #: (``min_shift``): a focal 2 % off already costs the Strecha scenes 0.25-1.3 deg and
    #: raises that sigma to 0.33-0.93 px, 1.5-4.3 noise sigmas; calibrated cameras reproject
    #: at 0.19-0.28 px (docs/tuning.md "Intrinsics")
    suspect_noise_sigmas: float = 1.5
    suspect_reprojection_px: float = 0.3
    #: auto: a camera marked known whose principal point lies within this many pixels of the
    #: image centre (both axes) carries the default COLMAP's and OpenMVG's front ends write
    #: when they do not know it, not a calibration: one adjustment on the first reconstruction
    #: checks it, and the camera is calibrated if that moves it significantly (``min_shift``).
    #: The Strecha scenes' principal points lie 11 px off the centre, and with it there their
    #: rotations are 2-8x worse while the reprojection errors stay below the suspect
    #: thresholds (docs/tuning.md "Intrinsics"). None: no check.
    centred_principal_point_px: float | None = 0.5
    #: the quick estimation pass checks the cameras before the full load stage when the load
    #: stage's noise sigma (essential-matrix fits, which wrong intrinsics inflate) is above this
    probe_noise_px: float = 0.5
    #: the largest pairs whose fundamental-matrix fits give the noise sigma
    noise_sample_pairs: int = 30
    #: F re-fit on each pair's verified matches before the view-graph calibration (pixels)
    fundamental_max_error_px: float = 2.0
    fundamental_min_trials: int = 20
    #: the view-graph calibration runs on at least this many fundamental matrices: a flat
    #: field seen from tilted views left one pair with F (the other 205 PLANAR_OR_PANORAMIC),
    #: and from it the focal went 1656 -> 9885 px (true 1380; the rounds then settled at
    #: 8002 px, 34 deg off). Below, the rotating-camera fit and the rounds calibrate
    min_fundamental_pairs: int = 5
    #: a rotating camera's focal length (a panorama: pairs a homography explains, no F) is kept
    #: when its pairs' median pure-rotation residual at it is within this (pixels): a tripod
    #: panorama fits at its noise (0.45 px at 0.3 px), a plane seen from two places at none
    rotation_fit_max_px: float = 2.0
    #: that fit reads at most this many matches of a pair (a seeded subset): the median
    #: residuals it compares hardly move, and on flat ground seen from above (every pair
    #: PLANAR_OR_PANORAMIC, the fit refused) it took 4.8 s with all 1400 matches of each of
    #: 201 pairs, 1.8 s with 300
    rotation_fit_max_matches: int = 300
    #: the bundle adjustment that estimates the intrinsics uses the longest tracks only
    max_points: int = 5000
    #: that bundle adjustment stops when an iteration lowers the cost by less than this
    #: fraction (Ceres's own default; COLMAP's 0 runs on to the gradient tolerance:
    #: 15 iterations instead of 9 on fountain-P11's guessed focal, for 0.001 px of focal)
    ba_function_tolerance: float = 1e-6
    #: that bundle adjustment weighs reprojection errors beyond this many pixels by a Huber
    #: loss (None: squared): wrong matches the rejection kept (repeated structure) otherwise
    #: pull the principal point, and the rounds drift with it (docs/tuning.md "Intrinsics")
    ba_huber_px: float | None = 1.0
    max_rounds: int = 4
    #: the principal point is estimated only for a camera (or group of cameras given the same
    #: intrinsics) seen in at least this many images: in one image a shift of it is, to first
    #: order, a rotation of the camera (fountain-P11 with a camera per image: the eleven
    #: estimates spread over 749-767 px, GT 761; shared, 759.4 px)
    min_images_principal_point: int = 2
    #: a parameter group (focal, principal point, distortion) changes only when the change
    #: moves some pixel of the image by more than this fraction of its half diagonal
    #: (0.5 %: 4.6 px on 1536 x 1024; calibrated inputs move by <= 4.2 px)
    min_shift: float = 0.005
    #: ... for matches whose noise (fundamental-matrix sigma, px) is at most this; above, the
    #: limit grows in proportion: one adjustment's estimate scatters with the keypoint noise
    #: (castle-P19's sequential fixture with 0.75 px of it: a right camera's fy came out 1.4 %
    #: long, 7.4 px of image shift, and was kept; docs/tuning.md "Intrinsics")
    min_shift_noise_px: float = 0.25
    #: ... and only when some parameter of the group moved by more than this many of its
    #: standard deviations in that adjustment (its covariance at the residuals' noise): where
    #: the data do not fix a parameter its estimate wanders. A flat field seen from above
    #: trades the focal for the flying height (one adjustment put a right camera's focal
    #: 2.7 % short there, 2.4x the rotation error); fountain-P11's phone database: 0.15 px
    min_change_sigmas: float = 3.0
    #: ... that standard deviation only up to this many images: pycolmap's covariance inverts
    #: the dense pose block (0.9 s at 200 images, 2.5 s at 300, 85 s at 1000 on 5000 points);
    #: beyond, the image-shift limit alone decides
    covariance_max_images: int = 200
    #: rounds stop when the intrinsics moved by less than this fraction of the half diagonal;
    #: the relative poses of the load stage are re-estimated when they moved by more
    converged_shift: float = 0.02
    #: ... and their focal lengths by less than this fraction: a round whose focal change a new
    #: distortion term and principal point partly undo at the image's edge has not settled
    #: (castle-P19 listed with the focal 15 % short: the first round took the view graph's
    #: 1234.9 px to 1260.3 (2.1 %), k1 -0.019, an image shift of 1.9 %; the rounds stopped there,
    #: 8.7 % short, and the rotations ended 4.05 deg off; docs/tuning.md "Intrinsics")
    converged_focal_change: float = 0.015
    #: once the calibration's rounds settle, each calibrated camera is checked: its images
    #: with at least ``zoom_min_pairs`` fundamental matrices are calibrated on a camera each
    #: (stages.intrinsics.Calibration.check_zoom), and when ``zoom_min_images`` or more were,
    #: two groups of focal lengths (stages.intrinsics.focal_groups: a gap of at least
    #: ``zoom_min_gap``, relative, and ``zoom_gap_to_spread`` times either group's own range)
    #: give the images of one group a camera of their own (a zoom lens under one camera:
    #: docs/algorithms.md §8 "Images at another zoom"); an image with one or two fundamental
    #: matrices took 548 px for 1381 (entry-P10)
    zoom_check: bool = True
    zoom_min_pairs: int = 3
    zoom_min_images: int = 4
    zoom_min_gap: float = 0.02
    zoom_gap_to_spread: float = 3.0
    #: warnings: final mean reprojection error above this (px) ...
    warn_reprojection_px: float = 1.0
    #: ... or the focal of a camera not marked as a guess moved by more than this fraction
    warn_focal_change: float = 0.02
    seed: int = 0

    def validate(self) -> IntrinsicsOptions:
        if self.mode not in INTRINSICS_MODES:
            raise InputError(f"must be one of {', '.join(INTRINSICS_MODES)}", field="intrinsics")
        if self.min_images_principal_point < 1:
            raise InputError("min_images_principal_point >= 1 needed", field="intrinsics")
        if not self.min_change_sigmas >= 0:
            raise InputError("min_change_sigmas must be >= 0", field="intrinsics")
        if not self.covariance_max_images >= 0:
            raise InputError("covariance_max_images must be >= 0", field="intrinsics")
        if not self.min_shift_noise_px > 0:
            raise InputError("min_shift_noise_px > 0 needed", field="intrinsics")
        if not self.converged_focal_change > 0:
            raise InputError("converged_focal_change must be > 0", field="intrinsics")
        if self.max_points < 100 or self.max_rounds < 1:
            raise InputError("max_points >= 100 and max_rounds >= 1 needed", field="intrinsics")
        if not 0 <= self.ba_function_tolerance < 1:
            raise InputError("ba_function_tolerance must be in [0, 1)", field="intrinsics")
        if self.ba_huber_px is not None and not self.ba_huber_px > 0:
            raise InputError("ba_huber_px must be > 0", field="intrinsics")
        if self.centred_principal_point_px is not None and not self.centred_principal_point_px >= 0:
            raise InputError("centred_principal_point_px must be >= 0", field="intrinsics")
        if self.min_fundamental_pairs < 1:
            raise InputError("min_fundamental_pairs must be >= 1", field="intrinsics")
        if not self.rotation_fit_max_px > 0:
            raise InputError("rotation_fit_max_px must be > 0", field="intrinsics")
        if not self.rotation_fit_max_matches >= 8:
            raise InputError("rotation_fit_max_matches must be >= 8", field="intrinsics")
        if self.zoom_min_images < 4 or self.zoom_min_pairs < 1 or not (self.zoom_min_gap > 0
                                                                       and self.zoom_gap_to_spread > 0):
            raise InputError("zoom_min_images >= 4, zoom_min_pairs >= 1, zoom_min_gap > 0 and zoom_gap_to_spread > 0 "
                             "needed",
                             field="intrinsics")
        return self


@dataclass(frozen=True)
class RejectOptions:
    """The reject stage (stages/reject.py): multi-view outlier rejection under the global poses."""

    #: rounds of reject -> GRRM -> LiGT; they stop earlier when a round drops nothing
    max_rounds: int = 3
    #: a match is dropped beyond this many robust sigmas of the Sampson errors under the global poses
    outlier_sigmas: float = 5.0
    #: ... and never within this many pixels
    min_threshold_px: float = 1.0
    #: a round that would drop fewer matches than this (and filter no edge) is not applied and
    #: the rounds end: fewer matches than one edge needs (--min-inliers' default) cannot move
    #: the rotations, and the GRRM + LiGT re-solve costs 10-20 % of a run (docs/tuning.md)
    min_dropped_to_resolve: int = 30
    #: ... and fewer than this many per edge of the round: at 1000 views (10 000 edges) rounds
    #: dropping 794 and 463 of 21 M matches each cost a GRRM + LiGT re-solve of 3-4 minutes
    min_dropped_per_edge: float = 0.1
    #: rounds confirming matches by their tracks, run first when LiGT left views out or its
    #: first solve misfits the tracks (chain._confirmation_rounds); 0: none
    confirm_max_rounds: int = 3
    #: ... the misfit: the first solve's sigma beyond this many times the last robust round's
    confirm_misfit_sigmas: float = 10.0
    #: a match is confirmed when a track of this many views or more holds its two keypoints
    confirm_min_views: int = 3
    #: ... and the rounds need at least this fraction of the matches confirmed: the
    #: unconfirmed ones a minority, as robust estimation needs of its outliers
    confirm_min_fraction: float = 0.5
    #: the rounds are kept when LiGT's first solve on every match fits the tracks under the
    #: new rotations with at most this ratio of the sigma before (stages/translate.first_solve_sigma_px)
    confirm_misfit_ratio: float = 0.5
    #: where LiGT's first solve misfits the tracks (``confirm_misfit_sigmas``), before the
    #: confirmation: pairs whose matches fit the relative rotation the other pairs imply this
    #: many times worse (median epipolar residual) than their own are filtered, the most refuted
    #: first (chain._refutation_rounds); clean inputs stay below 2.5
    refute_max_ratio: float = 6.0
    #: ... at most this many pairs; 0: none
    refute_max_edges: int = 3
    #: ... each is undone (and the test ends) when LiGT then leaves a view out that it tied in,
    #: or its first solve misfits the tracks by more than this factor of the misfit before
    refute_max_misfit_growth: float = 1.5

    def fewest_dropped_to_resolve(self, num_edges: int) -> int:
        """The fewest dropped matches for which a round is applied and re-solved."""
        return max(self.min_dropped_to_resolve, math.ceil(self.min_dropped_per_edge * num_edges))

    def validate(self) -> RejectOptions:
        if self.max_rounds < 0 or self.confirm_max_rounds < 0 or self.refute_max_edges < 0:
            raise InputError("must be >= 0", field="reject.max_rounds")
        if not self.min_dropped_per_edge >= 0:
            raise InputError("must be >= 0", field="reject.min_dropped_per_edge")
        if not (self.refute_max_ratio > 1.0 and self.refute_max_misfit_growth >= 1.0):
            # a pair's matches fit their own rotation best: a ratio of 1 or less refutes every pair
            raise InputError("must be > 1", field="reject.refute_max_ratio")
        if self.confirm_min_views < 3:
            # two views are any match's own pair: nothing would be confirmed by a third
            raise InputError("must be >= 3", field="reject.confirm_min_views")
        if not (0.0 < self.confirm_min_fraction <= 1.0 and 0.0 < self.confirm_misfit_ratio <= 1.0):
            raise InputError("must be in (0, 1]", field="reject.confirm_min_fraction")
        if not (self.confirm_misfit_sigmas > 0 and self.outlier_sigmas > 0 and self.min_threshold_px >= 0):
            raise InputError("must be > 0", field="reject.confirm_misfit_sigmas")
        return self


@dataclass(frozen=True)
class AverageOptions:
    """The average stage (stages/average.py)."""

    #: residual (deg) above which an edge is a gross outlier: the averaging's own inlier
    #: threshold (Geman-McClure σ = 5°, Chatterjee & Govindu ICCV 2013)
    max_residual_deg: float = 5.0
    max_rounds: int = 5
    #: Chatterjee & Govindu's averaging with its Geman-McClure σ measured on the edges (15 robust
    #: sigmas of the L1 solution's residuals, at most their 5°): TRRM's relative rotations
    #: are 0.05-0.2° off, and at σ = 5° a repeated-structure pair 1.9° off took a sparse graph's
    #: GRRM start with it (docs/tuning.md "Rotation averaging")
    averaging: AveragingOptions = AveragingOptions(irls_sigma_residual_factor=15.0)


@dataclass(frozen=True)
class RunOptions:
    """`rotonly run`: the whole chain."""

    matches_dir: str | None = None  #: OpenMVG input: features + matches folder
    matches_file: str | None = None  #: OpenMVG input: the matches file (-M; default: matches.e/f/putative)
    image_path: str | None = None  #: images for the point colours (default: beside the input)
    gt: str | None = None  #: ground truth for the final evaluation
    intrinsics: IntrinsicsOptions = IntrinsicsOptions()
    load: LoadOptions = LoadOptions()
    identification: IdentificationOptions = IdentificationOptions()
    trrm: TRRMOptions = TRRMOptions()
    average: AverageOptions = AverageOptions()
    optimize: GRRMOptions = GRRMOptions()
    translate: LiGTOptions = LiGTOptions()
    reject: RejectOptions = RejectOptions()
    triangulate: TriangulationOptions = TriangulationOptions()
    grrm: bool = True  #: False: keep the averaged rotations (ablation)
    progress: bool = False
    jobs: int = 1  #: processes for identification, TRRM, GRRM, robust LiGT (runtime/parallel); same numbers
    max_memory_gb: float | None = None  #: --max-memory: a stage predicted above it stops the run (runtime/memory)
