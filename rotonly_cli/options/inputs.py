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
    """Camera calibration (calibration/; docs/tuning.md "Intrinsics")."""

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
    #: (calibration.Calibration.check_zoom), and when ``zoom_min_images`` or more were,
    #: two groups of focal lengths (calibration.focal_groups: a gap of at least
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
