"""Small dense linear algebra in pure JAX: Cholesky factor and triangular solves.

Why not ``jnp.linalg.cholesky`` / ``jax.scipy.linalg.cho_solve``: on CPU those lower to LAPACK
custom calls, and jaxlib 0.10 runs a batched call as a ``ParallelBatchMap`` on XLA's intra-op
thread pool and blocks the calling pool thread until it finishes. When two such calls run at
once (independent branches of one program, e.g. the per-sample Cholesky and solves of a vmapped
training step) on a 2-core machine, both pool threads block waiting for work that no free thread
can pick up: the program deadlocks at 0% CPU. The functions here are ordinary XLA loops, so they
cannot deadlock, batch under ``vmap`` like any other op, and need no LAPACK.

The matrices are small (nv = 47 for the humanoid): one ``fori_loop`` over columns, each step a
matrix-vector product over all rows (left-looking Cholesky-Banachiewicz, forward/backward
substitution). Derivatives are analytic (``custom_jvp``), so reverse mode stores no per-column
intermediates; the rules are the standard ones (Murray 2016 for the Cholesky factor):

    dL = L Phi(L^-1 dM L^-T),  Phi = lower triangle with the diagonal halved
    d(L^-1 B) = L^-1 (dB - dL L^-1 B)

Shapes follow NumPy: leading batch axes are allowed everywhere.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

Array = jnp.ndarray


# ---- single-matrix kernels -----------------------------------------------------------------


def _cholesky_1(M: Array) -> Array:
    n = M.shape[-1]
    idx = jnp.arange(n)

    def column(j, L):
        # columns < j of L are final, the rest zero: (L @ L[j])_i = sum_{k<j} L_ik L_jk
        v = M[:, j] - L @ L[j]
        d = jnp.sqrt(v[j])  # NaN for a matrix that is not positive definite, as LAPACK's
        col = jnp.where(idx > j, v / d, jnp.where(idx == j, d, 0.0))
        return L.at[:, j].set(col)

    return lax.fori_loop(0, n, column, jnp.zeros_like(M))


#: Up to this many right-hand sides the substitutions build X transposed (see _solve_lower_1).
FEW_RHS = 8


def _solve_lower_1(L: Array, B: Array) -> Array:
    """L X = B for lower-triangular L (n, n) and B (n, k), forward substitution.

    For few right-hand sides (k <= FEW_RHS) the solution is built transposed, X^T (k, n), so
    that each step is one (k, n) x (n,) product: with X (n, k) the batched (n,) x (n, k)
    products ran 4x slower (k = 4, batch 512); for k ~ n (inverses, the Cholesky derivative)
    the (n, k) layout is the faster one.
    """
    n, k = B.shape
    idx = jnp.arange(n)
    if k <= FEW_RHS:
        BT = B.T

        def row_t(j, XT):
            l = jnp.where(idx < j, L[j], 0.0)  # columns >= j of X^T are still zero
            return XT.at[:, j].set((BT[:, j] - XT @ l) / L[j, j])

        return lax.fori_loop(0, n, row_t, jnp.zeros_like(BT)).T

    def row(j, X):
        l = jnp.where(idx < j, L[j], 0.0)  # rows >= j of X are still zero
        return X.at[j].set((B[j] - l @ X) / L[j, j])

    return lax.fori_loop(0, n, row, jnp.zeros_like(B))


def _solve_upper_1(L: Array, B: Array) -> Array:
    """L^T X = B for lower-triangular L (n, n) and B (n, k), backward substitution (layout as
    in :func:`_solve_lower_1`)."""
    n, k = B.shape
    idx = jnp.arange(n)
    if k <= FEW_RHS:
        BT = B.T

        def row_t(i, XT):
            j = n - 1 - i
            u = jnp.where(idx > j, L[:, j], 0.0)  # row j of L^T, right of the diagonal
            return XT.at[:, j].set((BT[:, j] - XT @ u) / L[j, j])

        return lax.fori_loop(0, n, row_t, jnp.zeros_like(BT)).T

    def row(i, X):
        j = n - 1 - i
        u = jnp.where(idx > j, L[:, j], 0.0)
        return X.at[j].set((B[j] - u @ X) / L[j, j])

    return lax.fori_loop(0, n, row, jnp.zeros_like(B))


def _phi(X: Array) -> Array:
    """Lower triangle of X with the diagonal halved."""
    return jnp.tril(X, -1) + 0.5 * jnp.diag(jnp.diag(X))


# ---- differentiable single-matrix functions -------------------------------------------------


@jax.custom_jvp
def _cholesky(M: Array) -> Array:
    return _cholesky_1(M)


@_cholesky.defjvp
def _cholesky_jvp(primals, tangents):
    (M,), (dM,) = primals, tangents
    L = _cholesky(M)
    dM = 0.5 * (dM + dM.T)  # only the symmetric part of a perturbation is meaningful
    X = _solve_lower(L, _solve_lower(L, dM).T)  # L^-1 dM L^-T
    return L, L @ _phi(X)


@jax.custom_jvp
def _solve_lower(L: Array, B: Array) -> Array:
    return _solve_lower_1(L, B)


@_solve_lower.defjvp
def _solve_lower_jvp(primals, tangents):
    (L, B), (dL, dB) = primals, tangents
    X = _solve_lower(L, B)
    return X, _solve_lower(L, dB - jnp.tril(dL) @ X)


@jax.custom_jvp
def _solve_upper(L: Array, B: Array) -> Array:
    return _solve_upper_1(L, B)


@_solve_upper.defjvp
def _solve_upper_jvp(primals, tangents):
    (L, B), (dL, dB) = primals, tangents
    X = _solve_upper(L, B)
    return X, _solve_upper(L, dB - jnp.tril(dL).T @ X)


# ---- public, batched ---------------------------------------------------------------------------


@functools.partial(jnp.vectorize, signature="(n,n)->(n,n)")
def cholesky(M: Array) -> Array:
    """Lower Cholesky factor of a symmetric positive definite matrix (..., n, n)."""
    return _cholesky(M)


def _with_matrix_rhs(fn, L: Array, b: Array) -> Array:
    """Apply a (n, n), (n, k) kernel to b of shape (..., n) or (..., n, k), batched over L's
    leading axes as well (b's trailing axes decide vector vs matrix, as in SciPy)."""
    if b.ndim == L.ndim - 1:  # vector right-hand side(s)
        return jnp.vectorize(lambda l, v: fn(l, v[:, None])[:, 0], signature="(n,n),(n)->(n)")(L, b)
    return jnp.vectorize(fn, signature="(n,n),(n,k)->(n,k)")(L, b)


def solve_lower(L: Array, b: Array) -> Array:
    """x with L x = b, L lower triangular (..., n, n); b (..., n) or (..., n, k)."""
    return _with_matrix_rhs(_solve_lower, L, b)


def solve_upper(L: Array, b: Array) -> Array:
    """x with L^T x = b, L lower triangular (..., n, n); b (..., n) or (..., n, k)."""
    return _with_matrix_rhs(_solve_upper, L, b)


def cho_solve(L: Array, b: Array) -> Array:
    """x with (L L^T) x = b given the lower Cholesky factor L; b (..., n) or (..., n, k)."""
    return solve_upper(L, solve_lower(L, b))


def solve_spd3(A: Array, b: Array) -> Array:
    """x with A x = b for symmetric positive definite 3x3 A (..., 3, 3), b (..., 3), in closed
    form (the adjugate), so that no LAPACK call is made for a 3x3 system."""
    a, bb, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    adj = jnp.stack(
        [
            jnp.stack([d * f - e * e, c * e - bb * f, bb * e - c * d], -1),
            jnp.stack([c * e - bb * f, a * f - c * c, bb * c - a * e], -1),
            jnp.stack([bb * e - c * d, bb * c - a * e, a * d - bb * bb], -1),
        ],
        -2,
    )
    det = a * adj[..., 0, 0] + bb * adj[..., 1, 0] + c * adj[..., 2, 0]
    return jnp.einsum("...ij,...j->...i", adj, b) / det[..., None]


def det3(A: Array) -> Array:
    """Determinant of (..., 3, 3) matrices in closed form (no LAPACK LU)."""
    return jnp.sum(A[..., 0, :] * jnp.cross(A[..., 1, :], A[..., 2, :]), -1)


__all__ = ["cho_solve", "cholesky", "det3", "solve_lower", "solve_spd3", "solve_upper"]


# ---- symmetric block-banded systems (a trajectory's normal equations) ------------------------


def banded_matvec(blocks: Array, x: Array) -> Array:
    """``H x`` for a symmetric block-banded ``H`` given by its upper blocks ``blocks`` (K, T, n, n),
    ``blocks[d, t] = H[t, t + d]`` (the rows past the end ignored; ``blocks[0]`` symmetric), and
    ``x`` (T, n)."""
    K, T = blocks.shape[0], blocks.shape[1]
    y = jnp.einsum("tij,tj->ti", blocks[0], x)
    for d in range(1, min(K, T)):
        up = jnp.einsum("tij,tj->ti", blocks[d, : T - d], x[d:])  # H[t, t+d] x[t+d]
        down = jnp.einsum("tji,tj->ti", blocks[d, : T - d], x[: T - d])  # H[t+d, t] x[t]
        y = y.at[: T - d].add(up).at[d:].add(down)
    return y


def spd_inverse(M: Array) -> Array:
    """Inverse of a symmetric positive definite matrix (..., n, n) by in-place Gauss-Jordan
    elimination without pivoting (stable for SPD matrices: every pivot is a Schur complement's
    diagonal, positive): n rank-one updates, one ``fori_loop``. No derivative rule: for solvers
    whose result is not differentiated (a Gauss-Newton step)."""
    n = M.shape[-1]
    idx = jnp.arange(n)

    def one(A):
        def sweep(k, A):
            d = A[k, k]
            col, row = A[:, k], A[k, :]
            B = A - jnp.outer(col, row) / d
            B = jnp.where(idx[:, None] == k, row[None, :] / d, B)
            B = jnp.where(idx[None, :] == k, -col[:, None] / d, B)
            return B.at[k, k].set(1.0 / d)

        return lax.fori_loop(0, n, sweep, A)

    return jnp.vectorize(one, signature="(n,n)->(n,n)")(M)


class BandedFactor(NamedTuple):
    """``H = L D L^T`` of a symmetric positive definite block-banded ``H`` (:func:`banded_factor`):
    ``L`` unit lower block-banded, ``D`` block diagonal."""

    d: Array  # (T, n, n) D[t]
    d_inv: Array  # (T, n, n) D[t]^-1
    low: Array  # (K - 1, T, n, n) low[k - 1, t] = L[t, t - k] (zero for t < k)


def banded_factor(blocks: Array) -> BandedFactor:
    """The block factorisation ``H = L D L^T`` of a symmetric positive definite block-banded ``H``
    given by its ``K`` upper block diagonals (``blocks`` (K, T, n, n) as in
    :func:`banded_matvec`): one ``lax.scan`` over the T block rows, O(T K^2 n^3) work instead of
    the dense O(T^3 n^3), exact, no LAPACK call (module docstring), and per block row a single
    n-step loop (the inverse of ``D[t]``, :func:`spd_inverse`): the loops' count, not their
    arithmetic, is what such small blocks cost on a CPU. Not differentiable (see
    :func:`spd_inverse`)."""
    K, T, n = blocks.shape[0], blocks.shape[1], blocks.shape[-1]
    z = jnp.zeros((n, n), blocks.dtype)
    eye = jnp.eye(n, dtype=blocks.dtype)
    # above[k - 1][t] = H[t - k, t]
    above = jnp.stack([jnp.concatenate([jnp.broadcast_to(z, (k, n, n)), blocks[k]])[:T] for k in range(1, K)]) \
        if K > 1 else jnp.zeros((0, T, n, n), blocks.dtype)

    def row(carry, xs):
        ds, invs, rows = carry  # ds[i] = D[t-1-i]; rows[i, j] = L[t-1-i, t-2-i-j]
        h0, up = xs  # H[t, t]; up[k - 1] = H[t - k, t]
        new = [z] * (K - 1)  # new[k - 1] = L[t, t - k]
        for k in range(K - 1, 0, -1):
            acc = up[k - 1].T
            for j in range(k + 1, K):
                acc = acc - new[j - 1] @ ds[j - 1] @ rows[k - 1, j - k - 1].T
            new[k - 1] = acc @ invs[k - 1]
        d = h0
        for k in range(1, K):
            d = d - new[k - 1] @ ds[k - 1] @ new[k - 1].T
        d = 0.5 * (d + d.T)
        inv = spd_inverse(d)
        new = jnp.stack(new) if K > 1 else jnp.zeros((0, n, n), blocks.dtype)
        if K > 1:
            ds = jnp.concatenate([d[None], ds[:-1]])
            invs = jnp.concatenate([inv[None], invs[:-1]])
            rows = jnp.concatenate([new[None], rows[:-1]])
        return (ds, invs, rows), (d, inv, new)

    m = max(K - 1, 1)
    init = (jnp.broadcast_to(eye, (m, n, n)), jnp.broadcast_to(eye, (m, n, n)),
            jnp.zeros((m, max(K - 1, 0), n, n), blocks.dtype))
    _, (d, inv, low) = lax.scan(row, init, (blocks[0], jnp.moveaxis(above, 0, 1)))
    return BandedFactor(d, inv, jnp.moveaxis(low, 1, 0))


def _below(f: BandedFactor) -> Array:
    """(K - 1, T, n, n): ``[k - 1, t] = L[t + k, t]`` (zero past the end)."""
    T = f.d.shape[0]
    return jnp.stack([jnp.concatenate([f.low[k - 1, k:], jnp.zeros_like(f.low[k - 1, :k])])[:T]
                      for k in range(1, f.low.shape[0] + 1)]) if f.low.shape[0] else f.low


def _back_substitute(f: BandedFactor, w: Array) -> Array:
    """``x`` with ``L^T x = w``."""
    K1, n = f.low.shape[0], w.shape[-1]
    if K1 == 0:
        return w

    def step(prev, xs):  # prev[k - 1] = x[t + k]
        below, wt = xs
        x = wt - jnp.einsum("kij,ki->j", below, prev)
        return jnp.concatenate([x[None], prev[:-1]]), x

    _, x = lax.scan(step, jnp.zeros((K1, n), w.dtype), (jnp.moveaxis(_below(f), 0, 1), w), reverse=True)
    return x


def banded_factor_solve(f: BandedFactor, b: Array) -> Array:
    """``x`` with ``H x = b`` (T, n) given ``H``'s :func:`banded_factor`."""
    K1, n = f.low.shape[0], b.shape[-1]
    if K1:
        def step(prev, xs):  # prev[k - 1] = y[t - k]
            low, bt = xs
            y = bt - jnp.einsum("kij,kj->i", low, prev)
            return jnp.concatenate([y[None], prev[:-1]]), y

        _, y = lax.scan(step, jnp.zeros((K1, n), b.dtype), (jnp.moveaxis(f.low, 0, 1), b))
    else:
        y = b
    return _back_substitute(f, jnp.einsum("tij,tj->ti", f.d_inv, y))


def banded_solve(blocks: Array, b: Array) -> Array:
    """``x`` with ``H x = b`` for a symmetric positive definite block-banded ``H`` (``blocks`` (K,
    T, n, n) as in :func:`banded_matvec`), ``b`` (T, n): :func:`banded_factor` and two
    substitutions."""
    return banded_factor_solve(banded_factor(blocks), b)


def banded_inverse_root(f: BandedFactor):
    """A linear map ``S`` (a function of (T, n) arrays) with ``S S^T = H^-1`` for ``H``'s
    :func:`banded_factor`: ``S y = L^-T C y`` with ``C C^T = D^-1`` (blockwise Cholesky). In the
    variables ``y`` of ``x = x0 + S y`` a quadratic with Hessian ``H`` has Hessian ``I``: the
    preconditioner of a first-order method whose curvature ``H`` approximates. Linear, hence
    differentiable in ``y`` (the factor is a constant)."""
    C = cholesky(f.d_inv)
    return lambda y: _back_substitute(f, jnp.einsum("tij,tj->ti", C, y))
