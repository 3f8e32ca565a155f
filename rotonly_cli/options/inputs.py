"""The options of reading the input: the load stage (re-estimation, RANSAC) and the
intrinsics calibration (the measurements behind the defaults: docs/tuning.md)."""

from __future__ import annotations

from dataclasses import dataclass

from rotonly_cli.errors import InputError
from rotonly_cli.options.common import (
    INTRINSICS_MODES,
    MIN_MATCHES,
    REESTIMATE_MODES,
    Intrinsics,
    Reestimate,
)

#: ``consensus_agreement`` of ``--consensus fast`` (an edge's two first runs differing in at most 1 %
#: of the matches either accepts; docs/tuning.md, Load)
FAST_CONSENSUS_AGREEMENT = 0.01
#: ``agreement_min_edges`` of ``--consensus auto``: the Strecha scenes re-estimate at most 171 pairs,
#: the simulated collections where the agreeing runs measured the same rotations 1225 and more
AUTO_AGREEMENT_MIN_EDGES = 1000


@dataclass(frozen=True)
class LoadOptions:
    """The load stage (stages/load.py)."""

    #: every edge: COLMAP verifies at 4 px, loose enough for repeated structure to pull its stored poses
    reestimate: Reestimate = Reestimate.ALL
    #: RANSAC inlier threshold (px, Sampson at the focal); None: inlier_threshold_sigmas x measured noise
    ransac_max_error_px: float | None = None
    #: the threshold in noise sigmas: wide enough for Gaussian inliers, tight for repeated structure
    inlier_threshold_sigmas: float = 2.5
    #: the loose threshold (px) of the RANSAC that measures the noise sigma
    noise_ransac_max_error_px: float = 2.0
    #: the largest edges whose RANSAC inliers give the noise sigma
    noise_sample_edges: int = 30
    #: seeded RANSAC runs per edge, keeping the matches all accept: three can agree on one wrong model
    consensus_runs: int = 4
    #: an edge whose first two runs agree to this fraction keeps them (faster, less robust); None: off
    consensus_agreement: float | None = FAST_CONSENSUS_AGREEMENT
    #: ... in a load of at least this many edges to re-estimate only (--consensus auto; 0: any)
    agreement_min_edges: int = AUTO_AGREEMENT_MIN_EDGES
    #: ... those two runs on at most this many matches
    agreement_max_matches: int = 500
    #: ... on the edges of more matches than this only: four runs of a smaller edge cost little
    agreement_min_matches: int = 1000
    #: a RANSAC run samples at most this many matches: its cost grows with them, its model hardly
    ransac_max_matches: int | None = 2000
    #: the matches are verified inliers already: pycolmap's floor of 1000 trials would dominate
    ransac_min_trials: int = 20
    #: enough for an inlier ratio of 1/3 at ransac_confidence; raw matches would run 100 000
    ransac_max_trials: int = 2000
    #: the adaptive trial count's confidence of finding an all-inlier sample
    ransac_confidence: float = 0.9999
    #: pycolmap's margin on its adaptive trial count
    ransac_trials_multiplier: float = 1.0
    #: RANSAC seed: runs are deterministic
    seed: int = 0
    min_inliers: int = 30  #: edges with fewer inlier matches are filtered
    #: progress bars (RunOptions.progress)
    progress: bool = False
    #: RANSAC threads (pycolmap releases the GIL; edges seeded apart: same results); 0: the usable CPUs
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
        if self.agreement_min_matches < 0:
            raise InputError("must be >= 0", field="agreement_min_matches")
        if self.agreement_min_edges < 0:
            raise InputError("must be >= 0", field="agreement_min_edges")
        if self.min_inliers < MIN_MATCHES:
            raise InputError(f"must be >= {MIN_MATCHES}", field="min_inliers")
        if self.jobs < 0:
            raise InputError("must be >= 0", field="jobs")
        return self


