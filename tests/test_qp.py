"""Tests of jmocap.physics.qp: the projection QP against Clarabel, its KKT conditions, gradients
against finite differences, and the friction helpers against hand-computed values / Clarabel.

Tolerances (float64 unless stated):
- x vs Clarabel: 1e-6 in max-norm (the brief's bound).  Clarabel (interior point, tolerances
  1e-14) itself is only accurate to about 1e-9 here, which is what the comparison measures; our
  KKT residuals are ~1e-13, so the KKT tests are the sharper ones.
- KKT residuals (relative): stationarity 1e-9 (W and W^-1 are both given and agree to about
  cond(W) * 1e-16 <= 1e-12), primal feasibility 1e-9 (absolute, the brief asks 1e-7),
  dual feasibility exactly >= 0, complementarity 1e-9.
- float32: compared with Clarabel on the float32-rounded data (so input rounding is not counted);
  the solver's own float32 rounding is about eps32 * cond(A_SS) * |x| with cond(A_SS) up to ~1e4
  for W with cond <= 1e3, so 2e-4 * (1 + |x|) is allowed (measured: about 1e-6).
- Gradients: ``jax.test_util.check_grads`` (central differences, eps 1e-6) at 1e-5 relative, at
  points with strict complementarity (so the active set does not change inside the stencil).
"""

from __future__ import annotations

import contextlib
import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jmocap.physics import qp
from jmocap.physics.qp import (
    friction_cone_loss,
    friction_pyramid_edges,
    friction_pyramid_rows,
    project_friction_pyramid,
    solve_projection,
    solve_projection_info,
    tangent_basis,
)
from qp_reference import clarabel_projection, kkt_optimal, polished_projection, random_instance


@contextlib.contextmanager
def _x64(enable: bool = True):
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", enable)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", old)


@pytest.fixture
def x64():
    with _x64():
        yield


def _stack(insts):
    return tuple(np.stack([inst[k] for inst in insts]) for k in range(5))


def _kkt(W, G, v, lower, x, lam):
    """KKT residuals of one solution, in float64 numpy (relative where a scale exists)."""
    fin = np.isfinite(lower)
    Gf = np.where(fin[:, None], G, 0.0)
    lf = np.where(fin, lower, 0.0)
    r = W @ (x - v)
    stat = np.max(np.abs(r - Gf.T @ lam)) / (1.0 + np.max(np.abs(r)))
    slack = Gf @ x - lf
    primal = max(0.0, float(np.max(-slack)))
    dual = max(0.0, float(np.max(-lam)))
    comp = np.max(np.abs(lam * slack)) / (1.0 + np.max(np.abs(lam)))
    return stat, primal, dual, comp


# The default-suite tests share one problem size and batch (n = 62 DoFs, BATCH instances), so
# that each (m, method) program compiles once for all of them.
N_DOF = 62
BATCH = 32


@functools.cache
def _batched_solver(method, iters):
    return jax.jit(jax.vmap(lambda a, b, c, d: solve_projection_info(a, b, c, d, method=method,
                                                                     iters=iters)))


def _solve_batch(insts, method="auto", iters=None):
    W, Winv, G, v, lower = _stack(insts)
    info = _batched_solver(method, iters)(Winv, G, v, lower)
    return jax.tree.map(np.asarray, info)


