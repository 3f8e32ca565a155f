"""rotonly_cli.runtime.parallel: edge-parallel TRRM / identification over forked processes gives the
numbers of one process, bit for bit; failures in a worker surface in the caller."""

from __future__ import annotations

import json
import os
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rotonly_cli import twoview
from rotonly_cli.runtime import parallel
from rotonly_cli.simulation.fivepoint import perturbed_rotation
from rotonly_cli.simulation.pair_scenes import simulate_twoview

from helpers import dies_in_a_child

pytestmark = pytest.mark.skipif(not parallel.fork_safe(), reason="needs fork (Linux, no other thread)")


def _edges(num_edges: int = 24, num_points: int = 150, seed: int = 3):
    rng = np.random.default_rng(seed)
    scenes = ("standard", "standard", "pure_rotation", "holoplane")
    problems = [simulate_twoview(scenes[e % len(scenes)], num_points=num_points + 7 * e, noise_px=1.0, rng=rng)
                for e in range(num_edges)]
    R0 = np.stack([perturbed_rotation(p.R_j_from_i, 2.0, rng) for p in problems])
    return R0, [p.x_i for p in problems], [p.x_j for p in problems]


@pytest.fixture
def small_parts(monkeypatch):
    """Let small test batches split (the default needs 20 000 matches per part)."""
    monkeypatch.setattr(parallel, "MIN_MATCHES_PER_JOB", 500)
    calls = []
    fork_map = parallel.fork_map

    def spy(fn, items):
        calls.append(len(items))
        return fork_map(fn, items)

    monkeypatch.setattr(parallel, "fork_map", spy)
    return calls


def test_edge_parts_are_contiguous_balanced_and_respect_the_minimum():
    counts = np.array([100, 300, 50, 50, 500, 200, 100, 700])  # 2000 matches
    parts = parallel.edge_parts(counts, 2, min_matches=100)
    assert parts[0][0] == 0 and parts[-1][1] == len(counts)
    assert all(a[1] == b[0] for a, b in zip(parts[:-1], parts[1:]))
    sizes = [int(counts[a:b].sum()) for a, b in parts]
    assert len(parts) == 2 and sizes == [1000, 1000]
    # thirds: the boundaries nearest to 667 and 1333 matches are after 500 and 1300
    assert parallel.edge_parts(counts, 3, min_matches=100) == [(0, 4), (4, 7), (7, 8)]
    assert parallel.edge_parts(counts, 8, min_matches=600) == [(0, 4), (4, 7), (7, 8)]  # 2000 // 600 = 3 parts
    assert parallel.edge_parts(counts, 4, min_matches=5000) == [(0, 8)]
    assert parallel.edge_parts(counts[:1], 4, min_matches=1) == [(0, 1)]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(6, 5000), min_size=1, max_size=60), st.integers(1, 8), st.integers(1, 20000))
