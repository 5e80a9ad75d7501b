"""Tests of jmocap.numerics: values against numpy / hand-worked values, gradients against
central finite differences and hand-derived derivatives, at the singular points the helpers
exist for (zero vectors, zero denominators, theta = 0).

Tolerances (float64): VALUE_TOL 1e-15 relative for values numpy computes the same way;
FD_TOL 1e-8 for central differences with step 1e-6 (conftest.central_diff) (truncation ~eps^2 * f''' ~ 1e-12,
rounding ~1e-16 / eps ~ 1e-10).  At the singular points the gradient is compared exactly with
its defined value (0), and asserted finite in both modes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import central_diff
from jmocap.numerics import safe_div, safe_norm, safe_normalize, sinc_half

VALUE_TOL = 1e-15
ULP4 = 4e-16  # a few float64 roundings of a value in [0.25, 1)
FD_TOL = 1e-8

pytestmark = pytest.mark.usefixtures("enable_x64")


def both_jacobians(f, x):
    return np.asarray(jax.jacfwd(f)(x)), np.asarray(jax.jacrev(f)(x))


# ----------------------------------------------------------------------------- safe_norm


def test_safe_norm_values_match_numpy():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 4, 3))
    for axis in (-1, 0, 1):
        np.testing.assert_allclose(np.asarray(safe_norm(x, axis=axis)), np.linalg.norm(x, axis=axis),
                                   rtol=VALUE_TOL)
    np.testing.assert_allclose(np.asarray(safe_norm(x, keepdims=True)),
                               np.linalg.norm(x, axis=-1, keepdims=True), rtol=VALUE_TOL)
    assert float(safe_norm(np.array([3.0, 4.0]))) == 5.0  # hand value
    assert float(safe_norm(np.zeros(3))) == 0.0


def test_safe_norm_gradient():
    f = jax.jit(safe_norm)
    x = np.array([0.3, -1.2, 0.5])
    # d|x|/dx = x / |x|, and central differences
    for jac in both_jacobians(f, x):
        np.testing.assert_allclose(jac, x / np.linalg.norm(x), rtol=1e-15)
        np.testing.assert_allclose(jac, central_diff(f, x), atol=FD_TOL)
    # at 0: |x| is not differentiable; the defined (sub)gradient is 0, never NaN
    z = np.zeros(3)
    for jac in both_jacobians(f, z):
        np.testing.assert_array_equal(jac, 0.0)
    # jnp.linalg.norm is the failure this helper exists for
    assert np.isnan(np.asarray(jax.grad(jnp.linalg.norm)(z))).all()
    # second derivative at a nonzero point: (I - u u^T) / |x|
    u = x / np.linalg.norm(x)
    np.testing.assert_allclose(np.asarray(jax.hessian(f)(x)),
                               (np.eye(3) - np.outer(u, u)) / np.linalg.norm(x), rtol=1e-13)


def test_safe_norm_below_tiny_is_zero_and_float32():
    # sum of squares below the dtype's smallest normal number counts as zero
    tiny32 = np.finfo(np.float32).tiny
    x32 = np.full(3, np.sqrt(tiny32) / 4, np.float32)  # x.x = 3/16 tiny < tiny
    assert float(safe_norm(jnp.asarray(x32))) == 0.0
    y32 = np.array([3.0, 4.0], np.float32)
    assert safe_norm(jnp.asarray(y32)).dtype == jnp.float32
    assert float(safe_norm(jnp.asarray(y32))) == 5.0
    g = jax.grad(safe_norm)(jnp.asarray(x32))
    assert np.isfinite(np.asarray(g)).all()


# ----------------------------------------------------------------------------- safe_normalize


def test_safe_normalize_values_and_zero():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(6, 3))
    want = x / np.linalg.norm(x, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(safe_normalize(x)), want, rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(np.asarray(safe_normalize(x, axis=0)),
                               x / np.linalg.norm(x, axis=0, keepdims=True), rtol=1e-15, atol=1e-16)
    np.testing.assert_array_equal(np.asarray(safe_normalize(np.zeros(3))), 0.0)
    # eps: x / max(|x|, eps) (hand values)
    np.testing.assert_allclose(np.asarray(safe_normalize(np.array([0.03, 0.04]), eps=0.1)), [0.3, 0.4],
                               rtol=1e-15)
    np.testing.assert_allclose(np.asarray(safe_normalize(np.array([3.0, 4.0]), eps=0.1)), [0.6, 0.8],
                               rtol=1e-15)


def test_safe_normalize_gradient():
    f = jax.jit(safe_normalize)
    x = np.array([0.3, -1.2, 0.5])
    n = np.linalg.norm(x)
    u = x / n
    for jac in both_jacobians(f, x):
        np.testing.assert_allclose(jac, (np.eye(3) - np.outer(u, u)) / n, rtol=1e-14, atol=1e-16)
        np.testing.assert_allclose(jac, central_diff(f, x), atol=FD_TOL)
    for jac in both_jacobians(f, np.zeros(3)):
        assert np.isfinite(jac).all()
        np.testing.assert_array_equal(jac, 0.0)
    # with eps, below eps the map is linear: x / eps
    g = jax.jit(lambda y: safe_normalize(y, eps=0.1))
    small = np.array([0.01, -0.02, 0.03])
    for jac in both_jacobians(g, small):
        np.testing.assert_allclose(jac, np.eye(3) / 0.1, rtol=1e-15)


# ----------------------------------------------------------------------------- safe_div


def test_safe_div_values_and_gradients():
    num = np.array([1.0, -3.0, 2.0, 0.0])
    den = np.array([4.0, 0.0, -0.5, 0.0])
    np.testing.assert_array_equal(np.asarray(safe_div(num, den)), [0.25, 0.0, -4.0, 0.0])
    np.testing.assert_array_equal(np.asarray(safe_div(num, den, fallback=7.0)), [0.25, 7.0, -4.0, 7.0])

    f = jax.jit(lambda nd: safe_div(nd[0], nd[1]))
    # d(n/d) = (1/d, -n/d^2) away from 0, and central differences
    nd = np.array([1.5, -0.4])
    for jac in both_jacobians(f, nd):
        np.testing.assert_allclose(jac, [1 / nd[1], -nd[0] / nd[1] ** 2], rtol=1e-15)
        np.testing.assert_allclose(jac, central_diff(f, nd), rtol=FD_TOL)
    # at den = 0 the value is the constant fallback: gradient exactly 0, not inf/NaN
    for jac in both_jacobians(f, np.array([1.5, 0.0])):
        np.testing.assert_array_equal(jac, 0.0)


# ----------------------------------------------------------------------------- sinc_half


def test_sinc_half_values():
    t = np.array([-2.0, -0.3, 1e-3, 0.5, 3.0, 10.0])
    np.testing.assert_allclose(np.asarray(sinc_half(t)), np.sin(t / 2) / t, rtol=1e-15)
    assert float(sinc_half(0.0)) == 0.5  # the limit
    # the Taylor branch (|theta| < 1e-3) against the closed form just below the switch, where
    # sin(t/2)/t has no cancellation: the omitted term t^6/645120 is ~1e-24 there
    small = np.array([9.99e-4, -5e-4, 1e-5, 1e-8])
    np.testing.assert_allclose(np.asarray(sinc_half(small)), np.sin(small / 2) / small, rtol=ULP4)
    # float32 too
    assert sinc_half(jnp.float32(0.0)).dtype == jnp.float32
    np.testing.assert_allclose(float(sinc_half(jnp.float32(1.0))), np.sin(0.5), rtol=1e-7)


def test_sinc_half_derivatives():
    f = jax.jit(sinc_half)
    d1 = jax.jit(jax.grad(sinc_half))
    d2 = jax.jit(jax.grad(jax.grad(sinc_half)))
    # hand-derived: d/dt [sin(t/2)/t] = cos(t/2)/(2t) - sin(t/2)/t^2
    for t in (0.7, -2.5, 2e-3):
        want = np.cos(t / 2) / (2 * t) - np.sin(t / 2) / t**2
        np.testing.assert_allclose(float(d1(t)), want, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(float(d1(t)), float(central_diff(f, np.array(t))), atol=FD_TOL)
    # Taylor series 1/2 - t^2/48 + t^4/3840: f'(0) = 0, f''(0) = -1/24
    assert float(d1(0.0)) == 0.0
    np.testing.assert_allclose(float(d2(0.0)), -1.0 / 24.0, rtol=1e-15)
    # the derivative is continuous across the branch switch at 1e-3: both sides equal the
    # series' derivative -t/24 + t^3/960 (the closed form loses ~1e-9 to cancellation there)
    for t in (0.999e-3, 1.001e-3):
        np.testing.assert_allclose(float(d1(t)), -t / 24 + t**3 / 960, rtol=1e-6)