def _compare_with_clarabel(n_per_group, seed, sizes=(47, N_DOF)):
    rng = np.random.default_rng(seed)
    worst = dict(err=0.0, stat=0.0, primal=0.0, dual=0.0, comp=0.0)
    statuses = {}
    for n, m in itertools.product(sizes, [4, 8, 16]):
        insts = [random_instance(rng, n, m) for _ in range(n_per_group)]
        info = _solve_batch(insts)
        assert info.converged.all(), f"n={n} m={m}: KKT check failed"
        # every method must agree (the fallback branch of "auto" included: iters=0)
        for method, iters in [("active_set", None), ("auto", 0)] + (
            [("enumerate", None)] if m <= 8 else []
        ):
            other = _solve_batch(insts, method, iters)
            np.testing.assert_allclose(other.x, info.x, rtol=0, atol=1e-9,
                                       err_msg=f"method {method} iters {iters} n={n} m={m}")
        for inst, x, lam in zip(insts, info.x, info.lam, strict=True):
            W, _, G, v, lower = inst
            xr, _, status = clarabel_projection(W, G, v, lower)
            statuses[status] = statuses.get(status, 0) + 1
            err = float(np.max(np.abs(x - xr)))
            stat, primal, dual, comp = _kkt(W, G, v, lower, x, lam)
            for k, val in zip(worst, (err, stat, primal, dual, comp), strict=True):
                worst[k] = max(worst[k], val)
            # never worse than the reference: objective and feasibility
            obj = 0.5 * (x - v) @ W @ (x - v)
            obj_r = 0.5 * (xr - v) @ W @ (xr - v)
            assert obj <= obj_r + 1e-9 * (1.0 + abs(obj_r))
    print(f"\nvs Clarabel ({statuses}): max|x - x_ref| {worst['err']:.2e}, KKT: stationarity "
          f"{worst['stat']:.2e}, primal {worst['primal']:.2e}, dual {worst['dual']:.2e}, "
          f"complementarity {worst['comp']:.2e}")
    assert worst["err"] <= 1e-6
    assert worst["stat"] <= 1e-9
    assert worst["primal"] <= 1e-9
    assert worst["dual"] == 0.0
    assert worst["comp"] <= 1e-9


def test_matches_clarabel(x64):
    _compare_with_clarabel(n_per_group=BATCH, seed=0, sizes=(N_DOF,))  # 96 instances


@pytest.mark.slow
def test_matches_clarabel_many(x64):
    _compare_with_clarabel(n_per_group=200, seed=1)  # 1,200 instances


# ----------------------------------------------------------------------------- properties


def test_feasible_v_is_returned_bitwise(x64):
    rng = np.random.default_rng(3)
    for m in (4, 8, 16):
        insts = [random_instance(rng, N_DOF, m, feasible_at_v=True) for _ in range(BATCH)]
        # some rows exactly tight at v (boundary, lambda = 0), and all rows disabled in one
        for inst in insts[: BATCH // 2]:
            _, _, G, v, lower = inst
            tight = rng.random(m) < 0.5
            lower[:] = np.where(tight & np.isfinite(lower), G @ v, lower)
        insts[BATCH // 2][4][:] = -np.inf
        info = _solve_batch(insts)
        v = np.stack([inst[3] for inst in insts])
        assert np.array_equal(info.x, v)
        assert not info.active.any()


def test_resolving_from_the_solution_returns_it(x64):
    rng = np.random.default_rng(4)
    for m in (4, 8, 16):
        insts = [random_instance(rng, N_DOF, m, feasible_at_v=False) for _ in range(BATCH)]
        info = _solve_batch(insts)
        again = _solve_batch([(W, Wi, G, x, lo) for (W, Wi, G, _, lo), x in zip(insts, info.x,
                                                                                strict=True)])
        np.testing.assert_allclose(again.x, info.x, rtol=0, atol=1e-12 * (1 + np.abs(info.x).max()))


def test_cholesky_metric_matches_inverse_metric(x64):
    """chol=L (W = L L^T, only L^-1 G^T formed) gives the same x, and the same derivatives."""
    rng = np.random.default_rng(9)
    for m in (4,):  # the metric enters through _prepare only, the same for every method
        insts = [random_instance(rng, 47, m, feasible_at_v=False) for _ in range(8)]
        W, Winv, G, v, lower = _stack(insts)
        L = np.linalg.cholesky(W)
        x_inv = np.asarray(jax.jit(jax.vmap(solve_projection))(Winv, G, v, lower))
        x_chol = np.asarray(jax.jit(jax.vmap(
            lambda L_, G_, v_, lo: solve_projection(None, G_, v_, lo, chol=L_)))(L, G, v, lower))
        np.testing.assert_allclose(x_chol, x_inv, rtol=0, atol=1e-9 * (1 + np.abs(x_inv).max()))
    Winv, G, v, lower = _grad_instance(2, seed=40)  # strictly complementary, two rows active
    L = np.linalg.cholesky(np.linalg.inv(Winv))

    def by_chol(L_, G_, v_):
        return solve_projection(None, G_, v_, lower, chol=jnp.tril(L_))

    check_grads(jax.jit(by_chol), (L, G, v), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5, eps=1e-6)
    with pytest.raises(ValueError, match="exactly one"):
        solve_projection(Winv, G, v, lower, chol=L)


def test_disabled_rows_are_the_same_as_deleted_rows(x64):
    rng = np.random.default_rng(5)
    W, Winv, G, v, lower = random_instance(rng, 47, 8, degenerate=False, feasible_at_v=False)
    lower2 = lower.copy()
    lower2[[1, 5]] = -np.inf
    x = solve_projection(Winv, G, v, lower2)
    keep = np.isfinite(lower2)
    x_del = solve_projection(Winv, G[keep], v, lower2[keep])
    np.testing.assert_allclose(x, x_del, rtol=0, atol=1e-12)


def test_float32():
    """float32 solve vs Clarabel on the float32-rounded data (see the module docstring)."""
    rng = np.random.default_rng(6)
    insts = []
    for n, m in itertools.product([47, 62], [4, 8, 16]):
        for _ in range(8):
            W, Winv, G, v, lower = random_instance(rng, n, m, cond=float(10 ** rng.uniform(0, 3)))
            Winv, G, v, lower = (a.astype(np.float32) for a in (Winv, G, v, lower))
            W = np.linalg.inv(Winv.astype(np.float64))
            insts.append((W, Winv, G, v, lower))
    worst = 0.0
    with _x64(False):
        for n, m in itertools.product([47, 62], [4, 8, 16]):
            group = [i for i in insts if i[2].shape == (m, n)]
            info = _solve_batch(group)
            assert info.x.dtype == np.float32
            for (W, _, G, v, lower), x in zip(group, info.x, strict=True):
                xr, _, _ = clarabel_projection(W, G, v, lower)
                rel = np.max(np.abs(x - xr)) / (1 + np.max(np.abs(xr)))
                worst = max(worst, rel)
                fin = np.isfinite(lower)
                slack = G[fin].astype(np.float64) @ x - lower[fin]
                assert slack.min() >= -2e-4 * (1 + np.abs(lower[fin]).max())
    print(f"\nfloat32: max |x - x_ref| / (1 + |x_ref|) = {worst:.2e}")
    assert worst <= 2e-4


def test_infeasible_problem_is_finite_and_flagged(x64):
    Winv = np.eye(3)
    G = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0]])
    for lower in (np.array([1.0, 0.0, 0.0]), np.array([-1.0, -1.0, 0.5])):
        for method in ("auto", "enumerate", "active_set"):
            info = solve_projection_info(Winv, G, np.zeros(3), lower, method=method)
            assert np.all(np.isfinite(info.x))
            assert not bool(info.converged)


