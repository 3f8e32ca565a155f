"""Two-view geometry on the rotation manifold, batched over many edges at once.

Paper: "Towards Rotation-only Imaging Geometry: Rotation Estimation" (rotation_only.tex).

For an edge (i, j) with relative rotation ``R_j_from_i`` (the paper's R_ij = R_j R_i^T) and
matched normalized points X_ik, X_jk (z = 1):

* θ_ijk = [R_ij X_ik]x X_jk                                       (eq:theta)
* P_ijk = θ θ^T (Theorem 1), Pˢ_ij = Σ_k θ θ^T                   (eq:observeDerive2)
* t_ij spans the null space of Pˢ: its smallest eigenpair in closed form
  (eq:minlambda, eq:anaTset), sign fixed by chirality.
* The TRRM residual (eq:ROMresBearing) in its bearing form, written with the linear
  S-form of eq:YPA1 so that it does not depend on the sign or scale of t
  (eq:PA3linearTbearing), with an exact analytic Jacobian.

Many edges with different match counts are packed into one :class:`EdgeBatch`: all matches
concatenated, edges delimited by ``offsets``; per-edge sums are segment sums
(``np.add.reduceat``), so there is no Python loop per edge or per match.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import so3
from rotonly_cli.geometry.tracks import segment_indices
from rotonly_cli.options import MIN_MATCHES  # noqa: F401 (re-exported)


# ----------------------------------------------------------------------------- packing
class _EdgeOffsets:
    """What both forms of many edges' matches derive from their ``offsets`` (E + 1,)."""

    offsets: np.ndarray

    @property
    def num_edges(self) -> int:
        return len(self.offsets) - 1

    @property
    def num_matches(self) -> int:
        return int(self.offsets[-1])

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


@dataclass
class EdgeBatch(_EdgeOffsets):
    """Matches of many edges, concatenated.

    ``x_i``, ``x_j``: (M, 3) homogeneous normalized coordinates (z = 1 for 2-column input);
    ``offsets``: (E + 1,) start of each edge's matches; ``edge_of_match``: (M,) edge index.
    """

    x_i: np.ndarray
    x_j: np.ndarray
    offsets: np.ndarray
    #: optional per-match weights (M,): the fast kernels then use Σ w θθᵀ for Pˢ (any
    #: positive weights keep the noise-free null vector exact) and weight each residual row;
    #: robust TRRM sets them by IRLS (geometry/trrm.py)
    weights: np.ndarray | None = None

    @property
    def edge_of_match(self) -> np.ndarray:
        return np.repeat(np.arange(self.num_edges), self.counts)

    def subset(self, edges: np.ndarray) -> EdgeBatch:
        """The batch restricted to ``edges`` (indices, in the given order)."""
        edges = np.asarray(edges, dtype=np.int64)
        counts = self.counts[edges]
        starts = self.offsets[:-1][edges]
        new_offsets = np.concatenate([[0], np.cumsum(counts)])
        idx = segment_indices(starts, counts)  # every kept match: its edge's start + its place in it
        return EdgeBatch(self.x_i[idx], self.x_j[idx], new_offsets,
                         None if self.weights is None else self.weights[idx])

    def edge_range(self, e0: int, e1: int) -> EdgeBatch:
        """Edges [e0, e1) as views of this batch's arrays (no copy, unlike :meth:`subset`)."""
        m0, m1 = int(self.offsets[e0]), int(self.offsets[e1])
        return EdgeBatch(self.x_i[m0:m1], self.x_j[m0:m1], self.offsets[e0:e1 + 1] - m0,
                         None if self.weights is None else self.weights[m0:m1])

    def with_weights(self, weights: np.ndarray | None) -> EdgeBatch:
        return EdgeBatch(self.x_i, self.x_j, self.offsets, weights)

    def segment_sum(self, values: np.ndarray) -> np.ndarray:
        """Per-edge sums of per-match ``values`` (M, ...) -> (E, ...)."""
        return segment_sum(values, self.offsets)


