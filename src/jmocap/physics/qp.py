r"""Exact, batched, differentiable contact projection QP (paper Sec. 3.4.4, eqs. 14-16).

The constrained pose update projects the integrated velocity onto the set of velocities that do
not push a contact point into the floor::

    x* = argmin_x  1/2 (x - v)^T W (x - v)    s.t.   G x >= lower          (eq. 15)

with W symmetric positive definite (in jmocap: the mass matrix, so that the projection is the
kinetic-energy-closest admissible velocity), G (m, n) the contact-normal rows of the Jacobian
(eq. 16) and m small (4 or 8 contact points, at most 16).  :func:`solve_projection` receives
``Winv = W^-1`` directly (the forward dynamics already has it), so nothing n x n is ever factorised.

Dual problem
------------
With multipliers lambda >= 0 the KKT conditions are::

    W (x - v) = G^T lambda,   w := G x - lower >= 0,   lambda >= 0,   lambda_i w_i = 0,

i.e. x = v + Winv G^T lambda, and lambda solves the m-dimensional linear complementarity problem
``w = A lambda - b >= 0, lambda >= 0, lambda^T w = 0`` with ``A = G Winv G^T`` (PSD, singular when
rows of G are dependent) and ``b = lower - G v``.  The primal x* is unique (W is PD) even when
lambda is not.  All work after forming ``Winv G^T`` (n x m) and A (m x m) is m-sized.

Algorithms (both end with the same exact, differentiable solve on the identified active set S)
-------------------------------------------------------------------------------------------------
``"enumerate"`` (default for m <= 8) -- exact active-set enumeration.  Every one of the 2^m
subsets S is examined: lambda_S = A_SS^-1 b_S, lambda_rest = 0, and the subset is accepted when
it satisfies the KKT conditions (lambda_S >= 0, w_rest >= 0).  The 2^m solves share work through
a binary tree of *sweep operators* (Gauss-Jordan pivots, Goodnight 1979) on the tableau
``[A | b]``: level k pivots on index k in one child and skips it in the other, and only the columns
still needed (k+1..m-1 and b) are updated, so all 2^m solutions cost about 2^(m+1) (m+1)
multiply-adds (~4,600 for m = 8) instead of 2^m m^3/3.  A pivot (the Schur complement of row k
on the earlier members of S, in the W^-1 metric) below ``PIVOT_RTOL * eps * A_kk`` marks the
subset, and all its supersets, as singular (a dependent, duplicated or zero row) and skips it.
Among the non-singular subsets the one with the smallest scaled KKT violation
``max(max_{i in S} -lambda_i sqrt(A_ii), max_{i notin S} -w_i / sqrt(A_ii), 0)`` is chosen
(ties: the lowest subset index, so the empty set wins whenever v is feasible).

*Guarantee*: a KKT point with linearly independent active rows always exists when the QP is
feasible (Caratheodory), so the enumeration always contains an exact solution; the result is the
exact minimiser up to the rounding of one m x m SPD solve.  No iteration count is involved.

``"active_set"`` (default for 8 < m <= 16) -- the Goldfarb-Idnani dual active-set method, run in
the dual on the sweep tableau.  Starting from the unconstrained minimiser (x = v, lambda = 0, S =
{}), it repeatedly picks the most violated constraint p (scaled by sqrt(A_pp)) and raises
lambda_p, keeping the constraints in S tight; either p becomes tight (full step: p joins S, one
sweep) or a multiplier in S reaches zero first (partial step: it leaves S, one reverse sweep; p
stays the constraint being added).  A constraint whose row depends on S (zero Schur complement)
can only take partial steps.  Each step is O(m^2) on the tableau.  The dual objective increases
strictly at every full step and S always has independent rows, so the method terminates finitely
at the exact optimum; the loop has a *fixed* count ``iters`` (default ``3 m + 4``) of steps
(``lax.fori_loop``), and steps after termination are no-ops.  *Guarantee*: the returned x is the
exact minimiser whenever the method has terminated within ``iters`` steps, which is verified
afterwards from the KKT conditions and reported by :func:`solve_projection_info` as
``converged``.  Goldfarb-Idnani needs at most one step per added constraint plus one per dropped
constraint; on 20,000 random instances with m = 16 (tests/test_qp.py) the largest count observed
was well below the default.

Derivatives
-----------
The active set is chosen on ``stop_gradient`` data; x is then recomputed by ordinary,
differentiable JAX operations from the active-set formula
``x = v + Winv G_S^T A_SS^-1 (lower_S - G_S v)`` (an unrolled LDL^T elimination of the masked
matrix ``D A D + (I - D)``, whose pivots are >= ``PIVOT_RTOL * eps * A_kk`` by construction).  This
is exactly implicit differentiation of the KKT system on the identified active set, so forward and
reverse mode both work and give the exact piecewise derivative.  At a degenerate point (a
constraint tight with lambda = 0) the subset without that constraint is preferred and its one-sided
derivative is returned.  Gradients are never NaN: zero / duplicated / dependent rows are never in S,
the elimination pivots are bounded away from zero, and when no constraint is active
``x = v`` exactly (bitwise) with d x / d v = I and zero gradients for G, lower and Winv.

Inactive constraints: a row with ``lower = -inf`` is dropped (treated as a zero row with lower 0);
a zero row with ``lower <= 0`` is satisfied by every x and is never active.  ``lower`` must not be
+inf or NaN.  For an infeasible problem (e.g. a zero row with lower > 0) the least-violating
candidate is returned (finite, ``converged = False``).

Friction helpers
----------------
:func:`friction_cone_loss` is paper eq. 10 with a gradient-safe angle; :func:`project_friction_pyramid`
is the exact Euclidean projection onto the inscribed linearised friction pyramid, solved with the
same QP solver (W = I).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jmocap.numerics import safe_norm, safe_normalize

Array = jax.Array

#: Largest m solved by exhaustive enumeration under ``method="auto"``.
ENUMERATE_MAX_M = 8
#: A pivot (Schur complement) below ``PIVOT_RTOL * eps * A_kk`` means "row k depends on S".
PIVOT_RTOL = 1e3
#: Scaled KKT violations below ``KKT_RTOL * eps * scale`` count as satisfied (``converged``).
KKT_RTOL = 1e4

__all__ = [
    "ENUMERATE_MAX_M",
    "ProjectionInfo",
    "friction_cone_loss",
    "friction_pyramid_rows",
    "project_friction_pyramid",
    "solve_projection",
    "solve_projection_info",
    "tangent_basis",
]


class ProjectionInfo(NamedTuple):
    """Solution and certificate of one projection QP."""

    x: Array  #: (n,) the minimiser
    lam: Array  #: (m,) multipliers of ``G x >= lower`` (0 off the active set)
    active: Array  #: (m,) bool, the active set S used for x
    converged: Array  #: () bool, KKT conditions verified to rounding on S
    kkt_violation: Array  #: () largest scaled KKT violation, relative to the problem scale


# ----------------------------------------------------------------------------- helpers


def _prepare(Winv, G, v, lower):
    dtype = jnp.result_type(float, Winv, G, v, lower)
    Winv, G, v, lower = (jnp.asarray(a, dtype) for a in (Winv, G, v, lower))
    if G.ndim != 2 or Winv.ndim != 2 or v.ndim != 1 or lower.ndim != 1:
        raise ValueError(
            "solve_projection expects one QP: Winv (n, n), G (m, n), v (n,), lower (m,); "
            f"got Winv {Winv.shape}, G {G.shape}, v {v.shape}, lower {lower.shape} "
            "(use jax.vmap for batches)"
        )
    m, n = G.shape
    if Winv.shape != (n, n) or v.shape != (n,) or lower.shape != (m,):
        raise ValueError(
            f"inconsistent shapes: Winv {Winv.shape}, G {G.shape}, v {v.shape}, lower {lower.shape}"
        )
    on = lower > -jnp.inf  # -inf: no constraint
    G = jnp.where(on[:, None], G, 0.0)
    lower = jnp.where(on, lower, 0.0)
    WG = Winv @ G.T  # (n, m)
    A = G @ WG
    A = 0.5 * (A + A.T)
    b = lower - G @ v
    return dtype, WG, A, b, v


def _row_scale(A):
    """sqrt(A_ii) (the W^-1 norm of row i), 1 for zero rows; and the 'row is nonzero' mask."""
    diag = jnp.diagonal(A)
    nz = diag > 0
    return jnp.sqrt(jnp.where(nz, diag, 1.0)), nz


def _subset_bits(m: int) -> np.ndarray:
    idx = np.arange(2**m)[:, None]
    return ((idx >> np.arange(m)[None, :]) & 1).astype(bool)  # (2^m, m), bit i <-> row i in S


def _enumerate(A, b, eps):
    """Active set by exhaustive enumeration over all 2^m subsets (sweep-operator tree)."""
    m = A.shape[0]
    diag = jnp.diagonal(A)
    C = jnp.concatenate([A, b[:, None]], axis=1)[None]  # (1, m, m+1): columns k.., b
    ok = jnp.ones((1,), bool)
    for k in range(m):
        piv = C[:, k, 0]
        good = piv > PIVOT_RTOL * eps * diag[k]
        piv = jnp.where(good, piv, 1.0)
        rest = C[:, :, 1:]
        rowk = rest[:, k, :] / piv[:, None]
        swept = rest - C[:, :, :1] * rowk[:, None, :]
        swept = swept.at[:, k, :].set(rowk)
        C = jnp.concatenate([rest, swept], axis=0)
        ok = jnp.concatenate([ok, ok & good])
    t = C[:, :, 0]  # (2^m, m): lambda_i (i in S) or -w_i (i not in S)
    bits = jnp.asarray(_subset_bits(m))
    d, _ = _row_scale(A)
    viol = jnp.where(bits, -t * d, t / d)
    score = jnp.maximum(jnp.max(viol, axis=1), 0.0)
    score = jnp.where(ok, score, jnp.inf)
    return bits[jnp.argmin(score)]


def _sweep(T, k, sign):
    """Sweep (sign=+1) or reverse sweep (sign=-1) of tableau T (m, m+1) on a traced index k."""
    m = T.shape[0]
    er = jax.nn.one_hot(k, m, dtype=T.dtype)
    ec = jax.nn.one_hot(k, m + 1, dtype=T.dtype)
    row = er @ T  # (m+1,)
    col = T @ ec  # (m,)
    d = row @ ec
    d = jnp.where(d != 0, d, 1.0)
    is_r = er[:, None] > 0
    is_c = ec[None, :] > 0
    new = T - col[:, None] * row[None, :] / d
    new = jnp.where(is_r, sign * row[None, :] / d, new)
    new = jnp.where(is_c, sign * col[:, None] / d, new)
    return jnp.where(is_r & is_c, -1.0 / d, new)


def _active_set(A, b, eps, iters):
    """Active set by the Goldfarb-Idnani dual method, a fixed number of steps on the tableau."""
    m = A.shape[0]
    diag = jnp.diagonal(A)
    d, nz = _row_scale(A)
    scale = jnp.max(jnp.where(nz, jnp.abs(b) / d, 0.0))
    tol_add = KKT_RTOL * eps * scale
    T0 = jnp.concatenate([A, b[:, None]], axis=1)
    idx = jnp.arange(m)

    def body(_, st):
        T, act, p, lam_p, done = st
        c = T[:, m]
        has_p = p >= 0
        lp = jnp.where(has_p, lam_p, 0.0)
        # pick a new constraint to add when none is being added
        colp_old = T[:, :m] @ jax.nn.one_hot(jnp.maximum(p, 0), m, dtype=T.dtype)
        w = -c + colp_old * lp
        viol = jnp.where(~act & nz, w / d, jnp.inf)
        pnew = jnp.argmin(viol)
        need = viol[pnew] < -tol_add
        run = ~done & (has_p | need)
        pc = jnp.where(has_p, p, pnew)
        ep = jax.nn.one_hot(pc, m, dtype=T.dtype)
        colp = T[:, :m] @ ep
        Tpp = colp @ ep
        lamS = jnp.maximum(c - colp * lp, 0.0)
        wp = -(c @ ep) + Tpp * lp
        full_ok = Tpp > PIVOT_RTOL * eps * (diag @ ep)
        t1 = jnp.where(full_ok, -wp / jnp.where(full_ok, Tpp, 1.0), jnp.inf)
        dec = act & (colp > 0)
        ratio = jnp.where(dec, lamS / jnp.where(dec, colp, 1.0), jnp.inf)
        j = jnp.argmin(ratio)
        t2 = ratio[j]
        full = t1 <= t2
        stuck = jnp.isinf(t1) & jnp.isinf(t2)  # infeasible: p cannot be satisfied
        run = run & ~stuck
        k = jnp.where(full, pc, j)
        Tn = _sweep(T, k, jnp.where(full, 1.0, -1.0).astype(T.dtype))
        actn = jnp.where(full, act | (idx == pc), act & (idx != j))
        T = jnp.where(run, Tn, T)
        act = jnp.where(run, actn, act)
        lam_p = jnp.where(run, jnp.where(full, 0.0, lp + t2), lam_p)
        p = jnp.where(run, jnp.where(full, -1, pc), p).astype(jnp.int32)
        done = done | ~run
        return T, act, p, lam_p, done

    st = (T0, jnp.zeros(m, bool), jnp.array(-1, jnp.int32), jnp.zeros((), A.dtype), jnp.array(False))
    _, act, _, _, _ = lax.fori_loop(0, iters, body, st)
    return act


def _solve_on_set(A, b, mask, eps):
    """lambda with lambda_S = A_SS^-1 b_S, 0 elsewhere; unrolled LDL^T, differentiable."""
    m = A.shape[0]
    both = mask[:, None] & mask[None, :]
    M = jnp.where(both, A, jnp.eye(m, dtype=A.dtype))
    r = jnp.where(mask, b, 0.0)
    floor = jnp.finfo(A.dtype).tiny
    Aug = jnp.concatenate([M, r[:, None]], axis=1)
    rows = []
    for k in range(m):  # forward elimination, keeping the normalised pivot rows
        piv = Aug[k, k]
        piv = jnp.where(piv > floor, piv, 1.0)
        rk = Aug[k] / piv
        rows.append(rk)
        if k + 1 < m:
            lower_block = Aug[k + 1 :] - Aug[k + 1 :, k : k + 1] * rk[None, :]
            Aug = jnp.concatenate([Aug[: k + 1], lower_block], axis=0)
    lam = [None] * m
    for k in reversed(range(m)):  # back substitution
        acc = rows[k][m]
        for j in range(k + 1, m):
            acc = acc - rows[k][j] * lam[j]
        lam[k] = acc
    lam = jnp.stack(lam)
    return jnp.where(mask, lam, 0.0)


def _resolve_method(m, method, iters):
    if method == "auto":
        method = "enumerate" if m <= ENUMERATE_MAX_M else "active_set"
    if method not in ("enumerate", "active_set"):
        raise ValueError(f"method must be 'auto', 'enumerate' or 'active_set', got {method!r}")
    if method == "enumerate" and m > 16:
        raise ValueError(f"enumeration over 2^{m} subsets is too large; use method='active_set'")
    if iters is None:
        iters = 3 * m + 4
    return method, int(iters)


def solve_projection_info(Winv, G, v, lower, *, method: str = "auto", iters: int | None = None):
    """Like :func:`solve_projection`, also returning multipliers, active set and a KKT check.

    ``method``: ``"auto"`` (enumeration for m <= 8, dual active set above), ``"enumerate"`` or
    ``"active_set"``; ``iters``: fixed step count of the active-set method (default 3 m + 4).
    """
    dtype, WG, A, b, v = _prepare(Winv, G, v, lower)
    m = A.shape[0]
    eps = float(jnp.finfo(dtype).eps)
    method, iters = _resolve_method(m, method, iters)
    if m == 0:
        z = jnp.zeros((0,), dtype)
        return ProjectionInfo(v, z, jnp.zeros((0,), bool), jnp.array(True), jnp.zeros((), dtype))
    As, bs = lax.stop_gradient(A), lax.stop_gradient(b)
    if method == "enumerate":
        mask = _enumerate(As, bs, eps)
    else:
        mask = _active_set(As, bs, eps, iters)
    lam = _solve_on_set(A, b, mask, eps)
    x = jnp.where(jnp.any(mask), v + WG @ lam, v)
    # certificate (no gradient needed)
    lam_s = lax.stop_gradient(lam)
    d, nz = _row_scale(As)
    w = As @ lam_s - bs
    viol = jnp.where(mask, -lam_s * d, jnp.where(nz, -w / d, jnp.where(bs > 0, jnp.inf, 0.0)))
    scale = jnp.max(jnp.where(nz, jnp.abs(bs) / d, 0.0)) + jnp.finfo(dtype).tiny
    kkt = jnp.maximum(jnp.max(viol), 0.0) / scale
    converged = kkt <= KKT_RTOL * eps
    return ProjectionInfo(x, lam, mask, converged, kkt)


def solve_projection(Winv, G, v, lower, *, method: str = "auto", iters: int | None = None):
    """argmin_x 1/2 (x - v)^T W (x - v) s.t. G x >= lower, given Winv = W^-1.

    One QP: ``Winv`` (n, n) symmetric positive definite, ``G`` (m, n), ``v`` (n,), ``lower`` (m,)
    (``-inf`` disables a row).  Returns x (n,).  Pure, jit/vmap-able (vmap it for batches), exact to
    rounding (see the module docstring for the algorithm and its guarantee), differentiable in
    forward and reverse mode w.r.t. all four inputs; x is bitwise v when v is feasible.
    """
    return solve_projection_info(Winv, G, v, lower, method=method, iters=iters).x


# ----------------------------------------------------------------------------- friction


def friction_cone_loss(force, normal, mu=0.8):
    """Paper eq. 10: theta^2 if theta > arctan(mu) else 0, theta = angle(normal, force).

    ``force`` (..., 3) and ``normal`` (..., 3) broadcast (the normal need not be unit length).
    theta = atan2(|f_t|, f_n) in [0, pi] (so f_n < 0 is handled); zero force gives loss 0 with a
    zero gradient; never NaN.
    """
    force = jnp.asarray(force)
    n_hat = safe_normalize(jnp.asarray(normal, force.dtype))
    fn = jnp.sum(force * n_hat, axis=-1)
    ft = safe_norm(force - fn[..., None] * n_hat)
    nonzero = (ft > 0) | (fn != 0)
    theta = jnp.where(nonzero, jnp.arctan2(ft, jnp.where(nonzero, fn, 1.0)), 0.0)
    return jnp.where(theta > jnp.arctan(mu), theta * theta, 0.0)


def tangent_basis(normal):
    """Deterministic orthonormal tangents (t1, t2) of a unit normal (Duff et al. 2017).

    For the floor normal (0, 0, 1) this is (x, y).  Shapes (..., 3) -> two (..., 3).
    """
    n = safe_normalize(jnp.asarray(normal))
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    s = jnp.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (s + z)
    bb = x * y * a
    t1 = jnp.stack([1.0 + s * x * x * a, s * bb, -s * x], axis=-1)
    t2 = jnp.stack([bb, s + y * y * a, -y], axis=-1)
    return t1, t2


def friction_pyramid_rows(normal, mu=0.8, facets: int = 4):
    """Rows C (..., facets, 3) with the inscribed pyramid = {f : C f >= 0}.

    Facet j has outward direction phi_j = 2 pi j / facets in the tangent plane (t1, t2) of
    :func:`tangent_basis` and the constraint ``mu cos(pi/facets) f_n - cos(phi_j) f_t1 -
    sin(phi_j) f_t2 >= 0``.  The pyramid's edges lie on the true cone |f_t| = mu f_n
    (inscribed), so every force it admits satisfies eq. 9; for ``facets = 4`` this is
    ``|f_t1| <= mu / sqrt(2) f_n, |f_t2| <= mu / sqrt(2) f_n`` (f_n >= 0 is implied).
    """
    if facets < 3:
        raise ValueError(f"a friction pyramid needs at least 3 facets, got {facets}")
    normal = jnp.asarray(normal)
    n = safe_normalize(normal)
    t1, t2 = tangent_basis(n)
    phi = 2.0 * np.pi * np.arange(facets) / facets
    cs, sn = np.cos(phi), np.sin(phi)
    cs = np.where(np.abs(cs) < 1e-12, 0.0, cs)
    sn = np.where(np.abs(sn) < 1e-12, 0.0, sn)
    mu_eff = jnp.asarray(mu, n.dtype) * float(np.cos(np.pi / facets))
    cs = jnp.asarray(cs, n.dtype)
    sn = jnp.asarray(sn, n.dtype)
    return (
        mu_eff[..., None, None] * n[..., None, :]
        - cs[:, None] * t1[..., None, :]
        - sn[:, None] * t2[..., None, :]
    )


def project_friction_pyramid(force, normal, mu=0.8, facets: int = 4):
    """Euclidean projection of contact forces (..., 3) onto the inscribed friction pyramid.

    Exact (the small QP ``min |f' - f|^2 s.t. C f' >= 0`` solved by :func:`solve_projection`
    with W = I, by enumeration for facets <= 8), differentiable, never NaN; forces already inside
    are returned unchanged (bitwise).  See :func:`friction_pyramid_rows` for the pyramid.
    """
    force = jnp.asarray(force)
    normal = jnp.asarray(normal, force.dtype)
    shape = jnp.broadcast_shapes(force.shape, normal.shape)
    if shape[-1] != 3:
        raise ValueError(f"forces and normals must have a last axis of 3, got {shape}")
    f = jnp.broadcast_to(force, shape).reshape(-1, 3)
    C = friction_pyramid_rows(jnp.broadcast_to(normal, shape).reshape(-1, 3), mu, facets)
    eye = jnp.eye(3, dtype=f.dtype)
    zero = jnp.zeros((facets,), f.dtype)
    out = jax.vmap(lambda Ci, fi: solve_projection(eye, Ci, fi, zero))(C, f)
    return out.reshape(shape)

