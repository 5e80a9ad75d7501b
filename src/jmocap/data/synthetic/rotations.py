"""Rotation helpers of the generator (matrices, rotation vectors, quaternions) on numpy arrays.

These deliberately stay numpy rather than calling the package's JAX rotations
(``jmocap.physics.rotations``: ``axis_angle_to_mat`` is :func:`_rx` / :func:`_ry` / :func:`_rz`
/ :func:`_exp_rot`, ``quat_to_mat`` is :func:`_quat2mat` after normalising; the package has no
matrix logarithm, ``quat_error`` is the quaternion form of :func:`_log_rot`). They run inside
the generator's Python loops on arrays whose shape changes with every clip and iteration: the
leg IK (:meth:`~jmocap.data.synthetic.character.Character.leg_fk` / ``solve_legs`` call
:func:`_exp_rot` and :func:`_log_rot` for every joint at every Gauss-Newton iteration on
sub-batches of the frames still moving, and :func:`_quat2mat` once per solve on all frames),
the foot geometry of every stance, the swing interpolation (:func:`_slerp_R`). JAX compiles
for every new shape -- measured on the 2-core machine: 0.5-1 s per shape under ``jit``, several
seconds per call of ``mat_to_quat`` run eagerly -- against microseconds here; routing
``_quat2mat`` / ``_mat2quat`` and the projection eagerly through the package code made clip
generation about 4x slower. :func:`_mat2quat` is MuJoCo C's ``mju_mat2Quat``.
"""

from __future__ import annotations

import math

import numpy as np

from jmocap.data.rotations import matrix_to_quat, quat_to_matrix


def _rx(a):
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0] = 1.0
    R[..., 1, 1], R[..., 1, 2], R[..., 2, 1], R[..., 2, 2] = c, -s, s, c
    return R


def _ry(a):
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 1, 1] = 1.0
    R[..., 0, 0], R[..., 0, 2], R[..., 2, 0], R[..., 2, 2] = c, s, -s, c
    return R


def _rz(a):
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 2, 2] = 1.0
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    return R


def _log_rot(R):
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3)."""
    R = np.asarray(R, float)
    tr = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(tr)
    v = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    s = np.sin(th)
    small = s < 1e-6
    scale = np.where(small, 0.5 + th**2 / 12.0, th / (2.0 * np.where(small, 1.0, s)))
    w = v * scale[..., None]
    # near pi, v = 2 sin(th) a vanishes: the axis comes from the symmetric part
    # (R + R^T) / 2 = cos(th) I + (1 - cos(th)) a a^T, its sign from v
    near_pi = (th > np.pi - 1e-3)
    if np.any(near_pi):
        out = []
        for Ri, ci, thi, vi in zip(R[near_pi], tr[near_pi], th[near_pi], v[near_pi], strict=True):
            aaT = ((Ri + Ri.T) / 2.0 - ci * np.eye(3)) / (1.0 - ci)
            k = int(np.argmax(np.diag(aaT)))
            axis = aaT[:, k] / math.sqrt(max(aaT[k, k], 1e-12))
            if np.dot(axis, vi) < 0.0:
                axis = -axis
            out.append(axis * thi)
        w[near_pi] = np.array(out)
    return w


def _exp_rot(w):
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    k = w / ths[..., None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    s = np.where(small, 0.0, np.sin(th))[..., None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(th))[..., None, None]
    return np.eye(3) + s * K + c * (K @ K)


def _slerp_R(R0, R1, h):
    """Geodesic interpolation of rotation matrices: ``R0 exp(h log(R0^T R1))``."""
    h = np.asarray(h, float)
    d = _log_rot(np.swapaxes(R0, -1, -2) @ R1)
    return R0 @ _exp_rot(d * h[..., None])


def _mat2quat(R):
    """wxyz quaternions (..., 4) of rotation matrices (..., 3, 3), w >= 0 (MuJoCo C's
    ``mju_mat2Quat``)."""
    return matrix_to_quat(R)


def _quat2mat(q):
    """Rotation matrices (..., 3, 3) of wxyz quaternions (..., 4), normalised first."""
    q = np.asarray(q, float)
    return quat_to_matrix(q / np.linalg.norm(q, axis=-1, keepdims=True))


def _continuous_quats(q):
    """Flip signs so consecutive quaternions lie in the same hemisphere."""
    q = np.array(q, float)
    for t in range(1, len(q)):
        if np.dot(q[t], q[t - 1]) < 0:
            q[t] = -q[t]
    return q
