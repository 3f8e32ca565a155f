"""Initial relative poses for the simulations: 5-point + RANSAC, or perturbed ground truth.

Choice (documented, task item 3): OpenCV ``findEssentialMat`` (Nistér's 5-point solver inside
plain RANSAC, no local optimisation or non-linear polishing) followed by ``recoverPose``
(cheirality test of the four decompositions), run on **normalized** coordinates with an
identity camera matrix, so the threshold is given in pixels and divided by the focal. This is
the closest available match to the paper's initialiser (Stewénius 5-pt in OpenGV's RANSAC,
"then inliers only", §"Default Settings"); pycolmap's ``estimate_relative_pose`` would add
LO-RANSAC and a non-linear refinement, i.e. an already-optimised start.

OpenCV's ``recoverPose`` returns ``x_2 = R x_1 + t`` with points1 = view i, so R is
``R_j_from_i`` and t the unit ``t_ij`` direction, in rotonly's convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import so3


@dataclass
class RelativePoseEstimate:
    R_j_from_i: np.ndarray  # (3, 3); identity when ``success`` is False
    t_direction: np.ndarray  # (3,) unit t_ij (zeros on failure)
    inlier_mask: np.ndarray  # (m,) bool: RANSAC (epipolar) inliers
    success: bool
    num_cheiral: int = 0  # inliers in front of both cameras for the chosen decomposition

    @property
    def num_inliers(self) -> int:
        return int(self.inlier_mask.sum())


def five_point_ransac(x_i: np.ndarray, x_j: np.ndarray, focal: float, threshold_px: float = 2.0,
                      confidence: float = 0.999, seed: int | None = None) -> RelativePoseEstimate:
    """5-point + RANSAC on normalized (m, 2) points; ``threshold_px`` is the epipolar distance in px."""
    import cv2  # local import: OpenCV is only needed by simulations and benchmarks

    x_i = np.ascontiguousarray(x_i[:, :2], dtype=np.float64)
    x_j = np.ascontiguousarray(x_j[:, :2], dtype=np.float64)
    m = x_i.shape[0]
    failure = RelativePoseEstimate(np.eye(3), np.zeros(3), np.zeros(m, dtype=bool), False)
    if m < 5:
        return failure
    if seed is not None:
        cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(x_i, x_j, np.eye(3), method=cv2.RANSAC, prob=confidence,
                                   threshold=threshold_px / focal)
    if E is None or E.shape[0] < 3 or not np.all(np.isfinite(E)):
        return failure
    E = E[:3]  # several stacked solutions are possible on degenerate data: keep the best-voted first
    inliers = mask.ravel() > 0
    n_cheiral, R, t, _ = cv2.recoverPose(E, x_i, x_j, np.eye(3), mask=mask.copy())
    if inliers.sum() < 5 or not np.all(so3.is_rotation(R)):
        return failure
    # The epipolar inliers are kept even when few of them pass the cheirality test: under pure
    # rotation (PR/B/I) E = [t]x R holds for any t, so depth signs carry no information there.
    t = t.ravel()
    return RelativePoseEstimate(np.asarray(R, dtype=float), t / np.linalg.norm(t), inliers, True, int(n_cheiral))


def perturbed_rotation(R: np.ndarray, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """R rotated by exactly ``angle_deg`` about a uniformly random axis (left perturbation)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return so3.exp(axis * np.deg2rad(angle_deg)) @ R
