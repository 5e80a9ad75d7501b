"""Dynamics in a moving camera's frame (D&D's inertial force control, issue 20): the recursive
Newton-Euler algorithm with a moving base, and the generalised inertial force.

The reference is the world-frame inverse dynamics (``physics.rnea``, itself tested against
MuJoCo C's ``mj_rne`` in test_physics.py) of the same motion: a body moving in the world, a
camera moving in the world, and the body's configuration, velocity and acceleration relative to
the camera obtained by differentiating the composed trajectory exactly (``jax.jacfwd`` in time).
The generalised force that moves the body must be the same whichever frame the motion is
written in (hinge torques equal; the root's force turned into the camera's axes; its torque,
in the root's own frame, equal).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import x64
from jmocap import physics as P
from jmocap.model import load_model
from jmocap.physics.rotations import axis_angle_to_mat, mat_to_quat, quat_conj, quat_mul


@pytest.fixture(scope="module")
def model64():
    with x64():
        yield load_model(with_mjx=False)


def _rot(t, axis, rate, phase):
    """A smooth rotation (3, 3) of time."""
    a = jnp.asarray(axis, jnp.float64)
    return axis_angle_to_mat(a / jnp.linalg.norm(a), rate * t + 0.4 * jnp.sin(1.3 * t + phase))


def _world_body(model, seed):
    """q_w(t): the root moves and turns, every hinge swings."""
    rng = np.random.default_rng(seed)
    q0 = jnp.asarray(model.qpos0, jnp.float64)
    amp = jnp.asarray(rng.uniform(0.1, 0.4, model.nq - 7))
    freq = jnp.asarray(rng.uniform(0.5, 3.0, model.nq - 7))
    axis, v = rng.normal(size=3), rng.normal(size=3)

    def q_w(t):
        pos = jnp.array([0.3, 2.0, 1.0]) + jnp.asarray(v) * t + jnp.array([0.0, 0.0, 0.1]) * jnp.sin(4 * t)
        quat = mat_to_quat(_rot(t, axis, 0.7, 0.2))
        return jnp.concatenate([pos, quat, q0[7:] + amp * jnp.sin(freq * t)])

    return q_w


def _camera(seed, still=False):
    """The camera's orientation R(t) (its axes in the world) and position c(t)."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    a, b = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))

    def R(t):
        base = jnp.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # OpenCV axes, looking along +y
        return base if still else _rot(t, axis, 0.9, 1.0) @ base

    def c(t):
        return jnp.zeros(3) if still else a * jnp.sin(1.7 * t) + b * t**2

    return R, c


def _relative(q_w, R, c):
    """The body's configuration relative to the camera, as a function of time."""

    def q_c(t):
        q = q_w(t)
        Rt = R(t)
        pos = Rt.T @ (q[:3] - c(t))
        quat = quat_mul(mat_to_quat(Rt.T), q[3:7])
        return q.at[:3].set(pos).at[3:7].set(quat)

    return q_c


def _state(q_of_t, t):
    """(q, qd, qdd) of a free-root trajectory at time t in MuJoCo's conventions: root linear
    velocity in the parent frame, angular velocity in the root's own frame."""

    def qd_of_t(s):
        q, dq = jax.jvp(q_of_t, (s,), (jnp.ones_like(s),))
        quat, dquat = q[3:7], dq[3:7]
        w_body = 2.0 * quat_mul(quat_conj(quat), dquat)[1:]
        return jnp.concatenate([dq[:3], w_body, dq[7:]])

    _, qdd = jax.jvp(qd_of_t, (t,), (jnp.ones_like(t),))
    return q_of_t(t), qd_of_t(t), qdd


def _frame_motion(R, c, t):
    """The camera's FrameMotion at t and the world's gravity in its axes."""

    def omega(s):  # in the camera's axes: vee(R^T dR/dt)
        Rs, dR = jax.jvp(R, (s,), (jnp.ones_like(s),))
        W = Rs.T @ dR
        return jnp.array([W[2, 1], W[0, 2], W[1, 0]])

    w, alpha = jax.jvp(omega, (t,), (jnp.ones_like(t),))
    accel = jax.jacfwd(jax.jacfwd(c))(t)
    Rt = R(t)
    return P.FrameMotion(w, alpha, Rt.T @ accel), Rt.T @ jnp.array([0.0, 0.0, -9.81]), Rt


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_same_force_moves_the_body_in_either_frame(model64, seed):
    """Inverse dynamics of the camera-frame motion with the camera's motion as a moving base
    equals the world-frame inverse dynamics, to float64 rounding; without the base's motion it
    does not (the inertial force is what differs)."""
    with x64():
        q_w = _world_body(model64, seed)
        R, c = _camera(seed + 10)
        q_c = _relative(q_w, R, c)
        for t in (0.3, 1.1, 2.5):
            t = jnp.asarray(t, jnp.float64)
            qw, qdw, qddw = _state(q_w, t)
            qc, qdc, qddc = _state(q_c, t)
            fm, g_c, Rt = _frame_motion(R, c, t)
            tau_w = np.asarray(P.rnea(model64, qw, qdw, qddw))
            tau_c = np.asarray(P.rnea(model64, qc, qdc, qddc, gravity=g_c, frame=fm))
            want = tau_w.copy()
            want[:3] = np.asarray(Rt).T @ tau_w[:3]  # the root's force in the camera's axes
            scale = np.abs(tau_w).max()
            np.testing.assert_allclose(tau_c, want, atol=1e-9 * scale)
            # the equation written in the camera frame as if it were inertial needs the inertial force
            as_if = np.asarray(P.rnea(model64, qc, qdc, qddc, gravity=g_c))
            inertial = np.asarray(P.inertial_force(model64, qc, qdc, fm, g_c))
            np.testing.assert_allclose(as_if - inertial, want, atol=1e-9 * scale)
            assert np.abs(as_if - want).max() > 1e-3 * scale


