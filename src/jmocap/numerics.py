"""Gradient-safe elementary math, in one place.

``jnp.linalg.norm`` has an undefined (NaN) gradient at zero, and ``x / y`` at ``y = 0`` is
infinite; both happen in practice (a quaternion with zero angular velocity, a contact force of
zero, a padded frame). These helpers return the mathematically sensible value and a finite
gradient everywhere, using the "double where" trick so that the unused branch never produces
NaN cotangents.
"""

from __future__ import annotations

import jax.numpy as jnp

Array = jnp.ndarray


def _tiny(x: Array) -> Array:
    return jnp.finfo(jnp.result_type(x)).tiny


def safe_norm(x: Array, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm with gradient 0 (not NaN) at x = 0."""
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    is_zero = sq <= _tiny(sq)
    return jnp.where(is_zero, 0.0, jnp.sqrt(jnp.where(is_zero, 1.0, sq)))


def safe_normalize(x: Array, axis: int = -1, eps: float = 0.0) -> Array:
    """x / |x|, returning x itself (zero) with finite gradients when |x| = 0."""
    n = safe_norm(x, axis=axis, keepdims=True)
    return safe_div(x, jnp.maximum(n, eps) if eps else n)


def safe_div(num: Array, den: Array, fallback: float = 0.0) -> Array:
    """num / den, and ``fallback`` where den == 0, with finite gradients."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def sinc_half(theta: Array) -> Array:
    """sin(theta/2)/theta, smooth at 0 (Taylor series below 1e-3; error < 1e-16)."""
    small = jnp.abs(theta) < 1e-3
    t = jnp.where(small, 1.0, theta)
    t2 = theta * theta
    return jnp.where(small, 0.5 - t2 / 48.0 + t2 * t2 / 3840.0, jnp.sin(0.5 * t) / t)
