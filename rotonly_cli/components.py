"""Every connected part of the view graph as its own model (issue 49 point 6).

The chain (chain/) reconstructs the largest connected component of the load stage's view
graph: OUT/sparse/ and OUT/sfm_data.json, as before (architecture.md: ``sparse/`` holds the
model). The load stage's other components of :data:`MIN_VIEWS` or more views are then
reconstructed one by one, largest first: the stages after load (identify ... triangulate) on a
view graph of that component alone, with the intrinsics the chain ended with (its calibration
is not run again), each written as OUT/sparse/<k>/ and OUT/sfm_data.component<k>.json,
k = 1, 2, ... in the order written. COLMAP's mapper numbers its models sparse/0, sparse/1, ...;
here sparse/ itself is model 0, so that readers of the contract's OUT/sparse/ find the largest
one where they always did, and sparse/<k>/ are the others (docs/formats.md §7).

A component that is smaller, whose chain fails, or of which fewer than MIN_VIEWS views end up
registered is not written; the run's warnings say so. Components that split off later (a
filter of identify, refine or average cutting the largest one apart) are not rebuilt here:
their views stay unregistered, as before.
"""

from __future__ import annotations

import copy
import logging
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

from rotonly_cli.chain import STAGE_FUNCTIONS, STAGES, Run, output_scene
from rotonly_cli.errors import AlgorithmError
from rotonly_cli.scene.types import SfMScene, View
from rotonly_cli.scene.view_graph import ACTIVE, Edge, ViewGraph, components

logger = logging.getLogger(__name__)

#: the fewest views a component needs to be written as a model of its own (two views give
#: one relative pose, no track through three views for LiGT to place them by)
MIN_VIEWS = 3
#: the reason scene/view_graph.largest_component gives the edges it filters
OUTSIDE_REASON = "outside largest component"


@dataclass
class Component:
    """A connected part of the load stage's view graph outside its largest one."""

    views: dict[int, View]
    #: copies of the load stage's edges between ``views``, active again
    edges: list[Edge]
    #: the output scene of its chain, when it is written
    scene: SfMScene | None = None
    #: why it has no model ("" when written)
    reason: str = ""
    #: k of OUT/sparse/<k>/ once written; 0 otherwise
    index: int = 0

    @property
    def view_ids(self) -> list[int]:
        return sorted(self.views)

    def entry(self) -> dict:
        """Its line of reports/run.json's ``components``."""
        written = self.scene is not None and self.index > 0
        structure = self.scene.structure if written else None
        return {"model": f"sparse/{self.index}" if written else None,
                "sfm_data": f"sfm_data.component{self.index}.json" if written else None,
                "num_views": len(self.views), "views": self.view_ids,
                "num_registered": len(self.scene.poses) if written else 0,
                "num_points": 0 if structure is None else len(structure.points),
                "reason": self.reason}


def split_off(loaded: Run) -> list[Component]:
    """The components of ``loaded``'s view graph (right after the load stage) other than the
    largest, largest first (ties: the smallest view id first), with copies of their edges:
    the chain's stages change ``loaded.graph`` in place."""
    outside = [edge for edge in loaded.graph.edges if edge.reason == OUTSIDE_REASON]
    if not outside:
        return []
    touched = sorted({v for edge in outside for v in (edge.i, edge.j)})
    label = components(touched, [(edge.i, edge.j) for edge in outside])
    groups: dict[int, list[int]] = {}
    for v in touched:
        groups.setdefault(label[v], []).append(v)
    edges_of: dict[int, list[Edge]] = {}
    for edge in outside:
        copied = copy.deepcopy(edge)
        copied.status, copied.reason = ACTIVE, ""
        edges_of.setdefault(label[edge.i], []).append(copied)
    order = sorted(groups, key=lambda c: (-len(groups[c]), groups[c][0]))
    return [Component({v: loaded.graph.views[v] for v in groups[c]}, edges_of[c]) for c in order]