def test_edge_parts_cover_every_edge_once(counts, jobs, min_matches):
    counts = np.array(counts)
    parts = parallel.edge_parts(counts, jobs, min_matches=min_matches)
    assert parts[0][0] == 0 and parts[-1][1] == len(counts)
    assert all(a[1] == b[0] and a[0] < a[1] for a, b in zip(parts[:-1], parts[1:]))
    assert len(parts) <= max(1, min(jobs, len(counts), int(counts.sum()) // min_matches))


def test_fork_map_runs_the_items_in_other_processes_in_order():
    results = parallel.fork_map(lambda k: (k * k, os.getpid()), [0, 1, 2])
    assert [r[0] for r in results] == [0, 1, 4]
    assert results[0][1] == os.getpid()
    assert len({r[1] for r in results}) == 3


def test_fork_map_raises_a_worker_exception_in_the_caller():
    def work(k):
        if k == 1:
            raise ValueError("edge 7: bad worker input")
        return k

    with pytest.raises(ValueError, match="edge 7: bad worker input"):
        parallel.fork_map(work, [0, 1])


def test_fork_map_computes_here_the_item_of_a_worker_that_dies(caplog):
    parent = os.getpid()

    def work(k):
        if k == 1 and os.getpid() != parent:
            os._exit(3)
        return k, os.getpid()

    result = parallel.fork_map(work, [0, 1, 2])
    assert result[:2] == [(0, parent), (1, parent)] and result[2][0] == 2 and result[2][1] != parent
    assert "a worker process died (exit code 3)" in caplog.text


def _slow_exit_writes(path):
    # runs when the child process exits normally, after its result was sent
    time.sleep(0.5)
    path.write_text("exited")


def test_fork_map_lets_a_child_that_delivered_exit_by_itself(tmp_path):
    """A child whose result arrived is joined, not sent SIGTERM while it is still exiting
    (its exit handlers run; a SIGTERM would kill it in the 0.5 s sleep)."""
    import multiprocessing.util

    marker = tmp_path / "exit.txt"

    def work(x):
        if x == 1:  # in the child: an exit handler that takes a while
            multiprocessing.util.Finalize(None, _slow_exit_writes, args=(marker,), exitpriority=10)
        return x * 10

    assert parallel.fork_map(work, [0, 1]) == [0, 10]
    assert marker.read_text() == "exited"


def test_fork_map_stays_in_process_while_another_thread_runs():
    release = threading.Event()
    thread = threading.Thread(target=release.wait)
    thread.start()
    try:
        assert not parallel.fork_safe()
        pids = parallel.fork_map(lambda k: os.getpid(), [0, 1])
    finally:
        release.set()
        thread.join()
    assert pids == [os.getpid(), os.getpid()]


def test_refine_rotations_with_jobs_equals_one_process_bit_for_bit(small_parts):
    R0, x_i, x_j = _edges()
    one = twoview.refine_rotations(R0, x_i, x_j)
    assert small_parts == []
    two = twoview.refine_rotations(R0, x_i, x_j, jobs=3)
    assert small_parts == [3]  # three parts, two of them in forked children
    for name in ("rotations", "translation_directions", "costs", "initial_costs", "iterations", "converged",
                 "detection_values", "pure_rotation_ratios"):
        assert np.array_equal(getattr(one, name), getattr(two, name)), name
    assert list(one.kinds) == list(two.kinds)
    assert {k.value for k in one.kinds} == {"REGULAR", "PURE_ROTATION", "ROTATION_SINGULAR"}


def test_identify_scenes_with_jobs_equals_one_process(small_parts):
    R0, x_i, x_j = _edges()
    one = twoview.identify_scenes(R0, x_i, x_j)
    two = twoview.identify_scenes(R0, x_i, x_j, jobs=2)
    assert small_parts == [2]
    assert one == two


@pytest.mark.parametrize("jobs", [0, -1, 1.5, True])
def test_bad_jobs_is_a_value_error_naming_it(jobs):
    R0, x_i, x_j = _edges(num_edges=2)
    with pytest.raises(ValueError, match="jobs"):
        twoview.refine_rotations(R0, x_i, x_j, jobs=jobs)


def test_run_with_jobs_writes_the_same_files(tmp_path, small_parts):
    """`rotonly run --jobs 2` (identification, TRRM and the tracks' robust match weights in two
    processes) writes the sfm_data.json of --jobs 1."""
    from rotonly_cli.io import colmap
    from rotonly_cli.options import IntrinsicsOptions
    from rotonly_cli.pipeline import RunOptions, run_pipeline
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    problem = simulate_multiview("linear", num_views=8, num_points=800, noise_px=0.5, rng=4, init="perturbed",
                                 init_noise_deg=0.5, window=3, min_shared=30)
    db = tmp_path / "database.db"
    colmap.write_database(db, problem.scene)
    # the camera is right; auto would also estimate the intrinsics once (this scene reprojects
    # at 1.6 noise sigmas, above auto's suspect threshold) and keep them, with one more fork
    fixed = IntrinsicsOptions(mode="fixed")
    run_pipeline(db, tmp_path / "one", RunOptions(jobs=1, intrinsics=fixed))
    run_pipeline(db, tmp_path / "two", RunOptions(jobs=2, intrinsics=fixed))
    assert small_parts == [2, 2, 2]  # identify, refine, and translate's match weights (scene/tracks)
    for stage in ("identify", "refine"):
        assert json.loads((tmp_path / "two" / "reports" / f"{stage}.json").read_text())["processes"] == 2
        assert json.loads((tmp_path / "one" / "reports" / f"{stage}.json").read_text())["processes"] == 1
    assert (tmp_path / "one" / "sfm_data.json").read_bytes() == (tmp_path / "two" / "sfm_data.json").read_bytes()


def test_a_progress_bar_leaves_forking_possible():
    """tqdm's monitor thread would outlive the bar and turn every later fork_map serial."""
    from rotonly_cli.runtime.progress import progress_bar

    assert sum(progress_bar(range(5), disable=False)) == 10
    assert parallel.fork_safe()


def test_forked_peer_answers_each_request_while_the_parent_works_and_shares_buffers():
    shared = parallel.shared_array((4,))
    local = np.zeros(4)  # an ordinary array is copied on write: the child's writes stay there

    def handler(message):
        shared[message] = message + 0.5
        local[message] = 7.0
        return os.getpid()

    with parallel.ForkedPeer(handler) as peer:
        peer.submit(1)
        shared[0] = 9.0  # the parent's own share, meanwhile
        child = peer.collect()
        peer.submit(3)
        assert peer.collect() == child != os.getpid()
    assert shared.tolist() == [9.0, 1.5, 0.0, 3.5]
    assert local.tolist() == [0.0] * 4


def test_forked_peer_raises_the_child_exception_and_serves_on():
    def handler(message):
        if message < 0:
            raise ValueError(f"negative {message}")
        return 2 * message

    with parallel.ForkedPeer(handler) as peer:
        peer.submit(-4)
        with pytest.raises(ValueError, match="negative -4"):
            peer.collect()
        peer.submit(21)
        assert peer.collect() == 42


def test_forked_peer_answers_in_this_process_once_the_child_died(caplog):
    """A child that dies (here: at its first request) costs time, not the answers: the
    pending request and every later one are answered by this process, after a warning."""
    parent = os.getpid()
    handler = dies_in_a_child(lambda message: (message, os.getpid()), 5)
    with parallel.ForkedPeer(handler) as peer:
        assert peer.alive
        peer.submit(1)
        assert peer.collect() == (1, parent)
        assert not peer.alive
        peer.submit(2)
        assert peer.collect() == (2, parent)
    assert "a helper process died (exit code 5)" in caplog.text


def test_helper_class_wants_the_callers_minimum():
    if not parallel.fork_safe():  # another thread runs here: no helper at any size
        assert parallel.helper_class(10**6, 2, 1000) is None
        return
    assert parallel.helper_class(10**6, 2, 10**6) is parallel.ForkedPeer
    assert parallel.helper_class(10**6 - 1, 2, 10**6) is None
    assert parallel.helper_class(10**6, 1, 10**6) is None
    assert parallel.helper_class(10**6, 2) is parallel.ForkedPeer  # no minimum but would_fork's


def test_forked_call_returns_from_a_child_and_raises_its_error(tmp_path):
    path = tmp_path / "written"
    call = parallel.ForkedCall(lambda: (path.write_text("x"), os.getpid())[1])
    assert call.result() != os.getpid()
    assert path.read_text() == "x"

    def fail():
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        parallel.ForkedCall(fail).result()


def test_forked_call_runs_here_when_its_child_dies(tmp_path, caplog):
    parent = os.getpid()
    path = tmp_path / "written"

    def write():
        path.write_text("here")
        return os.getpid()

    assert parallel.ForkedCall(dies_in_a_child(write, 4)).result() == parent
    assert path.read_text() == "here" and "a forked process died (exit code 4)" in caplog.text


def test_forked_call_runs_in_process_without_fork_or_while_a_thread_runs():
    assert parallel.ForkedCall(os.getpid, fork=False).result() == os.getpid()
    release = threading.Event()
    thread = threading.Thread(target=release.wait)
    thread.start()
    try:
        assert parallel.ForkedCall(os.getpid).result() == os.getpid()
    finally:
        release.set()
        thread.join()


def test_chunk_ranges_cover_the_range_within_the_chunk_and_leave_a_large_edge_alone():
    counts = np.array([100, 300, 50, 700, 20, 20])
    assert parallel.chunk_ranges(counts, 0, 6, 400) == [(0, 2), (2, 3), (3, 4), (4, 6)]
    assert parallel.chunk_ranges(counts, 1, 5, 400) == [(1, 3), (3, 4), (4, 5)]
    assert parallel.chunk_ranges(counts, 0, 6, 10_000) == [(0, 6)]


def _batch_of(x_i, x_j):
    from rotonly_cli.geometry import pairwise as pg

    return pg.pack_edges(x_i, x_j)


def _stage_like(fn, R0, batch, jobs: int, chunk: int):
    """map_edge_chunks as the identify / refine stages call it, the batch cut from ``batch``."""
    ranges = parallel.plan_counts(batch.counts, jobs)
    return parallel.map_edge_chunks(fn, R0, batch.counts, lambda e0, e1: batch.subset(np.arange(e0, e1)), ranges,
                                    chunk=chunk)


def test_refine_in_chunks_and_processes_equals_one_batch_bit_for_bit(small_parts):
    from rotonly_cli.geometry.trrm import refine

    R0, x_i, x_j = _edges()
    batch = _batch_of(x_i, x_j)
    whole = refine(R0, batch)
    # chunks of ~700 matches (2-4 edges) in 2 processes; the first edges have 150+ matches
    chunked = _stage_like(refine, R0, batch, jobs=2, chunk=700)
    assert small_parts == [2]
    assert len(parallel.chunk_ranges(batch.counts, 0, batch.num_edges, 700)) >= 8
    for name in ("rotations", "translation_directions", "initial_cost", "cost", "iterations", "converged"):
        assert np.array_equal(getattr(whole, name), getattr(chunked, name)), name
    for name in ("detection_value", "pure_rotation_ratio", "ps_eigenvalues"):
        assert np.array_equal(getattr(whole.identification, name), getattr(chunked.identification, name)), name
    assert list(whole.kinds) == list(chunked.kinds)
    assert {k.value for k in whole.kinds} == {"REGULAR", "PURE_ROTATION", "ROTATION_SINGULAR"}


def test_identify_in_chunks_equals_one_batch_bit_for_bit(small_parts):
    from rotonly_cli.geometry.identification import identify

    R0, x_i, x_j = _edges()
    batch = _batch_of(x_i, x_j)
    whole = identify(R0, batch)
    chunked = _stage_like(identify, R0, batch, jobs=1, chunk=500)
    assert small_parts == []  # one process: no fork_map call at all
    for name in ("detection_value", "pure_rotation_ratio", "ps_eigenvalues"):
        assert np.array_equal(getattr(whole, name), getattr(chunked, name)), name
    assert list(whole.kinds) == list(chunked.kinds)


def test_identify_and_refine_stages_in_small_chunks_write_the_same_files(tmp_path, monkeypatch):
    """The identify and refine stages of `rotonly run` with the edges cut into chunks of 1000
    matches write the workspace of one chunk."""
    from rotonly_cli.io import colmap
    from rotonly_cli.options import IntrinsicsOptions
    from rotonly_cli.pipeline import STAGES, RunOptions, run_pipeline
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    problem = simulate_multiview("linear", num_views=8, num_points=800, noise_px=0.5, rng=4, init="perturbed",
                                 init_noise_deg=0.5, window=3, min_shared=30)
    db = tmp_path / "database.db"
    colmap.write_database(db, problem.scene)
    options = RunOptions(jobs=1, intrinsics=IntrinsicsOptions(mode="fixed"))
    stages = STAGES[:STAGES.index("refine") + 1]
    run_pipeline(db, tmp_path / "one", options, stages)
    chunks = []
    chunk_ranges = parallel.chunk_ranges

    def spy(counts, e0, e1, chunk):
        chunks.append(len(chunk_ranges(counts, e0, e1, 1000)))
        return chunk_ranges(counts, e0, e1, 1000)

    monkeypatch.setattr(parallel, "chunk_ranges", spy)
    run_pipeline(db, tmp_path / "chunked", options, stages)
    assert len(chunks) == 2 and min(chunks) >= 3  # identify and refine, each in several chunks
    one, chunked = np.load(tmp_path / "one" / "state.npz"), np.load(tmp_path / "chunked" / "state.npz")
    for name in ("R_j_from_i", "t_dir"):
        assert np.array_equal(one[name], chunked[name]), name
    graph = "view_graph.json"
    assert (tmp_path / "one" / graph).read_bytes() == (tmp_path / "chunked" / graph).read_bytes()
    for stage in ("identify", "refine"):
        one = json.loads((tmp_path / "one" / "reports" / f"{stage}.json").read_text())
        chunked = json.loads((tmp_path / "chunked" / "reports" / f"{stage}.json").read_text())
        one.pop("time_s"), chunked.pop("time_s")
        assert one == chunked
