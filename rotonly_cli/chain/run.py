"""The Run: everything the stages of one chain produce, in memory, and what it says of its
outputs (the image folder, OUT/sfm_data.json's root_path, the posed scene)."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.io.detect import InputKind
from rotonly_cli.io.readers import READERS
from rotonly_cli.options import RunOptions
from rotonly_cli.scene.tracks import TrackCache
from rotonly_cli.scene.types import SfMScene, Structure
from rotonly_cli.scene.view_graph import ViewGraph, largest_component

if TYPE_CHECKING:
    from rotonly_cli.calibration import Calibration


@dataclass
class Run:
    """Everything the stages produce, in memory."""

    input_path: str
    input_kind: InputKind
    scene: SfMScene
    graph: ViewGraph
    options: RunOptions
    rotations: np.ndarray | None = None  # (n, 3, 3) sorted-view-id rows, NaN = unregistered
    centers: np.ndarray | None = None
    structure: Structure | None = None
    reports: dict = field(default_factory=dict)
    #: keypoint colours being decoded on a thread since loading (stages.triangulate)
    keypoint_rgb: Future | None = None
    #: tracks built by translate and reused by triangulate (scene/tracks)
    tracks: TrackCache = field(default_factory=TrackCache)
    #: the intrinsics as read, before any stage changed them (report.html)
    input_intrinsics: dict = field(default_factory=dict)
    #: the camera calibration of this run (calibration.Calibration)
    calibration: Calibration | None = None
    components: list = field(default_factory=list)  #: the graph's other parts (components.Component)


def ensure_two_views(graph: ViewGraph, after: str) -> None:
    if len(largest_component(graph)) < 2:
        usable = len(graph.views) - len(graph.unregistered_views)
        raise AlgorithmError(f"fewer than two usable images after {after} ({usable} of {len(graph.views)} "
                             f"connected by an edge); nothing to reconstruct")


def image_root(run: Run) -> Path | None:
    """--image-path; else where the input's kind keeps its images (io/readers: COLMAP,
    ``images/`` beside the database; OpenMVG, root_path the way its tools read it)."""
    if run.options.image_path:
        return Path(run.options.image_path)
    return READERS[run.input_kind].image_root(Path(run.input_path), run.scene)


def output_root_path(run: Run) -> str:
    """``root_path`` of OUT/sfm_data.json: --image-path as given, an OpenMVG input's root_path
    as it came (OpenMVG resolves both from the current directory), else the image folder found."""
    if run.options.image_path:
        return str(run.options.image_path)
    if READERS[run.input_kind].keeps_root_path:
        return run.scene.root_path
    root = image_root(run)
    return "" if root is None else str(root)


def output_scene(run: Run) -> SfMScene:
    """The input scene with the estimated poses (views with rotation and centre) and points."""
    from rotonly_cli.stages.export import posed_scene

    return posed_scene(run.scene, run.graph.view_ids(), run.rotations, run.centers, run.structure,
                       output_root_path(run) or None)