def test_vmap_broadcast_nested_and_jit(x64):
    rng = np.random.default_rng(7)
    W, Winv, G, _, _ = random_instance(rng, 47, 8, degenerate=False)
    V = rng.normal(size=(4, 3, 47)) * 2
    L = rng.normal(size=(4, 3, 8))
    f = jax.jit(jax.vmap(jax.vmap(solve_projection, (None, None, 0, 0)), (None, None, 0, 0)))
    X = np.asarray(f(Winv, G, V, L))
    for i, j in itertools.product(range(4), range(3)):
        x1 = np.asarray(solve_projection(Winv, G, V[i, j], L[i, j]))
        np.testing.assert_allclose(X[i, j], x1, rtol=0, atol=1e-12)
        xr, _, _ = clarabel_projection(W, G, V[i, j], L[i, j])
        np.testing.assert_allclose(X[i, j], xr, rtol=0, atol=1e-6)
    # inside lax.scan, as the dynamic cycle uses it
    xs = jax.jit(lambda V_, L_: jax.lax.scan(
        lambda c, vl: (c, jax.vmap(solve_projection, (None, None, 0, 0))(Winv, G, *vl)),
        0.0, (V_, L_))[1])(V, L)
    np.testing.assert_allclose(np.asarray(xs), X, rtol=0, atol=1e-12)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="inconsistent shapes"):
        solve_projection(np.eye(3), np.ones((2, 4)), np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="one QP"):
        solve_projection(np.eye(3), np.ones((5, 2, 3)), np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="method"):
        solve_projection(np.eye(3), np.ones((2, 3)), np.zeros(3), np.zeros(2), method="x")
    with pytest.raises(ValueError, match="facets"):
        friction_pyramid_rows(np.array([0.0, 0, 1]), facets=2)


# ----------------------------------------------------------------------------- gradients


def _grad_instance(n_active: int, seed: int):
    """A small QP (n = 12) with ``n_active`` active constraints and strict complementarity."""
    n, m = 12, 6
    for s in range(seed, seed + 500):
        rng = np.random.default_rng(s)
        W = np.eye(n) + 0.3 * (lambda B: B @ B.T)(rng.normal(size=(n, n)))
        Winv = np.linalg.inv(W)
        Winv = 0.5 * (Winv + Winv.T)
        G = rng.normal(size=(m, n))
        v = rng.normal(size=n)
        lower = G @ v - rng.uniform(0.3, 1.0, size=m)
        viol = rng.choice(m, size=n_active, replace=False)
        lower[viol] += rng.uniform(0.8, 2.0, size=n_active) + (G @ v - lower)[viol]
        with _x64():
            info = solve_projection_info(Winv, G, v, lower)
        lam = np.asarray(info.lam)
        slack = G @ np.asarray(info.x) - lower
        act = np.asarray(info.active)
        if (act.sum() == n_active and np.all(lam[act] > 1e-2) and np.all(slack[~act] > 1e-2)):
            return Winv, G, v, lower
    raise AssertionError("no instance found")


@pytest.mark.parametrize("n_active", [pytest.param(0, marks=pytest.mark.slow),
                                      pytest.param(1, marks=pytest.mark.slow), 3])
def test_gradients_match_finite_differences(x64, n_active):
    Winv, G, v, lower = _grad_instance(n_active, seed=10 * n_active)
    c = np.random.default_rng(0).normal(size=v.shape)

    def loss(Winv, G, v, lower):
        return jnp.dot(c, solve_projection(Winv, G, v, lower))

    args = (Winv, G, v, lower)
    for i in range(4):
        def f(a, i=i):
            full = list(args)
            full[i] = a
            return solve_projection(*full)

        # jit: the finite differences evaluate f many times (compiled once instead of op by op)
        check_grads(jax.jit(f), (args[i],), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-5)
    # and the scalar loss in reverse mode w.r.t. all four at once
    check_grads(jax.jit(loss), args, order=1, modes=("rev",), eps=1e-6, atol=1e-5, rtol=1e-5)
    if n_active == 0:  # x = v: dx/dv = I, nothing else
        J = jax.jacrev(solve_projection, argnums=(0, 1, 2, 3))(*args)
        np.testing.assert_array_equal(np.asarray(J[2]), np.eye(v.size))
        for k in (0, 1, 3):
            assert not np.any(np.asarray(J[k]))


