"""Kneip & Lynen (ICCV 2013) eigensolver rotation optimisation, reimplemented from
algorithms.md §4 (no OpenGV code copied). Benchmark baseline only.

Kneip's matrix for an edge (i, j) with R = R_ij = R_j R_iᵀ, f1 := x̂_j, f2 := x̂_i (unit bearings;
algorithms.md §4 "Seed <-> Kneip"):

    M(R) = Σ_k n_k n_kᵀ,   n_k = f1_k × R f2_k

equals the bearing-normalised Pˢ of the paper. OpenGV precomputes the sums
``G[b, e] = Σ_k f1_b f1_e f2 f2ᵀ`` (its xxF, xyF, ... — 6 distinct 3×3 blocks), so M(R) and
the gradient of λ_min(M(R)) cost O(1) per edge whatever the number of matches:

    M_ad = ε_abc ε_def (R G[b, e] Rᵀ)_cf
    ∂λ_min/∂δ = 2 Σ_k (u·w)(u × w),  u = R f2, w = v × f1   (left perturbation R <- exp(δ) R,
                v the unit eigenvector of λ_min; Hellmann–Feynman)

and the last sum is again a contraction of G. OpenGV runs Eigen's Levenberg–Marquardt with
the analytic gradient as a 3-vector residual (so LM drives the gradient to zero) and a
numerical Jacobian of that residual, ``ftol = 5e-5``, ``maxfev = 100``, over the Cayley
parameters of R. We do the same, in lock-step over many edges, with a central-difference
Jacobian of the gradient (more accurate than a forward one) and the Cayley vector
``R = cay(c) R_start`` relative to the start. Documented difference: OpenGV minimises the
"reduced" (1 + cᵀc)² λ_min of the absolute Cayley vector, whose minimiser is slightly pulled
towards R = I; we minimise λ_min itself, the cost Kneip and Lynen define.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry import so3

#: Levi-Civita symbol ε_abc
EPS3 = np.zeros((3, 3, 3))
EPS3[0, 1, 2] = EPS3[1, 2, 0] = EPS3[2, 0, 1] = 1.0
EPS3[0, 2, 1] = EPS3[2, 1, 0] = EPS3[1, 0, 2] = -1.0


@dataclass(frozen=True)
class KneipOptions:
    max_evaluations: int = 100  #: OpenGV maxfev
    function_tolerance: float = 5e-5  #: OpenGV ftol: relative decrease of ‖∂λ/∂c‖²
    initial_damping: float = 1e-3
    max_damping: float = 1e12
    difference_step: float = 1e-6  #: central-difference step on the Cayley vector


@dataclass
class KneipResult:
    rotations: np.ndarray  # (E, 3, 3) refined R_j_from_i
    translation_directions: np.ndarray  # (E, 3) unit eigenvector of λ_min, chirality sign
    smallest_eigenvalues: np.ndarray  # (E,) λ_min(M) at the end
    initial_eigenvalues: np.ndarray  # (E,)
    iterations: np.ndarray  # (E,)


def unit_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.shape[1] == 2:
        x = np.column_stack([x, np.ones(len(x))])
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def cayley_to_rotation(c: np.ndarray) -> np.ndarray:
    """R = ((1 − cᵀc) I + 2 c cᵀ + 2 [c]×) / (1 + cᵀc), batched (..., 3); complex-step safe."""
    c = np.asarray(c)
    cc = np.sum(c * c, axis=-1)[..., None, None]
    K = so3.hat(c) if not np.iscomplexobj(c) else _hat_complex(c)
    outer = c[..., :, None] * c[..., None, :]
    return ((1.0 - cc) * np.eye(3) + 2.0 * outer + 2.0 * K) / (1.0 + cc)


def _hat_complex(w: np.ndarray) -> np.ndarray:
    out = np.zeros(w.shape[:-1] + (3, 3), dtype=w.dtype)
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def kneip_sums(batch: pg.EdgeBatch) -> np.ndarray:
    """G (E, 3, 3, 3, 3) with G[e, b, c, :, :] = Σ_k f1_b f1_c f2 f2ᵀ (OpenGV's xxF ... zzF)."""
    f1 = unit_rows(batch.x_j)
    f2 = unit_rows(batch.x_i)
    starts = batch.offsets[:-1]
    G = np.zeros((batch.num_edges, 3, 3, 3, 3))
    if batch.num_edges == 0:
        return G
    for b in range(3):
        for c in range(b, 3):
            w = f1[:, b] * f1[:, c]
            for g in range(3):
                for h in range(g, 3):
                    G[:, b, c, g, h] = G[:, b, c, h, g] = np.add.reduceat(w * f2[:, g] * f2[:, h], starts)
            G[:, c, b] = G[:, b, c]
    return G


def _rotated_sums(R: np.ndarray, G: np.ndarray) -> np.ndarray:
    """H[e, b, c, :, :] = R G[e, b, c] Rᵀ = Σ_k f1_b f1_c u uᵀ with u = R f2."""
    return np.einsum("ncg,nfh,nbegh->nbecf", R, R, G, optimize=True)


def kneip_matrices(R: np.ndarray, G: np.ndarray) -> np.ndarray:
    """M(R) (E, 3, 3) from the precomputed sums (O(1) per edge)."""
    return np.einsum("abc,def,nbecf->nad", EPS3, EPS3, _rotated_sums(R, G), optimize=True)


def smallest_eigenvalue_and_gradient(R: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """λ_min(M(R)) (E,), its eigenvector v (E, 3), and ∂λ_min/∂δ (E, 3) for R <- exp(δ) R."""
    H = _rotated_sums(R, G)
    M = np.einsum("abc,def,nbecf->nad", EPS3, EPS3, H, optimize=True)
    lam, v = pg.smallest_eigenpair(M)
    V = so3.hat(v)
    # Σ_k (u·w)(u × w)_a = ε_ade V_cb V_eg H[b, g, c, d]
    grad = 2.0 * np.einsum("ade,ncb,neg,nbgcd->na", EPS3, V, V, H, optimize=True)
    return lam, v, grad


def refine_kneip_eigen(R_start: np.ndarray, batch: pg.EdgeBatch, options: KneipOptions = KneipOptions()) -> KneipResult:
    """Minimise λ_min(M(R)) per edge (LM on the gradient residual, lock-step over edges)."""
    R_start = np.asarray(R_start, dtype=float).reshape(-1, 3, 3)
    E = batch.num_edges
    G = kneip_sums(batch)
    # scale-free: divide by the number of matches so damping/step sizes do not depend on m
    G = G / batch.counts.astype(float)[:, None, None, None, None]
    h = options.difference_step

    def residual(c: np.ndarray, edges: np.ndarray) -> np.ndarray:
        return smallest_eigenvalue_and_gradient(cayley_to_rotation(c) @ R_start[edges], G[edges])[2]

    def jacobian(c: np.ndarray, edges: np.ndarray) -> np.ndarray:
        cols = []
        for k in range(3):
            d = np.zeros(3)
            d[k] = h
            cols.append((residual(c + d, edges) - residual(c - d, edges)) / (2 * h))
        return np.stack(cols, axis=2)

    c = np.zeros((E, 3))
    lam0 = smallest_eigenvalue_and_gradient(R_start, G)[0]
    g = residual(c, np.arange(E))
    f = np.einsum("na,na->n", g, g)
    mu = np.full(E, options.initial_damping)
    active = np.ones(E, dtype=bool)
    evaluations = np.ones(E, dtype=np.int64)
    iterations = np.zeros(E, dtype=np.int64)
    while np.any(active):
        idx = np.flatnonzero(active)
        J = jacobian(c[idx], idx)
        JtJ = np.einsum("nka,nkb->nab", J, J)
        Jtg = np.einsum("nka,nk->na", J, g[idx])
        diag = np.einsum("naa->na", JtJ)
        scale = np.maximum(diag, 1e-12 * np.maximum(diag.max(axis=1, keepdims=True), 1e-300))
        A = JtJ + (mu[idx, None] * scale)[:, :, None] * np.eye(3)
        step = -np.linalg.solve(A, Jtg[:, :, None])[:, :, 0]
        c_new = c[idx] + step
        g_new = residual(c_new, idx)
        f_new = np.einsum("na,na->n", g_new, g_new)
        evaluations[idx] += 7
        iterations[idx] += 1
        accept = f_new < f[idx]
        rel_decrease = np.where(accept, (f[idx] - f_new) / np.maximum(f[idx], 1e-300), 0.0)
        acc = idx[accept]
        c[acc], g[acc], f[acc] = c_new[accept], g_new[accept], f_new[accept]
        mu[idx] = np.where(accept, np.maximum(mu[idx] / 10.0, 1e-15), mu[idx] * 10.0)
        step_small = np.linalg.norm(step, axis=1) <= 1e-15 * (1.0 + np.linalg.norm(c[idx], axis=1))
        done = (accept & (rel_decrease < options.function_tolerance)) | step_small | (f[idx] == 0.0) \
            | (mu[idx] > options.max_damping) | (evaluations[idx] >= options.max_evaluations)
        active[idx[done]] = False

    R = cayley_to_rotation(c) @ R_start
    R = so3.project_to_so3(R)
    lam, v, _ = smallest_eigenvalue_and_gradient(R, G)
    t = v * pg.chirality_sign(R, batch, v)[:, None]
    counts = batch.counts.astype(float)
    return KneipResult(rotations=R, translation_directions=t, smallest_eigenvalues=lam * counts,
                       initial_eigenvalues=lam0 * counts, iterations=iterations)
