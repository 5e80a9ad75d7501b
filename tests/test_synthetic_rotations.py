"""The generator's numpy rotation helpers (``jmocap.data.synthetic.rotations``).

They stay numpy for speed (see the module docstring), so they are checked against independent
references: ``scipy.spatial.transform.Rotation`` / ``Slerp`` and MuJoCo C (``mju_quat2Mat``,
``mju_mat2Quat``), including rotations near 0 and near pi, where the rotation-vector formulas
switch branches.

Tolerances: 1e-12 (float64 rounding of a few operations); 1e-9 for the logarithm within 0.1
of pi (the angle comes from ``arccos`` near -1, whose rounding error grows as 1e-16 / (pi -
angle): 4e-11 measured at 1e-6 from pi); rotation vectors shorter than 1e-8 map to the
identity (error <= the angle).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from jmocap.data.synthetic.rotations import (
    _continuous_quats,
    _exp_rot,
    _log_rot,
    _mat2quat,
    _quat2mat,
    _rx,
    _ry,
    _rz,
    _slerp_R,
)

ATOL = 1e-12
ATOL_NEAR_PI = 1e-9
EXP_CUTOFF = 1e-8  # _exp_rot returns the identity below this angle


def _rotvecs(rng, n=50):
    """Random rotation vectors with angles spread over [0, pi), plus tiny ones and near-pi ones."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi - 1e-2, n - 10), [0.0, 1e-12, 1e-9, 1e-7, 1e-4],
                             np.pi - np.array([1e-2, 5e-4, 1e-4, 1e-5, 1e-6])])
    return axes * angles[:, None]


@pytest.mark.parametrize("fn, axis", [(_rx, "x"), (_ry, "y"), (_rz, "z")])
def test_elementary_rotations(fn, axis):
    a = np.random.default_rng(0).uniform(-4, 4, (3, 5))
    ref = Rotation.from_euler(axis, a.reshape(-1, 1)).as_matrix().reshape(3, 5, 3, 3)
    np.testing.assert_allclose(fn(a), ref, atol=ATOL, rtol=0)


def test_exp_matches_scipy():
    w = _rotvecs(np.random.default_rng(1))
    th = np.linalg.norm(w, axis=1)
    ref = Rotation.from_rotvec(w).as_matrix()
    big = th >= EXP_CUTOFF
    np.testing.assert_allclose(_exp_rot(w[big]), ref[big], atol=ATOL, rtol=0)
    # below the cutoff the helper returns the identity: off by at most the angle
    np.testing.assert_allclose(_exp_rot(w[~big]), np.broadcast_to(np.eye(3), ref[~big].shape), atol=0, rtol=0)
    assert np.all(np.abs(ref[~big] - np.eye(3)).max(axis=(1, 2)) <= EXP_CUTOFF)


def test_log_matches_scipy_including_near_pi():
    w = _rotvecs(np.random.default_rng(1))
    th = np.linalg.norm(w, axis=1)
    got = _log_rot(Rotation.from_rotvec(w).as_matrix())
    far = th < np.pi - 0.1
    np.testing.assert_allclose(got[far], w[far], atol=ATOL, rtol=0)
    # near pi: arccos loses digits; within 1e-3 of pi the axis comes from the symmetric
    # part, its sign from the skew part
    assert np.sum(th > np.pi - 1e-3) == 4
    np.testing.assert_allclose(got[~far], w[~far], atol=ATOL_NEAR_PI, rtol=0)


def test_slerp_matches_scipy():
    rng = np.random.default_rng(2)
    R0 = Rotation.random(20, random_state=3)
    R1 = Rotation.random(20, random_state=4)
    h = rng.uniform(0, 1, 20)
    got = _slerp_R(R0.as_matrix(), R1.as_matrix(), h)
    for i in range(20):
        pair = Rotation.concatenate([R0[i], R1[i]])
        ref = Slerp([0.0, 1.0], pair)([h[i]]).as_matrix()[0]
        np.testing.assert_allclose(got[i], ref, atol=ATOL, rtol=0)


def test_quaternions_match_mujoco():
    rng = np.random.default_rng(5)
    q = rng.normal(size=(30, 4)) * rng.uniform(0.5, 2.0, (30, 1))  # not unit: normalised first
    R = _quat2mat(q)
    for i in range(len(q)):
        ref = np.zeros(9)
        mujoco.mju_quat2Mat(ref, q[i] / np.linalg.norm(q[i]))
        np.testing.assert_allclose(R[i], ref.reshape(3, 3), atol=ATOL, rtol=0)
    back = _mat2quat(R)
    assert np.all(back[:, 0] >= 0)
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(back, unit * np.sign(unit[:, :1]), atol=ATOL, rtol=0)


def test_continuous_quats_flip_into_one_hemisphere():
    q = Rotation.from_rotvec(np.linspace(0, 6, 40)[:, None] * [0, 0, 1.0]).as_quat(scalar_first=True)
    q[1::3] *= -1  # arbitrary signs
    got = _continuous_quats(q)
    assert np.all(np.sum(got[1:] * got[:-1], axis=1) > 0)
    np.testing.assert_allclose(np.abs(got), np.abs(q), atol=0, rtol=0)  # only signs change