@dataclass(frozen=True)
class IntrinsicsOptions:
    """Camera calibration (calibration/; docs/tuning.md "Intrinsics")."""

    #: --intrinsics: fixed, refine or auto (calibration/)
    mode: Intrinsics = Intrinsics.AUTO
    #: auto: a camera reprojecting above this many noise sigmas ... is a suspect (a focal 2 % off)
    suspect_noise_sigmas: float = 1.5
    #: ... and above this many pixels: calibrated cameras reproject below it
    suspect_reprojection_px: float = 0.3
    #: auto: a principal point this close to the centre is the front ends' default, checked; None: not
    centred_principal_point_px: float | None = 0.5
    #: a quick estimation pass checks the cameras first when the E-based noise is above this
    probe_noise_px: float = 0.5
    #: the largest pairs whose fundamental-matrix fits give the noise sigma
    noise_sample_pairs: int = 30
    #: F re-fit on each pair's verified matches before the view-graph calibration (pixels)
    fundamental_max_error_px: float = 2.0
    #: ... its fewest RANSAC trials (the matches are verified already)
    fundamental_min_trials: int = 20
    #: fewer fundamental matrices cannot fix a focal (one pair sent it 7x off): rotations decide
    min_fundamental_pairs: int = 5
    #: a rotating camera's focal is kept when its pairs fit pure rotations within this (px)
    rotation_fit_max_px: float = 2.0
    #: that fit reads at most this many matches a pair: its medians hardly move, its time does
    rotation_fit_max_matches: int = 300
    #: the bundle adjustment that estimates the intrinsics uses the longest tracks only
    max_points: int = 5000
    #: ... and of those at most the ones holding this many observations: its memory grows with them
    max_observations: int = 100_000
    #: the adjustment stops at a relative decrease below this (Ceres's default: fewer iterations)
    ba_function_tolerance: float = 1e-6
    #: Huber loss beyond this (px): wrong matches the rejection kept would pull the principal point
    ba_huber_px: float | None = 1.0
    #: rounds of estimation passes at most (the rounds usually settle in one or two)
    max_rounds: int = 4
    #: a principal point seen in fewer images is kept: in one it is, to first order, a rotation
    min_images_principal_point: int = 2
    #: a change counts when it moves some pixel by this fraction of the half diagonal (right ones move less)
    min_shift: float = 0.005
    #: ... at matches this noisy (px) or less; above, the limit grows with the noise
    min_shift_noise_px: float = 0.25
    #: ... and only beyond this many standard deviations: a parameter the data do not fix wanders
    min_change_sigmas: float = 3.0
    #: ... that deviation only up to this many images: its cost grows as their cube
    covariance_max_images: int = 200
    #: rounds stop below this image shift (fraction of the half diagonal); above, poses are re-estimated
    converged_shift: float = 0.02
    #: ... and this focal change: a focal change the new distortion hides at the edge is not settled
    converged_focal_change: float = 0.015
    #: once settled, the images of each camera are calibrated apart: a zoom lens gets a second camera
    zoom_check: bool = True
    #: ... an image with fewer fundamental matrices is not calibrated apart (its focal is loose;
    #: a guess with twins then shares their focal: calibration/loose.py)
    zoom_min_pairs: int = 3
    #: ... a camera with fewer such images is not checked
    zoom_min_images: int = 4
    #: ... two groups of focal lengths at least this far apart (relative) ...
    zoom_min_gap: float = 0.02
    #: ... and this many times either group's own range: a zoom, not the calibration's scatter
    zoom_gap_to_spread: float = 3.0
    #: warnings: final mean reprojection error above this (px) ...
    warn_reprojection_px: float = 1.0
    #: ... or the focal of a camera not marked as a guess moved by more than this fraction
    warn_focal_change: float = 0.02
    #: the seed of the calibration's RANSAC and subsets
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
        if self.max_points < 100 or self.max_rounds < 1 or self.max_observations < 1000:
            raise InputError("max_points >= 100, max_observations >= 1000 and max_rounds >= 1 needed",
                             field="intrinsics")
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
