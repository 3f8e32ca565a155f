"""The lean TRRM evaluator of geometry/trrm.py: per-edge cost, JᵀJ and Jᵀr only.

The forward kernels (kernels/forward.py) serve GRRM and the tests with per-match outputs;
the TRRM driver only needs per-edge sums, so it uses this leaner evaluator:

* a MatchTable holds the per-match constants once (x_i, x_j, x̂_j, 1/‖x_i‖, ‖x_i‖², ‖x_j‖²,
  1/‖x_j‖) as rows of one (13, M) array, so subsets are one gather and chunks are views;
* everything in one pass per edge group, and scalar identities replace 3-vector
  products: with u = R x_i (‖u‖ = ‖x_i‖), unit t and the three dots x_j·t, u·t, u·x_j,
    ‖x_j × t‖² = ‖x_j‖² - (x_j·t)²,   ‖u × t‖² = ‖x_i‖² - (u·t)²,
    θ·(x_j × t) = (u·x_j)(x_j·t) - ‖x_j‖²(u·t),  θ·(u × t) = ‖x_i‖²(x_j·t) - (u·x_j)(u·t)
  (chirality depths, eq:crosspruduct1 and eq:crosspruduct2), and because t·dt = 0 (unit t; the shifted
  pseudo-inverse maps into t's complement) the depth derivatives are scalars times
  x_j·dt and u·dt;
* the sign of t enters only through ‖θ‖ t, so it is carried as a per-match sign of ‖θ‖;
* the Jacobian is needed per edge only through JᵀJ and Jᵀr; an edge whose LM step will
  end it if accepted is evaluated without it (trrm.py);
* at ~16k matches per group a numpy call costs about as much in interpreter overhead as in
  arithmetic, so the pass makes few calls: 3-vectors are (3, n) blocks, temporaries are rows
  of one scratch block (out=), the closed-form eigenproblems of several groups are solved in
  one call (_lean_head, then _head_eigen, then _lean_group), and a group whose edges share a
  mode is one call on its contiguous slice. Every rewrite keeps the order of the
  floating-point operations, so results are bit-identical to the per-component expressions
  written in the comments.

The λ_min(Pˢ) phase needs no per-match work per iteration at all (kernels/moments.py).
"""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry.kernels.match_table import INV_NXI, NXI2, NXJ2, XI, XJ, XJH, MatchTable
from rotonly_cli.geometry.kernels.soa import pinv_shifted


def smallest_eigenpair_lean(p00, p01, p02, p11, p12, p22, rel_tol: float = 1e-8):
    """pairwise.smallest_eigenpair on the six entries of symmetric 3x3 matrices: the same
    Cardano root (eq:minlambda), eq:anaTset vector with the longest ξ, two Rayleigh passes
    and the eigh fallback near a double root, in component arithmetic (few numpy calls for
    the small edge groups of one pass)."""
    mean = (p00 + p11 + p22) * (1.0 / 3.0)
    b00, b11, b22 = p00 - mean, p11 - mean, p22 - mean
    o2 = p01 * p01 + p02 * p02 + p12 * p12
    s2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * o2) * (1.0 / 6.0)
    s = np.sqrt(s2)
    inv_s = 1.0 / np.where(s > 0, s, 1.0)
    det = b00 * (b11 * b22 - p12 * p12) - p01 * (p01 * b22 - p12 * p02) + p02 * (p01 * p12 - b11 * p02)
    half_det = 0.5 * det * inv_s * inv_s * inv_s
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) * (1.0 / 3.0)
    lam = mean + 2.0 * s * np.cos(phi + 2.0 * np.pi / 3.0)
    fro2 = p00 * p00 + p11 * p11 + p22 * p22 + 2.0 * o2
    thresh = (rel_tol ** 2) * fro2 * fro2
    for _ in range(2):
        a00, a11, a22 = p00 - lam, p11 - lam, p22 - lam
        # ξ = rows (0,1), (0,2), (1,2) of P - λI crossed
        x0 = (p01 * p12 - p02 * a11, p02 * p01 - a00 * p12, a00 * a11 - p01 * p01)
        x1 = (p01 * a22 - p02 * p12, p02 * p02 - a00 * a22, a00 * p12 - p01 * p02)
        x2 = (a11 * a22 - p12 * p12, p12 * p02 - p01 * a22, p01 * p12 - a11 * p02)
        n0 = x0[0] * x0[0] + x0[1] * x0[1] + x0[2] * x0[2]
        n1 = x1[0] * x1[0] + x1[1] * x1[1] + x1[2] * x1[2]
        n2 = x2[0] * x2[0] + x2[1] * x2[1] + x2[2] * x2[2]
        # argmax with numpy's tie rule (first maximum)
        use1 = n1 > n0
        best_n = np.where(use1, n1, n0)
        use2 = n2 > best_n
        best_n = np.where(use2, n2, best_n)
        v = [np.where(use2, x2[k], np.where(use1, x1[k], x0[k])) for k in range(3)]
        ok = best_n > thresh
        inv = np.where(ok, 1.0 / np.sqrt(np.where(ok, best_n, 1.0)), 0.0)
        v = [vk * inv for vk in v]
        rq = (p00 * v[0] * v[0] + p11 * v[1] * v[1] + p22 * v[2] * v[2]
              + 2.0 * (p01 * v[0] * v[1] + p02 * v[0] * v[2] + p12 * v[1] * v[2]))
        lam = np.where(ok, rq, lam)
    t = np.stack(v, axis=-1)
    if not np.all(ok):
        bad = ~ok
        P = np.stack([np.stack([p00, p01, p02], -1), np.stack([p01, p11, p12], -1),
                      np.stack([p02, p12, p22], -1)], -2)[bad]
        w, V = np.linalg.eigh(P)
        lam[bad] = w[:, 0]
        t[bad] = V[:, :, 0]
    return lam, t


