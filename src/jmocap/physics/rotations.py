"""Rotations: quaternions (MuJoCo order w, x, y, z), rotation matrices, axis-angle.

All functions broadcast over leading dimensions and are safe to differentiate.
"""

from __future__ import annotations

import jax.numpy as jnp

from jmocap.numerics import safe_norm, safe_normalize, sinc_half

Array = jnp.ndarray


def quat_normalize(q: Array) -> Array:
    """Unit quaternion; the zero quaternion maps to the identity."""
    n = safe_norm(q, keepdims=True)
    ident = jnp.zeros_like(q).at[..., 0].set(1.0)
    return jnp.where(n > 0, safe_normalize(q), ident)


def quat_mul(a: Array, b: Array) -> Array:
    """Hamilton product a ⊗ b."""
    aw, ax, ay, az = jnp.moveaxis(a, -1, 0)
    bw, bx, by, bz = jnp.moveaxis(b, -1, 0)
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: Array) -> Array:
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_to_mat(q: Array) -> Array:
    """Rotation matrix of a unit quaternion (w, x, y, z); (..., 4) -> (..., 3, 3)."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def quat_exp(v: Array) -> Array:
    """Unit quaternion of the rotation vector v (axis * angle): [cos(|v|/2), sin(|v|/2) v/|v|]."""
    theta = safe_norm(v)
    return jnp.concatenate([jnp.cos(0.5 * theta)[..., None], sinc_half(theta)[..., None] * v], -1)


def quat_error(target: Array, current: Array) -> Array:
    """Rotation vector r with target = current ⊗ exp(r) (body-frame error; MuJoCo's mju_subQuat).

    Takes the short way round (|r| <= pi).
    """
    dq = quat_mul(quat_conj(current), target)
    dq = jnp.where(dq[..., :1] < 0, -dq, dq)
    s = safe_norm(dq[..., 1:])
    angle = 2.0 * jnp.arctan2(s, dq[..., 0])
    # angle / sin(angle/2) -> 2 as s -> 0
    small = s < 1e-7
    scale = jnp.where(small, 2.0 / jnp.where(small, dq[..., 0], 1.0), angle / jnp.where(small, 1.0, s))
    return dq[..., 1:] * scale[..., None]


def axis_angle_to_mat(axis: Array, angle: Array) -> Array:
    """Rodrigues' formula for a unit axis (..., 3) and an angle (...)."""
    x, y, z = jnp.moveaxis(axis, -1, 0)
    c, s = jnp.cos(angle), jnp.sin(angle)
    C = 1.0 - c
    rows = [
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def mat_to_quat(R: Array) -> Array:
    """Unit quaternion (w >= 0) of a rotation matrix, branch-free and differentiable."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # four candidate (unnormalised) quaternions; pick the best-conditioned one
    cands = jnp.stack(
        [
            jnp.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            jnp.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            jnp.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
            jnp.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    diag = jnp.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = jnp.argmax(diag, axis=-1)
    q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = safe_normalize(q)
    return jnp.where(q[..., :1] < 0, -q, q)


def skew(v: Array) -> Array:
    x, y, z = jnp.moveaxis(v, -1, 0)
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )
