"""The speed paths of geometry/kernels/ give the same bits as the plain paths they replace:
eigenproblems batched over edge groups, mostly-COST groups evaluated without a gather, the
Jacobian stage in blocks, consecutive equal-size medians read as a view, and the
all-accepted commit of the TRRM problem."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.trrm import _TRRMProblem
from rotonly_cli.simulation.pair_scenes import simulate_twoview


def _batch(seed: int = 0):
    sizes = [40, 300, 25, 700, 90, 60, 500, 33, 120, 80, 45, 210]
    scenes = ["standard", "planar", "standard", "standard", "pure_rotation", "standard"] * 2
    problems = [simulate_twoview(s, num_points=n, noise_px=1.0, rng=seed + k)
                for k, (s, n) in enumerate(zip(scenes, sizes))]
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    rng = np.random.default_rng(seed)
    R = np.stack([so3.exp(rng.normal(scale=0.01, size=3)) @ p.R_j_from_i for p in problems])
    w = rng.uniform(0.0, 1.0, batch.x_i.shape[0])
    w[rng.random(w.size) < 0.05] = 0.0
    return batch, R, w


def _evaluate(R, table, **kw):
    sq = np.full(table.data.shape[1], -1.0)
    out = kernels.trrm_evaluate(R, table, sq_out=sq, **kw)
    return out, sq


def _assert_same(a, b):
    (out_a, sq_a), (out_b, sq_b) = a, b
    assert out_a.keys() == out_b.keys()
    for key in out_a:
        assert np.array_equal(out_a[key], out_b[key]), key
    assert np.array_equal(sq_a, sq_b)


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("kw", [dict(jacobian=True), dict(), dict(unit_theta=True, plain_ps=True),
                                dict(gradient=True)])
def test_batched_eigenproblems_and_blocks_give_the_same_bits(monkeypatch, weighted, kw):
    batch, R, w = _batch()
    table = kernels.MatchTable.from_batch(batch, w if weighted else None, chunk=300)  # 9 groups
    assert len(table.groups) >= 8
    monkeypatch.setattr(kernels.lean, "EIGEN_BATCH_GROUPS", 1)
    monkeypatch.setattr(kernels.lean, "NORMAL_BLOCK", 1 << 14)
    per_group = _evaluate(R, table, **kw)
    monkeypatch.setattr(kernels.lean, "EIGEN_BATCH_GROUPS", 3)
    monkeypatch.setattr(kernels.lean, "NORMAL_BLOCK", 128)  # blocks that cut edges in two
    _assert_same(_evaluate(R, table, **kw), per_group)
    # and one group per call of the unbatched _lean_group (no `pre`) agrees as well
    out = {"cost": np.zeros(table.num_edges), "t": np.zeros((table.num_edges, 3))}
    if kw.get("jacobian") or kw.get("gradient"):
        out["JtJ"], out["Jtr"] = np.zeros((table.num_edges, 3, 3)), np.zeros((table.num_edges, 3))
    if kw.get("plain_ps"):
        out["ps"], out["t_plain"] = np.zeros((table.num_edges, 6)), np.zeros((table.num_edges, 3))
    mode = kernels.NORMAL if kw.get("jacobian") else kernels.GRADIENT if kw.get("gradient") else kernels.COST
    sq = np.full(table.data.shape[1], -1.0)
    for e0, e1, m0, m1, cnt, starts in table.group_slices():
        kernels.lean._lean_group(R[e0:e1], cnt, starts, table.data[:, m0:m1],
                            None if table.weights is None else table.weights[m0:m1], mode,
                            bool(kw.get("unit_theta")), out, slice(e0, e1), sq[m0:m1], bool(kw.get("plain_ps")))
    for key in ("cost", "t", "JtJ", "Jtr"):
        if key in out:
            assert np.array_equal(out[key], per_group[0][key]), key
    assert np.array_equal(sq, per_group[1])


def test_mixed_modes_equal_each_edge_alone():
    """A group where most edges are COST is evaluated whole in COST mode, then its NORMAL and
    GRADIENT edges again: each edge's numbers equal those of the edge evaluated on its own."""
    batch, R, w = _batch(seed=5)
    table = kernels.MatchTable.from_batch(batch, w, chunk=1 << 14)  # one group
    E = table.num_edges
    jac = np.zeros(E, bool)
    jac[[1, 6]] = True
    grad = np.zeros(E, bool)
    grad[9] = True
    got, sq = _evaluate(R, table, jacobian=jac, gradient=grad)
    for e in range(E):
        alone = table.subset(np.array([e]))
        ref, sq_ref = _evaluate(R[e:e + 1], alone, jacobian=bool(jac[e]), gradient=bool(grad[e]))
        assert got["cost"][e] == ref["cost"][0]
        assert np.array_equal(got["t"][e], ref["t"][0])
        if jac[e] or grad[e]:
            assert np.array_equal(got["Jtr"][e], ref["Jtr"][0])
            assert np.array_equal(got["JtJ"][e], ref["JtJ"][0])
        else:
            assert not got["Jtr"][e].any()
        m0, m1 = table.offsets[e], table.offsets[e + 1]
        assert np.array_equal(sq[m0:m1], sq_ref)
    # not every edge evaluated: the gathered path, same numbers
    ev = np.ones(E, bool)
    ev[3] = False
    part, sq_part = _evaluate(R, table, jacobian=jac, gradient=grad, evaluate=ev)
    assert part["cost"][3] == 0.0 and np.all(sq_part[table.offsets[3]:table.offsets[4]] == -1.0)
    assert np.array_equal(part["cost"][ev], got["cost"][ev])
    assert np.array_equal(part["JtJ"][ev], got["JtJ"][ev])