def _pinv_times(P6, lam: np.ndarray, t: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(Pˢ - λI)^+ D on the complement of t (as pinv_shifted), P6 the six entries."""
    E = len(lam)
    P = np.empty((E, 3, 3))
    P[:, 0, 0], P[:, 0, 1], P[:, 0, 2] = P6[0], P6[1], P6[2]
    P[:, 1, 0], P[:, 1, 1], P[:, 1, 2] = P6[1], P6[3], P6[4]
    P[:, 2, 0], P[:, 2, 1], P[:, 2, 2] = P6[2], P6[4], P6[5]
    return pinv_shifted(P, lam, t) @ D


COST, GRADIENT, NORMAL = 0, 1, 2  #: what _lean_group computes: cost; + Jᵀr; + JᵀJ and Jᵀr


#: edge groups whose Pˢ eigenproblems are solved in one call (the closed form is ~200 numpy
#: calls whatever the number of edges); their heads stay alive meanwhile, so more groups
#: than this fall out of the cache before their second use
EIGEN_BATCH_GROUPS = 4


def _lean_head(R: np.ndarray, cnt: np.ndarray, starts: np.ndarray, d: np.ndarray, w: np.ndarray | None,
               unit_theta: bool, plain_ps: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """First part of a pass: ``head`` (13, n) = u = R x_i (3), θ = u × x_j (3), ‖θ‖², pw θ (3)
    (rows 7-9 unused when pw is None), 3 scratch rows; the Pˢ weights ``pw`` and the per-edge
    Pˢ sums (6, E) (12 with ``plain_ps`` and weights: the unweighted sums follow)."""
    n = d.shape[1]
    head = np.empty((13, n))
    u, th, bb, tmp3 = head[0:3], head[3:6], head[6], head[10:13]
    Rr = np.repeat(R.reshape(-1, 9).T, cnt, axis=1)  # Rr[3k + c] = R_kc per match
    xi, xj = d[XI:XI + 3], d[XJ:XJ + 3]
    np.multiply(Rr[0::3], xi[0], out=u)  # u_k = R_k0 x_i0 + R_k1 x_i1 + R_k2 x_i2
    np.multiply(Rr[1::3], xi[1], out=tmp3)
    u += tmp3
    np.multiply(Rr[2::3], xi[2], out=tmp3)
    u += tmp3
    _cross_into(th, u, xj, tmp3[0])  # θ = u × x_j
    _rowsum_into(bb, np.multiply(th, th, out=tmp3))  # ‖θ‖²
    pw = 1.0 / np.maximum(bb, 1e-300) if unit_theta else w
    wt = th if pw is None else np.multiply(th, pw, out=head[7:10])
    nsum = 12 if plain_ps and pw is not None else 6
    prods = np.empty((nsum, n))
    np.multiply(th, wt[0], out=prods[0:3])  # wt_0 θ_0, wt_0 θ_1, wt_0 θ_2, wt_1 θ_1, wt_1 θ_2, wt_2 θ_2
    np.multiply(th[1:], wt[1], out=prods[3:5])
    np.multiply(th[2], wt[2], out=prods[5])
    if nsum == 12:
        np.multiply(th, th[0], out=prods[6:9])
        np.multiply(th[1:], th[1], out=prods[9:11])
        np.multiply(th[2], th[2], out=prods[11])
    return head, pw, np.add.reduceat(prods, starts, axis=1)


def _head_eigen(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """λ_min and null vector of the Pˢ sums (6 or 12 rows, edges along axis 1) and the null
    vector of the unweighted Pˢ (the same one when there are 6 rows)."""
    lam, t = smallest_eigenpair_lean(*sums[:6])
    t_plain = t if sums.shape[0] == 6 else smallest_eigenpair_lean(*sums[6:])[1]
    return lam, t, t_plain


def _lean_group(R: np.ndarray, cnt: np.ndarray, starts: np.ndarray, d: np.ndarray, w: np.ndarray | None,
                mode: int, unit_theta: bool, out: dict, rows: np.ndarray | slice, sq_out: np.ndarray | None,
                plain_ps: bool, pre: tuple | None = None) -> None:
    """TRRM terms of one edge group (edges ``rows`` of the outputs), one pass.

    Pˢ weights: 1/‖θ‖² with ``unit_theta`` (each match one vote), else ``w`` (or 1).
    Residual weights: ``w`` (or 1) times validity. ``sq_out`` receives the per-match
    validity-masked ‖r‖² (without ``w``), the input of the IRLS weights. ``pre``: the
    group's (_lean_head, _head_eigen) results when the caller batched the eigenproblems.

    3-vectors are (3, n) blocks of one scratch array, so a vector operation is one numpy call
    (a third of the calls of per-component arrays, no allocation); a dot product is a product
    block summed over its rows, which numpy adds row after row: the same operation order, and
    so the same bits, as the per-component expressions in the comments."""
    if pre is None:
        head, pw, sums = _lean_head(R, cnt, starts, d, w, unit_theta, plain_ps)
        eig = _head_eigen(sums)
    else:
        (head, pw, sums), eig = pre
    lam, t, t_plain = eig
    n = d.shape[1]
    work = np.empty((45, n))
    u, th, bb = head[0:3], head[3:6], head[6]
    wt = th if pw is None else head[7:10]
    tm, tmp3 = work[0:3], work[3:6]
    sj, si, r = work[6:9], work[9:12], work[12:18]  # r: r_i (3), r_j (3)
    hj, hi, uh = work[18:21], work[21:24], work[24:27]
    ux, xt, ut, aj, ai, b, bs, nsj, nsi, isj, isi, tmp = work[27:39]
    xj = d[XJ:XJ + 3]
    u0, u1, u2 = u
    xj0, xj1, xj2 = xj
    th0, th1, th2 = th
    P6 = sums[:6]
    if plain_ps:
        out["ps"][rows] = sums[-6:].T
    ni2, nj2 = d[NXI2], d[NXJ2]
    _rowsum_into(ux, np.multiply(u, xj, out=tmp3))

    def chirality(t: np.ndarray, tm: np.ndarray, xt: np.ndarray, ut: np.ndarray) -> np.ndarray:
        """t per match, x_j·t, u·t (into ``tm``, ``xt``, ``ut``) and the chirality sign per edge
        (pairwise.chirality_sign): the depths in views i and j from the dot identities."""
        tm[:] = np.repeat(t.T, cnt, axis=1)
        _rowsum_into(xt, np.multiply(xj, tm, out=tmp3))
        _rowsum_into(ut, np.multiply(u, tm, out=tmp3))
        depth_i = ux * xt - nj2 * ut
        depth_j = ni2 * xt - ux * ut
        # +1 in front of both cameras, -1 behind both, else 0 (NaN compares false either way)
        both = (np.minimum(depth_i, depth_j) > 0).view(np.int8) - (np.maximum(depth_i, depth_j) < 0).view(np.int8)
        vote = np.add.reduceat(both, starts, dtype=np.int64)
        return np.where(vote < 0, -1.0, 1.0)

    if plain_ps:  # t of the plain Pˢ with its chirality sign (= pairwise.translation_directions)
        out["t_plain"][rows] = t_plain * chirality(t_plain, tm, xt, ut)[:, None]
    sign = chirality(t, tm, xt, ut)
    t0, t1, t2 = tm
    out["t"][rows] = t * sign[:, None]
    sg = np.repeat(sign, cnt)
    np.multiply(xt, xt, out=aj)  # ‖x_j × t‖ = sqrt(‖x_j‖² - (x_j·t)²)
    np.subtract(nj2, aj, out=aj)
    np.maximum(aj, 0.0, out=aj)
    np.sqrt(aj, out=aj)
    np.multiply(ut, ut, out=ai)  # ‖u × t‖
    np.subtract(ni2, ai, out=ai)
    np.maximum(ai, 0.0, out=ai)
    np.sqrt(ai, out=ai)
    np.sqrt(bb, out=b)
    np.multiply(b, sg, out=bs)  # ‖θ‖ with the sign of t
    bt = np.multiply(tm, bs, out=tmp3)
    np.multiply(u, aj, out=sj)  # Y^j = a_j u + bs t (eq:PA1)
    sj += bt
    np.multiply(xj, ai, out=si)  # R Y^i = a_i x_j - bs t
    si -= bt
    _rowsum_into(nsj, np.multiply(sj, sj, out=tmp3))
    np.sqrt(nsj, out=nsj)
    _rowsum_into(nsi, np.multiply(si, si, out=tmp3))
    np.sqrt(nsi, out=nsi)
    valid = (nsj > 1e-14) & (nsi > 1e-14)  # a match on the baseline has no prediction
    np.maximum(nsj, 1e-14, out=isj)
    np.divide(1.0, isj, out=isj)
    np.maximum(nsi, 1e-14, out=isi)
    np.divide(1.0, isi, out=isi)
    np.multiply(sj, isj, out=hj)
    np.multiply(si, isi, out=hi)
    inv_ni = d[INV_NXI]
    np.multiply(u, inv_ni, out=uh)
    np.subtract(uh, hi, out=r[0:3])
    np.subtract(d[XJH:XJH + 3], hj, out=r[3:6])
    sq = _rowsum_into(np.empty(n) if sq_out is None else sq_out, np.multiply(r, r, out=work[39:45]))
    sq *= valid
    hj0, hj1, hj2 = hj
    hi0, hi1, hi2 = hi
    uh0, uh1, uh2 = uh
    ri0, ri1, ri2, rj0, rj1, rj2 = r
    rw = valid if w is None else w * valid  # residual weight
    if mode == COST:
        out["cost"][rows] = np.add.reduceat(sq if w is None else w * sq, starts)
        return
    # dt/dδ = -(Pˢ - λI)^+ (dPˢ t)/dδ, dPˢ t = Σ pw [(θ·t) A + θ (Aᵀt)ᵀ], A = u x_jᵀ - (u·x_j) I
    e = _rowsum_into(np.empty(n), np.multiply(th, tm, out=tmp3))
    pe = e if pw is None else pw * e
    pu = np.multiply(u, pe)
    pux = pe * ux
    At = np.multiply(xj, ut)  # Aᵀt = x_j (u·t) - (u·x_j) t
    np.multiply(tm, ux, out=tmp3)
    At -= tmp3
    acc = np.empty((10, n))
    for k in range(3):  # acc[3k + c] = pu_k x_j,c + wt_k (Aᵀt)_c - [k = c] pux
        np.multiply(xj, pu[k], out=acc[3 * k:3 * k + 3])
        np.multiply(At, wt[k], out=tmp3)
        acc[3 * k:3 * k + 3] += tmp3
        acc[4 * k] -= pux
    dPt = np.add.reduceat(acc[:9], starts, axis=1).T.reshape(-1, 3, 3)
    T = -_pinv_times(P6, lam, t, dPt)  # unsigned t; the sign rides on bs and kb
    if mode == GRADIENT:
        _adjoint_gradient(locals(), acc, out, rows)
        return
    _normal_equations(locals(), acc, out, rows)


def _rowsum_into(dst: np.ndarray, block: np.ndarray) -> np.ndarray:
    """dst = block[0] + block[1] + ... (numpy reduces axis 0 of a C-contiguous block row after
    row, so the order is that of the written-out sum)."""
    return np.add.reduce(block, axis=0, out=dst)


def _cross_into(dst: np.ndarray, a, b, tmp: np.ndarray) -> np.ndarray:
    """dst = a × b per match (rows of (3, n) blocks), as a_1 b_2 - a_2 b_1, ..."""
    for k, (p, q) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(a[p], b[q], out=dst[k])
        np.multiply(a[q], b[p], out=tmp)
        dst[k] -= tmp
    return dst


def _dot3_into(dst: np.ndarray, a, b, tmp: np.ndarray) -> np.ndarray:
    """dst = a[0] b[0] + a[1] b[1] + a[2] b[2] (left to right, as the expression), no allocation."""
    np.multiply(a[0], b[0], out=dst)
    np.multiply(a[1], b[1], out=tmp)
    dst += tmp
    np.multiply(a[2], b[2], out=tmp)
    dst += tmp
    return dst


#: matches per block of the Jacobian stage of a NORMAL pass (its ~60 live rows are one scratch
#: block reused by every block): smaller blocks pay numpy call overhead, larger ones
#: overflow the cache
NORMAL_BLOCK = 1 << 14
_NORMAL_INPUTS = ("u0", "u1", "u2", "xj0", "xj1", "xj2", "t0", "t1", "t2", "th0", "th1", "th2", "hj0", "hj1", "hj2",
                  "hi0", "hi1", "hi2", "uh0", "uh1", "uh2", "ri0", "ri1", "ri2", "rj0", "rj1", "rj2",
                  "aj", "ai", "b", "bs", "sg", "xt", "ut", "ux", "isj", "isi", "rw", "sq")


def _normal_equations(v: dict, acc: np.ndarray, out: dict, rows: np.ndarray) -> None:
    """JᵀJ, Jᵀr and the cost of one edge group from the forward pass of _lean_group (its locals
    ``v``): the three forward-mode Jacobian columns (6 rows each), then the per-edge sums.

    The per-match work runs in blocks of NORMAL_BLOCK matches (edges may straddle blocks: the
    per-match products land in ``acc`` and are summed per edge at the end), every temporary
    written with ``out=`` into one scratch block reused by all blocks. The order of the
    floating-point operations is that of the plain expressions in the comments (same bits)."""
    n = len(v["u0"])
    Tm = np.repeat(v["T"].reshape(-1, 9).T, v["cnt"], axis=1)  # Tm[3k + c] = dt_k / dδ_c
    block = min(n, NORMAL_BLOCK)
    work = np.empty((44, block))
    inputs = {name: v[name] for name in _NORMAL_INPUTS}
    if v["rw"].dtype != float:
        inputs["rw"] = v["rw"].astype(float)
    for m0 in range(0, n, block):
        m1 = min(n, m0 + block)
        blk = {name: x[m0:m1] for name, x in inputs.items()}
        _normal_block(blk, Tm[:, m0:m1], acc[:, m0:m1], work[:, :m1 - m0])
    sums = np.add.reduceat(acc, v["starts"], axis=1)
    out["cost"][rows] = sums[9]
    JtJ = out["JtJ"]
    JtJ[rows, 0, 0], JtJ[rows, 1, 1], JtJ[rows, 2, 2] = sums[0], sums[3], sums[5]
    JtJ[rows, 0, 1] = JtJ[rows, 1, 0] = sums[1]
    JtJ[rows, 0, 2] = JtJ[rows, 2, 0] = sums[2]
    JtJ[rows, 1, 2] = JtJ[rows, 2, 1] = sums[4]
    out["Jtr"][rows] = sums[6:9].T


#: du = e_c × u has two non-zero entries: (component k, sign, index of u) for each c
_DU_TERMS = (((1, -1, 2), (2, 1, 1)), ((0, 1, 2), (2, -1, 0)), ((0, -1, 1), (1, 1, 0)))
_DOT_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _normal_block(v: dict, Tm: np.ndarray, acc: np.ndarray, work: np.ndarray) -> None:
    """Per-match products of one block: acc[0:6] = w J_aᵀJ_b (upper triangle), acc[6:9] = w J_aᵀr,
    acc[9] = w ‖r‖²; ``work`` (44, block) scratch."""
    u, xj, t = (v["u0"], v["u1"], v["u2"]), (v["xj0"], v["xj1"], v["xj2"]), (v["t0"], v["t1"], v["t2"])
    th, uh = (v["th0"], v["th1"], v["th2"]), (v["uh0"], v["uh1"], v["uh2"])
    hj, hi = (v["hj0"], v["hj1"], v["hj2"]), (v["hi0"], v["hi1"], v["hi2"])
    bs, isj, isi, rw = v["bs"], v["isj"], v["isi"], v["rw"]
    J = work[:18].reshape(3, 6, -1)  # J[c] = dr/dδ_c: rows r_i (3), r_j (3)
    ka_j, ka_i, kb, tmp, da_j, da_i, db, pj, pi = work[18:27]
    q, dj, di, uxt, au = work[27:30], work[30:33], work[33:36], work[36:39], work[39:42]
    u0, u1, u2 = u
    t0, t1, t2 = t
    # ka_j = -x_j·t / a_j (da_j = ka_j (x_j·dt)), ka_i = -u·t / a_i (da_i = ka_i ((u × t)·δ + u·dt)),
    # kb = -(u·x_j) sg / ‖θ‖ (d(±‖θ‖) = kb θ·δ); zero where the norm is zero
    for k_out, num, den in ((ka_j, v["xt"], v["aj"]), (ka_i, v["ut"], v["ai"]), (kb, v["ux"], v["b"])):
        np.maximum(den, 1e-300, out=tmp)
        np.greater(den, 0, out=k_out)
        k_out /= tmp
        np.negative(num, out=tmp)
        k_out *= tmp  # (-num) * inv
    kb *= v["sg"]
    for k, (a0, b0, a1, b1) in enumerate(((u1, t2, u2, t1), (u2, t0, u0, t2), (u0, t1, u1, t0))):
        np.multiply(a0, b0, out=uxt[k])  # u × t
        np.multiply(a1, b1, out=tmp)
        uxt[k] -= tmp
        np.multiply(v["aj"], u[k], out=au[k])
    for c in range(3):
        Tc = (Tm[c], Tm[3 + c], Tm[6 + c])
        _dot3_into(da_j, xj, Tc, tmp)  # da_j = ka_j (x_j·T_c)
        da_j *= ka_j
        np.multiply(u0, Tc[0], out=tmp)  # da_i = ka_i ((u × t)_c + u·T_c)
        np.add(uxt[c], tmp, out=da_i)
        np.multiply(u1, Tc[1], out=tmp)
        da_i += tmp
        np.multiply(u2, Tc[2], out=tmp)
        da_i += tmp
        da_i *= ka_i
        np.multiply(kb, th[c], out=db)
        for k in range(3):
            np.multiply(db, t[k], out=q[k])  # q = db t + bs T_c
            np.multiply(bs, Tc[k], out=tmp)
            q[k] += tmp
            np.multiply(da_j, u[k], out=dj[k])  # ds_j = (da_j u + a_j du) + q
            np.multiply(da_i, xj[k], out=di[k])  # ds_i = da_i x_j - q
            di[k] -= q[k]
        for k, sign, m in _DU_TERMS[c]:
            if sign > 0:
                dj[k] += au[m]
            else:
                dj[k] -= au[m]
        for k in range(3):
            dj[k] += q[k]
        _dot3_into(pj, hj, dj, tmp)  # ŝ_j·ds_j
        _dot3_into(pi, hi, di, tmp)
        for k in range(3):
            row = J[c, 3 + k]  # (ŝ_j (ŝ_j·ds_j) - ds_j) / ‖s_j‖
            np.multiply(hj[k], pj, out=row)
            row -= dj[k]
            row *= isj
            row = J[c, k]  # (ŝ_i (ŝ_i·ds_i) - ds_i) / ‖s_i‖ + du/‖u‖, du/‖u‖ = e_c × û
            np.multiply(hi[k], pi, out=row)
            row -= di[k]
            row *= isi
        for k, sign, m in _DU_TERMS[c]:
            if sign > 0:
                J[c, k] += uh[m]
            else:
                J[c, k] -= uh[m]
    r = (v["ri0"], v["ri1"], v["ri2"], v["rj0"], v["rj1"], v["rj2"])
    # w (a_0 b_0 + ... + a_5 b_5), left to right
    for k, (a, b) in enumerate([(J[p], J[q_]) for p, q_ in _DOT_PAIRS] + [(J[c], r) for c in range(3)]):
        dst = acc[k]
        np.multiply(a[0], b[0], out=dst)
        for i in range(1, 6):
            np.multiply(a[i], b[i], out=tmp)
            dst += tmp
        dst *= rw
    np.multiply(rw, v["sq"], out=acc[9])


def _adjoint_gradient(v: dict, acc: np.ndarray, out: dict, rows: np.ndarray) -> None:
    """Jᵀr = ½ ∇_δ Σ w ‖r‖² by reverse mode through the forward pass of _lean_group (its
    locals ``v``): about a third of the work of the three forward-mode Jacobian columns.

    Adjoints (x̄ = ∂f/∂x, f = ½ Σ w ‖r‖²): ŝ = s/‖s‖ gives s̄ = -(w/‖s‖)(r - ŝ(ŝ·r)); then
    through s_j = a_j u + b_s t, s_i = a_i x_j - b_s t, a_j = ‖x_j × t‖, a_i = ‖u × t‖,
    b = ‖θ‖ (x_j × θ̄ = (b̄/b)(‖x_j‖² u - (u·x_j) x_j)); finally du = δ × u gives u × ū,
    and dt = T δ gives Tᵀ Σ t̄."""
    u0, u1, u2, xj0, xj1, xj2 = v["u0"], v["u1"], v["u2"], v["xj0"], v["xj1"], v["xj2"]
    t0, t1, t2 = v["t0"], v["t1"], v["t2"]
    hj0, hj1, hj2, hi0, hi1, hi2 = v["hj0"], v["hj1"], v["hj2"], v["hi0"], v["hi1"], v["hi2"]
    rj0, rj1, rj2, ri0, ri1, ri2 = v["rj0"], v["rj1"], v["rj2"], v["ri0"], v["ri1"], v["ri2"]
    rw, aj, ai, b, bs, sg = v["rw"], v["aj"], v["ai"], v["b"], v["bs"], v["sg"]
    xt, ut, ux, nj2 = v["xt"], v["ut"], v["ux"], v["nj2"]
    kj = -(rw * v["isj"])
    alpha = hj0 * rj0 + hj1 * rj1 + hj2 * rj2
    sjb = ((rj0 - hj0 * alpha) * kj, (rj1 - hj1 * alpha) * kj, (rj2 - hj2 * alpha) * kj)
    ki = -(rw * v["isi"])
    alpha = hi0 * ri0 + hi1 * ri1 + hi2 * ri2
    sib = ((ri0 - hi0 * alpha) * ki, (ri1 - hi1 * alpha) * ki, (ri2 - hi2 * alpha) * ki)
    ajb = u0 * sjb[0] + u1 * sjb[1] + u2 * sjb[2]
    aib = xj0 * sib[0] + xj1 * sib[1] + xj2 * sib[2]
    dsb = (sjb[0] - sib[0], sjb[1] - sib[1], sjb[2] - sib[2])
    bsb = t0 * dsb[0] + t1 * dsb[1] + t2 * dsb[2]
    xtb = ajb * (-xt * ((aj > 0) / np.maximum(aj, 1e-300)))  # a_j² = ‖x_j‖² - (x_j·t)²
    utb = aib * (-ut * ((ai > 0) / np.maximum(ai, 1e-300)))  # a_i² = ‖u‖² - (u·t)²
    k_theta = bsb * sg * ((b > 0) / np.maximum(b, 1e-300))
    c_u = k_theta * nj2
    c_x = k_theta * ux
    c_r = rw * v["inv_ni"]
    ub = [c_r * r + aj * sb + c_u * uk - c_x * xk + utb * tk
          for r, sb, uk, xk, tk in ((ri0, sjb[0], u0, xj0, t0), (ri1, sjb[1], u1, xj1, t1), (ri2, sjb[2], u2, xj2, t2))]
    # per-edge sums: u × ū (direct part) and t̄ = b_s (s̄_j - s̄_i) + (x_j·t)‾ x_j + (u·t)‾ u
    np.multiply(u1, ub[2], out=acc[0]); acc[0] -= u2 * ub[1]  # noqa: E702
    np.multiply(u2, ub[0], out=acc[1]); acc[1] -= u0 * ub[2]  # noqa: E702
    np.multiply(u0, ub[1], out=acc[2]); acc[2] -= u1 * ub[0]  # noqa: E702
    for k, (dk, xk, uk) in enumerate(((dsb[0], xj0, u0), (dsb[1], xj1, u1), (dsb[2], xj2, u2))):
        np.multiply(bs, dk, out=acc[3 + k])
        acc[3 + k] += xtb * xk
        acc[3 + k] += utb * uk
    np.multiply(rw, v["sq"], out=acc[6])
    sums = np.add.reduceat(acc[:7], v["starts"], axis=1)
    out["cost"][rows] = sums[6]
    out["Jtr"][rows] = sums[0:3].T + np.einsum("eac,ea->ec", v["T"], sums[3:6].T)


def trrm_evaluate(R: np.ndarray, table: MatchTable, jacobian: np.ndarray | bool = False,
                  evaluate: np.ndarray | None = None, unit_theta: bool = False,
                  sq_out: np.ndarray | None = None, plain_ps: bool = False,
                  gradient: np.ndarray | bool = False) -> dict:
    """Per-edge TRRM cost Σ w ‖r‖² (eq:ROMerr), signed t and, for the edges where
    ``jacobian`` is true, JᵀJ and Jᵀr of the exact Jacobian (left perturbation); where
    only ``gradient`` is true, Jᵀr alone (reverse mode, JᵀJ left zero).

    ``evaluate`` (E,) bool: the edges to evaluate (default all; ``jacobian`` implies it).
    ``sq_out`` (M,): per-match ‖r‖² (validity-masked, without weights) of evaluated edges.
    ``plain_ps``: also return the unweighted Pˢ (E, 3, 3) (identification eigenvalues) and
    its null vector with the chirality sign, ``t_plain`` (= pairwise.translation_directions).
    Per-edge results do not depend on which other edges are evaluated with them.
    """
    E = table.num_edges
    jac = np.broadcast_to(np.asarray(jacobian, dtype=bool), (E,))
    grad = np.broadcast_to(np.asarray(gradient, dtype=bool), (E,)) & ~jac
    ev = np.ones(E, dtype=bool) if evaluate is None else np.asarray(evaluate, dtype=bool) | jac | grad
    mode = np.where(jac, NORMAL, np.where(grad, GRADIENT, COST))
    out = {"cost": np.zeros(E), "t": np.zeros((E, 3))}
    if jac.any() or grad.any():
        out["JtJ"] = np.zeros((E, 3, 3))
        out["Jtr"] = np.zeros((E, 3))
    if plain_ps:
        out["ps"] = np.zeros((E, 6))
        out["t_plain"] = np.zeros((E, 3))
    data, w_all = table.data, table.weights
    # per group: one task on the contiguous slice when all its edges share a mode (the common
    # case), else one task per mode on gathered matches; mode -1: not evaluated
    code = np.where(ev, mode, -1)
    group_lo, group_hi = table.group_code_range(code)
    tasks = []  # (R, cnt, starts, d, w, mode, rows, sq, idx): idx = where to scatter a gathered sq
    for g, (e0, e1, m0, m1, cnt, starts) in enumerate(table.group_slices()):
        lo, hi = group_lo[g], group_hi[g]
        if hi < 0:
            continue
        whole = (R[e0:e1], cnt, starts, data[:, m0:m1], None if w_all is None else w_all[m0:m1])
        sq_view = None if sq_out is None else sq_out[m0:m1]
        modes = (NORMAL, GRADIENT, COST)
        if lo >= 0 and np.count_nonzero(code[e0:e1] == COST) * 2 >= e1 - e0:
            # mostly COST (an LM iteration where most edges test their last candidate): COST on
            # the whole slice without a gather, then the other modes on their edges, which
            # overwrite the same cost, t and ‖r‖² (the forward pass is shared) with their own
            tasks.append((*whole, COST, slice(e0, e1), sq_view, None))
            if lo == hi:
                continue
            modes = (NORMAL, GRADIENT)
        elif lo == hi:
            tasks.append((*whole, int(lo), slice(e0, e1), sq_view, None))
            continue
        for group_mode in modes:
            sel = np.flatnonzero(code[e0:e1] == group_mode)
            if sel.size == 0:
                continue
            cnt_sel = cnt[sel]
            starts_sel = np.concatenate([[0], np.cumsum(cnt_sel)[:-1]])
            within = np.arange(cnt_sel.sum()) - np.repeat(starts_sel, cnt_sel)
            idx = np.repeat(table.offsets[e0:e1][sel], cnt_sel) + within
            tasks.append((R[e0:e1][sel], cnt_sel, starts_sel, data[:, idx], None if w_all is None else w_all[idx],
                          group_mode, e0 + sel, None if sq_out is None else np.empty(idx.size), idx))
    for k0 in range(0, len(tasks), EIGEN_BATCH_GROUPS):
        batch_tasks = tasks[k0:k0 + EIGEN_BATCH_GROUPS]
        heads = [_lean_head(Rk, cnt, starts, d, w, unit_theta, plain_ps)
                 for Rk, cnt, starts, d, w, *_ in batch_tasks]
        sizes = np.cumsum([len(cnt) for _, cnt, *_ in batch_tasks])[:-1]
        lam, t, t_plain = _head_eigen(np.concatenate([h[2] for h in heads], axis=1))
        for task, head, lam_k, t_k, tp_k in zip(batch_tasks, heads, np.split(lam, sizes), np.split(t, sizes),
                                                np.split(t_plain, sizes)):
            Rk, cnt, starts, d, w, group_mode, rows, sq, idx = task
            _lean_group(Rk, cnt, starts, d, w, group_mode, unit_theta, out, rows, sq, plain_ps,
                        pre=(head, (lam_k, t_k, tp_k)))
            if idx is not None and sq is not None:
                sq_out[idx] = sq
    if plain_ps:
        p = out["ps"]
        out["ps"] = p[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(E, 3, 3)
    return out
