"""The synthetic generator's character (``jmocap.data.synthetic.character``): foot geometry and
leg inverse kinematics.

References: MuJoCo C forward kinematics (``mj_kinematics``: body poses, ``site_xpos``,
``geom_xpos`` / ``geom_xmat``, ``mj_jacBody``) and ``mju_quat2Mat``; joint ranges read from
``MjModel.jnt_range``.

Tolerances: 1e-12 where both sides evaluate the same kinematic chain in float64 (rounding
only); IK to 1e-6 m / 1e-5 rad (the solver stops at 1e-7 m / 5e-7 rad).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from jmocap.data import synthetic as S

FK_ATOL = 1e-12
IK_ATOL_M = 1e-6
IK_ATOL_RAD = 1e-5


@pytest.fixture(scope="module")
def ch():
    return S.character(1.8)


def _quat2mat_mujoco(quat):
    """Rotation matrices (T, 3, 3) of unit quaternions (T, 4) by MuJoCo C."""
    out = np.zeros((len(quat), 9))
    for t, qt in enumerate(quat):
        mujoco.mju_quat2Mat(out[t], qt)
    return out.reshape(-1, 3, 3)


def _random_leg_poses(ch, rng, T=5, margin=0.0):
    """Standing pose with a random root and random leg angles inside the joint ranges."""
    q = np.tile(ch.q_stand, (T, 1))
    q[:, :3] = rng.normal(size=(T, 3))
    quat = rng.normal(size=(T, 4))
    q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    for L in ch.legs:
        rng_ = ch.mj.jnt_range[ch.mj.dof_jntid[L.ik_dof]]
        span = rng_[:, 1] - rng_[:, 0]
        q[:, L.ik_qadr] = rng.uniform(rng_[:, 0] + margin * span, rng_[:, 1] - margin * span, (T, 7))
        lo, hi = ch.mj.jnt_range[ch.mj.dof_jntid[ch.mj.jnt_dofadr[_toe_joint(ch, L)]]]
        q[:, L.toe_qadr] = rng.uniform(lo, hi, T)
    return q


def _toe_joint(ch, L):
    return int(np.nonzero(ch.mj.jnt_qposadr == L.toe_qadr)[0][0])


def test_leg_fk_matches_mujoco(ch):
    rng = np.random.default_rng(0)
    q = _random_leg_poses(ch, rng)
    d = mujoco.MjData(ch.mj)
    jp, jr = np.zeros((3, ch.nv)), np.zeros((3, ch.nv))
    for f, L in enumerate(ch.legs):
        R, p, J = ch.leg_fk(f, _quat2mat_mujoco(q[:, 3:7]), q[:, :3], q[:, L.ik_qadr])
        for t in range(len(q)):
            d.qpos[:] = q[t]
            mujoco.mj_kinematics(ch.mj, d)
            mujoco.mj_comPos(ch.mj, d)
            mujoco.mj_jacBody(ch.mj, d, jp, jr, L.ankle_body)
            np.testing.assert_allclose(p[t], d.xpos[L.ankle_body], atol=FK_ATOL, rtol=0)
            np.testing.assert_allclose(R[t], d.xmat[L.ankle_body].reshape(3, 3), atol=FK_ATOL, rtol=0)
            np.testing.assert_allclose(J[t], np.vstack([jp[:, L.ik_dof], jr[:, L.ik_dof]]), atol=FK_ATOL, rtol=0)


def _mujoco_foot_points(mj, d, body):
    """The sites of a body, then the 8 corners of each of its box geoms (sx, sy, sz = -1, 1)."""
    pts = [d.site_xpos[s].copy() for s in range(mj.nsite) if mj.site_bodyid[s] == body]
    for g in range(mj.ngeom):
        if mj.geom_bodyid[g] == body and mj.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            Rg = d.geom_xmat[g].reshape(3, 3)
            for sx in (-1, 1):
                for sy in (-1, 1):
                    for sz in (-1, 1):
                        pts.append(d.geom_xpos[g] + Rg @ (mj.geom_size[g] * [sx, sy, sz]))
    return np.array(pts)


def test_foot_points_match_mujoco(ch):
    rng = np.random.default_rng(1)
    q = _random_leg_poses(ch, rng)
    d = mujoco.MjData(ch.mj)
    for f, L in enumerate(ch.legs):
        for t in range(len(q)):
            d.qpos[:] = q[t]
            mujoco.mj_kinematics(ch.mj, d)
            R = d.xmat[L.ankle_body].reshape(1, 3, 3)
            p = d.xpos[L.ankle_body][None]
            got = ch.foot_points(f, R, p, q[t:t + 1, L.toe_qadr])[0]
            ref = np.concatenate([_mujoco_foot_points(ch.mj, d, L.ankle_body),
                                  _mujoco_foot_points(ch.mj, d, L.toe_body)])
            assert got.shape == ref.shape and len(ref) > 6
            np.testing.assert_allclose(got, ref, atol=FK_ATOL, rtol=0)


def test_stance_rockers_keep_their_pivot(ch):
    """Heel rocker (phi < 0): the heel contact site stays where the flat foot had it. Ball
    rocker (phi > 0): the toe body (its contact site and sole) stays flat and in place."""
    mj = ch.mj
    G = np.array([0.3, -0.2, 0.7])
    for f, L in enumerate(ch.legs):
        side = L.side
        n_a = len(L.pts_ankle)
        names_a = [mj.site(s).name for s in range(mj.nsite) if mj.site_bodyid[s] == L.ankle_body]
        names_t = [mj.site(s).name for s in range(mj.nsite) if mj.site_bodyid[s] == L.toe_body]
        heel = names_a.index(f"contact_{side}_heel")
        toe = n_a + names_t.index(f"contact_{side}_toe")
        flat = ch.foot_points(f, *ch.stance_pose(f, G, np.array(0.0)))
        np.testing.assert_allclose(flat[[heel, toe], 2], 0.0, atol=1e-9, rtol=0)  # flat: both on the floor
        for phi in (-0.4, -0.1):
            pts = ch.foot_points(f, *ch.stance_pose(f, G, np.array(phi)))
            np.testing.assert_allclose(pts[heel], flat[heel], atol=FK_ATOL, rtol=0)
            assert pts[toe, 2] > 0.01  # toes up
        for phi in (0.1, 0.5):
            pts = ch.foot_points(f, *ch.stance_pose(f, G, np.array(phi)))
            np.testing.assert_allclose(pts[n_a:], flat[n_a:], atol=1e-9, rtol=0)  # toe body unmoved
            assert pts[heel, 2] > 0.005  # heel up


def test_solve_legs_reaches_mujoco_targets(ch):
    """Targets are MuJoCo FK of random leg angles; the IK started 0.2 rad away must put the
    ankle bodies there (it may use the leg's redundant rotation differently) within range."""
    rng = np.random.default_rng(2)
    T = 8
    q_true = _random_leg_poses(ch, rng, T, margin=0.15)
    d = mujoco.MjData(ch.mj)
    R_t = np.zeros((2, T, 3, 3))
    p_t = np.zeros((2, T, 3))
    for t in range(T):
        d.qpos[:] = q_true[t]
        mujoco.mj_kinematics(ch.mj, d)
        for f, L in enumerate(ch.legs):
            R_t[f, t] = d.xmat[L.ankle_body].reshape(3, 3)
            p_t[f, t] = d.xpos[L.ankle_body]
    q = q_true.copy()
    for L in ch.legs:
        q[:, L.ik_qadr] += rng.uniform(-0.2, 0.2, (T, 7))
        q[:, L.ik_qadr] = np.clip(q[:, L.ik_qadr], ch.lower[L.ik_qadr], ch.upper[L.ik_qadr])
    res = ch.solve_legs(q, R_t, p_t)
    assert res.shape == (T, 2) and res.max() < IK_ATOL_M
    for t in range(T):
        d.qpos[:] = q[t]
        mujoco.mj_kinematics(ch.mj, d)
        for f, L in enumerate(ch.legs):
            np.testing.assert_allclose(d.xpos[L.ankle_body], p_t[f, t], atol=IK_ATOL_M, rtol=0)
            np.testing.assert_allclose(d.xmat[L.ankle_body].reshape(3, 3), R_t[f, t], atol=IK_ATOL_RAD, rtol=0)
            lo, hi = ch.mj.jnt_range[ch.mj.dof_jntid[L.ik_dof]].T
            assert np.all(q[t, L.ik_qadr] >= lo) and np.all(q[t, L.ik_qadr] <= hi)


def test_character_cache_rounds_to_a_centimetre():
    a = S.character(1.7649)
    assert S.character(1.7551) is a
    assert S.character(1.77) is not a
    # the model is the subject's: its standing height and mass follow the rounded height
    np.testing.assert_allclose(a.height, 1.76, rtol=1e-9)
    np.testing.assert_allclose(a.mass, 22.0 * 1.76**2, rtol=1e-9)