@dataclass
class ObservedMatches(_EdgeOffsets):
    """Matches of many edges held as rows of one table of observation coordinates: what an
    :class:`EdgeBatch` holds, in 16 bytes per match instead of 48 (two int64 rows instead of
    two float64 3-vectors), the coordinates stored once per observation however many matches
    share it. :meth:`subset` gathers an EdgeBatch of some edges (GRRM's parts, issue 49).

    ``coords``: (U, 3) normalized coordinates; ``rows``: (M, 2) the rows of a match's two
    sides (view i, view j); ``offsets``: (E + 1,) as EdgeBatch's; optional ``weights`` (M,)."""

    coords: np.ndarray
    rows: np.ndarray
    offsets: np.ndarray
    weights: np.ndarray | None = None

    def subset(self, edges: np.ndarray) -> EdgeBatch:
        """The EdgeBatch of ``edges`` (indices, in the given order): coordinates gathered."""
        edges = np.asarray(edges, dtype=np.int64)
        counts = self.counts[edges]
        idx = segment_indices(self.offsets[:-1][edges], counts)
        rows = self.rows[idx]
        return EdgeBatch(self.coords[rows[:, 0]], self.coords[rows[:, 1]], np.concatenate([[0], np.cumsum(counts)]),
                         None if self.weights is None else self.weights[idx])

    def with_weights(self, weights: np.ndarray | None) -> ObservedMatches:
        return ObservedMatches(self.coords, self.rows, self.offsets, weights)


def num_matches(batch: EdgeBatch | ObservedMatches) -> int:
    """M of either form."""
    return batch.num_matches


def edge_group_batches(batch: EdgeBatch | ObservedMatches, max_matches: int = 1 << 19, e_lo: int = 0,
                       e_hi: int | None = None):
    """(e0, e1, EdgeBatch of edges [e0, e1)) for consecutive groups of about ``max_matches``
    matches of edges [e_lo, e_hi) (default: all): per-edge work on either form without a full
    per-match copy at once."""
    counts = batch.counts
    before = np.concatenate([[0], np.cumsum(counts)])
    e_hi = len(counts) if e_hi is None else e_hi
    e0 = e_lo
    while e0 < e_hi:
        e1 = max(e0 + 1, int(np.searchsorted(before, before[e0] + max_matches, side="right")) - 1)
        e1 = min(e1, e_hi)
        if isinstance(batch, EdgeBatch):
            yield e0, e1, batch.edge_range(e0, e1)
        else:
            yield e0, e1, batch.subset(np.arange(e0, e1))
        e0 = e1