def reconstruct(run: Run, parts: list[Component]) -> None:
    """The stages after load on each of ``parts`` in turn, with ``run``'s final scene (its
    intrinsics) and options; sets each part's ``scene`` or ``reason``."""
    for part in parts:
        if len(part.views) < MIN_VIEWS:
            part.reason = f"{len(part.views)} views (a model needs {MIN_VIEWS})"
            continue
        graph = ViewGraph(views=part.views, edges=part.edges)
        component_run = Run(run.input_path, run.input_kind, run.scene, graph, replace(run.options, progress=False),
                            keypoint_rgb=run.keypoint_rgb)
        logger.info("component of %d views (%s): the stages after load", len(part.views),
                    _listed(part.view_ids))
        try:
            for stage in STAGES[1:]:
                STAGE_FUNCTIONS[stage](component_run)
        except AlgorithmError as exc:
            part.reason = str(exc)
            continue
        scene = output_scene(component_run)
        if len(scene.poses) < MIN_VIEWS:
            part.reason = f"{len(scene.poses)} of its {len(part.views)} views registered (a model needs {MIN_VIEWS})"
            continue
        part.scene = scene


def write_models(directory: Path, run: Run, parts: list[Component]) -> None:
    """OUT/sparse/<k>/ and OUT/sfm_data.component<k>.json of each reconstructed part
    (stages/export.write_outputs, one process: they are small beside the main model)."""
    from rotonly_cli.stages.export import write_outputs

    for stale in model_files(directory):  # an earlier run's, when a stage command rewrites OUT in place
        (directory / stale).unlink()
    for stale in (directory / "sparse").glob("[0-9]*") if (directory / "sparse").is_dir() else []:
        if stale.is_dir() and stale.name.isdigit():
            shutil.rmtree(stale)
    index = 0
    for part in parts:
        if part.scene is None:
            continue
        index += 1
        part.index = index
        write_outputs(directory, part.scene, run.input_kind, 1, sfm_data_name=f"sfm_data.component{index}.json",
                      sparse_name=f"sparse/{index}").result()
        logger.info("component %d: %d of %d views registered, %d points -> sparse/%d, sfm_data.component%d.json",
                    index, len(part.scene.poses), len(part.views),
                    0 if part.scene.structure is None else len(part.scene.structure.points), index, index)


def model_files(directory: Path) -> set[str]:
    """The names of the components' sfm_data files in OUT (``sfm_data.component<k>.json``)."""
    if not Path(directory).is_dir():
        return set()
    return {path.name for path in Path(directory).glob("sfm_data.component*.json")
            if path.name.removeprefix("sfm_data.component").removesuffix(".json").isdigit()}


def summary_entries(main: dict, parts: list[Component]) -> list[dict]:
    """reports/run.json's ``components``: the main model (``main``: its num_views,
    num_registered, num_points), then every other component, written or not."""
    return [{"model": "sparse", "sfm_data": "sfm_data.json", **main, "reason": ""}] + [p.entry() for p in parts]


def views_in_other_models(parts: list[Component]) -> set[int]:
    """The views registered in a component's model (not unregistered, though not in sparse/)."""
    return {v for part in parts if part.scene is not None for v in part.scene.poses}


def components_warning(parts: list[Component]) -> str | None:
    """The run summary's warning for the components not written; None when there is none."""
    missing = [part for part in parts if part.scene is None]
    if not missing:
        return None
    described = "; ".join(f"views {_listed(part.view_ids)}: {part.reason}" for part in missing)
    return (f"{len(missing)} part(s) of the view graph not connected to the rest are not written as models: "
            f"{described}")


def _listed(view_ids: list[int], most: int = 12) -> str:
    shown = ", ".join(map(str, view_ids[:most]))
    return shown + (f", ... ({len(view_ids)} views)" if len(view_ids) > most else "")
