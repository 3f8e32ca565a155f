"""The options of the geometry: identification, TRRM, averaging, GRRM, resection, LiGT,
triangulation (the measurements behind the defaults: docs/tuning.md)."""

from __future__ import annotations

from dataclasses import dataclass

from rotonly_cli.errors import InputError
from rotonly_cli.options.common import (
    LOSSES,
    RESIDUALS,
    ResidualForm,
    RobustLoss,
    RobustWeight,
    _require_non_negative,
)


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
    """LiGT camera centres (geometry/ligt/)."""

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