def test_segment_median_view_path_equals_gather_path():
    rng = np.random.default_rng(2)
    counts = np.array([9, 9, 9, 12, 9, 9, 40, 41, 9])  # equal sizes, consecutive and not
    offsets = np.concatenate([[0], np.cumsum(counts)])
    values = rng.normal(size=offsets[-1])
    got = kernels.segment_median(values, offsets)
    want = [np.sort(values[a:b])[(b - a) // 2] for a, b in zip(offsets[:-1], offsets[1:])]
    assert np.array_equal(got, want)
    equal = np.full(50, 7)
    offsets = np.concatenate([[0], np.cumsum(equal)])
    values = rng.normal(size=offsets[-1])
    assert np.array_equal(kernels.segment_median(values, offsets), np.sort(values.reshape(50, 7), axis=1)[:, 3])


def test_rotated_bearing_sq_equals_formula():
    batch, R, _ = _batch(seed=7)
    table = kernels.MatchTable.from_batch(batch, chunk=500)
    got = kernels.rotated_bearing_sq(R, table)
    R_m = np.repeat(R, batch.counts, axis=0)
    xi = batch.x_i / np.linalg.norm(batch.x_i, axis=1, keepdims=True)
    xj = batch.x_j / np.linalg.norm(batch.x_j, axis=1, keepdims=True)
    want = np.sum((xj - np.einsum("mab,mb->ma", R_m, xi)) ** 2, axis=1)
    assert np.max(np.abs(got - want)) < 1e-15
    assert got.max() > 1e-4  # the rotations are off: the test sees real residuals


def test_epipolar_moments_equal_outer_products():
    batch, _, w = _batch(seed=8)
    table = kernels.MatchTable.from_batch(batch, w, chunk=700)
    got = kernels.epipolar_moments(table)
    xi = batch.x_i / np.linalg.norm(batch.x_i, axis=1, keepdims=True)
    xj = batch.x_j / np.linalg.norm(batch.x_j, axis=1, keepdims=True)
    m = (xi[:, :, None] * xj[:, None, :]).reshape(-1, 9)
    for e in (0, 3, 11):
        a, b = batch.offsets[e], batch.offsets[e + 1]
        want = (m[a:b] * w[a:b, None]).T @ m[a:b]
        assert np.max(np.abs(got[e] - want)) < 1e-12 * np.abs(want).max()


def test_problem_commit_all_accepted_and_partial():
    batch, R, w = _batch(seed=9)
    problem = _TRRMProblem(kernels.MatchTable.from_batch(batch, w))
    E = batch.num_edges
    rows = np.arange(E)
    problem.evaluate(R, rows, np.full(E, kernels.COST))
    problem.commit(rows)  # every edge: the whole candidate vector
    _, sq_ref = _evaluate(R, problem.full)
    assert np.array_equal(problem.sq, sq_ref)
    R2 = np.stack([so3.exp(np.array([1e-3, 0, 0])) @ r for r in R])
    few = np.array([2, 7])
    problem.evaluate(R2[few], few, np.full(2, kernels.COST))  # recut to the two edges
    assert problem.cur.num_edges == 2
    problem.commit(few)  # every edge of the recut table
    _, sq2 = _evaluate(R2, problem.full)
    moved = np.zeros(batch.x_i.shape[0], bool)
    for e in few:
        moved[batch.offsets[e]:batch.offsets[e + 1]] = True
    assert np.array_equal(problem.sq[moved], sq2[moved])
    assert np.array_equal(problem.sq[~moved], sq_ref[~moved])
    assert not np.array_equal(sq2[moved], sq_ref[moved])