def segment_sum(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    if len(offsets) <= 1:
        return np.zeros((0,) + values.shape[1:], dtype=values.dtype)
    return np.add.reduceat(values, offsets[:-1], axis=0)


def outer_segment_sum(a: np.ndarray, b: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Per-edge Σ_k a_k b_k^T (E, 3, 3) without an (M, 3, 3) temporary."""
    E = len(offsets) - 1
    out = np.zeros((E, 3, 3))
    if E == 0:
        return out
    starts = offsets[:-1]
    symmetric = a is b
    for r in range(3):
        for c in range(3):
            if symmetric and c < r:
                out[:, r, c] = out[:, c, r]
                continue
            out[:, r, c] = np.add.reduceat(a[:, r] * b[:, c], starts)
    return out


def _as_points(x, name: str) -> np.ndarray:
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise ValueError(f"{name}: expected an (m, 2) or (m, 3) array of normalized coordinates, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    if arr.shape[1] == 2:
        arr = np.hstack([arr, np.ones((arr.shape[0], 1))])
    return arr


def as_rotations(R, name: str = "R_j_from_i", batch: int | None = None, tol: float = 1e-6) -> np.ndarray:
    """Validate a rotation (3, 3) or a stack (E, 3, 3); raise ValueError naming ``name``."""
    try:
        arr = np.asarray(R, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric array ({exc})") from None
    if arr.shape[-2:] != (3, 3) or arr.ndim not in (2, 3):
        raise ValueError(f"{name}: expected a (3, 3) rotation or an (E, 3, 3) stack, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    stack = arr.reshape(-1, 3, 3)
    if batch is not None and stack.shape[0] != batch:
        raise ValueError(f"{name}: {stack.shape[0]} rotations for {batch} edges")
    bad = ~so3.is_rotation(stack, tol)
    if np.any(bad):
        raise ValueError(f"{name}: not a rotation matrix (orthonormal, det +1) at index {int(np.flatnonzero(bad)[0])}")
    return arr


def pack_edges(x_i: Sequence, x_j: Sequence, name_i: str = "x_i", name_j: str = "x_j") -> EdgeBatch:
    """Validate and concatenate per-edge match arrays into an :class:`EdgeBatch`."""
    if len(x_i) != len(x_j):
        raise ValueError(f"{name_i}, {name_j}: {len(x_i)} edges vs {len(x_j)} edges")
    xs_i, xs_j, counts = [], [], []
    for e, (a, b) in enumerate(zip(x_i, x_j)):
        a = _as_points(a, f"{name_i}[{e}]")
        b = _as_points(b, f"{name_j}[{e}]")
        if a.shape[0] != b.shape[0]:
            raise ValueError(f"{name_i}[{e}], {name_j}[{e}]: {a.shape[0]} vs {b.shape[0]} points (shapes disagree)")
        if a.shape[0] < MIN_MATCHES:
            raise ValueError(f"{name_i}[{e}]: {a.shape[0]} matches, need at least {MIN_MATCHES}")
        xs_i.append(a)
        xs_j.append(b)
        counts.append(a.shape[0])
    offsets = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
    if not counts:
        return EdgeBatch(np.zeros((0, 3)), np.zeros((0, 3)), offsets)
    return EdgeBatch(np.concatenate(xs_i), np.concatenate(xs_j), offsets)


def pack_flat(x_i: np.ndarray, x_j: np.ndarray, offsets: np.ndarray) -> EdgeBatch:
    """Wrap already concatenated (M, 2|3) arrays and (E + 1,) offsets (validated)."""
    a = _as_points(x_i, "x_i")
    b = _as_points(x_j, "x_j")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"x_i, x_j: {a.shape[0]} vs {b.shape[0]} points (shapes disagree)")
    offsets = np.asarray(offsets, dtype=np.int64)
    if offsets.ndim != 1 or offsets[0] != 0 or offsets[-1] != a.shape[0] or np.any(np.diff(offsets) < MIN_MATCHES):
        raise ValueError(f"offsets: must start at 0, end at {a.shape[0]} and give >= {MIN_MATCHES} matches per edge")
    return EdgeBatch(a, b, offsets)


# ----------------------------------------------------------------------------- θ and Pˢ
def rotate_per_match(R_j_from_i: np.ndarray, batch: EdgeBatch) -> np.ndarray:
    """u_k = R_ij X_ik for every match (M, 3)."""
    R_per_match = np.repeat(R_j_from_i, batch.counts, axis=0)
    return np.einsum("mab,mb->ma", R_per_match, batch.x_i)


def theta_vectors(R_j_from_i: np.ndarray, batch: EdgeBatch) -> np.ndarray:
    """θ_ijk = [R_ij X_ik]x X_jk (eq:theta), one row per match."""
    return np.cross(rotate_per_match(R_j_from_i, batch), batch.x_j)


def ps_matrices(R_j_from_i: np.ndarray, batch: EdgeBatch) -> np.ndarray:
    """Pˢ_ij = Σ_k θ θ^T per edge (eq:observeDerive2, Theorem 1), (E, 3, 3)."""
    theta = theta_vectors(R_j_from_i, batch)
    return outer_segment_sum(theta, theta, batch.offsets)


def ppo_matrix(R_j_from_i: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """P_ijk of eq:TwoViewPPOLinear2 built term by term (for checking Theorem 1), (m, 3, 3)."""
    u = np.einsum("ab,mb->ma", R_j_from_i, x_i)
    theta = np.cross(u, x_j)
    hat_u = so3.hat(u)
    hat_xj = so3.hat(x_j)
    term1 = -np.einsum("ma,mb,mbc->mac", x_j, theta, hat_u)
    term2 = np.einsum("ma,mb,mbc->mac", u, theta, hat_xj)
    return term1 + term2 + np.sum(theta * theta, axis=1)[:, None, None] * np.eye(3)


# ----------------------------------------------------------------------------- eigen
def symmetric_eigenvalues3(P: np.ndarray) -> np.ndarray:
    """All three eigenvalues of symmetric 3x3 matrices, ascending, in closed form.

    This is Cardano's trigonometric solution of the characteristic polynomial
    (eq:characteristicPolynomial - eq:minlambda) written in the shifted form
    B = (P - tr(P)/3 I) / s, s = sqrt(tr(B^2)/6), cos 3φ = det(B)/2, which avoids the
    cancellation of computing p and q from the raw invariants when the eigenvalues are
    clustered; mathematically it is identical to eq:minlambda.
    """
    P = np.asarray(P, dtype=float)
    mean = np.trace(P, axis1=-2, axis2=-1) / 3.0
    B = P - mean[..., None, None] * np.eye(3)
    s2 = np.einsum("...ij,...ij->...", B, B) / 6.0  # = -p/3 of eq:p_Cardano
    s = np.sqrt(s2)
    safe = np.where(s > 0, s, 1.0)
    Bn = B / safe[..., None, None]
    half_det = np.linalg.det(Bn) * 0.5  # = cos 3φ (eq:car_theta)
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0
    lam_max = mean + 2.0 * s * np.cos(phi)
    lam_min = mean + 2.0 * s * np.cos(phi + 2.0 * np.pi / 3.0)  # eq:minlambda
    lam_mid = 3.0 * mean - lam_max - lam_min
    return np.stack([lam_min, lam_mid, lam_max], axis=-1)


def smallest_eigenpair(P: np.ndarray, rel_tol: float = 1e-8) -> tuple[np.ndarray, np.ndarray]:
    """λ_min (eq:minlambda) and its unit eigenvector (eq:anaTset, longest ξ).

    The ξ's are cross products of rows of (P - λ_min I). When λ_min is (nearly) a double
    root, every ξ is tiny relative to ‖P‖² and the direction is ill-conditioned; those
    matrices fall back to ``numpy.linalg.eigh`` (any vector of the near-degenerate
    eigenspace is then a valid answer).
    """
    P = np.asarray(P, dtype=float)
    single = P.ndim == 2
    Pb = P.reshape(-1, 3, 3)
    lam = symmetric_eigenvalues3(Pb)[:, 0]
    scale = np.einsum("eij,eij->e", Pb, Pb)  # ‖P‖_F²
    rows = np.arange(Pb.shape[0])
    # The trigonometric root loses accuracy (~sqrt(eps)) when λ_min is close to λ_mid, so
    # the eq:anaTset vector is followed by a Rayleigh quotient and one more pass: each pass
    # squares the relative error (Rayleigh-quotient iteration on a 3x3).
    for _ in range(2):
        A = Pb - lam[:, None, None] * np.eye(3)
        xi = np.stack([np.cross(A[:, 0], A[:, 1]), np.cross(A[:, 0], A[:, 2]), np.cross(A[:, 1], A[:, 2])], axis=1)
        norms2 = np.einsum("eki,eki->ek", xi, xi)
        best = np.argmax(norms2, axis=1)
        n2 = norms2[rows, best]
        ok = n2 > (rel_tol ** 2) * scale * scale
        v_out = np.zeros((Pb.shape[0], 3))
        v_out[ok] = xi[rows, best][ok] / np.sqrt(n2[ok])[:, None]
        lam = np.where(ok, np.einsum("ei,eij,ej->e", v_out, Pb, v_out), lam)
    if np.any(~ok):
        w, V = np.linalg.eigh(Pb[~ok])
        lam[~ok] = w[:, 0]
        v_out[~ok] = V[:, :, 0]
    if single:
        return lam[0], v_out[0]
    return lam.reshape(P.shape[:-2]), v_out.reshape(P.shape[:-2] + (3,))


def _chirality_sign_from(theta: np.ndarray, u: np.ndarray, batch: EdgeBatch, t: np.ndarray) -> np.ndarray:
    t_m = np.repeat(t, batch.counts, axis=0)
    depth_i = np.einsum("ma,ma->m", theta, np.cross(batch.x_j, t_m))
    depth_j = np.einsum("ma,ma->m", theta, np.cross(u, t_m))
    front = ((depth_i > 0) & (depth_j > 0)).astype(np.int64)
    back = ((depth_i < 0) & (depth_j < 0)).astype(np.int64)
    vote = batch.segment_sum(front - back)
    return np.where(vote < 0, -1.0, 1.0)


def chirality_sign(R_j_from_i: np.ndarray, batch: EdgeBatch, t: np.ndarray) -> np.ndarray:
    """+1/-1 per edge: the sign of t that puts most points in front of both cameras.

    Depth in view i is positive iff θ·([X_j]x t) > 0 (eq:crosspruduct1, eq:modulus4) and
    in view j iff θ·([R X_i]x t) > 0 (eq:crosspruduct2, eq:modulus3); flipping t flips both.
    """
    u = rotate_per_match(R_j_from_i, batch)
    return _chirality_sign_from(np.cross(u, batch.x_j), u, batch, t)


def translation_directions(R_j_from_i: np.ndarray, batch: EdgeBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form t_ij (unit, chirality sign) per edge; also returns Pˢ and λ_min."""
    P = ps_matrices(R_j_from_i, batch)
    lam, t = smallest_eigenpair(P)
    t = t * chirality_sign(R_j_from_i, batch, t)[:, None]
    return t, P, lam


# ----------------------------------------------------------------------------- TRRM residual
@dataclass
class ResidualEvaluation:
    residuals: np.ndarray  # (M, 6): [r_i (in camera-j axes), r_j]
    cost: np.ndarray  # (E,) sum of squared residuals per edge (eq:ROMerr)
    t: np.ndarray  # (E, 3) unit translation direction used
    jacobian: np.ndarray | None = None  # (M, 6, 3) d r / d δ for R <- exp(δ) R
    JtJ: np.ndarray | None = None  # (E, 3, 3)
    Jtr: np.ndarray | None = None  # (E, 3)


def _unit(v: np.ndarray, tiny: float = 1e-300) -> tuple[np.ndarray, np.ndarray]:
    n = np.sqrt(np.einsum("ma,ma->m", v, v))
    safe = np.where(n > tiny, n, 1.0)
    return v / safe[:, None], n


def trrm_residuals(R_j_from_i: np.ndarray, batch: EdgeBatch, with_jacobian: bool = False,
                   t: np.ndarray | None = None, weights: np.ndarray | None = None) -> ResidualEvaluation:
    """TRRM bearing residuals of every match (eq:ROMresBearing) and, optionally, the exact
    Jacobian w.r.t. a left perturbation R_ij <- exp([δ]x) R_ij, including dt/dδ.

    t is the closed-form null vector of Pˢ (eq:minlambda, eq:anaTset), unit length, its
    sign fixed by chirality (:func:`chirality_sign`), so the residual does not depend on
    the sign or scale the eigen-solver happened to return. With u = R_ij X_i, θ = u x X_j:
      view j: Y^j = ‖X_j x t‖ u + ‖θ‖ t                      (eq:PA1)
      view i: R_ij Y^i = ‖u x t‖ X_j - ‖θ‖ t                 (eq:PA1 for the edge (j, i))
      r_j = x̂_j - Ŷ^j,  r_i = û - (R_ij Y^i)^                (eq:PA3bearing, eq:PA4bearing)
    r_i is view i's residual rotated into camera-j axes (same norm, so the same cost).
    The norm form keeps every analytic depth positive (eq:analyticalDepth), so a match whose
    θ is dominated by noise (far points, tiny parallax) still predicts ≈ its pure-rotation
    position instead of flipping behind the camera.
    ``weights`` (M,) multiply the residuals of each match (robust reweighting).
    ``t`` (E, 3), when given, must already be unit length with the chirality sign.
    """
    counts = batch.counts
    x_j = batch.x_j
    u = rotate_per_match(R_j_from_i, batch)
    theta = np.cross(u, x_j)
    P = lam = None
    if t is None:
        P = batch.segment_sum(theta[:, :, None] * theta[:, None, :])
        lam, t = smallest_eigenpair(P)
        t = t * _chirality_sign_from(theta, u, batch, t)[:, None]
    t_m = np.repeat(t, counts, axis=0)
    xj_x_t = np.cross(x_j, t_m)
    u_x_t = np.cross(u, t_m)
    a_j = np.sqrt(np.einsum("ma,ma->m", xj_x_t, xj_x_t))
    a_i = np.sqrt(np.einsum("ma,ma->m", u_x_t, u_x_t))
    b = np.sqrt(np.einsum("ma,ma->m", theta, theta))
    s_j = a_j[:, None] * u + b[:, None] * t_m
    s_i = a_i[:, None] * x_j - b[:, None] * t_m
    xj_hat, _ = _unit(x_j)
    u_hat, _ = _unit(u)
    sj_hat, sj_norm = _unit(s_j)
    si_hat, si_norm = _unit(s_i)
    # a match on the baseline itself (X ∥ t) has no defined prediction: drop it
    valid = (sj_norm > 1e-14) & (si_norm > 1e-14)
    r = np.concatenate([u_hat - si_hat, xj_hat - sj_hat], axis=1)
    w = valid.astype(float) if weights is None else valid * np.asarray(weights, dtype=float)
    r = r * w[:, None]
    cost = batch.segment_sum(np.einsum("mk,mk->m", r, r))
    out = ResidualEvaluation(residuals=r, cost=cost, t=t)
    if not with_jacobian:
        return out
    if P is None:
        P = batch.segment_sum(theta[:, :, None] * theta[:, None, :])
    if lam is None:
        lam = symmetric_eigenvalues3(P)[:, 0]

    I3 = np.eye(3)
    xj_dot_u = np.einsum("ma,ma->m", x_j, u)
    # dθ = A δ with A = [X_j]x [u]x = u X_j^T - (X_j·u) I   (du = δ x u)
    A = u[:, :, None] * x_j[:, None, :] - xj_dot_u[:, None, None] * I3
    At_t = x_j * np.einsum("ma,ma->m", u, t_m)[:, None] - xj_dot_u[:, None] * t_m  # A^T t
    # dt/dδ = -(Pˢ - λI)^+ (dPˢ t)/dδ with dPˢ t = Σ [(θ·t) A + θ (A^T t)^T] δ
    theta_dot_t = np.einsum("ma,ma->m", theta, t_m)
    dPt = batch.segment_sum(theta_dot_t[:, None, None] * A + theta[:, :, None] * At_t[:, None, :])
    scale = np.trace(P, axis1=1, axis2=2)[:, None, None] + 1e-300
    tt = t[:, :, None] * t[:, None, :]
    pinv = np.linalg.inv(P - lam[:, None, None] * I3 + scale * tt) - tt / scale
    T = np.repeat(-pinv @ dPt, counts, axis=0)  # (M, 3, 3)

    safe = lambda v: np.where(v > 0, v, 1.0)  # noqa: E731
    hat_u = so3.hat(u)
    # db = θ^T A δ / b, A^T θ = -(X_j·u) θ (u ⟂ θ)
    db = (-xj_dot_u / safe(b))[:, None] * theta
    # da_j = (X_j x t)^T [X_j]x T δ / a_j = -((X_j x (X_j x t))^T T) δ / a_j
    da_j = -np.einsum("ma,mab->mb", np.cross(x_j, xj_x_t), T) / safe(a_j)[:, None]
    # d(u x t) = [t]x[u]x δ + [u]x T δ ; da_i = (u x t)^T d(u x t) / a_i
    d_uxt = so3.hat(t_m) @ hat_u + hat_u @ T
    da_i = np.einsum("ma,mab->mb", u_x_t, d_uxt) / safe(a_i)[:, None]
    ds_j = u[:, :, None] * da_j[:, None, :] - a_j[:, None, None] * hat_u + t_m[:, :, None] * db[:, None, :] \
        + b[:, None, None] * T
    ds_i = x_j[:, :, None] * da_i[:, None, :] - t_m[:, :, None] * db[:, None, :] - b[:, None, None] * T

    def d_unit(s_hat, s_norm, ds):  # d(s/‖s‖) = (I - ŝŝ^T) ds / ‖s‖
        proj = ds - s_hat[:, :, None] * np.einsum("ma,mab->mb", s_hat, ds)[:, None, :]
        return proj / safe(s_norm)[:, None, None]

    dr_j = -d_unit(sj_hat, sj_norm, ds_j)
    dr_i = -so3.hat(u_hat) - d_unit(si_hat, si_norm, ds_i)
    J = np.concatenate([dr_i, dr_j], axis=1) * w[:, None, None]
    out.jacobian = J
    out.JtJ = batch.segment_sum(np.einsum("mki,mkj->mij", J, J))
    out.Jtr = batch.segment_sum(np.einsum("mki,mk->mi", J, r))
    return out


def epipolar_residuals(R_j_from_i: np.ndarray, batch: EdgeBatch, with_jacobian: bool = False) -> ResidualEvaluation:
    """e_k = θ̂_k · t with θ̂ = θ / (‖X_i‖ ‖X_j‖), t the unit null vector of their Pˢ.

    Σ_k e_k² = λ_min(Pˢ) of the bearing-normalised Pˢ: the cost Kneip and Lynen minimise
    (the paper notes Pˢ and their M coincide, §"Reprojection-error Optimization"). It is
    smooth where TRRM is not: TRRM's analytic depths jump when a point changes side of the
    epipolar plane, so far from the optimum the TRRM cost is rugged while λ_min decreases
    steadily along the geodesic to the truth. TRRM uses it as a first phase (trrm.py).
    Jacobian (left perturbation): de = t^T A δ + θ̂^T dt, A = dθ̂/dδ, dt from the eigenvector
    perturbation of the normalised Pˢ.
    """
    counts = batch.counts
    u = rotate_per_match(R_j_from_i, batch)
    norm_scale = 1.0 / (np.sqrt(np.einsum("ma,ma->m", batch.x_i, batch.x_i))
                        * np.sqrt(np.einsum("ma,ma->m", batch.x_j, batch.x_j)))
    x_j = batch.x_j
    theta = np.cross(u, x_j) * norm_scale[:, None]
    P = batch.segment_sum(theta[:, :, None] * theta[:, None, :])
    lam, t = smallest_eigenpair(P)
    t_m = np.repeat(t, counts, axis=0)
    e = np.einsum("ma,ma->m", theta, t_m)
    cost = batch.segment_sum(e * e)
    out = ResidualEvaluation(residuals=e[:, None], cost=cost, t=t)
    if not with_jacobian:
        return out
    I3 = np.eye(3)
    xj_dot_u = np.einsum("ma,ma->m", x_j, u)
    A = (u[:, :, None] * x_j[:, None, :] - xj_dot_u[:, None, None] * I3) * norm_scale[:, None, None]
    At_t = np.einsum("mab,ma->mb", A, t_m)
    dPt = batch.segment_sum(e[:, None, None] * A + theta[:, :, None] * At_t[:, None, :])
    scale = np.trace(P, axis1=1, axis2=2)[:, None, None] + 1e-300
    tt = t[:, :, None] * t[:, None, :]
    pinv = np.linalg.inv(P - lam[:, None, None] * I3 + scale * tt) - tt / scale
    T = np.repeat(-pinv @ dPt, counts, axis=0)
    J = At_t + np.einsum("ma,mab->mb", theta, T)
    out.jacobian = J[:, None, :]
    out.JtJ = batch.segment_sum(J[:, :, None] * J[:, None, :])
    out.Jtr = batch.segment_sum(J * e[:, None])
    return out


# ----------------------------------------------------------------------------- RANSAC
def ransac_trials_needed(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """Trials after which a RANSAC has drawn at least one all-inlier sample with probability
    ``confidence`` when a fraction ``inlier_ratio`` of the data are inliers:
    log(1 - confidence) / log(1 - ratio^sample_size) (Fischler & Bolles 1981; the same count
    COLMAP's adaptive stopping uses). inf for a ratio of 0, 1 for a ratio of 1."""
    p_sample = float(np.clip(inlier_ratio, 0.0, 1.0)) ** sample_size
    if p_sample >= 1.0:
        return 1.0
    if p_sample <= 0.0:
        return float("inf")
    return float(np.ceil(np.log1p(-confidence) / np.log1p(-p_sample)))


# ----------------------------------------------------------------------------- pure rotation
def sampson_errors(R_j_from_i: np.ndarray, t: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """First-order geometric distance of each match to the epipolar geometry E = [t]x R_ij
    (Sampson), in normalized image units (x pixels / focal length): (m,)."""
    E = so3.hat(np.asarray(t, dtype=float)) @ np.asarray(R_j_from_i, dtype=float)
    return epipolar_sampson_errors(E, x_i, x_j)


def epipolar_sampson_errors(M: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Sampson distance of each match (x_j^T M x_i = 0) to an essential or fundamental
    matrix ``M``, in the units of ``x_i``, ``x_j`` ((m, 2) or (m, 3) with z = 1): (m,)."""
    a = _as_points(x_i, "x_i")
    b = _as_points(x_j, "x_j")
    Ea = a @ np.asarray(M, dtype=float).T  # epipolar lines in view j
    Etb = b @ np.asarray(M, dtype=float)  # epipolar lines in view i
    algebraic = np.einsum("ma,ma->m", b, Ea)
    gradient = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return np.abs(algebraic) / np.sqrt(np.maximum(gradient, 1e-300))


def homography_transfer_errors(H: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """First-order geometric distance of each match to the homography x_j ~ H x_i, with the
    same noise in both views: the transfer error r = x_j - π(H x_i) whitened by its
    covariance I + A Aᵀ (A = ∂π(H x_i)/∂x_i). Under isotropic Gaussian noise σ per coordinate
    its square is σ² χ²₂, so σ = median / √(2 ln 2). Units of ``x_i``, ``x_j``: (m,)."""
    a = _as_points(x_i, "x_i")
    b = _as_points(x_j, "x_j")
    H = np.asarray(H, dtype=float)
    mapped = a @ H.T
    w = mapped[:, 2:3]
    projected = mapped[:, :2] / w
    r = b[:, :2] - projected
    A = (H[None, :2, :2] - projected[:, :, None] * H[None, 2:3, :2]) / w[:, :, None]  # (m, 2, 2)
    covariance = np.eye(2) + A @ np.swapaxes(A, 1, 2)
    whitened = np.linalg.solve(covariance, r[:, :, None])[:, :, 0]
    return np.sqrt(np.maximum(np.einsum("ma,ma->m", r, whitened), 0.0))


def pure_rotation_residuals(R_j_from_i: np.ndarray, batch: EdgeBatch) -> np.ndarray:
    """eq:PureRotationReprojBearingError for both views: per-edge cost Σ ‖x̂_j - R x̂_i‖² · 2."""
    xi_hat, _ = _unit(batch.x_i)
    xj_hat, _ = _unit(batch.x_j)
    # Σ‖x̂_j - R x̂_i‖² = Σ (2 - 2 x̂_j·R x̂_i) = 2m - 2 tr(R^T H), H = Σ x̂_j x̂_i^T: no per-match rotation
    H = outer_segment_sum(xj_hat, xi_hat, batch.offsets)
    m = batch.counts.astype(float)
    return 2.0 * np.maximum(2.0 * m - 2.0 * np.einsum("eab,eab->e", R_j_from_i, H), 0.0)


def best_pure_rotation(batch: EdgeBatch, robust_iterations: int = 0) -> np.ndarray:
    """argmin_R Σ ‖x̂_j - R x̂_i‖² per edge (orthogonal Procrustes on bearings): the exact
    minimiser of the PR/B/I form of the TRRM cost (eq:PureRotationReprojBearingError).

    ``robust_iterations`` > 0 re-solves with Cauchy weights (scale 3 x 1.4826 x the edge's
    median residual) so that wrong matches do not bias it."""
    xi_hat, _ = _unit(batch.x_i)
    xj_hat, _ = _unit(batch.x_j)
    R = so3.project_to_so3(outer_segment_sum(xj_hat, xi_hat, batch.offsets))
    for _ in range(robust_iterations):
        d = xj_hat - np.einsum("mab,mb->ma", np.repeat(R, batch.counts, axis=0), xi_hat)
        sq = np.einsum("ma,ma->m", d, d)
        c2 = np.repeat((3.0 * 1.4826) ** 2 * segment_median(sq, batch) + 1e-30, batch.counts)
        w = 1.0 / (1.0 + sq / c2)
        R = so3.project_to_so3(outer_segment_sum(xj_hat * w[:, None], xi_hat, batch.offsets))
    return R


def segment_median(values: np.ndarray, batch: EdgeBatch) -> np.ndarray:
    """Per-edge (upper) median of non-negative per-match ``values`` (M,), vectorised: one
    argsort of edge + value / edge max (each edge's values land in [edge, edge + 1)), then the
    original value is gathered, so the result does not depend on the other edges."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return np.zeros(batch.num_edges)
    edge_max = np.maximum.reduceat(values, batch.offsets[:-1])
    scale = np.repeat(edge_max * (1.0 + 1e-9) + 1e-300, batch.counts)
    edge = np.repeat(np.arange(batch.num_edges, dtype=float), batch.counts)
    order = np.argsort(edge + values / scale, kind="stable")
    return values[order[batch.offsets[:-1] + batch.counts // 2]]
