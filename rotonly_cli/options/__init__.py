"""Every option of rotonly, one frozen dataclass per stage composed in :class:`RunOptions`,
and every choice as a StrEnum.

A StrEnum member equals its string (``RobustLoss.CAUCHY == "cauchy"``), so callers may pass
either. This package imports nothing of rotonly but ``compat`` and ``errors``: the geometry
modules take their options from here, and each re-exports its own (``trrm.TRRMOptions``).
The measurements behind the defaults are in docs/tuning.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rotonly_cli.errors import InputError
from rotonly_cli.options.common import (
    CONSENSUS_MODES,
    INTRINSICS_MODES,
    LOSSES,
    MIN_MATCHES,
    REESTIMATE_MODES,
    RESIDUALS,
    Consensus,
    Intrinsics,
    Reestimate,
    ResidualForm,
    RobustLoss,
    RobustWeight,
    cluster_address,  # noqa: F401 (re-exported: the CLI and the API check --cluster with it)
)
from rotonly_cli.options.inputs import (
    IntrinsicsOptions,
    LoadOptions,
)
from rotonly_cli.options.solvers import (
    AveragingOptions,
    GRRMOptions,
    IdentificationOptions,
    LiGTOptions,
    ResectionOptions,
    TriangulationOptions,
    TRRMOptions,
)

__all__ = [
    "AverageOptions", "AveragingOptions", "Consensus", "GRRMOptions", "IdentificationOptions", "Intrinsics",
    "IntrinsicsOptions", "LiGTOptions", "LoadOptions", "Reestimate", "RejectOptions", "ResectionOptions",
    "ResidualForm", "RobustLoss", "RobustWeight", "RunOptions", "TRRMOptions", "TriangulationOptions",
    "CONSENSUS_MODES", "INTRINSICS_MODES", "LOSSES", "MIN_MATCHES", "REESTIMATE_MODES", "RESIDUALS",
]


# ============================================================================ stages

@dataclass(frozen=True)
class RejectOptions:
    """The reject stage (stages/reject.py): multi-view outlier rejection under the global poses."""

    #: rounds of reject -> GRRM -> LiGT; they stop earlier when a round drops nothing
    max_rounds: int = 3
    #: a match is dropped beyond this many robust sigmas of the Sampson errors under the global poses
    outlier_sigmas: float = 5.0
    #: ... and never within this many pixels
    min_threshold_px: float = 1.0
    #: fewer drops than one edge needs (--min-inliers) cannot move the rotations: not worth a re-solve
    min_dropped_to_resolve: int = 30
    #: ... nor fewer than this per edge of the round: a re-solve of a large graph costs minutes
    min_dropped_per_edge: float = 0.1
    #: rounds confirming matches by tracks, where LiGT's solve misfits them (chain/reject); 0: none
    confirm_max_rounds: int = 3
    #: ... the misfit: the first solve's sigma beyond this many times the last robust round's
    confirm_misfit_sigmas: float = 10.0
    #: a match is confirmed when a track of this many views or more holds its two keypoints
    confirm_min_views: int = 3
    #: ... and at least this fraction confirmed: the unconfirmed must be a minority, as outliers are
    confirm_min_fraction: float = 0.5
    #: the rounds are kept when LiGT's first solve misfits the tracks by at most this ratio of before
    confirm_misfit_ratio: float = 0.5
    #: a pair fitting the others' rotation this many times worse than its own is filtered (chain/reject)
    refute_max_ratio: float = 6.0
    #: ... at most this many pairs; 0: none
    refute_max_edges: int = 3
    #: ... undone when LiGT then loses a view or misfits the tracks by more than this factor
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

    #: an edge further than this from the averaged rotations is a gross outlier (the averaging's own σ)
    max_residual_deg: float = 5.0
    #: averaging rounds: each filters the gross outliers and solves again
    max_rounds: int = 5
    #: σ measured on the edges (15 robust sigmas, at most 5°): a pair 1-2° off must not pull the others
    averaging: AveragingOptions = AveragingOptions(irls_sigma_residual_factor=15.0)
    #: then drop the matches on a keypoint of one match whose track sees its view through one of
    #: three or more (wrong matches two-view tests pass: GRRM bent to them, LiGT lost their tracks)
    drop_minority_keypoints: bool = True


@dataclass(frozen=True)
class RunOptions:
    """`rotonly run`: the whole chain."""

    matches_dir: str | None = None  #: OpenMVG input: features + matches folder
    matches_file: str | None = None  #: OpenMVG input: the matches file (-M; default: matches.e/f/putative)
    image_path: str | None = None  #: images for the point colours (default: beside the input)
    gt: str | None = None  #: ground truth for the final evaluation
    #: --intrinsics: which cameras are calibrated (calibration/)
    intrinsics: IntrinsicsOptions = IntrinsicsOptions()
    #: the load stage: relative poses re-estimated by RANSAC
    load: LoadOptions = LoadOptions()
    #: the identify stage: scene kinds
    identification: IdentificationOptions = IdentificationOptions()
    #: the refine stage: TRRM per edge
    trrm: TRRMOptions = TRRMOptions()
    #: the average stage: robust rotation averaging
    average: AverageOptions = AverageOptions()
    #: the optimize stage: GRRM
    optimize: GRRMOptions = GRRMOptions()
    #: the translate stage: robust LiGT
    translate: LiGTOptions = LiGTOptions()
    #: the reject stage: multi-view outlier rejection
    reject: RejectOptions = RejectOptions()
    #: the triangulate stage
    triangulate: TriangulationOptions = TriangulationOptions()
    grrm: bool = True  #: False: keep the averaged rotations (ablation)
    #: progress bars (the CLI: on a terminal, unless -q)
    progress: bool = False
    jobs: int = 1  #: processes for identification, TRRM, GRRM, robust LiGT (runtime/parallel); same numbers
    #: --cluster: the per-pair and per-track work on a Dask cluster, ``tcp://HOST:PORT`` or
    #: ``local:N`` (runtime/cluster); None: this machine's processes (``jobs``). Same numbers
    cluster: str | None = None
    max_memory_gb: float | None = None  #: --max-memory: a stage predicted above it stops the run (runtime/memory)
