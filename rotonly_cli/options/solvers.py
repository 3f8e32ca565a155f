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

    #: v_rs below this -> ROTATION_SINGULAR (the paper's 1e-4, on z = 1 normalized coordinates)
    rotation_singular_threshold: float = 1e-4
    #: PURE_ROTATION beyond this many sigmas of log ρ above the mode of pure rotations
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
    #: stop after a step below this (rad) when the contraction predicts the rest below tolerance
    contraction_stop_below: float = 1e-5
    #: keep JᵀJ after steps below this (rad); off (0): from far off it can end in another minimum
    frozen_hessian_below: float = 0.0
    gradient_tolerance: float = 1e-14  #: stop when ‖J^T r‖ / (cost + tiny) is below this
    initial_damping: float = 1e-4  #: μ relative to the diagonal of J^T J (Marquardt scaling)
    #: μ's floor: LM stays well posed
    min_damping: float = 1e-12
    #: μ's ceiling: beyond it LM gives up (no step lowers the cost)
    max_damping: float = 1e8
    #: a first phase on the smooth λ_min(Pˢ) cost brings starts degrees off into the basin; 0: none
    epipolar_max_iterations: int = 30
    #: that phase only has to reach TRRM's basin: it stops at steps below this (rad) ...
    epipolar_step_tolerance: float = 1e-4
    #: ... or at a relative cost decrease below this
    epipolar_function_tolerance: float = 1e-4
    #: Cauchy (IRLS): wrong matches and points near the epipole would outweigh the good ones
    loss: RobustLoss = RobustLoss.CAUCHY
    #: Cauchy scale c = loss_scale_factor x 1.4826 x the edge's median per-match residual norm
    loss_scale_factor: float = 3.0
    #: floor of c (bearing units); noise-free data would otherwise get c = 0
    min_loss_scale: float = 1e-9
    #: IRLS rounds; one plus the final inlier pass is as accurate as more
    irls_rounds: int = 1
    #: every round's step tolerance but the last's (None: step_tolerance); looser moves single edges
    irls_step_tolerance: float | None = None
    #: plain least squares on the inliers after IRLS: Cauchy weights also down-weight good matches
    final_inlier_pass: bool = True
    #: k of the inlier test ‖r‖ <= k σ: 3σ keeps ~99.7 % of Gaussian inliers
    inlier_threshold_sigmas: float = 3.0
    #: edges moved more than this (deg) restart from the 8-point E: TRRM has minima degrees off
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

    #: L1RA outer steps (algorithms.md §2.1 step 4) ...
    max_num_l1_iterations: int = 5
    #: ... until the mean step (rad) is below this
    l1_step_convergence_threshold: float = 1e-3
    #: start the IRLS from the spanning-tree rotations (ablation)
    skip_l1: bool = False
    #: ADMM's ρ of each L1 step (PoSDK/OpenMVG L1ADMM.h)
    admm_rho: float = 1.0
    #: ADMM iterations of the first L1 step, doubling each step (COLMAP) ...
    admm_initial_iterations: int = 10
    #: ... up to this many
    admm_max_iterations: int = 100
    #: ADMM's absolute tolerance (PoSDK, Boyd §3.3)
    admm_absolute_tolerance: float = 1e-4
    #: ADMM's relative tolerance (PoSDK, Boyd §3.3)
    admm_relative_tolerance: float = 1e-2
    #: IRLS kernel (§2.1 step 5): Geman-McClure, COLMAP's default
    weight_type: RobustWeight = RobustWeight.GEMAN_MCCLURE
    irls_loss_parameter_sigma_deg: float = 5.0  #: GM σ in degrees (COLMAP header "in degrees")
    #: None: σ fixed; else this many robust sigmas of the L1 residuals: 5° lets 1° pairs pull
    irls_sigma_residual_factor: float | None = None
    #: σ's floor (deg) when measured
    irls_min_sigma_deg: float = 0.1
    #: IRLS iterations at most ...
    max_num_irls_iterations: int = 100
    #: ... until the mean step over the free views (rad) is below this (Theia/COLMAP)
    irls_step_convergence_threshold: float = 1e-3
    #: residual floor of ℓ½ weights, which blow up at 0 (Chatterjee caps the same)
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
    #: stop at a relative cost decrease below this (ε of Alg. 4; Ceres' default): on a long strip
    #: what follows is a nearly free bend (docs/tuning.md, GRRM)
    function_tolerance: float = 1e-6
    #: stop after a step below this (rad): far below real rotation errors, even at LM's linear rate
    step_tolerance: float = 1e-4
    #: μ relative to diag(JᵀJ): small, or a long chain's smooth bend (eigenvalues far below the
    #: diagonal) is unlocked a tenth of μ per iteration
    initial_damping: float = 1e-8
    #: μ's ceiling: beyond it LM gives up (no step lowers the cost)
    max_damping: float = 1e10
    #: redescending: wrong matches a few px off their epipolar lines keep pulling under Cauchy
    loss: RobustLoss = RobustLoss.GEMAN_MCCLURE
    #: loss scale; None = loss_scale_factor x 1.4826 x median ‖V_ik‖ at the start
    loss_scale: float | None = None
    #: a tight scale: the wrong matches lie a few noise sigmas out
    loss_scale_factor: float = 1.5
    #: a first phase on Σ λ_min(Pˢ) brings starts a degree or more off into the basin; 0: none
    epipolar_max_iterations: int = 10
    epipolar_step_tolerance: float = 1e-4  #: rad; this phase only has to reach the basin
    #: that phase runs only when LM's first step fails or moves a view beyond this (rad); None: always
    epipolar_trigger: float | None = 1e-2
    #: units of V_ik; bearing matches TRRM's residual and measured no worse
    residual: ResidualForm = ResidualForm.BEARING
    #: the loss's second-order term in the Hessian: the same optimum in fewer iterations
    robust_hessian: bool = True
    #: full radial curvature after steps below this (rad; 0: never): LM's linear rate turns
    #: quadratic, but the exact model fails on large collections, and step_tolerance stops the
    #: clamped one as early (docs/tuning.md, GRRM)
    exact_curvature_below: float = 0.0
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
    #: ... and never within less than this (px): each resected centre's error passes to the next
    min_threshold_px: float = 2.0
    #: two-point RANSAC samples: at 30 % inliers 200 miss with probability 1e-8
    trials: int = 200
    #: least-squares refinements on the inliers (each re-selects them)
    refinements: int = 5
    #: RANSAC seed: runs are deterministic
    seed: int = 0


