"""Structure-of-arrays helpers of the kernels: every 3-vector is a tuple of three contiguous
1-D arrays (one entry per match), so cross and dot products are a handful of elementwise
operations; edges are processed in groups of about ``CHUNK_MATCHES`` matches so the
temporaries of a pass stay in cache."""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry import pairwise as pg

CHUNK_MATCHES = 1 << 15


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def axpy(alpha, a, beta, b):  # alpha a + beta b with per-match scalars
    return (alpha * a[0] + beta * b[0], alpha * a[1] + beta * b[1], alpha * a[2] + beta * b[2])


def edge_groups(counts: np.ndarray, chunk: int) -> list[tuple[int, int]]:
    """Consecutive edge ranges [e0, e1) of about ``chunk`` matches each."""
    cum = np.cumsum(counts)
    groups = []
    e0 = 0
    E = len(counts)
    while e0 < E:
        base = cum[e0 - 1] if e0 else 0
        e1 = int(np.searchsorted(cum, base + chunk, side="right"))
        e1 = max(e1, e0 + 1)
        groups.append((e0, min(e1, E)))
        e0 = e1
    return groups


def rep(values: np.ndarray, counts: np.ndarray):
    return np.repeat(values, counts)


def seg(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    return np.add.reduceat(values, starts)


def rotate(R: np.ndarray, counts: np.ndarray, x):
    """u = R_e x per match, R (E, 3, 3)."""
    return tuple(rep(R[:, k, 0], counts) * x[0] + rep(R[:, k, 1], counts) * x[1] + rep(R[:, k, 2], counts) * x[2]
                 for k in range(3))


def pinv_shifted(P: np.ndarray, lam: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(Pˢ - λI)^+ restricted to the complement of t (eigenvector perturbation)."""
    scale = np.trace(P, axis1=1, axis2=2)[:, None, None] + 1e-300
    tt = t[:, :, None] * t[:, None, :]
    return np.linalg.inv(P - lam[:, None, None] * np.eye(3) + scale * tt) - tt / scale




def edge_chunks(batch: pg.EdgeBatch, chunk: int, e_lo: int = 0, e_hi: int | None = None):
    """Per group of about ``chunk`` matches of edges [e_lo, e_hi) (default: all): edge range,
    match range, per-edge counts and starts in the group, the coordinates as component
    arrays and the weights."""
    counts = batch.counts
    e_hi = len(counts) if e_hi is None else e_hi
    for g0, g1 in edge_groups(counts[e_lo:e_hi], chunk):
        e0, e1 = e_lo + g0, e_lo + g1
        m0, m1 = batch.offsets[e0], batch.offsets[e1]
        xi = tuple(np.ascontiguousarray(batch.x_i[m0:m1, k]) for k in range(3))
        xj = tuple(np.ascontiguousarray(batch.x_j[m0:m1, k]) for k in range(3))
        wk = None if batch.weights is None else np.ascontiguousarray(batch.weights[m0:m1], dtype=float)
        yield e0, e1, m0, m1, counts[e0:e1], batch.offsets[e0:e1] - m0, xi, xj, wk
