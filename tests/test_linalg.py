"""jmocap.physics.linalg (pure-JAX Cholesky and triangular solves) against LAPACK (NumPy) and
finite differences. Tolerances: float64 round-off of a 7x7 / 47x47 factorisation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jmocap.physics import linalg as la


def spd(rng, batch, n):
    A = rng.normal(size=(*batch, n, n))
    return A @ np.swapaxes(A, -1, -2) + n * np.eye(n)


@pytest.mark.parametrize("n", [1, 7, 47])
def test_matches_lapack(enable_x64, n):
    rng = np.random.default_rng(n)
    M = spd(rng, (4,), n)
    b, B = rng.normal(size=(4, n)), rng.normal(size=(4, n, 3))
    L = la.cholesky(M)
    np.testing.assert_allclose(L, np.linalg.cholesky(M), rtol=0, atol=1e-12)
    np.testing.assert_allclose(la.cho_solve(L, b), np.linalg.solve(M, b[..., None])[..., 0], atol=1e-12)
    np.testing.assert_allclose(la.cho_solve(L, B), np.linalg.solve(M, B), atol=1e-12)
    np.testing.assert_allclose(la.solve_lower(L, B), np.linalg.solve(L, B), atol=1e-12)
    np.testing.assert_allclose(la.solve_upper(L, B), np.linalg.solve(np.swapaxes(L, -1, -2), B), atol=1e-12)
    # one factor, a batch of right-hand sides (broadcasting)
    np.testing.assert_allclose(la.cho_solve(L[0], B), np.linalg.solve(M[0], B), atol=1e-12)
    # many right-hand sides: the (n, k) layout of the substitutions (k > FEW_RHS)
    C = rng.normal(size=(4, n, la.FEW_RHS + 3))
    np.testing.assert_allclose(la.solve_lower(L, C), np.linalg.solve(L, C), atol=1e-12)
    np.testing.assert_allclose(la.solve_upper(L, C), np.linalg.solve(np.swapaxes(L, -1, -2), C), atol=1e-12)


def test_float32_and_jit_vmap():
    rng = np.random.default_rng(0)
    M = spd(rng, (8,), 47).astype(np.float32)
    b = rng.normal(size=(8, 47)).astype(np.float32)
    x = jax.jit(jax.vmap(lambda m, v: la.cho_solve(la.cholesky(m), v)))(M, b)
    assert x.dtype == jnp.float32
    ref = np.linalg.solve(M.astype(np.float64), b[..., None].astype(np.float64))[..., 0]
    np.testing.assert_allclose(x, ref, rtol=1e-4, atol=1e-5)


def test_not_positive_definite_is_nan_not_a_wrong_answer(enable_x64):
    assert np.isnan(la.cholesky(np.diag([1.0, -1.0, 1.0]))).any()


def test_gradients_match_finite_differences(enable_x64):
    rng = np.random.default_rng(1)
    A, b, B = rng.normal(size=(7, 7)), rng.normal(size=7), rng.normal(size=(7, 2))

    def solve(A, b):  # a symmetric positive definite parametrisation of M
        return la.cho_solve(la.cholesky(A @ A.T + 3.0 * jnp.eye(7)), b)

    check_grads(jax.jit(solve), (A, b), order=2, modes=["fwd", "rev"])
    check_grads(jax.jit(lambda A: la.cholesky(A @ A.T + 3.0 * jnp.eye(7))), (A,), order=1, modes=["fwd", "rev"])
    L = np.linalg.cholesky(A @ A.T + 3.0 * np.eye(7))
    check_grads(jax.jit(lambda L, B: la.solve_lower(jnp.tril(L), B)), (L, B), order=1, modes=["fwd", "rev"])
    check_grads(jax.jit(lambda L, B: la.solve_upper(jnp.tril(L), B)), (L, B), order=1, modes=["fwd", "rev"])


def test_solve_spd3(enable_x64):
    rng = np.random.default_rng(2)
    A, b = spd(rng, (5,), 3), rng.normal(size=(5, 3))
    np.testing.assert_allclose(la.solve_spd3(A, b), np.linalg.solve(A, b[..., None])[..., 0], atol=1e-12)
    check_grads(jax.jit(la.solve_spd3), (A[0], b[0]), order=1, modes=["fwd", "rev"])


def test_no_lapack_custom_call_in_the_compiled_program():
    """The point of the module (see its docstring): no LAPACK custom calls that could deadlock
    XLA's CPU thread pool."""
    M = spd(np.random.default_rng(3), (4,), 10).astype(np.float32)
    hlo = jax.jit(jax.vmap(lambda m: la.cho_solve(la.cholesky(m), jnp.eye(10)))).lower(M).as_text()
    assert "lapack" not in hlo and "custom_call" not in hlo


