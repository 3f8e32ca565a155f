"""ROBA — rotation-only bundle adjustment (Lee & Civera, CVPR 2021), reimplemented from the
description in algorithms.md §3 (the public code is GPL; nothing copied). Benchmark only.

Cost over all global rotations R_v (= R_cam_from_world):

    C({R}) = Σ_{(i, j) ∈ E} sqrt(|λ_min(M_ij(R_j R_iᵀ))|)

with M_ij Kneip's matrix of the edge's unit bearings (f1 = x̂_j, f2 = x̂_i, see
:mod:`rotonly_cli.baselines.kneip`), evaluated in O(1) per edge from the six precomputed
3×3 sums per edge. λ_min by the closed-form cubic (same formula as ROBA/OpenGV).

Optimiser as ROBA's: Adam on the stacked rotation vectors r_v = Log R_v (additive update,
R_v = Exp(r_v)), α = 0.01, β1 = 0.9, β2 = 0.999, ε = 1e-8, 100 iterations; after 5
consecutive cost increases α drops to 0.001; the best (lowest-cost) iterate is returned.
Gradient: forward differences with a 1e-4 step on every rotation-vector component (ROBA's
``dev_angle``), all edges and components at once (no approximation of the k-side gradient).
The gauge view ``fixed_view`` is not updated (the cost is gauge invariant).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rotonly_cli.baselines.kneip import EPS3, kneip_sums
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry import so3


@dataclass(frozen=True)
class ROBAOptions:
    learning_rate: float = 0.01
    reduced_learning_rate: float = 0.001
    beta1: float = 0.9
    beta2: float = 0.999
    epsilon: float = 1e-8
    iterations: int = 100
    increases_before_switch: int = 5
    difference_step: float = 1e-4  #: ROBA's dev_angle (rad, on each rotation-vector component)
    square_rooting: bool = True  #: sqrt(|λ|) per edge (ROBA default); False: λ


@dataclass
class ROBAResult:
    R_cam_from_world: np.ndarray  # (n, 3, 3), best iterate
    initial_cost: float
    cost: float
    best_iteration: int
    history: list = field(default_factory=list)  # cost per iteration


def _smallest_eigenvalues(R_rel: np.ndarray, G: np.ndarray) -> np.ndarray:
    H = np.einsum("ncg,nfh,nbegh->nbecf", R_rel, R_rel, G, optimize=True)
    M = np.einsum("abc,def,nbecf->nad", EPS3, EPS3, H, optimize=True)
    return pg.symmetric_eigenvalues3(M)[:, 0]


class ROBAProblem:
    """Precomputed per-edge sums; cost and forward-difference gradient of all views at once."""

    def __init__(self, num_views: int, edge_views: np.ndarray, batch: pg.EdgeBatch, options: ROBAOptions):
        self.n = num_views
        self.edge_views = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2)
        self.G = kneip_sums(batch)
        self.options = options

    def _edge_costs(self, R_rel: np.ndarray, G: np.ndarray) -> np.ndarray:
        lam = _smallest_eigenvalues(R_rel, G)
        return np.sqrt(np.abs(lam)) if self.options.square_rooting else lam

    def cost(self, r: np.ndarray) -> float:
        R = so3.exp(r)
        i, j = self.edge_views.T
        return float(self._edge_costs(R[j] @ np.swapaxes(R[i], 1, 2), self.G).sum())

    def cost_and_gradient(self, r: np.ndarray) -> tuple[float, np.ndarray]:
        h = self.options.difference_step
        R = so3.exp(r)
        i, j = self.edge_views.T
        E = len(i)
        base = self._edge_costs(R[j] @ np.swapaxes(R[i], 1, 2), self.G)
        # perturbed rotations of both ends, 3 components each: (E, 3, 3, 3)
        steps = h * np.eye(3)
        R_i_pert = so3.exp(r[i][:, None, :] + steps)  # (E, 3, 3, 3)
        R_j_pert = so3.exp(r[j][:, None, :] + steps)
        rel_i = R[j][:, None] @ np.swapaxes(R_i_pert, -1, -2)  # view i perturbed
        rel_j = R_j_pert @ np.swapaxes(R[i], 1, 2)[:, None]  # view j perturbed
        rel = np.concatenate([rel_i, rel_j], axis=1).reshape(-1, 3, 3)
        G6 = np.repeat(self.G, 6, axis=0)
        pert = self._edge_costs(rel, G6).reshape(E, 6)
        d = (pert - base[:, None]) / h
        grad = np.zeros((self.n, 3))
        np.add.at(grad, i, d[:, :3])
        np.add.at(grad, j, d[:, 3:])
        return float(base.sum()), grad


def roba(R_cam_from_world: np.ndarray, edge_views: np.ndarray, batch: pg.EdgeBatch, fixed_view: int = 0,
         options: ROBAOptions = ROBAOptions()) -> ROBAResult:
    """Refine global rotations with ROBA's Adam on Σ sqrt(|λ_min|) (module docstring)."""
    R0 = np.asarray(R_cam_from_world, dtype=float)
    n = R0.shape[0]
    problem = ROBAProblem(n, edge_views, batch, options)
    r = so3.log(R0).reshape(n, 3)
    m = np.zeros_like(r)
    v = np.zeros_like(r)
    alpha = options.learning_rate
    best_r, best_cost, best_iteration = r.copy(), np.inf, 0
    previous, increases = np.inf, 0
    history = []
    initial_cost = None
    for it in range(options.iterations + 1):
        cost, grad = problem.cost_and_gradient(r)
        if initial_cost is None:
            initial_cost = cost
        history.append(cost)
        if cost < best_cost:
            best_cost, best_r, best_iteration = cost, r.copy(), it
        increases = increases + 1 if cost > previous else 0
        if increases >= options.increases_before_switch:
            alpha = options.reduced_learning_rate
        previous = cost
        if it == options.iterations:
            break
        grad[fixed_view] = 0.0
        m = options.beta1 * m + (1 - options.beta1) * grad
        v = options.beta2 * v + (1 - options.beta2) * grad * grad
        m_hat = m / (1 - options.beta1 ** (it + 1))
        v_hat = v / (1 - options.beta2 ** (it + 1))
        r = r - alpha * m_hat / (np.sqrt(v_hat) + options.epsilon)
    return ROBAResult(R_cam_from_world=so3.exp(best_r), initial_cost=float(initial_cost), cost=float(best_cost),
                      best_iteration=best_iteration, history=history)