def _all_finite(tree):
    return all(bool(jnp.all(jnp.isfinite(t))) for t in jax.tree.leaves(tree))


@pytest.mark.parametrize("case", ["duplicates", "dependent", "inactive", "boundary", "zero_rows"])
@pytest.mark.parametrize("method", ["auto", "enumerate", "active_set"])
def test_gradients_never_nan(x64, case, method):
    rng = np.random.default_rng(11)
    n = 10
    W = np.eye(n) + 0.2 * (lambda B: B @ B.T)(rng.normal(size=(n, n)))
    Winv = np.linalg.inv(W)
    v = rng.normal(size=n)
    g = rng.normal(size=(3, n))
    if case == "duplicates":  # the same violated constraint three times
        G = np.stack([g[0], g[0], g[0], g[1]])
        lower = np.array([1.0, 1.0, 1.0, -1.0]) + G @ v
    elif case == "dependent":  # a violated row that is a combination of two violated rows
        G = np.stack([g[0], g[1], g[0] + g[1], g[2]])
        lower = G @ v + np.array([0.5, 0.5, 1.0, -1.0])
    elif case == "inactive":  # every row disabled
        G = np.stack([g[0], g[1], np.zeros(n), g[2]])
        lower = np.array([-np.inf, -np.inf, 0.0, -np.inf])
    elif case == "boundary":  # v exactly on one plane, lambda = 0 there
        G = np.stack([g[0], g[1], g[2], -g[0]])
        lower = G @ v - np.array([0.0, 0.5, 0.5, 0.7])
    else:  # zero rows, and one violated constraint
        G = np.stack([np.zeros(n), g[1], np.zeros(n), g[2]])
        lower = np.array([0.0, (g[1] @ v) + 0.3, 0.0, -5.0])

    @jax.jit
    def f(*a):
        return solve_projection(*a, method=method)

    args = (Winv, G, v, lower)
    x = f(*args)
    assert _all_finite(x)
    assert _all_finite(jax.jacrev(f, argnums=(0, 1, 2, 3))(*args))
    assert _all_finite(jax.jacfwd(f, argnums=(0, 1, 2, 3))(*args))
    if case in ("inactive", "boundary"):
        assert np.array_equal(np.asarray(x), v)
    if case in ("duplicates", "dependent", "zero_rows"):
        xr, _, _ = clarabel_projection(W, G, v, lower)
        np.testing.assert_allclose(np.asarray(x), xr, rtol=0, atol=1e-7)


# ----------------------------------------------------------------------------- friction


def test_friction_cone_loss_values(x64):
    up = np.array([0.0, 0.0, 1.0])
    theta_max = np.arctan(0.8)
    cases = {
        (1.0, 0.0, 1.0): (np.pi / 4) ** 2,  # 45 deg > 38.7 deg
        (0.1, 0.2, 1.0): 0.0,  # inside the cone
        (0.0, 0.0, 0.0): 0.0,  # no force
        (0.0, 0.0, -1.0): np.pi**2,  # pulling the foot into the floor
        (0.0, 3.0, 0.0): (np.pi / 2) ** 2,  # purely tangential
        (0.0, np.tan(theta_max) * 0.999, 1.0): 0.0,  # just inside
    }
    for f, want in cases.items():
        got = float(friction_cone_loss(np.array(f), up))
        assert got == pytest.approx(want, rel=1e-12, abs=1e-15), f
    # broadcasting and non-unit normals
    F = np.array(list(cases))
    np.testing.assert_allclose(np.asarray(friction_cone_loss(F, 2.5 * up)), list(cases.values()),
                               rtol=1e-12, atol=1e-15)
    # a tilted normal: rotate the force with it
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    np.testing.assert_allclose(np.asarray(friction_cone_loss(F @ R.T, R @ up)),
                               list(cases.values()), rtol=1e-9, atol=1e-12)
    # mu as an argument
    assert float(friction_cone_loss(np.array([1.0, 0, 1]), up, mu=1.5)) == 0.0