def test_det3(enable_x64):
    A = np.random.default_rng(4).normal(size=(6, 3, 3))
    np.testing.assert_allclose(la.det3(A), np.linalg.det(A), atol=1e-12)


def test_mass_inverse_matches_numpy(enable_x64):
    from jmocap.physics.dynamics import mass_inverse

    M = spd(np.random.default_rng(5), (3,), 47)
    np.testing.assert_allclose(mass_inverse(la.cholesky(M)), np.linalg.inv(M), atol=1e-12)


def _dense_banded(blocks):
    K, T, n, _ = blocks.shape
    H = np.zeros((T * n, T * n))
    for d in range(K):
        for t in range(T - d):
            H[t * n:(t + 1) * n, (t + d) * n:(t + d + 1) * n] = blocks[d, t]
            H[(t + d) * n:(t + d + 1) * n, t * n:(t + 1) * n] = blocks[d, t].T
    return H


@pytest.mark.parametrize("n", [1, 6, 47])
def test_spd_inverse_matches_lapack(enable_x64, n):
    M = spd(np.random.default_rng(n), (3,), n)
    np.testing.assert_allclose(la.spd_inverse(M), np.linalg.inv(M), atol=1e-10 * np.abs(np.linalg.inv(M)).max())


@pytest.mark.parametrize("K", [1, 2, 3, 4])
@pytest.mark.parametrize("T,n", [(1, 4), (2, 5), (3, 3), (40, 7)])
def test_block_banded_solve_and_product_against_dense(enable_x64, T, n, K):
    """A symmetric positive definite block-banded matrix (K stored block diagonals, rows past the
    end ignored) assembled densely: the product and the block LDL^T solve equal NumPy's,
    including the short systems whose off-diagonal blocks hang past the end; the factor's
    inverse root S (``x = x0 + S y``) satisfies ``S S^T = H^-1``."""
    rng = np.random.default_rng(T * 100 + n * 10 + K)
    blocks = rng.normal(size=(K, T, n, n))
    blocks[0] = spd(rng, (T,), n) + 4 * K * n * np.eye(n)  # diagonally dominant: positive definite
    H = _dense_banded(blocks)
    assert np.all(np.linalg.eigvalsh(H) > 0)
    x = rng.normal(size=(T, n))
    np.testing.assert_allclose(la.banded_matvec(jnp.asarray(blocks), jnp.asarray(x)), (H @ x.ravel()).reshape(T, n),
                               atol=1e-10)
    b = rng.normal(size=(T, n))
    want = np.linalg.solve(H, b.ravel()).reshape(T, n)
    got = jax.jit(la.banded_solve)(jnp.asarray(blocks), jnp.asarray(b))
    np.testing.assert_allclose(got, want, atol=1e-10 * np.abs(want).max())
    S = la.banded_inverse_root(la.banded_factor(jnp.asarray(blocks)))
    cols = np.asarray(jax.jit(jax.vmap(S))(jnp.asarray(np.eye(T * n).reshape(T * n, T, n)))).reshape(T * n, -1).T
    np.testing.assert_allclose(cols @ cols.T, np.linalg.inv(H), atol=1e-10 * np.abs(np.linalg.inv(H)).max())


def test_block_banded_solve_of_an_ill_conditioned_trajectory_system(enable_x64):
    """The normal equations of a smoothed trajectory: a weak per-frame anchor (1e-7) plus a
    strong second-difference (acceleration) penalty coupling frames two apart; condition number
    about 1e8. The solve keeps float64's accuracy relative to that conditioning."""
    T, n = 60, 3
    D2 = np.zeros((T - 2, T))
    for i in range(T - 2):
        D2[i, i:i + 3] = [1.0, -2.0, 1.0]
    scalar = 1e-7 * np.eye(T) + D2.T @ D2
    H = np.kron(scalar, np.eye(n))
    blocks = np.zeros((3, T, n, n))
    for d in range(3):
        for t in range(T - d):
            blocks[d, t] = H[t * n:(t + 1) * n, (t + d) * n:(t + d + 1) * n]
    b = np.random.default_rng(0).normal(size=(T, n))
    want = np.linalg.solve(H, b.ravel()).reshape(T, n)
    got = la.banded_solve(jnp.asarray(blocks), jnp.asarray(b))
    assert np.linalg.cond(H) > 1e7
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max())
