"""Tests of jmocap.physics.rotations against MuJoCo C (mju_* functions, float64) and
scipy.spatial.transform, and of its derivatives (the module claims every function is safe to
differentiate) against central finite differences and hand-derived Jacobians at the singular
points (zero rotation, 180-degree rotations).

Tolerances (float64): MJ_TOL 1e-14 for closed forms MuJoCo evaluates with the same
arithmetic up to operation order; FD_TOL 1e-8 for central differences with step 1e-6.
Random cases include the awkward ones: identity, rotations by pi about each axis (trace -1,
where a matrix -> quaternion routine must switch branches) and angles just below/above pi.
"""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import central_diff
from jmocap.physics.rotations import (
    axis_angle_to_mat,
    mat_to_quat,
    quat_conj,
    quat_error,
    quat_exp,
    quat_mul,
    quat_normalize,
    quat_to_mat,
    skew,
)

MJ_TOL = 1e-14
FD_TOL = 1e-8

pytestmark = pytest.mark.usefixtures("enable_x64")


def random_quats(n, seed):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def awkward_quats():
    """Identity, pi about x/y/z and a generic axis, and near-pi / near-zero rotations."""
    out = [[1.0, 0, 0, 0], [0.0, 1, 0, 0], [0.0, 0, 1, 0], [0.0, 0, 0, 1]]
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    for angle in (np.pi, np.pi - 1e-7, np.pi + 1e-7, 1e-9, -1e-9, 2 * np.pi - 1e-3):
        out.append([np.cos(angle / 2), *(np.sin(angle / 2) * axis)])
    return np.array(out)


def mj(fn, out_size, *args):
    res = np.zeros(out_size)
    fn(res, *args)
    return res


# ----------------------------------------------------------------------------- values vs MuJoCo


def test_quat_mul_conj_to_mat_match_mujoco():
    qa = np.concatenate([random_quats(20, 0), awkward_quats()])
    qb = np.concatenate([random_quats(20, 1), awkward_quats()[::-1]])
    mul = np.asarray(jax.jit(quat_mul)(qa, qb))
    mat = np.asarray(jax.jit(quat_to_mat)(qa))
    conj = np.asarray(jax.jit(quat_conj)(qa))
    for i in range(len(qa)):
        np.testing.assert_allclose(mul[i], mj(mujoco.mju_mulQuat, 4, qa[i], qb[i]), atol=MJ_TOL)
        np.testing.assert_allclose(mat[i].ravel(), mj(mujoco.mju_quat2Mat, 9, qa[i]), atol=MJ_TOL)
        np.testing.assert_array_equal(conj[i], mj(mujoco.mju_negQuat, 4, qa[i]))
    # broadcasting over leading axes: one quaternion times a batch
    np.testing.assert_allclose(np.asarray(quat_mul(qa[:1], qb)), np.asarray(quat_mul(
        np.repeat(qa[:1], len(qb), 0), qb)), atol=0)
    # scipy (scalar-last) agrees on the matrix: an independent second reference
    np.testing.assert_allclose(mat, Rotation.from_quat(qa[:, [1, 2, 3, 0]]).as_matrix(), atol=1e-14)


