r"""Exact, batched, differentiable contact projection QP (paper Sec. 3.4.4, eqs. 14-16).

The constrained pose update projects the integrated velocity onto the set of velocities that do
not push a contact point into the floor::

    x* = argmin_x  1/2 (x - v)^T W (x - v)    s.t.   G x >= lower          (eq. 15)

with W symmetric positive definite (in jmocap: the mass matrix, so that the projection is the
kinetic-energy-closest admissible velocity), G (m, n) the contact-normal rows of the Jacobian
(eq. 16) and m small (4 or 8 contact points, at most 16).  :func:`solve_projection` receives
``Winv = W^-1`` directly, or the Cholesky factor L of W that the forward dynamics already computed
(``chol=L``: then only ``L^-1 G^T`` is formed), so nothing n x n is ever factorised here.

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

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.custom_batching import custom_vmap

from jmocap.constants import FRICTION_MU
from jmocap.numerics import safe_div, safe_norm, safe_normalize
from jmocap.physics.linalg import solve_lower, solve_upper

Array = jax.Array

#: ``method="auto"``: up to this m, enumeration only (2^m subsets are cheaper than iterating).
ENUMERATE_DIRECT_MAX_M = 4
#: ``method="auto"``: up to this m, the active-set fast path falls back to enumeration.
ENUMERATE_MAX_M = 8
#: A pivot (Schur complement) below ``PIVOT_RTOL * eps * A_kk`` means "row k depends on S".
PIVOT_RTOL = 1e3
#: Batch chunk of the enumeration (keeps its 2^m-subset working set in cache).
ENUM_CHUNK = 32
#: The active-set method adds constraint i only if ``G_i x - lower_i < -ADD_RTOL * eps * mag_i``,
#: mag_i = |lower_i| + |G_i| |v| + |A_i| |lambda| (the size of the terms summed into the slack).
#: These tolerances must stay a small multiple of eps: in float32, 1e3 eps (1.2e-4 relative) let
#: a humanoid foot-corner constraint violated by 450 eps of its magnitude go unadded, moving x by
#: up to 0.2 (the computed slacks are accurate to ~1e-6 relative there; tests/test_contact.py).
ADD_RTOL = 16.0
#: KKT violations below ``KKT_RTOL * eps`` (relative to the same magnitudes) count as satisfied.
KKT_RTOL = 64.0

__all__ = [
    "ENUMERATE_DIRECT_MAX_M",
    "ENUMERATE_MAX_M",
    "ProjectionInfo",
    "friction_cone_loss",
    "friction_pyramid_edges",
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
    kkt_violation: Array  #: () largest KKT violation relative to the magnitudes it is made of


# ----------------------------------------------------------------------------- problem data


def _check_shapes(W, G, v, lower, name):
    if G.ndim != 2 or W.ndim != 2 or v.ndim != 1 or lower.ndim != 1:
        raise ValueError(
            f"solve_projection expects one QP: {name} (n, n), G (m, n), v (n,), lower (m,); "
            f"got {name} {W.shape}, G {G.shape}, v {v.shape}, lower {lower.shape} "
            "(use jax.vmap for batches)"
        )
    m, n = G.shape
    if W.shape != (n, n) or v.shape != (n,) or lower.shape != (m,):
        raise ValueError(
            f"inconsistent shapes: {name} {W.shape}, G {G.shape}, v {v.shape}, lower {lower.shape}"
        )


def _prepare(Winv, G, v, lower, chol=None):
    """Dual data (A, b, bmag) and ``step(lam) = W^-1 G^T lam`` of one QP.

    The metric is given either as ``Winv`` or (``chol``, with ``Winv=None``) as the lower
    Cholesky factor L of W = L L^T: then ``Y = L^-1 G^T`` (one forward substitution with m
    right-hand sides), ``A = Y^T Y`` and ``W^-1 G^T lam = L^-T (Y lam)`` (one backward
    substitution, one right-hand side), so W^-1 is never formed.
    """
    metric = Winv if chol is None else chol
    dtype = jnp.result_type(float, metric, G, v, lower)
    metric, G, v, lower = (jnp.asarray(a, dtype) for a in (metric, G, v, lower))
    _check_shapes(metric, G, v, lower, "Winv" if chol is None else "chol")
    on = lower > -jnp.inf  # -inf: no constraint
    G = jnp.where(on[:, None], G, 0.0)
    lower = jnp.where(on, lower, 0.0)
    if chol is None:
        GW = G @ metric  # (m, n) = (Winv G^T)^T for symmetric Winv
        A = GW @ G.T

        def step(lam):
            return lam @ GW

    else:
        Y = solve_lower(metric, G.T)  # (n, m)
        A = Y.T @ Y

        def step(lam):
            return solve_upper(metric, Y @ lam)

    A = 0.5 * (A + A.T)
    b = lower - G @ v
    bmag = jnp.abs(lower) + jnp.abs(G) @ jnp.abs(v)  # size of the terms of b (rounding scale)
    return dtype, step, A, b, bmag, v


def _eps(x) -> float:
    return float(jnp.finfo(x.dtype).eps)


def _row_scale(A):
    """sqrt(A_ii) (the W^-1 norm of row i), 1 for zero rows; and the 'row is nonzero' mask."""
    diag = jnp.diagonal(A, axis1=-2, axis2=-1)
    nz = diag > 0
    return jnp.sqrt(jnp.where(nz, diag, 1.0)), nz


# ----------------------------------------------------------------------------- enumeration


def _subset_bits(m: int) -> np.ndarray:
    idx = np.arange(2**m)[None, :]
    return ((idx >> np.arange(m)[:, None]) & 1).astype(bool)  # (m, 2^m): row i in subset s


def _enumerate(A, b, bmag):
    """Active set of one QP by exhaustive enumeration of all 2^m subsets (sweep-operator tree)."""
    m = A.shape[0]
    eps = _eps(A)
    diag = jnp.diagonal(A)
    # tableau columns k.., b for every subset of {0..k-1} (subsets last: they vectorise)
    C = jnp.concatenate([A, b[:, None]], axis=1)[:, :, None]  # (m, m+1, 1)
    ok = jnp.ones((1,), bool)
    for k in range(m):
        piv = C[k, 0, :]
        good = piv > PIVOT_RTOL * eps * diag[k]  # Schur complement of row k on S: independent?
        piv = jnp.where(good, piv, 1.0)
        rest = C[:, 1:, :]
        rowk = rest[k] / piv[None, :]
        swept = rest - C[:, 0:1, :] * rowk[None]
        swept = swept.at[k].set(rowk)
        C = jnp.concatenate([rest, swept], axis=2)  # subset bit k: 0 | 1
        ok = jnp.concatenate([ok, ok & good])
    t = C[:, 0, :]  # (m, 2^m): lambda_i for i in S, -w_i for i not in S
    bits = jnp.asarray(_subset_bits(m))
    d, _ = _row_scale(A)
    # slack violations within the rounding of b count as none (so a v on the boundary stays v)
    t_out = jnp.where(t > ADD_RTOL * eps * bmag[:, None], t, 0.0)
    viol = jnp.where(bits, -t * d[:, None], t_out / d[:, None])
    score = jnp.maximum(jnp.max(viol, axis=0), 0.0)
    score = jnp.where(ok, score, jnp.inf)
    return bits[:, jnp.argmin(score)]


def _enumerate_batch(A, b, bmag):
    if A.shape[0] <= ENUM_CHUNK:
        return jax.vmap(_enumerate)(A, b, bmag)
    return lax.map(lambda args: _enumerate(*args), (A, b, bmag), batch_size=ENUM_CHUNK)


# ----------------------------------------------------------------------------- dual active set


class _GIState(NamedTuple):
    T: Array  # (m, m+1) tableau [A | b] swept on the active set
    act: Array  # (m,) bool active set
    p: Array  # () int32 constraint being added, -1 if none
    lam_p: Array  # () its multiplier so far
    done: Array  # () bool: no violated constraint left (or stuck)
    stuck: Array  # () bool: a violated constraint cannot be satisfied (infeasible)


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


def _gi_init(A, b):
    m = A.shape[0]
    T = jnp.concatenate([A, b[:, None]], axis=1)
    z = jnp.zeros((), A.dtype)
    f = jnp.array(False)
    return _GIState(T, jnp.zeros(m, bool), jnp.array(-1, jnp.int32), z, f, f)


def _gi_candidate(A, bmag, st):
    """Most violated inactive constraint (in W-distance) and whether it violates beyond rounding.

    Only meaningful when no constraint is being added (p = -1, so lambda = T_Sc on S).
    """
    m = A.shape[0]
    d, nz = _row_scale(A)
    c = st.T[:, m]
    w = -c  # slack of the inactive rows
    mag = bmag + jnp.abs(A) @ jnp.where(st.act, jnp.abs(c), 0.0)
    viol = jnp.where(~st.act & nz & (w < -ADD_RTOL * _eps(A) * mag), w / d, jnp.inf)
    pnew = jnp.argmin(viol)
    return pnew, viol[pnew] < 0


def _gi_steps(A, bmag, st, steps: int):
    """``steps`` Goldfarb-Idnani steps (no-ops once done) on one QP."""
    m = A.shape[0]
    eps = _eps(A)
    diag = jnp.diagonal(A)
    idx = jnp.arange(m)

    def body(_, st):
        T, act, p, lam_p, done, stuck = st
        c = T[:, m]
        has_p = p >= 0
        pnew, need = _gi_candidate(A, bmag, st)
        run = ~done & (has_p | need)
        pc = jnp.where(has_p, p, pnew)
        lp = jnp.where(has_p, lam_p, 0.0)
        ep = jax.nn.one_hot(pc, m, dtype=T.dtype)
        colp = T[:, :m] @ ep  # A_SS^-1 A_Sp on S, Schur complement column elsewhere
        Tpp = colp @ ep
        lamS = jnp.maximum(c - colp * lp, 0.0)
        wp = -(c @ ep) + Tpp * lp
        full_ok = Tpp > PIVOT_RTOL * eps * (diag @ ep)  # p independent of S
        t1 = jnp.where(full_ok, -wp / jnp.where(full_ok, Tpp, 1.0), jnp.inf)
        dec = act & (colp > 0)  # multipliers that decrease as lambda_p grows
        ratio = jnp.where(dec, lamS / jnp.where(dec, colp, 1.0), jnp.inf)
        j = jnp.argmin(ratio)
        t2 = ratio[j]
        full = t1 <= t2
        blocked = jnp.isinf(t1) & jnp.isinf(t2)  # p cannot be satisfied: infeasible
        stuck = stuck | (run & blocked)
        run = run & ~blocked
        k = jnp.where(full, pc, j)
        Tn = _sweep(T, k, jnp.where(full, 1.0, -1.0).astype(T.dtype))
        actn = jnp.where(full, act | (idx == pc), act & (idx != j))
        T = jnp.where(run, Tn, T)
        act = jnp.where(run, actn, act)
        lam_p = jnp.where(run, jnp.where(full, 0.0, lp + t2), lam_p)
        p = jnp.where(run, jnp.where(full, -1, pc), p).astype(jnp.int32)
        done = done | ~run
        return _GIState(T, act, p, lam_p, done, stuck)

    st = lax.fori_loop(0, steps, body, st)
    # a state with nothing left to add is finished even if the last step was used
    _, need = _gi_candidate(A, bmag, st)
    return st._replace(done=st.done | ((st.p < 0) & ~need))


# ----------------------------------------------------------------------------- batch selection


@functools.cache
def _selector(method: str, fast: int, extra: int, fallback: bool):
    """Active-set selector over a batch (N, m, m), (N, m) -> (N, m) bool.

    It is a ``custom_vmap`` function whose vmap rule folds the vmapped axis into N, so that
    however the caller nests ``jax.vmap``, the body sees the whole batch and its fallbacks are
    real conditionals (``lax.cond`` on "did every QP of the batch converge?") instead of being
    turned into a ``select`` that always pays for both branches.
    """

    @custom_vmap
    def select(A, b, bmag):
        if method == "enumerate":
            return _enumerate_batch(A, b, bmag)
        st = jax.vmap(_gi_init)(A, b)
        st = jax.vmap(lambda a_, m_, s_: _gi_steps(a_, m_, s_, fast))(A, bmag, st)
        ok = st.done & ~st.stuck
        if extra:
            st = lax.cond(
                jnp.all(ok),
                lambda s: s,
                lambda s: jax.vmap(lambda a_, m_, s_: _gi_steps(a_, m_, s_, extra))(A, bmag, s),
                st,
            )
            ok = st.done & ~st.stuck
        mask = st.act
        if fallback:
            mask = lax.cond(
                jnp.all(ok),
                lambda mk: mk,
                lambda mk: jnp.where(ok[:, None], mk, _enumerate_batch(A, b, bmag)),
                mask,
            )
        return mask

    @select.def_vmap
    def _rule(axis_size, in_batched, *args):
        args = [a if bat else jnp.broadcast_to(a, (axis_size, *a.shape))
                for a, bat in zip(args, in_batched, strict=True)]
        N = args[0].shape[1]
        out = select(*(a.reshape(axis_size * N, *a.shape[2:]) for a in args))
        return out.reshape(axis_size, N, -1), True

    return select


def _resolve_method(m, method, iters):
    if method not in ("auto", "enumerate", "active_set"):
        raise ValueError(f"method must be 'auto', 'enumerate' or 'active_set', got {method!r}")
    if method == "enumerate" and m > 16:
        raise ValueError(f"enumeration over 2^{m} subsets is too large; use method='active_set'")
    if method == "enumerate":
        return ("enumerate", 0, 0, False)
    if method == "active_set":
        return ("active_set", int(3 * m + 4 if iters is None else iters), 0, False)
    if m <= ENUMERATE_DIRECT_MAX_M:
        return ("enumerate", 0, 0, False)
    fast = int(m + 4 if iters is None else iters)
    if m <= ENUMERATE_MAX_M:
        return ("auto", fast, 0, True)
    return ("auto", fast, 8 * m, False)


# ----------------------------------------------------------------------------- final solve


def _solve_on_set(A, b, mask):
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
    return jnp.where(mask, jnp.stack(lam), 0.0)


def solve_projection_info(
    Winv, G, v, lower, *, method: str = "auto", iters: int | None = None, chol=None
):
    """Like :func:`solve_projection`, also returning multipliers, active set and a KKT check.

    ``method``: ``"auto"`` (default; see the module docstring), ``"enumerate"`` (always the full
    2^m enumeration) or ``"active_set"`` (Goldfarb-Idnani only, ``iters`` steps, default 3 m + 4);
    ``iters`` for ``"auto"`` is the fast-path step count (default m + 4).  ``chol``: see
    :func:`solve_projection`.
    """
    if (Winv is None) == (chol is None):
        raise ValueError("give the metric as exactly one of Winv (W^-1) or chol (L, W = L L^T)")
    dtype, step, A, b, bmag, v = _prepare(Winv, G, v, lower, chol)
    m = A.shape[0]
    if m == 0:
        z = jnp.zeros((0,), dtype)
        return ProjectionInfo(v, z, jnp.zeros((0,), bool), jnp.array(True), jnp.zeros((), dtype))
    select = _selector(*_resolve_method(m, method, iters))
    As, bs, ms = (lax.stop_gradient(a) for a in (A, b, bmag))
    mask = select(As[None], bs[None], ms[None])[0]
    lam = _solve_on_set(A, b, mask)
    x = jnp.where(jnp.any(mask), v + step(lam), v)
    # certificate (no gradient needed): primal slack relative to the magnitude of its terms,
    # multipliers (in W-distance units, lambda_i sqrt(A_ii)) relative to the largest on S
    lam_s = lax.stop_gradient(lam)
    d, _ = _row_scale(As)
    w = As @ lam_s - bs
    mag = ms + jnp.abs(As) @ jnp.abs(lam_s)
    primal = jnp.where(mask, 0.0, safe_div(-w, mag, jnp.where(w < 0, jnp.inf, 0.0)))
    lam_hat = lam_s * d
    lam_scale = jnp.max(jnp.where(mask, jnp.abs(lam_hat) + jnp.abs(bs) / d, 0.0))
    dual = jnp.where(mask, safe_div(-lam_hat, lam_scale), 0.0)
    kkt = jnp.maximum(jnp.max(jnp.maximum(primal, dual)), 0.0)
    converged = kkt <= KKT_RTOL * _eps(As)
    return ProjectionInfo(x, lam, mask, converged, kkt)


def solve_projection(
    Winv, G, v, lower, *, method: str = "auto", iters: int | None = None, chol=None
):
    """argmin_x 1/2 (x - v)^T W (x - v) s.t. G x >= lower, given Winv = W^-1.

    One QP: ``Winv`` (n, n) symmetric positive definite, ``G`` (m, n), ``v`` (n,), ``lower`` (m,)
    (``-inf`` disables a row).  Returns x (n,).  Pure, jit/vmap-able (vmap it for batches), exact to
    rounding (see the module docstring for the algorithm and its guarantee), differentiable in
    forward and reverse mode w.r.t. all four inputs; x is bitwise v when v is feasible.

    ``solve_projection(None, G, v, lower, chol=L)`` takes the metric as its lower Cholesky
    factor (W = L L^T) instead: the solver then needs only L^-1 G^T (m right-hand sides) and one
    backward substitution, never W^-1 (n right-hand sides); the dynamic cycle uses this with the
    factor of M that its forward dynamics computed anyway.
    """
    return solve_projection_info(Winv, G, v, lower, method=method, iters=iters, chol=chol).x


# ----------------------------------------------------------------------------- friction


def friction_cone_loss(force, normal, mu=FRICTION_MU):
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


def _pyramid_angles(facets: int, offset: float):
    if facets < 3:
        raise ValueError(f"a friction pyramid needs at least 3 facets, got {facets}")
    phi = offset + 2.0 * np.pi * np.arange(facets) / facets
    cs, sn = np.cos(phi), np.sin(phi)
    return np.where(np.abs(cs) < 1e-12, 0.0, cs), np.where(np.abs(sn) < 1e-12, 0.0, sn)


def friction_pyramid_edges(normal, mu=FRICTION_MU, facets: int = 4):
    """Edges E (..., facets, 3) of the friction pyramid: ``n + mu (cos phi_j t1 + sin phi_j t2)``,
    ``phi_j = 2 pi j / facets``, in the tangent basis of :func:`tangent_basis`.

    A force is admissible exactly when it is a non-negative combination ``f = E^T c, c >= 0`` of
    the edges. For ``facets = 4`` these are MuJoCo's ``pyramidal`` cone edges ``n +- mu t1``,
    ``n +- mu t2`` (jmocap's one friction model, :data:`jmocap.constants.FRICTION_CONE`).
    """
    n = safe_normalize(jnp.asarray(normal))
    t1, t2 = tangent_basis(n)
    cs, sn = _pyramid_angles(facets, 0.0)
    mu = jnp.asarray(mu, n.dtype)[..., None, None]
    return n[..., None, :] + mu * (jnp.asarray(cs, n.dtype)[:, None] * t1[..., None, :]
                                   + jnp.asarray(sn, n.dtype)[:, None] * t2[..., None, :])


def friction_pyramid_rows(normal, mu=FRICTION_MU, facets: int = 4):
    """Rows C (..., facets, 3) with the inscribed pyramid = {f : C f >= 0}.

    The facet form of :func:`friction_pyramid_edges`: facet j lies between edges j and j + 1 and
    has outward direction ``phi_j = pi / facets + 2 pi j / facets`` in the tangent plane (t1, t2)
    of :func:`tangent_basis`; its constraint is ``mu cos(pi/facets) f_n - cos(phi_j) f_t1 -
    sin(phi_j) f_t2 >= 0``. The pyramid's edges lie on the true cone |f_t| = mu f_n
    (inscribed), so every force it admits satisfies eq. 9; for ``facets = 4`` this is MuJoCo's
    pyramidal cone ``|f_t1| + |f_t2| <= mu f_n`` (f_n >= 0 is implied).
    """
    normal = jnp.asarray(normal)
    n = safe_normalize(normal)
    t1, t2 = tangent_basis(n)
    cs, sn = _pyramid_angles(facets, np.pi / facets)
    mu_eff = jnp.asarray(mu, n.dtype) * float(np.cos(np.pi / facets))
    cs = jnp.asarray(cs, n.dtype)
    sn = jnp.asarray(sn, n.dtype)
    return (
        mu_eff[..., None, None] * n[..., None, :]
        - cs[:, None] * t1[..., None, :]
        - sn[:, None] * t2[..., None, :]
    )


def project_friction_pyramid(force, normal, mu=FRICTION_MU, facets: int = 4):
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