def test_a_body_at_rest_in_the_world_is_explained_by_the_inertial_force(model64):
    """The issue's check: a body standing still in the world, seen from a camera that
    accelerates and turns, moves in the camera's image of it; written in the camera frame, that
    motion is explained by the world's own static forces plus the inertial force, with no
    residual on the root; without the inertial force the root would need a residual wrench of
    the order of the body's weight times the camera's accelerations."""
    with x64():
        q0 = jnp.asarray(model64.qpos0, jnp.float64).at[:3].set(jnp.array([0.2, 3.0, 0.95]))
        R, c = _camera(5)
        q_c = _relative(lambda t: q0, R, c)
        for t in (0.4, 1.7):
            t = jnp.asarray(t, jnp.float64)
            qc, qdc, qddc = _state(q_c, t)
            assert np.abs(np.asarray(qdc)).max() > 0.1  # it moves, seen from the camera
            fm, g_c, Rt = _frame_motion(R, c, t)
            static = np.array(P.rnea(model64, q0, jnp.zeros(model64.nv), jnp.zeros(model64.nv)))  # holds it still
            static[:3] = np.asarray(Rt).T @ static[:3]
            M = np.asarray(P.mass_matrix(model64, qc))
            h = np.asarray(P.rnea(model64, qc, qdc, jnp.zeros(model64.nv), gravity=g_c))  # h with the camera's gravity
            residual = M @ np.asarray(qddc) + h - np.asarray(P.inertial_force(model64, qc, qdc, fm, g_c)) - static
            weight = float(np.sum(model64.body_mass)) * 9.81
            assert np.abs(residual).max() < 1e-9 * weight
            without = M @ np.asarray(qddc) + h - static
            assert np.abs(without[:6]).max() > 0.05 * weight


def test_a_still_camera_has_no_inertial_force(model64):
    with x64():
        q_w = _world_body(model64, 3)
        t = jnp.asarray(0.8, jnp.float64)
        q, qd, _ = _state(q_w, t)
        I = P.inertial_force(model64, q, qd, P.FrameMotion.at_rest(jnp.float64))
        np.testing.assert_allclose(np.asarray(I), 0.0, atol=1e-12)


def test_a_uniformly_accelerating_camera_pushes_by_minus_m_a(model64):
    """Any pose, any velocity: a camera accelerating by ``a`` without turning exerts the uniform
    fictitious force ``-m_i a`` on every body i: ``-m a`` on the root, and on the hinges exactly
    what a change of gravity by ``-a`` would do."""
    with x64():
        q_w = _world_body(model64, 4)
        t = jnp.asarray(1.3, jnp.float64)
        q, qd, _ = _state(q_w, t)
        a = jnp.array([0.5, -2.0, 1.5])
        I = np.asarray(P.inertial_force(model64, q, qd, P.FrameMotion(jnp.zeros(3), jnp.zeros(3), a)))
        m = float(np.sum(model64.body_mass))
        np.testing.assert_allclose(I[:3], -m * np.asarray(a), rtol=1e-10)
        # a uniform field -a acts exactly like gravity changed by -a; gravity's own generalised
        # force is minus what rnea needs to hold it (rnea(g) - rnea(0) = -(force of g))
        g = jnp.array([0.0, 0.0, -9.81])
        field = -np.asarray(P.rnea(model64, q, qd, jnp.zeros(model64.nv), gravity=g - a)
                            - P.rnea(model64, q, qd, jnp.zeros(model64.nv), gravity=g))
        np.testing.assert_allclose(I, field, atol=1e-9 * m)


def test_inertial_force_is_differentiable(model64):
    """Gradients through the moving base (for training through it, D&D Sec. 3.3) against
    central finite differences."""
    from jax.test_util import check_grads

    with x64():
        q_w = _world_body(model64, 6)
        t = jnp.asarray(0.5, jnp.float64)
        q, qd, _ = _state(q_w, t)

        def f(w, a, al):
            return jnp.sum(P.inertial_force(model64, q, qd, P.FrameMotion(w, al, a)) ** 2)

        check_grads(f, (jnp.array([0.3, -0.2, 0.5]), jnp.array([1.0, 0.0, -0.5]), jnp.array([0.1, 0.2, 0.0])),
                    order=1, modes=("rev",), atol=1e-5, rtol=1e-5)