def test_friction_cone_loss_gradients(x64):
    up = np.array([0.1, -0.2, 1.0])
    rng = np.random.default_rng(0)
    loss = jax.jit(friction_cone_loss)
    for _ in range(5):
        f = rng.normal(size=3) * np.array([1, 1, 0.2])  # mostly outside the cone
        check_grads(lambda f_: loss(f_, up), (f,), order=1, modes=("fwd", "rev"),
                    eps=1e-6, atol=1e-6, rtol=1e-6)
        check_grads(lambda n_: loss(f, n_), (up,), order=1, modes=("fwd", "rev"),  # noqa: B023 (called within the iteration)
                    eps=1e-6, atol=1e-6, rtol=1e-6)
    for f in ([0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]):
        g = jax.grad(friction_cone_loss, argnums=(0, 1))(np.array(f), up)
        assert _all_finite(g)
    g0 = jax.grad(friction_cone_loss)(np.zeros(3), up)
    assert not np.any(np.asarray(g0))


def test_tangent_basis_is_orthonormal(x64):
    rng = np.random.default_rng(1)
    N = rng.normal(size=(200, 3))
    N = np.concatenate([N, np.eye(3), -np.eye(3)])
    t1, t2 = (np.asarray(t) for t in tangent_basis(N))
    n = N / np.linalg.norm(N, axis=1, keepdims=True)
    B = np.stack([t1, t2, n], axis=1)
    np.testing.assert_allclose(np.einsum("bij,bkj->bik", B, B), np.broadcast_to(np.eye(3), B.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(B), 1.0, atol=1e-12)  # right-handed
    t1, t2 = tangent_basis(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_array_equal(np.asarray(t1), [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(np.asarray(t2), [0.0, 1.0, 0.0])


@pytest.mark.parametrize("facets", [4, 6, 8])
def test_friction_pyramid_projection_matches_clarabel(x64, facets):
    rng = np.random.default_rng(facets)
    F = rng.normal(size=(60, 3)) * 2
    N = rng.normal(size=(60, 3)) * 0.2 + np.array([0.0, 0.0, 1.0])
    mu = 0.8
    project = jax.jit(project_friction_pyramid, static_argnames="facets")
    P = np.asarray(project(F, N, mu, facets=facets))
    C = np.asarray(friction_pyramid_rows(N, mu, facets))
    for f, c, p in zip(F, C, P, strict=True):
        xr, _, _ = clarabel_projection(np.eye(3), c, f, np.zeros(facets))
        np.testing.assert_allclose(p, xr, rtol=0, atol=1e-7)
        assert np.min(c @ p) >= -1e-12
        # inscribed: inside the true cone |f_t| <= mu f_n
        n = c.sum(0)  # proportional to the normal
        n /= np.linalg.norm(n)
        fn = p @ n
        assert np.linalg.norm(p - fn * n) <= mu * fn + 1e-9
    # forces already inside are returned unchanged, bitwise
    inside = np.array([[0.1, -0.2, 1.0], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(
        np.asarray(project(inside, np.array([0.0, 0, 1]), mu, facets=facets)), inside)


def test_friction_pyramid_four_facets_is_mujocos_pyramidal_cone(x64):
    """Four facets: |f_x| + |f_y| <= mu f_z, the cone MuJoCo uses for condim 3 (edges n +- mu t)."""
    mu = 0.8
    C = np.asarray(friction_pyramid_rows(np.array([0.0, 0.0, 1.0]), mu, 4))
    r = 1 / np.sqrt(2)
    want = r * np.array([[-1, -1, mu], [1, -1, mu], [1, 1, mu], [-1, 1, mu]])
    np.testing.assert_allclose(C, want, atol=1e-15)
    E = np.asarray(friction_pyramid_edges(np.array([0.0, 0.0, 1.0]), mu, 4))
    np.testing.assert_allclose(E, [[mu, 0, 1], [0, mu, 1], [-mu, 0, 1], [0, -mu, 1]], atol=1e-15)
    # each edge lies on two facets and inside the others
    CE = C @ E.T
    assert np.all(CE > -1e-15) and np.all(np.sum(np.abs(CE) < 1e-15, axis=0) == 2)
    # closed form on the floor: projection onto the facet x + y = mu z
    f = np.array([2.0, 1.0, 1.0])
    p = np.asarray(project_friction_pyramid(f, np.array([0.0, 0, 1]), mu))
    a = np.array([1.0, 1.0, -mu])
    want = f - (f @ a) / (a @ a) * a
    np.testing.assert_allclose(p, want, atol=1e-12)


def test_friction_pyramid_gradients(x64):
    rng = np.random.default_rng(2)
    n = np.array([0.1, 0.05, 1.0])
    project = jax.jit(project_friction_pyramid)  # compiled once, for every point below
    for _ in range(4):
        f = rng.normal(size=3)
        check_grads(lambda f_: project(f_, n), (f,), order=1,
                    modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)
        check_grads(lambda n_: project(f, n_), (n,), order=1,  # noqa: B023 (called within the iteration)
                    modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)
    jr = jax.jit(jax.jacrev(project_friction_pyramid, argnums=(0, 1)))
    jf = jax.jit(jax.jacfwd(project_friction_pyramid, argnums=(0, 1)))
    for f in (np.zeros(3), np.array([0.0, 0, -1.0]), np.array([0.0, 0, 1.0])):
        assert _all_finite(jr(f, n))
        assert _all_finite(jf(f, n))


def test_auto_plan_switches_match_clarabel(x64):
    """``method="auto"`` changes plan above ENUMERATE_DIRECT_MAX_M (enumeration only -> active
    set with an enumeration fallback) and above ENUMERATE_MAX_M (-> active set with 8 m fallback
    steps).  Just above each switch (m = 4, 8, 16 are in test_matches_clarabel), with the default
    fast path and with the fast path cut to 0 steps (the fallback alone must solve it), the
    solutions equal Clarabel's and are certified."""
    rng = np.random.default_rng(12)
    for m in (qp.ENUMERATE_DIRECT_MAX_M + 1, qp.ENUMERATE_MAX_M + 1):
        assert m <= 16  # the enumeration fallback's hard limit (2^m subsets)
        insts = [random_instance(rng, 20, m, feasible_at_v=False) for _ in range(12)]
        refs = [clarabel_projection(W, G, v, lower)[0] for W, _, G, v, lower in insts]
        for iters in (None, 0):
            info = _solve_batch(insts, "auto", iters)
            assert info.converged.all(), f"m={m} iters={iters}"
            assert info.active.any(), "the instances must have active constraints"
            np.testing.assert_allclose(info.x, np.stack(refs), rtol=0, atol=1e-6,
                                       err_msg=f"m={m} iters={iters}")


def test_kkt_reference_accepts_clarabels_optimum_and_rejects_others():
    """The numpy KKT check (the tracking test's fallback reference where Clarabel stalls) agrees
    with Clarabel: its polished optimum passes, a perturbed or a merely feasible point fails."""
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(20):
        W, _, G, v, lower = random_instance(rng, 12, 10, cond=1e3, degenerate=False, feasible_at_v=False)
        x, status = polished_projection(W, G, v, lower)
        if status != "polished":
            continue
        assert kkt_optimal(W, G, v, lower, x)
        assert not kkt_optimal(W, G, v, lower, x + 1e-3 * rng.normal(size=x.shape))
        fin = np.isfinite(lower)
        if np.any(G[fin] @ v < lower[fin] - 1e-6):  # v itself (infeasible here) is not optimal
            assert not kkt_optimal(W, G, v, lower, v)
        checked += 1
    assert checked >= 10, checked