def test_quat_exp_matches_axis_angle_and_integrate():
    rng = np.random.default_rng(2)
    axes = rng.normal(size=(12, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = np.concatenate([rng.uniform(-3 * np.pi, 3 * np.pi, 8), [0.0, 1e-9, np.pi, 1e-3]])
    got = np.asarray(jax.jit(quat_exp)(axes * angles[:, None]))
    for i in range(len(axes)):
        np.testing.assert_allclose(got[i], mj(mujoco.mju_axisAngle2Quat, 4, axes[i], angles[i]),
                                   atol=MJ_TOL)
    # the free joint's orientation update (paper eq. 1, MuJoCo's mju_quatIntegrate):
    # q <- q (x) exp(omega dt), omega in the body frame
    q0 = random_quats(12, 3)
    omega = rng.normal(scale=5.0, size=(12, 3))
    dt = 0.01
    step = np.asarray(jax.jit(lambda q, w: quat_mul(q, quat_exp(w * dt)))(q0, omega))
    for i in range(len(q0)):
        want = q0[i].copy()
        mujoco.mju_quatIntegrate(want, omega[i], dt)
        np.testing.assert_allclose(step[i], want, atol=MJ_TOL)
    assert np.all(np.isfinite(np.asarray(quat_exp(np.zeros(3)))))
    np.testing.assert_array_equal(np.asarray(quat_exp(np.zeros(3))), [1.0, 0, 0, 0])


def test_quat_error_matches_mj_subquat():
    target = np.concatenate([random_quats(20, 4), awkward_quats()])
    current = np.concatenate([random_quats(20, 5), np.tile([1.0, 0, 0, 0], (len(awkward_quats()), 1))])
    # the same rotation in the other hemisphere (q and -q) and equal quaternions
    target = np.concatenate([target, -current[:3], current[3:6]])
    current = np.concatenate([current, current[:3], current[3:6]])
    got = np.array(jax.jit(quat_error)(target, current))
    for i in range(len(target)):
        want = mj(mujoco.mju_subQuat, 3, target[i], current[i])
        # at exactly pi the two directions are the same rotation; MuJoCo and jmocap may pick
        # either sign, so compare the rotation they represent
        if abs(np.linalg.norm(want) - np.pi) < 1e-6:
            np.testing.assert_allclose(Rotation.from_rotvec(got[i]).as_matrix(),
                                       Rotation.from_rotvec(want).as_matrix(), atol=1e-6)
        else:
            np.testing.assert_allclose(got[i], want, atol=1e-12)
        assert np.linalg.norm(got[i]) <= np.pi + 1e-12  # short way round
    # definition: target = current (x) exp(r)
    back = np.asarray(quat_mul(current, quat_exp(got)))
    sign = np.sign(np.sum(back * target, -1, keepdims=True))
    np.testing.assert_allclose(back * sign, target, atol=1e-7)


def test_axis_angle_to_mat_matches_mujoco_and_scipy():
    rng = np.random.default_rng(6)
    axes = rng.normal(size=(10, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = np.concatenate([rng.uniform(-4, 4, 7), [0.0, np.pi, -np.pi / 2]])
    got = np.asarray(jax.jit(axis_angle_to_mat)(axes, angles))
    for i in range(len(axes)):
        q = mj(mujoco.mju_axisAngle2Quat, 4, axes[i], angles[i])
        np.testing.assert_allclose(got[i].ravel(), mj(mujoco.mju_quat2Mat, 9, q), atol=MJ_TOL)
    np.testing.assert_allclose(got, Rotation.from_rotvec(axes * angles[:, None]).as_matrix(), atol=1e-14)
    # hand value: +90 degrees about z takes x to y
    np.testing.assert_allclose(np.asarray(axis_angle_to_mat(np.array([0.0, 0, 1]), np.pi / 2)),
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-16)


def test_mat_to_quat_matches_mujoco():
    q = np.concatenate([random_quats(30, 7), awkward_quats()])
    R = np.stack([mj(mujoco.mju_quat2Mat, 9, qi).reshape(3, 3) for qi in q])
    got = np.asarray(jax.jit(mat_to_quat)(R))
    assert np.all(got[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, atol=1e-15)
    for i in range(len(q)):
        want = mj(mujoco.mju_mat2Quat, 4, R[i].ravel())
        # q and -q are the same rotation: compare the rotation, then (away from w = 0, where
        # the sign is a free choice) the convention w >= 0
        np.testing.assert_allclose(abs(got[i] @ want), 1.0, atol=1e-14, err_msg=str(q[i]))
        if abs(want[0]) > 1e-7:
            np.testing.assert_allclose(got[i], want * np.sign(want[0]), atol=1e-14)
    # round trip through the matrix
    np.testing.assert_allclose(np.asarray(quat_to_mat(got)), R, atol=1e-14)


def test_quat_normalize_and_skew():
    q = np.array([[2.0, 0, 0, 0], [1.0, 1, 1, 1], [0.0, 0, 0, 0], [0.0, -3, 4, 0]])
    want = np.array([[1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [1.0, 0, 0, 0], [0.0, -0.6, 0.8, 0]])
    np.testing.assert_allclose(np.asarray(quat_normalize(q)), want, atol=1e-16)
    for qi in q[[0, 1, 3]]:
        w = qi.copy()
        mujoco.mju_normalize4(w)
        np.testing.assert_allclose(np.asarray(quat_normalize(qi)), w, atol=1e-16)
    rng = np.random.default_rng(8)
    v, w = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", np.asarray(skew(v)), w), np.cross(v, w), atol=1e-15)
    np.testing.assert_array_equal(np.asarray(skew(v)), -np.swapaxes(np.asarray(skew(v)), -1, -2))


# ----------------------------------------------------------------------------- derivatives


def test_quat_exp_jacobian_at_zero_and_fd():
    f = jax.jit(quat_exp)
    # d exp(v)/dv at 0: [0; I/2] (cos(|v|/2) is flat, sin(|v|/2) v/|v| ~ v/2)
    want0 = np.vstack([np.zeros((1, 3)), 0.5 * np.eye(3)])
    for jac in (jax.jacfwd(f)(np.zeros(3)), jax.jacrev(f)(np.zeros(3))):
        np.testing.assert_allclose(np.asarray(jac), want0, atol=1e-16)
    np.testing.assert_allclose(central_diff(f, np.zeros(3)), want0, atol=FD_TOL)
    v = np.array([0.4, -1.1, 2.0])
    for jac in (jax.jacfwd(f)(v), jax.jacrev(f)(v)):
        np.testing.assert_allclose(np.asarray(jac), central_diff(f, v), atol=FD_TOL)


def test_quat_error_jacobian_at_zero_and_fd():
    """r -> quat_error(current (x) exp(r), current) is the identity near 0: its Jacobian is I
    exactly at 0 (the removable singularity angle / sin(angle / 2)), and it matches finite
    differences there and elsewhere, also with respect to the current orientation."""
    current = random_quats(1, 9)[0]

    def err_of(r):
        return quat_error(quat_mul(current, quat_exp(r)), current)

    f = jax.jit(err_of)
    for jac in (jax.jacfwd(f)(np.zeros(3)), jax.jacrev(f)(np.zeros(3))):
        np.testing.assert_allclose(np.asarray(jac), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(central_diff(f, np.zeros(3)), np.eye(3), atol=FD_TOL)
    target = random_quats(1, 10)[0]
    g = jax.jit(lambda c: quat_error(target, c))
    for point in (current, target):  # generic, and target == current (zero error)
        for jac in (jax.jacfwd(g)(point), jax.jacrev(g)(point)):
            assert np.all(np.isfinite(np.asarray(jac)))
            np.testing.assert_allclose(np.asarray(jac), central_diff(g, point), atol=1e-7)


def test_mat_to_quat_and_quat_to_mat_derivatives():
    f = jax.jit(mat_to_quat)
    R_generic = np.asarray(quat_to_mat(random_quats(1, 11)[0]))
    R_pi = np.diag([1.0, -1.0, -1.0])  # pi about x: 1 + trace = 0, another branch is taken
    for R in (np.eye(3), R_generic, R_pi):
        jac_f, jac_r = (np.asarray(j(R)) for j in (jax.jacfwd(f), jax.jacrev(f)))
        assert np.all(np.isfinite(jac_f)) and np.all(np.isfinite(jac_r))
        np.testing.assert_allclose(jac_f, jac_r, atol=1e-14)
        # at R_pi (w = 0) the convention w >= 0 flips the sign inside any stencil: the map is
        # discontinuous there, so finite differences only apply at the other two
        if R is not R_pi:
            np.testing.assert_allclose(jac_f, central_diff(f, R), atol=FD_TOL)
    g = jax.jit(quat_to_mat)
    q = random_quats(1, 12)[0]
    np.testing.assert_allclose(np.asarray(jax.jacfwd(g)(q)), central_diff(g, q), atol=FD_TOL)
    h = jax.jit(quat_normalize)
    for jac in (jax.jacfwd(h)(np.zeros(4)), jax.jacrev(h)(np.zeros(4))):
        assert np.all(np.isfinite(np.asarray(jac)))