@dataclass(frozen=True, kw_only=True)
class LiGTOptions:
    """LiGT camera centres (geometry/ligt/)."""

    #: tracks with a base pair's ‖θ_lr‖ below this carry no translation (pure rotation, far points)
    min_base_theta_norm: float = 1e-10
    #: up to this many unknowns the dense eigh, above it shift-invert Lanczos (faster there, the same)
    max_dense_unknowns: int = 150
    #: constraints assembled per chunk; bounds the memory of one chunk's per-constraint terms
    chunk_size: int = 50_000
    #: longer tracks choose their base pair among their first views: the full scan costs Σ L²
    max_base_search_views: int = 64
    #: views needing at least this many constraint rows to be solved
    min_constraints_per_view: int = 1
    #: rounds of solve, triangulate, drop: a few wrong tracks wreck a least-squares solve; 0: plain
    robust_rounds: int = 10
    #: an observation is an outlier beyond this many robust sigmas of the reprojection errors
    outlier_sigmas: float = 4.0
    #: ... and never within this many pixels (the sigma is measured, this is its floor)
    min_outlier_threshold_px: float = 1.0
    #: the floor starts here and halves each round (None: no annealing): bent first solves
    outlier_threshold_start_px: float | None = 4.0
    #: at most this fraction dropped per round: a wrecked first solve leaves most data to the next
    max_drop_fraction: float = 0.3
    #: the rounds stop once fewer than this fraction of observations change status
    min_change_fraction: float = 1e-3
    #: views whose baselines point further than this from their pairs' are reported (the run warns)
    max_baseline_disagreement_deg: float = 10.0
    #: views the rounds left without a centre are resected from the positioned views (None: not)
    resection: ResectionOptions | None = ResectionOptions()


@dataclass(frozen=True, kw_only=True)
class TriangulationOptions:
    """Triangulation of the tracks (geometry/triangulation.py)."""

    #: Gauss-Newton iterations of the reprojection error (3 is plenty from the linear start)
    num_refinement_iterations: int = 5
    #: mean reprojection threshold (normalized ≈ px / f): OpenMVG's 4 px at f = 1000
    max_reprojection_error: float = 4e-3
    #: least ray angle over a track: 1°, below COLMAP's 1.5° and OpenMVG's 2°, keeps more points
    min_parallax_deg: float = 1.0
    #: points must have positive depth in every observing camera
    min_depth: float = 1e-9
    #: longer tracks test the parallax on their first rays: the exact max costs Σ L²
    max_parallax_views: int = 64

    def validate(self) -> None:
        if self.num_refinement_iterations < 0 or self.max_reprojection_error <= 0:
            raise InputError("num_refinement_iterations >= 0 and max_reprojection_error > 0 needed", field="options")
        if self.min_parallax_deg < 0 or self.max_parallax_views < 2:
            raise InputError("min_parallax_deg >= 0 and max_parallax_views >= 2 needed", field="options")
