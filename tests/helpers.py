"""Helpers shared by the tests (tests/ is on sys.path through conftest.py)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rotonly_cli.runtime.parallel import ForkedPeer
from rotonly_cli.simulation.street import StreetScene, make_street_scene, similarity_align_error  # noqa: F401

REPOSITORY = Path(__file__).resolve().parents[1]
DATA_FIXTURES = REPOSITORY / "data_fixtures"  #: the bundled fixtures: the only data the tests read


def rotonly(*args) -> int:
    """The exit code of ``rotonly ARGS`` run in this process (``rotonly_cli.cli.main``)."""
    import pytest

    from rotonly_cli.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    return exit_info.value.code


def grrm_problem(setup="circular", noise=1.0, seed=1, views=10, points=400, window=3, init="ransac", corrupt=0.0):
    """A simulated multi-view problem for the GRRM tests: (simulation, multiview problem, R_gt)."""
    from rotonly_cli import multiview
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    p = simulate_multiview(setup, num_views=views, num_points=points, noise_px=noise, rng=seed, window=window,
                           init=init, corrupt_fraction=corrupt)
    vids = sorted(p.scene.views)
    keys = sorted(p.scene.pairs)
    prob = multiview.build_problem(p.scene.normalized, {k: p.scene.pairs[k].matches for k in keys}, vids)
    R_gt = np.stack([p.gt_poses[v].R_cam_from_world for v in vids])
    return p, prob, R_gt


def l1_irls_start(p, prob) -> np.ndarray:
    """GRRM's start: the L1-IRLS average of the simulation's relative rotations, inlier-weighted."""
    from rotonly_cli.geometry import averaging

    sc = p.scene
    R_rel = np.stack([sc.pairs[k].R_j_from_i for k in prob.pair_keys])
    weights = np.array([len(sc.pairs[k].matches) for k in prob.pair_keys], dtype=float)
    res = averaging.average_rotations(len(prob.view_ids), prob.edge_views[:, 0], prob.edge_views[:, 1], R_rel, weights)
    return res.R_cam_from_world


def dies_in_a_child(fn, exitcode: int):
    """``fn`` as called in this process; in a forked child ``os._exit(exitcode)`` instead (a
    worker killed mid-run)."""
    parent = os.getpid()

    def in_parent_only(*args):
        if os.getpid() != parent:
            os._exit(exitcode)
        return fn(*args)

    return in_parent_only


class DyingPeer(ForkedPeer):
    """A ForkedPeer whose child dies at its first request (a helper killed mid-run)."""

    def __init__(self, handler):
        super().__init__(dies_in_a_child(handler, 9))


def folder_bytes(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes): a folder compared before and after a run."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
