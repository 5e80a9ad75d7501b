"""Synthetic motion clips with exact ground truth: a procedural motion generator on MuJoCo.

See ``docs/data.md`` for the full description. In short:

* :func:`generate_motion` plans a motion (walking, running, jumps, squats, lunges, kicks,
  standing with arm motion, dance-like stepping, and transitions between them) for a
  character of random height, as footsteps + a centre-of-mass (COM) trajectory + upper-body
  joint tracks, and turns it into MuJoCo joint angles:

  - every foot contact is a *stance* on a planned footstep: the foot is flat, or rocks about
    the heel contact point (heel strike) or about the ball of the foot (heel off / toe off);
    the rocking pivot stays exactly where it is (no sliding);
  - the horizontal COM trajectory is solved from the support phases (a least-squares
    "dynamics filter" on the linear inverted pendulum: the zero-moment point stays on the
    loaded feet; ballistic, ``x'' = 0``, while no foot touches the floor);
  - the root (pelvis) height follows a ``g = 9.81`` parabola whenever both feet are off the
    floor (running, jumps);
  - the legs are solved by Gauss-Newton inverse kinematics on MuJoCo C Jacobians
    (``mj_jacBody``) so that the feet are exactly where planned; every joint is clipped to
    its range.

* :func:`generate_clip` adds ground truth (``gt_q``, ``gt_qd`` by ``mj_differentiatePos``,
  3D keypoints, Rempe et al.'s contact labels), optionally tracks the motion in a MuJoCo
  simulation (``physics=True``: PD + inverse-dynamics feed-forward on the hinges and a
  residual root force/torque, giving ``gt_tau`` and ``gt_grf``), samples a static camera
  and projects noisy 2D keypoints (:class:`Corruption`).

Everything is deterministic for a seed: a clip's random stream is
``numpy.random.default_rng([seed, index])``.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.optimize import nnls

from jmocap.data.clip import Clip
from jmocap.layouts import CONTACT_SITES, get_layout
from jmocap.model import load_model

GRAVITY = 9.81
GENERATOR = "jmocap.data.synthetic/1"

# Rempe et al. (2020), Sec. 3.2: a heel/toe point is in contact when it moved less than 2 cm
# since the previous frame and is less than 5 cm above the floor.
CONTACT_MAX_STEP_M = 0.02
CONTACT_MAX_HEIGHT_M = 0.05

_DEBUG = False
MOTION_KINDS = ("walk", "run", "jump", "squat", "lunge", "kick", "stand", "dance")


class GenerationError(RuntimeError):
    """A motion attempt that failed validation (the generator retries with new draws)."""


# =========================================================================================
# small numpy math
# =========================================================================================


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
    # near pi: use the symmetric part
    near_pi = (th > np.pi - 1e-3)
    if np.any(near_pi):
        Rp = R[near_pi]
        out = []
        for Ri, thi in zip(Rp, th[near_pi], strict=True):
            B = (Ri + np.eye(3)) / 2.0
            k = int(np.argmax(np.diag(B)))
            axis = B[:, k] / math.sqrt(max(B[k, k], 1e-12))
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
    """wxyz quaternions (..., 4) of rotation matrices (..., 3, 3), w >= 0."""
    R = np.asarray(R, float)
    shp = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    q = np.empty((R.shape[0], 4))
    for i, Ri in enumerate(R):
        mujoco.mju_mat2Quat(q[i], Ri.reshape(9))
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(shp + (4,))


def _quat2mat(q):
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def _continuous_quats(q):
    """Flip signs so consecutive quaternions lie in the same hemisphere."""
    q = np.array(q, float)
    for t in range(1, len(q)):
        if np.dot(q[t], q[t - 1]) < 0:
            q[t] = -q[t]
    return q


def _smoothstep(s):
    """Quintic 0 -> 1 on [0, 1] with zero first and second derivatives at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


def _bump(s):
    """0 at s = 0 and 1, peak 1 at s = 0.4, zero slope at both ends; the descent is gentler
    than the rise (a swinging foot lands softly)."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * (1.0 - s) ** 3 / (0.4**2 * 0.6**3)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class _Track:
    """A scalar function of time through knots (t, value): monotone cubic (PCHIP), constant
    outside the knots. A single knot is a constant."""

    def __init__(self, knots):
        knots = sorted(knots, key=lambda k: k[0])
        ts = [knots[0][0]]
        vs = [knots[0][1]]
        for t, v in knots[1:]:
            if t - ts[-1] < 1e-9:  # a repeated time: the later value wins (a step is not allowed)
                vs[-1] = v
                continue
            ts.append(t)
            vs.append(v)
        self.t = np.array(ts, float)
        self.v = np.array(vs, float)
        self._f = PchipInterpolator(self.t, self.v, extrapolate=False) if len(ts) > 1 else None

    def __call__(self, t):
        t = np.asarray(t, float)
        if self._f is None:
            return np.full(t.shape, self.v[0])
        out = self._f(np.clip(t, self.t[0], self.t[-1]))
        return np.asarray(out, float)


# =========================================================================================
# the character
# =========================================================================================

SIDES = ("left", "right")


@dataclass
class _Leg:
    side: str
    hip_body: int
    ankle_body: int
    toe_body: int
    ik_qadr: np.ndarray  # qpos addresses of hip (3), knee (1), ankle (3) hinges
    ik_dof: np.ndarray
    toe_qadr: int
    pref_w: np.ndarray  # null-space preference weights over the IK joints
    hip_offset: np.ndarray  # hip joint centre in the pelvis frame
    A0_R: np.ndarray  # ankle body rotation in the foot ground frame (standing, flat)
    A0_p: np.ndarray  # ankle body origin in the foot ground frame
    heel_G: np.ndarray  # heel contact site in the ground frame (z = 0)
    toe_G: np.ndarray  # toe contact site in the ground frame (z = 0)
    ball_G: np.ndarray  # toe joint anchor (ball of the foot) in the ground frame
    toe_sign: float  # q_toe = q_toe0 - toe_sign * phi keeps the toes flat in a toe rocker
    q_toe0: float
    toe_rest_R: np.ndarray  # toe body rotation relative to the ankle body at q_toe = 0
    toe_rest_p: np.ndarray  # toe body origin in the ankle body frame
    toe_axis: np.ndarray  # toe hinge axis in the toe body frame
    pts_ankle: np.ndarray  # (n, 3) foot points on the ankle body (sites + sole box corners)
    pts_toe: np.ndarray  # (m, 3) foot points on the toe body
    yaw0: float  # foot yaw at stand
    chain: list = field(default_factory=list)  # [(body_pos, body_R, [(axis, jnt_pos, qpos0)])]


class Character:
    """A scaled humanoid and everything the generator precomputes about it.

    Wraps a :class:`jmocap.Model` (``load_model(height_m=...)``) and a scratch ``MjData``.
    Joint names follow ``models/mjcf/humanoid.xml`` (SMPL bodies, ``<body>_x/_y/_z`` hinges).
    """

    def __init__(self, model):
        self.model = model
        mj = self.mj = model.mj
        self.d = mujoco.MjData(mj)
        self.nq, self.nv = mj.nq, mj.nv
        self.q_stand = np.array(model.keyframe("stand"), float)
        # joint ranges: model.q_lower / q_upper, completed from MuJoCo's jnt_range where a
        # limited joint is reported unlimited (an older model.py had that bug)
        self.lower = np.array(model.q_lower, float)
        self.upper = np.array(model.q_upper, float)
        for j in range(mj.njnt):
            if mj.jnt_limited[j] and int(mj.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE),
                                                             int(mujoco.mjtJoint.mjJNT_SLIDE)):
                a = int(mj.jnt_qposadr[j])
                if not (np.isfinite(self.lower[a]) and np.isfinite(self.upper[a])):
                    self.lower[a], self.upper[a] = mj.jnt_range[j]
        self.mass = float(np.sum(mj.body_mass))
        self.pelvis = mj.body("pelvis").id
        self.qadr: dict[str, int] = {}
        for j in range(mj.njnt):
            if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                self.qadr[mj.joint(j).name] = int(mj.jnt_qposadr[j])
        d = self.d
        d.qpos[:] = self.q_stand
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        self.pelvis_p0 = d.xpos[self.pelvis].copy()
        self.z_stand = float(self.pelvis_p0[2])
        self.height = float(d.site_xpos[mj.site("kp_head_top").id, 2])
        self.com0 = d.subtree_com[self.pelvis].copy() - self.pelvis_p0
        self.contact_sites = np.array([mj.site(s).id for s in CONTACT_SITES])
        self.legs = [self._leg(side) for side in SIDES]
        self.thigh = float(np.linalg.norm(d.xpos[mj.body("left_knee").id] - d.xpos[mj.body("left_hip").id]))
        self.shank = float(np.linalg.norm(d.xpos[mj.body("left_ankle").id] - d.xpos[mj.body("left_knee").id]))
        self.reach = self.thigh + self.shank
        self.scale = self.height / 1.75
        # keypoint sites (every kp_* site) for validation
        self.kp_sites = np.array([i for i in range(mj.nsite) if mj.site(i).name.startswith("kp_")])
        self.check_sites = np.concatenate([self.kp_sites, self.contact_sites])

    # ---- construction helpers ---------------------------------------------------------

    def _hinges_of(self, body: int) -> list[int]:
        mj = self.mj
        return [
            j for j in range(mj.njnt)
            if mj.jnt_bodyid[j] == body and mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
        ]

    def _leg(self, side: str) -> _Leg:
        mj, d = self.mj, self.d
        hip, knee = mj.body(f"{side}_hip").id, mj.body(f"{side}_knee").id
        ankle, toe = mj.body(f"{side}_ankle").id, mj.body(f"{side}_foot").id
        joints = self._hinges_of(hip) + self._hinges_of(knee) + self._hinges_of(ankle)
        toe_j = self._hinges_of(toe)
        if len(toe_j) != 1:
            raise ValueError(f"expected one toe hinge on body {side}_foot, got {len(toe_j)}")
        ik_qadr = np.array([mj.jnt_qposadr[j] for j in joints])
        ik_dof = np.array([mj.jnt_dofadr[j] for j in joints])
        names = [mj.joint(j).name for j in joints]
        # null-space preference: no hip axial rotation, no ankle ab/adduction / inversion
        pref_w = np.array(
            [1.0 if (n.startswith(f"{side}_hip_z") or n.startswith(f"{side}_ankle_z")
                     or n.startswith(f"{side}_ankle_x")) else 0.0 for n in names]
        )
        R_pel = d.xmat[self.pelvis].reshape(3, 3)
        hip_offset = R_pel.T @ (d.xpos[hip] - d.xpos[self.pelvis])
        heel_w = d.site_xpos[mj.site(f"contact_{side}_heel").id].copy()
        toe_w = d.site_xpos[mj.site(f"contact_{side}_toe").id].copy()
        if abs(heel_w[2]) > 1e-3 or abs(toe_w[2]) > 1e-3:
            raise ValueError("keyframe 'stand' must have the contact sites on the floor (z = 0)")
        fwd = toe_w - heel_w
        yaw0 = math.atan2(fwd[1], fwd[0])
        origin = np.array([(heel_w[0] + toe_w[0]) / 2, (heel_w[1] + toe_w[1]) / 2, 0.0])
        RG = _rz(yaw0)
        to_G = lambda p: RG.T @ (p - origin)  # noqa: E731
        A_R = d.xmat[ankle].reshape(3, 3).copy()
        A0_R = RG.T @ A_R
        A0_p = to_G(d.xpos[ankle])
        heel_G, toe_G = to_G(heel_w), to_G(toe_w)
        heel_G[2] = toe_G[2] = 0.0
        ball_G = to_G(d.xpos[toe])
        toe_qadr = int(mj.jnt_qposadr[toe_j[0]])
        toe_axis = np.array(mj.jnt_axis[toe_j[0]], float)
        q_toe0 = float(self.q_stand[toe_qadr])
        R_toe_rel0 = A_R.T @ d.xmat[toe].reshape(3, 3)  # toe relative to ankle at stand
        # toe_rest_R: relative rotation at q_toe = 0
        toe_rest_R = R_toe_rel0 @ _exp_rot(-toe_axis * q_toe0)
        toe_rest_p = A_R.T @ (d.xpos[toe] - d.xpos[ankle])
        # the toe-rocker rotation Ry(phi) about the ground frame's lateral axis, seen in the
        # toe body frame, must be the toe hinge axis (or its negative)
        lateral_in_toe = (A0_R @ R_toe_rel0).T @ np.array([0.0, 1.0, 0.0])
        toe_sign = float(np.dot(lateral_in_toe, toe_axis))
        if abs(abs(toe_sign) - 1.0) > 1e-6:
            raise ValueError(f"{side} toe hinge is not the foot's lateral axis")

        pts_a, pts_t = [], []
        for body, pts in ((ankle, pts_a), (toe, pts_t)):
            for s in range(mj.nsite):
                if mj.site_bodyid[s] == body:
                    pts.append(np.array(mj.site_pos[s]))
            for g in range(mj.ngeom):
                if mj.geom_bodyid[g] == body and mj.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
                    R = _quat2mat(mj.geom_quat[g])
                    for sx in (-1, 1):
                        for sy in (-1, 1):
                            for sz in (-1, 1):
                                pts.append(mj.geom_pos[g] + R @ (mj.geom_size[g] * [sx, sy, sz]))
        chain = []
        for b in (hip, knee, ankle):
            js = [(np.array(mj.jnt_axis[j], float), np.array(mj.jnt_pos[j], float),
                   float(mj.qpos0[mj.jnt_qposadr[j]])) for j in self._hinges_of(b)]
            chain.append((np.array(mj.body_pos[b], float), _quat2mat(mj.body_quat[b]), js))
        return _Leg(
            chain=chain, side=side, hip_body=hip, ankle_body=ankle, toe_body=toe, ik_qadr=ik_qadr,
            ik_dof=ik_dof, toe_qadr=toe_qadr, pref_w=pref_w, hip_offset=hip_offset,
            A0_R=A0_R, A0_p=A0_p, heel_G=heel_G, toe_G=toe_G, ball_G=ball_G,
            toe_sign=toe_sign, q_toe0=q_toe0, toe_rest_R=toe_rest_R, toe_rest_p=toe_rest_p,
            toe_axis=toe_axis, pts_ankle=np.array(pts_a), pts_toe=np.array(pts_t), yaw0=yaw0,
        )

    # ---- foot geometry ----------------------------------------------------------------

    def stance_pose(self, leg: int, G, phi):
        """Ankle body pose and toe angle of a foot planted on ground frame ``G = (x, y, yaw)``,
        rocked by ``phi`` (< 0: about the heel contact point, toes up; > 0: about the ball of
        the foot, heel up, toes kept flat). Vectorised over leading dims of G / phi."""
        L = self.legs[leg]
        G = np.asarray(G, float)
        phi = np.asarray(phi, float)
        shape = np.broadcast_shapes(G.shape[:-1], phi.shape)
        G = np.broadcast_to(G, shape + (3,))
        phi = np.broadcast_to(phi, shape)
        pivot = np.where((phi < 0)[..., None], L.heel_G, L.ball_G)
        Rp = _ry(phi)
        R_loc = Rp @ L.A0_R
        p_loc = pivot + np.einsum("...ij,...j->...i", Rp, L.A0_p - pivot)
        RG = _rz(G[..., 2])
        R = RG @ R_loc
        p = np.einsum("...ij,...j->...i", RG, p_loc)
        p[..., 0] += G[..., 0]
        p[..., 1] += G[..., 1]
        toe = L.q_toe0 - L.toe_sign * np.maximum(phi, 0.0)
        return R, p, toe

    def foot_points(self, leg: int, R, p, toe):
        """World positions (..., n, 3) of the foot points for ankle pose (R, p) and toe angle."""
        L = self.legs[leg]
        pa = np.einsum("...ij,nj->...ni", R, L.pts_ankle) + p[..., None, :]
        Rt = R @ L.toe_rest_R @ _exp_rot(np.asarray(toe)[..., None] * L.toe_axis)
        pt0 = p + np.einsum("...ij,j->...i", R, L.toe_rest_p)
        pt = np.einsum("...ij,nj->...ni", Rt, L.pts_toe) + pt0[..., None, :]
        return np.concatenate([pa, pt], axis=-2)

    def contact_points_G(self, leg: int, G):
        """Heel and toe contact points (world) of a flat foot on ground frame G: (..., 2, 3)."""
        L = self.legs[leg]
        G = np.asarray(G, float)
        RG = _rz(G[..., 2])
        pts = np.einsum("...ij,nj->...ni", RG, np.stack([L.heel_G, L.toe_G]))
        pts[..., 0] += G[..., None, 0]
        pts[..., 1] += G[..., None, 1]
        return pts

    def stand_feet(self, x=0.0, y=0.0, yaw=0.0, width=None, toe_out=0.0):
        """Ground frames of both feet standing at (x, y) facing ``yaw``."""
        feet = []
        for i, L in enumerate(self.legs):
            side = 1.0 if i == 0 else -1.0
            if width is None:
                off = np.array([0.0, side * abs(L.heel_G[1] * 0 + self._stand_half_width())])
            else:
                off = np.array([0.0, side * width / 2])
            c, s = math.cos(yaw), math.sin(yaw)
            feet.append(np.array([x + c * off[0] - s * off[1], y + s * off[0] + c * off[1],
                                  yaw + side * toe_out]))
        return feet

    def _stand_half_width(self):
        return abs(self.legs[0].hip_offset[1])

    # ---- inverse kinematics -----------------------------------------------------------

    def leg_fk(self, leg: int, R_pel, p_pel, ql):
        """Ankle body pose and its Jacobian w.r.t. the 7 leg hinges, vectorised over frames.

        A numpy transcription of MuJoCo's ``mj_kinematics`` for the hinge chain pelvis -> hip
        -> knee -> ankle (``tests/test_synthetic.py`` checks it against MuJoCo C).
        Returns (R (B, 3, 3), p (B, 3), J (B, 6, 7): rows = linear, angular).
        """
        L = self.legs[leg]
        R, p = R_pel, p_pel
        axes, anchors = [], []
        col = 0
        for bpos, bR, joints in L.chain:
            p = p + np.einsum("bij,j->bi", R, bpos)
            R = R @ bR
            for axis, jpos, q0 in joints:
                anchor = p + np.einsum("bij,j->bi", R, jpos)
                axes.append(np.einsum("bij,j->bi", R, axis))
                anchors.append(anchor)
                R = R @ _exp_rot((ql[:, col] - q0)[:, None] * axis)
                p = anchor - np.einsum("bij,j->bi", R, jpos)
                col += 1
        aw = np.stack(axes, axis=-1)  # (B, 3, 7)
        an = np.stack(anchors, axis=-1)
        Jp = np.cross(aw, p[:, :, None] - an, axis=1)
        return R, p, np.concatenate([Jp, aw], axis=1)

    def solve_legs(self, q, R_t, p_t, iters=40, tol_p=1e-7, tol_r=5e-7, damping=1e-6, lower=None,
                   w_rot=None):
        """Leg IK for all frames at once, in place in ``q`` (T, nq), warm-started from the leg
        angles already in ``q``: damped Gauss-Newton with a trust region, a null-space pull
        towards no hip/ankle axial rotation, and clipping to the joint ranges.

        ``w_rot`` (2, T) weighs the orientation error against the position error (1 for
        planted feet; lower for swinging feet, whose position matters more).

        Returns (T, 2) residuals (max abs position error in metres) per frame and leg.
        """
        T = len(q)
        R_pel = _quat2mat(q[:, 3:7])
        p_pel = q[:, 0:3]
        res = np.zeros((T, 2))
        eye6 = np.eye(6) * damping
        for f, L in enumerate(self.legs):
            idx = L.ik_qadr
            lo, hi = (self.lower if lower is None else lower)[idx], self.upper[idx]
            ql = q[:, idx].copy()
            active = np.ones(T, bool)
            for _it in range(iters):
                a = np.nonzero(active)[0]
                if _DEBUG:
                    print("   leg", f, "iter", _it, "active", len(a))
                if len(a) == 0:
                    break
                R, p, J = self.leg_fk(f, R_pel[a], p_pel[a], ql[a])
                ep = p_t[f, a] - p
                er = _log_rot(R_t[f, a] @ np.swapaxes(R, -1, -2))
                conv = (np.max(np.abs(ep), axis=1) < tol_p) & (np.max(np.abs(er), axis=1) < tol_r)
                active[a[conv]] = False
                res[a, f] = np.max(np.abs(ep), axis=1)
                keep = ~conv
                a, J, ep, er = a[keep], J[keep], ep[keep], er[keep]
                if len(a) == 0:
                    break
                if w_rot is not None:
                    wr = w_rot[f, a][:, None]
                    er = er * wr
                    J = np.concatenate([J[:, :3], J[:, 3:] * wr[:, :, None]], axis=1)
                e = np.concatenate([ep, er], axis=1)
                Jt = np.swapaxes(J, -1, -2)
                W = np.linalg.solve(J @ Jt + eye6, np.broadcast_to(np.eye(6), (len(a), 6, 6)))
                Jpinv = Jt @ W  # (n, 7, 6)
                dq = np.einsum("nij,nj->ni", Jpinv, e)
                z = -0.5 * L.pref_w * ql[a]
                dq += z - np.einsum("nij,nj->ni", Jpinv, np.einsum("nij,nj->ni", J, z))
                big = np.max(np.abs(dq), axis=1, keepdims=True)
                dq *= np.minimum(1.0, 0.2 / np.maximum(big, 1e-12))
                new = np.clip(ql[a] + dq, lo, hi)
                stalled = np.max(np.abs(new - ql[a]), axis=1) < 1e-7  # at a limit / infeasible
                ql[a] = new
                active[a[stalled]] = False
            q[:, idx] = ql
        return res

    def fk(self, q):
        """Run kinematics at ``q`` in the scratch data; returns it."""
        self.d.qpos[:] = q
        mujoco.mj_kinematics(self.mj, self.d)
        return self.d


_CHAR_CACHE: dict[float, Character] = {}


def character(height_m: float) -> Character:
    """A cached :class:`Character` for a height (rounded to 1 cm)."""
    h = round(float(height_m), 2)
    ch = _CHAR_CACHE.get(h)
    if ch is None:
        mass = 22.0 * h * h  # BMI 22
        ch = Character(load_model(height_m=h, mass_kg=mass, with_mjx=False))
        if len(_CHAR_CACHE) > 64:
            _CHAR_CACHE.pop(next(iter(_CHAR_CACHE)))
        _CHAR_CACHE[h] = ch
    return ch


# =========================================================================================
# motion plan: stances (footsteps), segments (pelvis / upper-body tracks)
# =========================================================================================


@dataclass
class Stance:
    """One contact of one foot with the floor, on ground frame ``G = (x, y, yaw)``.

    ``phi`` knots (t, angle) rock the foot during the stance (< 0 about the heel contact
    point, > 0 about the ball of the foot); ``alpha`` knots (t, a) place the foot's share of the
    zero-moment point between heel (0) and toe (1). ``swing`` says how the foot moves after
    ``t_off`` until its next stance: ``{"mode": "world", "clear": m}`` (a swing between the
    two footsteps, lifted by ``clear``) or ``{"mode": "rel", "keys": [...], "tuck": m}``
    (relative to the pelvis heading frame: flights and kicks).
    """

    foot: int
    G: np.ndarray
    t_on: float
    t_off: float = math.inf
    phi: list = field(default_factory=list)
    alpha: list = field(default_factory=list)
    load: bool = True
    swing: dict | None = None

    def phi_at(self, t):
        return _Track(self.phi)(t) if self.phi else np.zeros(np.shape(t))

    def alpha_at(self, t):
        return _Track(self.alpha)(t) if self.alpha else np.full(np.shape(t), 0.3)


@dataclass
class Segment:
    kind: str
    t0: float
    t1: float
    fn: Callable[[np.ndarray], dict]  # times -> {"z", "yaw", "pitch", "roll", "upper", ...}
    info: dict = field(default_factory=dict)


class Plan:
    """A motion under construction: stances of both feet, segments, weight pins."""

    def __init__(self, ch: Character, rng: np.random.Generator, style: dict):
        self.ch = ch
        self.rng = rng
        self.style = style
        self.t = 0.0
        self.stances: tuple[list[Stance], list[Stance]] = ([], [])
        self.segments: list[Segment] = []
        self.lam_pins: list[tuple[float, float]] = []  # (t, share of the left foot)
        self.heading = 0.0
        self.z_rest = ch.z_stand - style["z_rest_drop"]

    # -- state -----------------------------------------------------------------------------
    def stance(self, foot: int) -> Stance:
        return self.stances[foot][-1]

    def feet(self):
        return [self.stance(0).G.copy(), self.stance(1).G.copy()]

    def mid(self):
        a, b = self.feet()
        return (a[:2] + b[:2]) / 2

    # -- footsteps -----------------------------------------------------------------------
    def start(self, feet, heading, alpha):
        for f in (0, 1):
            self.stances[f].append(Stance(f, np.asarray(feet[f], float), -math.inf,
                                          phi=[], alpha=[(0.0, alpha)]))
        self.heading = heading

    def lift(self, foot, t, phi_off=0.0, r_off=0.0, alpha_off=None, swing=None, alpha_flat=None):
        s = self.stance(foot)
        if t <= s.t_on:
            raise GenerationError("lift before landing")
        s.t_off = t
        if phi_off != 0.0 and r_off > 0:
            s.phi += [(t - r_off, 0.0), (t, phi_off)]
        elif phi_off != 0.0:
            raise GenerationError("a rocker needs a duration")
        if alpha_off is None:
            alpha_off = 1.0 if phi_off > 0 else (0.0 if phi_off < 0 else None)
        if alpha_flat is not None and r_off > 0:
            s.alpha.append((t - r_off, alpha_flat))
        if alpha_off is not None:
            s.alpha.append((t, alpha_off))
        s.swing = swing or {"mode": "world", "clear": 0.05 * self.ch.scale}

    def land(self, foot, G, t, phi_on=0.0, r_on=0.0, alpha_on=None, alpha_flat=None, load=True):
        prev = self.stance(foot)
        if t <= prev.t_off:
            raise GenerationError("landing before lift-off")
        s = Stance(foot, np.asarray(G, float), t, load=load)
        if phi_on != 0.0:
            if r_on <= 0:
                raise GenerationError("a rocker needs a duration")
            s.phi = [(t, phi_on), (t + r_on, 0.0)]
        if alpha_on is None:
            alpha_on = 1.0 if phi_on > 0 else (0.0 if phi_on < 0 else self.style["alpha"])
        s.alpha = [(t, alpha_on)]
        if alpha_flat is not None and r_on > 0:
            s.alpha.append((t + r_on, alpha_flat))
        self.stances[foot].append(s)
        return s

    def step(self, foot, G, t_lift, t_land, phi_off=0.0, r_off=0.0, phi_on=0.0, r_on=0.0,
             clear=None, swing=None, alpha_flat_off=None, alpha_flat_on=None, load=True):
        if swing is None:
            swing = {"mode": "world", "clear": (0.05 * self.ch.scale) if clear is None else clear}
        self.lift(foot, t_lift, phi_off, r_off, swing=swing, alpha_flat=alpha_flat_off)
        return self.land(foot, G, t_land, phi_on, r_on, alpha_flat=alpha_flat_on, load=load)

    def add_segment(self, kind, t0, t1, fn, **info):
        if t1 <= t0:
            raise GenerationError("empty segment")
        self.segments.append(Segment(kind, t0, t1, fn, info))
        self.t = t1


# -----------------------------------------------------------------------------------------
# upper body poses
# -----------------------------------------------------------------------------------------

_MIRROR_SIGN = {"x": -1.0, "y": 1.0, "z": -1.0}


def _upper_names(ch: Character) -> list[str]:
    legs = set()
    for L in ch.legs:
        legs.update(int(a) for a in L.ik_qadr)
        legs.add(L.toe_qadr)
    return [n for n, a in sorted(ch.qadr.items(), key=lambda kv: kv[1]) if a not in legs]


class Pose:
    """Upper-body hinge angles (radians) as a dict of (T,) arrays, with mirrored helpers.

    Arm angles are given for the *left* side's sign convention and mirrored for the right
    (x and z negated, y kept), as ``docs/model.md`` describes.
    """

    def __init__(self, names, T, base=None):
        self.names = names
        self.v = {n: np.zeros(T) for n in names}
        if base:
            for k, val in base.items():
                self.v[k] = self.v[k] + val

    def add(self, name, val):
        if name in self.v:
            self.v[name] = self.v[name] + val

    def add_sym(self, side, joint, axis, val):
        s = 1.0 if side == "left" else _MIRROR_SIGN[axis]
        self.add(f"{side}_{joint}_{axis}", s * np.asarray(val))

    def arm(self, side, down=0.0, fwd=0.0, twist=0.0, elbow=0.0, wrist=0.0, shrug=0.0, protract=0.0):
        """Arm relative to the T-pose: ``down`` lowers it (rad, pi/2 = at the side, < 0 raises it
        above the shoulder), ``fwd`` swings it forward, ``twist`` internal rotation, ``elbow``
        flexion, ``wrist`` flexion; collar ``shrug`` / ``protract``."""
        self.add_sym(side, "shoulder", "x", -np.asarray(down))
        self.add_sym(side, "shoulder", "z", -np.asarray(fwd))
        self.add_sym(side, "shoulder", "y", np.asarray(twist))
        self.add_sym(side, "elbow", "z", -np.asarray(elbow))
        self.add_sym(side, "wrist", "x", -np.asarray(wrist))
        self.add_sym(side, "collar", "x", np.asarray(shrug))
        self.add_sym(side, "collar", "z", -np.asarray(protract))

    def spine(self, flex=0.0, lat=0.0, twist=0.0):
        """Trunk flexion (forward), lateral bend (to the right), twist (to the left), split
        between the lumbar (spine1) and thoracic (spine3) joints."""
        self.add("spine1_y", 0.6 * np.asarray(flex))
        self.add("spine3_y", 0.4 * np.asarray(flex))
        self.add("spine1_x", 0.55 * np.asarray(lat))
        self.add("spine3_x", 0.45 * np.asarray(lat))
        self.add("spine1_z", 0.35 * np.asarray(twist))
        self.add("spine3_z", 0.65 * np.asarray(twist))

    def neck(self, flex=0.0, lat=0.0, turn=0.0):
        self.add("neck_y", np.asarray(flex))
        self.add("neck_x", np.asarray(lat))
        self.add("neck_z", np.asarray(turn))

    def array(self):
        return np.stack([self.v[n] for n in self.names], axis=1)


def _neutral(plan: Plan, T) -> Pose:
    st = plan.style
    P = Pose(plan.upper_names, T)
    for side in SIDES:
        P.arm(side, down=st["arm_down"], fwd=st["arm_fwd"], twist=st["arm_twist"], elbow=st["elbow"])
    P.spine(flex=st["spine_flex"])
    P.neck(flex=st["neck_flex"])
    return P


def _keys(t, knots):
    """PCHIP track through (time, value) knots evaluated at t."""
    return _Track(knots)(t)


def _ease(t, t0, t1):
    """0 before t0, smooth rise to 1 at t1."""
    if t1 <= t0:
        return (np.asarray(t) >= t0).astype(float)
    return _smoothstep((np.asarray(t) - t0) / (t1 - t0))


def _window(t, t0, t1, ramp):
    """1 inside [t0 + ramp, t1 - ramp], smooth ramps to 0 at t0 and t1."""
    ramp = max(min(ramp, (t1 - t0) / 2), 1e-6)
    return _ease(t, t0, t0 + ramp) * (1.0 - _ease(t, t1 - ramp, t1))


# =========================================================================================
# from plan to joint angles
# =========================================================================================


@dataclass
class Motion:
    """A kinematic motion: joint angles and its plan-level annotations (frame-aligned)."""

    q: np.ndarray  # (T, nq)
    fps: float
    planted: np.ndarray  # (T, 4) bool: planned contact of each contact site (CONTACT_SITES order)
    flight: np.ndarray  # (T,) bool: no foot on the floor
    kind: np.ndarray  # (T,) int index into MOTION_KINDS (the segment kind of each frame)
    character: Character
    com: np.ndarray  # (T, 3) whole-body centre of mass
    zmp_ref: np.ndarray  # (T, 2) planned zero-moment point (NaN in flight)
    info: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.q.shape[0])

    def slice(self, a: int, b: int) -> Motion:
        return dataclasses.replace(
            self, q=self.q[a:b], planted=self.planted[a:b], flight=self.flight[a:b],
            kind=self.kind[a:b], com=self.com[a:b], zmp_ref=self.zmp_ref[a:b],
        )


def _runs(mask):
    """(start, stop) index pairs of the True runs of a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(int))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0], strict=True))


def _flights(plan: Plan, t_end: float):
    """Continuous-time intervals with no foot on the floor."""
    iv = sorted((s.t_on, s.t_off) for f in (0, 1) for s in plan.stances[f])
    out = []
    cur_end = -math.inf
    for a, b in iv:
        if a > cur_end and cur_end > -math.inf:
            out.append((cur_end, a))
        cur_end = max(cur_end, b)
    if cur_end < t_end:
        raise GenerationError("plan ends with a foot in the air")
    return out


def _seg_eval(plan: Plan, t: float, key: str) -> float:
    for seg in plan.segments:
        if seg.t0 <= t <= seg.t1:
            return float(np.asarray(seg.fn(np.array([t]))[key])[0])
    raise GenerationError(f"no segment covers t = {t}")


def _z_profile(plan: Plan, t: np.ndarray, z_des: np.ndarray, flights) -> np.ndarray:
    """Pelvis height: the segments' desired height, a g-parabola in every flight, and C1
    corrections of the support phases next to a flight."""
    z = z_des.copy()
    eps = 1e-4
    bc = []  # (time, dv, side) velocity mismatches to fix at support-interval ends
    for a, b in flights:
        z0, z1 = _seg_eval(plan, a, "z"), _seg_eval(plan, b, "z")
        Tf = b - a
        v0 = (z1 - z0) / Tf + GRAVITY * Tf / 2
        v1 = v0 - GRAVITY * Tf
        m = (t > a) & (t < b)
        u = t[m] - a
        z[m] = z0 + v0 * u - 0.5 * GRAVITY * u * u
        d_before = (_seg_eval(plan, a, "z") - _seg_eval(plan, a - eps, "z")) / eps
        d_after = (_seg_eval(plan, b + eps, "z") - _seg_eval(plan, b, "z")) / eps
        bc.append((a, v0 - d_before, "end"))
        bc.append((b, v1 - d_after, "start"))
    # support intervals
    edges = [0.0] + [x for ab in flights for x in ab] + [max(t[-1], plan.t)]
    for s0, s1 in zip(edges[0::2], edges[1::2], strict=True):
        dv0 = next((dv for tt, dv, side in bc if side == "start" and abs(tt - s0) < 1e-9), 0.0)
        dv1 = next((dv for tt, dv, side in bc if side == "end" and abs(tt - s1) < 1e-9), 0.0)
        if dv0 == 0.0 and dv1 == 0.0:
            continue
        m = (t >= s0) & (t <= s1)
        tt = t[m]
        L = s1 - s0
        if L < 0.5:
            u = (tt - s0) / L
            z[m] += (u**3 - 2 * u**2 + u) * dv0 * L + (u**3 - u**2) * dv1 * L
        else:
            w = 0.25
            z[m] += dv0 * (tt - s0) * (1.0 - _ease(tt, s0, s0 + w))
            z[m] += dv1 * (tt - s1) * _ease(tt, s1 - w, s1)
    return z


def _load_share(plan: Plan, t, st_idx):
    """Share of the body weight on the left foot (NaN while no foot is loaded)."""
    N = len(t)
    loaded = np.zeros((2, N), bool)
    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            if s.load:
                loaded[f] |= st_idx[f] == j
    lam = np.full(N, np.nan)
    lam[loaded[0] & ~loaded[1]] = 1.0
    lam[~loaded[0] & loaded[1]] = 0.0
    pins = sorted(plan.lam_pins)
    r = 0.3
    for k0, k1 in _runs(loaded[0] & loaded[1]):
        a = t[k0 - 1] if k0 > 0 else t[k0]
        b = t[k1] if k1 < N else t[k1 - 1]
        va = lam[k0 - 1] if k0 > 0 and not np.isnan(lam[k0 - 1]) else 0.5
        vb = lam[k1] if k1 < N and not np.isnan(lam[k1]) else 0.5
        inner = [(pt, pv) for pt, pv in pins if a < pt < b]
        knots = [(a, va)] + inner + [(b, vb)]
        if not inner and b - a > 2 * r:
            knots = [(a, va), (a + r, 0.5), (b - r, 0.5), (b, vb)]
        lam[k0:k1] = _Track(knots)(t[k0:k1])
    return lam, loaded


def _com_filter(p_ref, support, z_com, intent, fps, c_start, c_end):
    """Horizontal COM trajectory (T, 2): its zero-moment point follows ``p_ref`` on support
    frames (linear inverted pendulum with the given COM height), ``c'' = 0`` in flight, least
    squares with small jerk and intent terms, at rest at both ends."""
    N = len(p_ref)
    dt = 1.0 / fps
    zdd = np.zeros(N)
    zdd[1:-1] = (z_com[:-2] - 2 * z_com[1:-1] + z_com[2:]) / dt**2
    beta = z_com / np.maximum(zdd + GRAVITY, 0.5)
    rows, cols, vals = [], [], []
    rhs = []
    r = 0

    def add(cs, vs, b):
        nonlocal r
        rows.extend([r] * len(cs))
        cols.extend(cs)
        vals.extend(vs)
        rhs.append(b)
        r += 1

    w_z, w_f, w_j, w_i, w_b = 1.0, 1.0 * dt**2, 2e-3 * dt**3, 0.03, 100.0
    for k in range(1, N - 1):
        if support[k] and not np.isnan(p_ref[k, 0]):
            bk = beta[k] / dt**2
            add([k - 1, k, k + 1], [-w_z * bk, w_z * (1 + 2 * bk), -w_z * bk], w_z * p_ref[k])
        else:
            add([k - 1, k, k + 1], [w_f / dt**2, -2 * w_f / dt**2, w_f / dt**2], np.zeros(2))
    for k in range(1, N - 2):
        add([k - 1, k, k + 1, k + 2], [-w_j / dt**3, 3 * w_j / dt**3, -3 * w_j / dt**3, w_j / dt**3],
            np.zeros(2))
    for k in range(N):
        add([k], [w_i], w_i * intent[k])
    add([0], [w_b], w_b * c_start)
    add([N - 1], [w_b], w_b * c_end)
    if N > 2:
        add([0, 1], [-w_b / dt, w_b / dt], np.zeros(2))
        add([N - 2, N - 1], [-w_b / dt, w_b / dt], np.zeros(2))
    A = sp.csr_matrix((vals, (rows, cols)), shape=(r, N))
    B = np.array(rhs)
    AtA = (A.T @ A).tocsc()
    return np.column_stack([spla.spsolve(AtA, A.T @ B[:, i]) for i in range(2)])


def _interp_rows(t, tq, X):
    """Linear interpolation of the rows of X (sampled at t) at times tq."""
    X = np.asarray(X)
    flat = X.reshape(len(t), -1)
    out = np.stack([np.interp(tq, t, flat[:, i]) for i in range(flat.shape[1])], axis=-1)
    return out.reshape(np.shape(tq) + X.shape[1:])


def _foot_targets(plan: Plan, t, st_idx, fb, lift):
    """Ankle targets of every stance and world-frame swing frame, with the extra heel raise
    ``fb`` (2, T) added to the planned rocker angles. Returns (R_t, p_t, toe_t, planted,
    P_zmp, rel_swings)."""
    ch = plan.ch
    N = len(t)
    R_t = np.tile(np.eye(3), (2, N, 1, 1))
    p_t = np.zeros((2, N, 3))
    toe_t = np.zeros((2, N))
    planted = np.zeros((N, 4), bool)
    P_zmp = np.zeros((2, N, 2))

    phi_max = min(1.1, -min(ch.lower[L.toe_qadr] for L in ch.legs) - 0.05)

    def phi_of(f, s, tq):
        return np.clip(s.phi_at(tq) + np.interp(tq, t, fb[f]), -0.6, phi_max)

    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            m = st_idx[f] == j
            if not m.any():
                continue
            ph = phi_of(f, s, t[m])
            R, p, toe = ch.stance_pose(f, s.G, ph)
            R_t[f, m], p_t[f, m], toe_t[f, m] = R, p, toe
            planted[m, 2 * f] = ph <= 0
            planted[m, 2 * f + 1] = ph >= 0
            pts = ch.contact_points_G(f, s.G)
            a = s.alpha_at(t[m])
            a = np.where(ph > 0.02, np.maximum(a, np.clip(ph / 0.1, 0, 1)), a)
            P_zmp[f, m] = (pts[0, :2] + a[:, None] * (pts[1, :2] - pts[0, :2]))
    rel = []
    for f in (0, 1):
        S = plan.stances[f]
        for j in range(len(S) - 1):
            a, b = S[j], S[j + 1]
            if a.swing.get("mode", "world") != "world":
                rel.append((f, j))
                continue
            m = (t > a.t_off) & (t < b.t_on) & (st_idx[f] < 0)
            if not m.any():
                continue
            R0, p0, k0 = ch.stance_pose(f, a.G, phi_of(f, a, np.array(a.t_off)))
            R1, p1, k1 = ch.stance_pose(f, b.G, phi_of(f, b, np.array(b.t_on)))
            s = (t[m] - a.t_off) / (b.t_on - a.t_off)
            h = _smoothstep(s)
            p = p0 + h[:, None] * (p1 - p0)
            p[:, 2] += a.swing.get("clear", 0.05) * _bump(s)
            R = _slerp_R(np.broadcast_to(R0, (len(s), 3, 3)), np.broadcast_to(R1, (len(s), 3, 3)), h)
            toe = k0 + _smoothstep(s / 0.5) * (k1 - k0)
            minz = ch.foot_points(f, R, p, toe)[..., 2].min(axis=-1)
            p[:, 2] += np.maximum(0.0, 0.002 * _bump(s) - minz) + lift[f, m]
            R_t[f, m], p_t[f, m], toe_t[f, m] = R, p, toe
    return R_t, p_t, toe_t, planted, P_zmp, rel


def _smooth_upper(x, fps, width_s=0.12):
    """A smooth envelope >= x (dilate, then a truncated Gaussian of the dilation radius)."""
    k = max(1, int(round(width_s * fps)))
    S = gaussian_filter1d(maximum_filter1d(x, size=2 * k + 1, mode="nearest"), sigma=k / 3.0,
                          truncate=3.0, mode="nearest")
    return np.maximum(S, x)


def _realize(plan: Plan, fps: float, n_pass: int = 8) -> Motion:
    ch = plan.ch
    T_end = plan.t
    N = int(math.floor(T_end * fps + 1e-9)) + 1
    t = np.arange(N) / fps
    names = plan.upper_names
    nu = len(names)
    upper_qadr = np.array([ch.qadr[n] for n in names])

    # ---- segment tracks ----
    z_des = np.zeros(N)
    yaw = np.zeros(N)
    pitch = np.zeros(N)
    roll = np.zeros(N)
    upper = np.zeros((N, nu))
    kind = np.zeros(N, int)
    for i, seg in enumerate(plan.segments):
        last = i == len(plan.segments) - 1
        m = (t >= seg.t0) & ((t < seg.t1) if not last else (t <= seg.t1 + 1e-9))
        if not m.any():
            continue
        out = seg.fn(t[m])
        z_des[m] = out["z"]
        yaw[m] = out["yaw"]
        pitch[m] = out.get("pitch", 0.0)
        roll[m] = out.get("roll", 0.0)
        upper[m] = out["upper"]
        kind[m] = MOTION_KINDS.index(seg.kind)
    yaw = np.unwrap(yaw)
    upper = np.clip(upper, ch.lower[upper_qadr], ch.upper[upper_qadr])
    R_pel = _rz(yaw) @ _ry(pitch) @ _rx(roll)

    # ---- stances, flights, pelvis height ----
    st_idx = -np.ones((2, N), int)
    for f in (0, 1):
        for j, s in enumerate(plan.stances[f]):
            st_idx[f, (t >= s.t_on - 1e-9) & (t <= s.t_off + 1e-9)] = j
    flights = _flights(plan, T_end)
    flight = (st_idx[0] < 0) & (st_idx[1] < 0)
    z0 = _z_profile(plan, t, z_des, flights)
    lam, loaded = _load_share(plan, t, st_idx)
    support = ~np.isnan(lam)

    q = np.tile(ch.q_stand, (N, 1))
    q[:, upper_qadr] = upper
    q[:, 3:7] = _continuous_quats(_mat2quat(R_pel))
    off = np.einsum("tij,j->ti", R_pel, ch.com0)
    fb = np.zeros((2, N))  # extra heel raise where the ankle cannot dorsiflex enough
    lift = np.zeros((2, N))  # extra swing-foot lift where the solved foot dips below the floor
    swing_w = np.zeros((2, N))  # 0 at the ends of each swing, 1 inside
    for f in (0, 1):
        for a, b in _runs(st_idx[f] < 0):
            ta, tb = (t[a - 1] if a > 0 else t[a]), (t[b] if b < N else t[b - 1])
            u = (t[a:b] - ta) / max(tb - ta, 1e-9)
            swing_w[f, a:b] = _smoothstep(u / 0.2) * _smoothstep((1 - u) / 0.2)
    relaxed = ch.lower.copy()
    for L in ch.legs:
        relaxed[L.ik_qadr[4]] = -1.2  # ankle_y (dorsiflexion) relaxed while measuring the need
    info = {"flights": flights}
    intent = None
    for it in range(n_pass):
        R_t, p_t, toe_t, planted, P_zmp, rel = _foot_targets(plan, t, st_idx, fb, lift)
        world = np.ones((2, N), bool)  # legs with world-frame targets (stances and world swings)
        for f, j in rel:
            S_ = plan.stances[f]
            world[f] &= ~((t > S_[j].t_off) & (t < S_[j + 1].t_on))
        world |= st_idx >= 0
        p_ref = np.full((N, 2), np.nan)
        p_ref[support] = (lam[support, None] * P_zmp[0, support]
                          + (1 - lam[support, None]) * P_zmp[1, support])
        if intent is None:
            intent = p_ref.copy()
            for i in range(2):
                ok = ~np.isnan(intent[:, i])
                intent[:, i] = np.interp(t, t[ok], intent[ok, i])
            intent = gaussian_filter1d(intent, sigma=0.25 * fps, axis=0, mode="nearest")
        z_com = z0 + off[:, 2]
        c = _com_filter(p_ref, support, z_com, intent, fps, intent[0], intent[-1])
        pel = np.column_stack([c - off[:, :2], z0])
        _rel_swings(plan, ch, t, pel, yaw, rel, st_idx, R_t, p_t, toe_t, lift)
        dz = _reach_fix(ch, pel, R_pel, p_t, world, flights, t, fps)
        pel[:, 2] = _limit_fall(t, pel[:, 2] - dz, flights, 0.6 * GRAVITY)
        _rel_swings(plan, ch, t, pel, yaw, rel, st_idx, R_t, p_t, toe_t, lift)
        for f, L in enumerate(ch.legs):
            q[:, L.toe_qadr] = toe_t[f]
        q[:, 0:3] = pel
        com, err = _solve_all(ch, q, R_t, p_t, planted, first=(it == 0), lower=relaxed)
        # feedback: heel raise where the ankle would dorsiflex beyond its range, swing-foot lift
        # where the solved foot dips below the floor
        clean = True
        for f, L in enumerate(ch.legs):
            a = L.ik_qadr[4]
            excess = np.maximum(ch.lower[a] + 0.02 - q[:, a], 0.0)
            excess[st_idx[f] < 0] = 0.0
            if np.any(q[:, a] < ch.lower[a] - 1e-9):
                clean = False
            if np.any(excess > 0):
                fb[f] += 1.5 * _smooth_upper(excess, fps)
            R_a, p_a, _ = ch.leg_fk(f, R_pel, q[:, 0:3], q[:, L.ik_qadr])
            minz = ch.foot_points(f, R_a, p_a, q[:, L.toe_qadr])[..., 2].min(axis=-1)
            need = np.where(st_idx[f] < 0, np.maximum(0.004 - minz, 0.0), 0.0)
            if np.any(np.where(st_idx[f] < 0, minz, 1.0) < 0.0):
                clean = False
            if np.any(need > 0):
                lift[f] += _smooth_upper(need, fps, 0.08) * swing_w[f]
        new_off = com - pel
        info["com_change"] = float(np.max(np.abs(new_off[:, :2] - off[:, :2])))
        off = new_off
        info["ik_err"] = err
        info["passes"] = it + 1
        if clean and it >= 2:
            break
        if it >= 3 and err > 0.01:
            raise GenerationError(f"leg IK cannot place the planted feet (residual {err:.3f} m)")
    for L in ch.legs:
        q[:, L.ik_qadr] = np.clip(q[:, L.ik_qadr], ch.lower[L.ik_qadr], ch.upper[L.ik_qadr])
    info["zmp_com"] = c
    info["heel_raise_fb"] = float(fb.max())
    info["swing_lift_fb"] = float(lift.max())
    return Motion(q=q, fps=fps, planted=planted, flight=flight, kind=kind, character=ch,
                  com=com, zmp_ref=p_ref, info=info)


def _rel_swings(plan, ch, t, pel, yaw, swings, st_idx, R_t, p_t, toe_t, lift):
    for f, j in swings:
        S = plan.stances[f]
        a, b = S[j], S[j + 1]
        m = (t > a.t_off) & (t < b.t_on) & (st_idx[f] < 0)
        if not m.any():
            continue
        sw = a.swing

        def H(tq):
            pp = _interp_rows(t, np.atleast_1d(tq), pel)
            yy = np.interp(np.atleast_1d(tq), t, yaw)
            return _rz(yy), pp

        R0, p0, k0 = ch.stance_pose(f, a.G, a.phi_at(a.t_off))
        R1, p1, k1 = ch.stance_pose(f, b.G, b.phi_at(b.t_on))
        HR0, Hp0 = H(a.t_off)
        HR1, Hp1 = H(b.t_on)
        rel0 = (HR0[0].T @ R0, HR0[0].T @ (p0 - Hp0[0]), k0)
        rel1 = (HR1[0].T @ R1, HR1[0].T @ (p1 - Hp1[0]), k1)
        keys = [(0.0, rel0)] + [(k["s"], (k["R"], k["p"], k["toe"])) for k in sw.get("keys", [])] + [(1.0, rel1)]
        s = (t[m] - a.t_off) / (b.t_on - a.t_off)
        Rr = np.zeros((len(s), 3, 3))
        pr = np.zeros((len(s), 3))
        kr = np.zeros(len(s))
        for (sa, (Ra, pa, ka)), (sb, (Rb, pb, kb)) in zip(keys[:-1], keys[1:], strict=True):
            mm = (s >= sa) & (s <= sb)
            if not mm.any():
                continue
            h = _smoothstep((s[mm] - sa) / (sb - sa))
            Rr[mm] = _slerp_R(np.broadcast_to(Ra, (mm.sum(), 3, 3)), np.broadcast_to(Rb, (mm.sum(), 3, 3)), h)
            pr[mm] = pa + h[:, None] * (pb - pa)
            kr[mm] = ka + h * (kb - ka)
        pr[:, 2] += sw.get("tuck", 0.0) * _bump(s)
        HR, Hp = H(t[m])
        R = HR @ Rr
        p = Hp + np.einsum("tij,tj->ti", HR, pr)
        minz = ch.foot_points(f, R, p, kr)[..., 2].min(axis=-1)
        p[:, 2] += np.maximum(0.0, 0.002 * _bump(s) - minz) + lift[f, m]
        R_t[f, m], p_t[f, m], toe_t[f, m] = R, p, kr


def _reach_fix(ch, pel, R_pel, p_t, world, flights, t, fps):
    """How much to lower the pelvis (T,) so both ankles are within 99.5% of the leg length;
    smooth, >= the need at every frame, and affine (parabola-preserving) inside flights."""
    r = 0.995 * ch.reach
    need = np.zeros(len(t))
    for f, L in enumerate(ch.legs):
        hip = pel + np.einsum("tij,j->ti", R_pel, L.hip_offset)
        v = hip - p_t[f]
        h2 = v[:, 0] ** 2 + v[:, 1] ** 2
        dist = np.sqrt(h2 + v[:, 2] ** 2)
        bad = (dist > r) & world[f]
        if np.any(bad & (h2 >= r * r)):
            raise GenerationError("a foot target is out of reach horizontally")
        nd = np.where(bad, v[:, 2] - np.sqrt(np.maximum(r * r - h2, 0.0)), 0.0)
        need = np.maximum(need, nd)
    if not np.any(need > 0):
        return need
    for a, b in flights:  # a flight's need moves to its ends (the correction is affine inside)
        m = (t > a) & (t < b)
        if m.any() and need[m].max() > 0:
            top = need[m].max()
            need[m] = 0.0
            ia = int(np.nonzero(t <= a)[0][-1]) if np.any(t <= a) else 0
            ib = int(np.nonzero(t >= b)[0][0]) if np.any(t >= b) else len(t) - 1
            need[ia] = max(need[ia], top)
            need[ib] = max(need[ib], top)
    S = _smooth_upper(need, fps, 0.06)
    for a, b in flights:
        m = (t > a) & (t < b)
        if m.any():
            ia = max(np.nonzero(t <= a)[0][-1], 0) if np.any(t <= a) else 0
            ib = np.nonzero(t >= b)[0][0] if np.any(t >= b) else len(t) - 1
            S[m] = np.interp(t[m], [t[ia], t[ib]], [S[ia], S[ib]])
    return S


def _semiconvex_minorant(t, z, a):
    """The largest function <= z (sampled at t) whose second derivative is >= -a: the lower
    convex hull of z + a t^2 / 2, minus a t^2 / 2. Keeps a height profile from accelerating
    downwards faster than ``a`` (the floor can push, not pull)."""
    y = z + 0.5 * a * t * t
    hull = []
    for i in range(len(t)):
        while len(hull) >= 2:
            i0, i1 = hull[-2], hull[-1]
            # drop i1 if it lies above the segment i0 -> i
            if (y[i1] - y[i0]) * (t[i] - t[i0]) >= (y[i] - y[i0]) * (t[i1] - t[i0]):
                hull.pop()
            else:
                break
        hull.append(i)
    yh = np.interp(t, t[hull], y[hull])
    return yh - 0.5 * a * t * t


def _limit_fall(t, z, flights, a):
    """Apply :func:`_semiconvex_minorant` on every support interval (flights stay ballistic)."""
    z = z.copy()
    edges = [t[0] - 1.0] + [x for ab in flights for x in ab] + [t[-1] + 1.0]
    for s0, s1 in zip(edges[0::2], edges[1::2], strict=True):
        m = np.nonzero((t >= s0) & (t <= s1))[0]
        if len(m) > 2:
            z[m] = _semiconvex_minorant(t[m], z[m], a)
    return z


def _solve_all(ch: Character, q, R_t, p_t, planted, first: bool, lower=None):
    """Leg IK for every frame, in place; returns (com (T, 3), max planted-foot residual (m))."""
    N = len(q)
    if first:
        init = np.array([-0.2, 0.0, 0.0, 0.4, -0.2, 0.0, 0.0])
        for L in ch.legs:
            q[:, L.ik_qadr] = np.clip(init, ch.lower[L.ik_qadr], ch.upper[L.ik_qadr])
    w_rot = np.where(np.stack([planted[:, 0] | planted[:, 1], planted[:, 2] | planted[:, 3]]), 1.0, 0.3)
    res = ch.solve_legs(q, R_t, p_t, lower=lower, w_rot=w_rot)
    if _DEBUG:
        print("ik: frames not converged", int(np.sum(np.max(res, axis=1) > 1e-6)), "of", N)
    # frames whose planted feet did not converge: restart from a converged neighbour
    pl = np.stack([planted[:, 0] | planted[:, 1], planted[:, 2] | planted[:, 3]], axis=1)
    for _ in range(3):
        r_pl = np.max(np.where(pl, res, 0.0), axis=1)
        bad = np.nonzero(r_pl > 1e-6)[0]
        if len(bad) == 0:
            break
        good = np.nonzero(r_pl <= 1e-6)[0]
        if len(good) == 0:
            break
        nb = good[np.clip(np.searchsorted(good, bad), 0, len(good) - 1)]
        sub = q[bad].copy()
        for L in ch.legs:
            sub[:, L.ik_qadr] = q[nb[:, None], L.ik_qadr[None, :]]
        r2 = ch.solve_legs(sub, R_t[:, bad], p_t[:, bad], iters=60, lower=lower, w_rot=w_rot[:, bad])
        better = np.max(np.where(pl[bad], r2, 0), axis=1) < r_pl[bad]
        q[bad[better]] = sub[better]
        res[bad[better]] = r2[better]
    com = np.zeros((N, 3))
    d = ch.d
    for k in range(N):
        d.qpos[:] = q[k]
        mujoco.mj_kinematics(ch.mj, d)
        mujoco.mj_comPos(ch.mj, d)
        com[k] = d.subtree_com[ch.pelvis]
    worst = float(np.max(np.where(pl, res, 0.0))) if N else 0.0
    return com, worst


# =========================================================================================
# motion segments
# =========================================================================================


def _style(rng: np.random.Generator, ch: Character) -> dict:
    """Per-clip personal style: neutral posture, stance width, ..."""
    s = ch.scale
    return dict(
        arm_down=rng.uniform(1.30, 1.50),
        arm_fwd=rng.uniform(-0.05, 0.15),
        arm_twist=rng.uniform(-0.2, 0.2),
        elbow=rng.uniform(0.08, 0.35),
        spine_flex=rng.uniform(-0.04, 0.10),
        neck_flex=rng.uniform(-0.08, 0.12),
        width=rng.uniform(0.14, 0.22) * s,
        toe_out=rng.uniform(0.0, 0.18),
        alpha=rng.uniform(0.15, 0.4),
        z_rest_drop=rng.uniform(0.002, 0.008) * s,
        arm_swing=rng.uniform(0.6, 1.3),
    )


def _heading_of(feet) -> float:
    a, b = feet
    # mean facing of the two feet (toe-out cancels)
    return math.atan2(math.sin(a[2]) + math.sin(b[2]), math.cos(a[2]) + math.cos(b[2]))


def _place(mid, facing, side_sign, width, toe_out, forward=0.0):
    """Ground frame of a foot beside a point ``mid`` (on a line facing ``facing``)."""
    c, s = math.cos(facing), math.sin(facing)
    lat = side_sign * width / 2
    return np.array([mid[0] + c * forward - s * lat, mid[1] + s * forward + c * lat,
                     facing + side_sign * toe_out])


def _sgn(foot):
    return 1.0 if foot == 0 else -1.0


def _gesture(plan: Plan, P: Pose, u, dur, name, side, rng_vals):
    """Add an arm/head gesture to pose P over local times u in [0, dur]."""
    st = plan.style
    ramp = min(0.6, dur / 3)
    w = _window(u, 0.0, dur, ramp)
    a = rng_vals
    nd = st["arm_down"]
    if name == "wave":
        P.arm(side, down=w * (-a[0] - nd), twist=w * (-1.35 - st["arm_twist"]),
              elbow=w * (a[1] - st["elbow"]))
        P.add_sym(side, "elbow", "z", -w * 0.35 * np.sin(2 * np.pi * a[2] * u))
        P.neck(turn=w * _sgn(0 if side == "left" else 1) * 0.3)
    elif name == "reach":
        sides = SIDES if a[3] > 0.5 else (side,)
        for sd in sides:
            P.arm(sd, fwd=w * (a[0] * 1.2 + 0.8 - st["arm_fwd"]), elbow=w * (0.05 - st["elbow"]))
        P.spine(flex=w * 0.15 * a[1])
    elif name == "arms_up":
        for sd in SIDES:
            P.arm(sd, down=w * (-1.15 - 0.3 * a[0] - nd), elbow=w * (0.1 - st["elbow"]))
        P.spine(flex=-w * 0.1)
        P.neck(flex=-w * 0.2 * a[1])
    elif name == "cross":
        for sd in SIDES:
            P.arm(sd, fwd=w * (1.2 + 0.3 * a[0] - st["arm_fwd"]), elbow=w * (1.7 + 0.3 * a[1] - st["elbow"]),
                  twist=w * 0.3)
    elif name == "hips":
        for sd in SIDES:
            P.arm(sd, down=w * (0.95 - nd), fwd=w * (-0.35 - st["arm_fwd"]), twist=w * 0.9,
                  elbow=w * (1.6 - st["elbow"]))
    elif name == "look":
        P.neck(turn=w * (a[0] - 0.5) * 1.6 * np.sin(np.pi * u / dur), flex=w * (a[1] - 0.5) * 0.4)
        P.spine(twist=w * (a[0] - 0.5) * 0.6 * np.sin(np.pi * u / dur))
    elif name == "stretch":
        for sd in SIDES:
            P.arm(sd, down=w * (-1.3 - nd), elbow=w * (0.05 - st["elbow"]))
        P.spine(lat=w * (a[0] - 0.5) * 0.6 * np.sin(2 * np.pi * u / dur))
    elif name == "circles":
        f = 0.6 + 0.6 * a[1]
        for sd in SIDES:
            P.arm(sd, down=w * (0.1 * np.sin(2 * np.pi * f * u) - nd + 0.2 * a[0]),
                  fwd=w * 0.35 * np.cos(2 * np.pi * f * u), elbow=w * (0.05 - st["elbow"]))
    elif name == "clap":
        f = 1.2 + 1.2 * a[1]
        osc = 0.5 - 0.5 * np.cos(2 * np.pi * f * u)
        for sd in SIDES:
            P.arm(sd, fwd=w * (1.25 - st["arm_fwd"] + 0.25 * osc), elbow=w * (0.5 - st["elbow"] + 0.4 * osc),
                  twist=w * 0.8)
    elif name == "point":
        P.arm(side, down=w * (1.45 - 0.5 * a[0] - nd), fwd=w * (1.45 - st["arm_fwd"]), elbow=-w * st["elbow"])
        P.neck(turn=w * 0.2 * (1 if side == "left" else -1))


GESTURES = ("wave", "reach", "arms_up", "cross", "hips", "look", "stretch", "circles", "clap", "point")


def seg_stand(plan: Plan, dur: float | None = None, gestures: bool = True, kind: str = "stand"):
    """Standing: weight shifts, small knee bends, arm gestures."""
    rng = plan.rng
    dur = float(rng.uniform(2.0, 4.5) if dur is None else dur)
    t0, t1 = plan.t, plan.t + dur
    heading = _heading_of(plan.feet())
    plan.heading = heading
    if gestures:
        for _ in range(int(rng.integers(0, 3))):
            plan.lam_pins.append((t0 + float(rng.uniform(0.35, max(0.4, dur - 0.35))),
                                  float(rng.uniform(0.3, 0.7))))
    plan.lam_pins.append((t1, 0.5))
    gs = []
    if gestures and dur > 1.2:
        n = 1 if dur < 3.0 else int(rng.integers(1, 3))
        edges = np.sort(rng.uniform(0, dur, n - 1)) if n > 1 else np.array([])
        bounds = np.concatenate([[0.0], edges, [dur]])
        for i in range(n):
            if bounds[i + 1] - bounds[i] > 1.0:
                gs.append((bounds[i], bounds[i + 1], GESTURES[int(rng.integers(len(GESTURES)))],
                           SIDES[int(rng.integers(2))], rng.uniform(0, 1, 4)))
    bend = float(rng.uniform(0.0, 0.04)) * plan.ch.scale if gestures else 0.0
    z_rest = plan.z_rest

    def fn(t):
        u = t - t0
        P = _neutral(plan, len(t))
        for a, b, name, side, vals in gs:
            m = (u >= a) & (u <= b)
            if m.any():
                sub = Pose(P.names, len(t))
                _gesture(plan, sub, np.where(m, u - a, 0.0), b - a, name, side, vals)
                for k in P.v:
                    P.v[k] = P.v[k] + np.where(m, sub.v[k], 0.0)
        z = z_rest - bend * np.sin(np.pi * np.clip(u / dur, 0, 1)) ** 2
        return dict(z=z, yaw=np.full(len(t), heading), upper=P.array())

    plan.add_segment(kind, t0, t1, fn, gestures=[g[2] for g in gs])


def _interp_extrap(t, tp, fp):
    """Piecewise-linear interpolation, extrapolated linearly beyond the ends."""
    t = np.asarray(t, float)
    if len(tp) == 1:
        return np.full(t.shape, fp[0])
    out = np.interp(t, tp, fp)
    lo, hi = t < tp[0], t > tp[-1]
    out[lo] = fp[0] + (t[lo] - tp[0]) * (fp[1] - fp[0]) / (tp[1] - tp[0])
    out[hi] = fp[-1] + (t[hi] - tp[-1]) * (fp[-1] - fp[-2]) / (tp[-1] - tp[-2])
    return out


def _gait_timing(v, run=False):
    """(step period, stance duration, swing time) of a walking or running step at speed v."""
    if not run:
        cad = float(np.clip(1.05 + 0.6 * v, 1.3, 2.3))
        Ts = 1.0 / cad
        ds = float(np.clip(0.12 + 0.14 * (1.3 - v), 0.07, 0.22))
        return Ts, Ts + ds, Ts - ds
    cad = float(np.clip(2.45 + 0.12 * v, 2.6, 3.1))
    Ts = 1.0 / cad
    tc = float(np.clip(0.36 - 0.04 * v, 0.17, 0.29))
    return Ts, tc, 2 * Ts - tc


def seg_locomotion(plan: Plan, run: bool = False, backward: bool = False):
    """Walking (forwards or backwards) or running, with speed ramps and turns, from standing
    to standing."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    if run:
        v = float(rng.uniform(2.0, 4.2))
        n = int(rng.integers(8, 15))
    elif backward:
        v = float(rng.uniform(0.4, 0.95))
        n = int(rng.integers(4, 9))
    else:
        v = float(rng.uniform(0.6, 1.7))
        n = int(rng.integers(4, 12))
    v *= math.sqrt(s)
    turn = 0.0
    if rng.uniform() < 0.5:
        turn = float(rng.uniform(-1.0, 1.0) * (0.6 if backward else (1.2 if run else 1.8)))
    width = st["width"] * (0.8 if run else 1.0) + float(rng.uniform(-0.02, 0.02)) * s
    toe_out = st["toe_out"]
    facing0 = _heading_of(plan.feet())
    path_dir0 = facing0 + (math.pi if backward else 0.0)
    f1 = int(rng.integers(2))
    # per-step speeds: ramp up over the first steps, down over the last ones
    n_ramp = max(2, int(math.ceil(v / (0.75 * math.sqrt(s)))))
    n = max(n, 2 * n_ramp + 2)
    speeds = []
    for k in range(1, n + 1):
        up = min(1.0, k / (n_ramp + 1))
        down = min(1.0, (n - k + 0.5) / (n_ramp + 0.5))
        vk = max(0.45 * math.sqrt(s), v * min(up, down))
        speeds.append(vk)
    mid = plan.mid()
    P_prev = np.array(mid)
    t_lift = t0 + float(rng.uniform(0.3, 0.5))
    prev_land = None
    heel = -float(rng.uniform(0.12, 0.22)) * (0.6 if run else 1.0)
    toe_off = float(rng.uniform(0.25, 0.4)) if not run else float(rng.uniform(0.35, 0.55))
    back_land = float(rng.uniform(0.12, 0.22))
    back_lift = -float(rng.uniform(0.08, 0.18))
    psi = path_dir0
    steps = []
    for k in range(1, n + 1):
        vk = speeds[k - 1]
        is_run = run and vk > 1.9 * math.sqrt(s)
        Ts, Tc, Tsw = _gait_timing(vk / math.sqrt(s), is_run)
        Tsw = min(Tsw, 0.6)
        if prev_land is not None:
            # the other foot landed at prev_land; this foot lifts Tc - Ts later (< 0: flight),
            # with the gait timing of the previous step
            pTc, pTs = steps[-1]["Tc"], steps[-1]["Ts"]
            t_lift = prev_land + (pTc - pTs)
            t_lift = max(t_lift, steps[-2]["land"] + 0.12 if len(steps) >= 2 else t_lift)
        last = k == n
        frac = (k - 1) / max(n - 2, 1)
        psi = path_dir0 + turn * float(_smoothstep(np.array(min(frac, 1.0))))
        Lk = 0.0 if last else vk * Ts
        if k == 1:
            Lk *= 0.6
        psi_bar = psi
        P = P_prev + Lk * np.array([math.cos(psi_bar), math.sin(psi_bar)])
        foot = f1 if k % 2 == 1 else 1 - f1
        facing = psi + (math.pi if backward else 0.0)
        G = _place(P, facing, _sgn(foot), width, toe_out)
        if last:
            Tsw = max(Tsw, 0.35)
        t_land = t_lift + Tsw
        steps.append(dict(foot=foot, G=G, lift=t_lift, land=t_land, Tc=Tc, Ts=Ts, run=is_run, v=vk))
        P_prev = P
        prev_land = t_land
    # emit stances
    for i, sd in enumerate(steps):
        foot = sd["foot"]
        prev = plan.stance(foot)
        stance_len = sd["lift"] - (prev.t_on if prev.t_on > -math.inf else sd["lift"] - 1.0)
        is_run = sd["run"]
        if backward:
            phi_off, r_off = back_lift, min(0.3 * stance_len, 0.2)
            phi_on, r_on = back_land, min(0.22, 0.5 * sd["Tc"])
            a_off, a_on = 0.25, 0.75
        else:
            phi_off = toe_off * (0.5 if i == 0 else 1.0)
            r_off = min((0.55 if is_run else 0.4) * stance_len, 0.3)
            phi_on = heel if i < len(steps) - 1 else heel * 0.5
            if is_run and rng.uniform() < 0.5:
                phi_on = 0.0  # mid-foot strike
            r_on = min(0.1, 0.3 * sd["Tc"]) if phi_on != 0.0 else 0.0
            a_off, a_on = 0.8, 0.3
        clear = ((0.05 + 0.025 * sd["v"]) if not is_run else (0.08 + 0.04 * sd["v"])) * s
        swing = {"mode": "world", "clear": clear}
        plan.step(foot, sd["G"], sd["lift"], sd["land"], phi_off=phi_off, r_off=r_off,
                  phi_on=phi_on, r_on=r_on, swing=swing, alpha_flat_off=a_off, alpha_flat_on=a_on)
    t_end = steps[-1]["land"] + float(rng.uniform(0.35, 0.6))
    plan.lam_pins.append((t_end, 0.5))
    facing_end = _heading_of(plan.feet())
    # gait phase: 0 at a left landing, pi at a right landing (linear between landings)
    land_t = np.array([sd["land"] for sd in steps])
    ph = (0.0 if steps[0]["foot"] == 0 else math.pi) + math.pi * np.arange(len(steps))
    facing_knots = [(t0, facing0)]
    f_prev = facing0
    for sd in steps:
        f_now = sd["G"][2] - _sgn(sd["foot"]) * toe_out
        f_now = f_prev + _wrap(f_now - f_prev)
        facing_knots.append((sd["land"], (f_now + f_prev) / 2 if sd is not steps[0] else f_prev))
        f_prev = f_now
    facing_knots.append((t_end, f_prev + _wrap(facing_end - f_prev)))
    env_a, env_b = steps[0]["lift"] - 0.1, steps[-1]["land"] + 0.1
    vmax = max(sd["v"] for sd in steps)
    A_rot = (0.04 + 0.04 * min(vmax, 2.0)) * (0.6 if backward else 1.0)
    A_roll = 0.02 + 0.02 * min(vmax, 2.0)
    A_arm = st["arm_swing"] * (0.12 + 0.14 * min(vmax, 2.0)) * (0.5 if backward else 1.0)
    lean = (float(rng.uniform(0.02, 0.08)) + (0.04 * min(vmax, 4.0) if run else 0.0)) * (-0.5 if backward else 1.0)
    tilt = float(rng.uniform(0.08, 0.16))  # anterior pelvic tilt while walking, undone by the spine
    z_rest = plan.z_rest
    z_loco = z_rest - 0.015 * s if not run else z_rest - 0.03 * s
    run_elbow = float(rng.uniform(1.2, 1.6))

    def fn(t):
        env = _window(t, env_a, env_b, 0.5)
        phase = _interp_extrap(t, land_t, ph)
        c = np.cos(phase)
        yaw = _keys(t, facing_knots) - env * A_rot * c
        roll = env * A_roll * np.sin(phase)
        pitch = env * (lean + tilt)
        P = _neutral(plan, len(t))
        P.arm("left", fwd=-env * A_arm * c)
        P.arm("right", fwd=env * A_arm * c)
        if run:
            P.arm("left", elbow=env * (run_elbow - st["elbow"] + 0.25 * c), down=-env * 0.15)
            P.arm("right", elbow=env * (run_elbow - st["elbow"] - 0.25 * c), down=-env * 0.15)
        else:
            P.arm("left", elbow=env * 0.15 * A_arm * (1 + c))
            P.arm("right", elbow=env * 0.15 * A_arm * (1 - c))
        P.spine(twist=env * 0.8 * A_rot * c, flex=env * (lean * 0.5 - tilt))
        P.neck(turn=-env * 0.2 * A_rot * c, flex=-env * lean)
        z = z_rest + (z_loco - z_rest) * _window(t, t0, t_end, 0.4)
        return dict(z=z, yaw=yaw, pitch=pitch, roll=roll, upper=P.array())

    kind = "run" if run else "walk"
    plan.add_segment(kind, t0, t_end, fn, speed=v, backward=backward, turn=turn, steps=n)
    plan.heading = facing_end


def _hermite(t, ta, tb, za, va, zb, vb):
    """Cubic Hermite from (za, va) at ta to (zb, vb) at tb."""
    L = tb - ta
    u = np.clip((np.asarray(t) - ta) / L, 0.0, 1.0)
    h00 = 2 * u**3 - 3 * u**2 + 1
    h10 = u**3 - 2 * u**2 + u
    h01 = -2 * u**3 + 3 * u**2
    h11 = u**3 - u**2
    return h00 * za + h10 * L * va + h01 * zb + h11 * L * vb


class _Piecewise:
    """A scalar function of time made of pieces (t0, t1, f); the last piece extends."""

    def __init__(self):
        self.pieces = []

    def add(self, t0, t1, f):
        self.pieces.append((t0, t1, f))
        return t1

    def __call__(self, t):
        t = np.asarray(t, float)
        out = np.zeros(t.shape)
        for i, (a, b, f) in enumerate(self.pieces):
            last = i == len(self.pieces) - 1
            m = (t >= a) & ((t < b) if not last else np.ones(t.shape, bool))
            if i == 0:
                m |= t < a
            if m.any():
                out[m] = f(t[m])
        return out


def _const(v):
    return lambda t: np.full(np.shape(t), float(v))


def _ramp(ta, tb, za, zb):
    return lambda t: za + (zb - za) * _smoothstep((np.asarray(t) - ta) / max(tb - ta, 1e-9))


def _moved_feet(feet, mid, heading, dx, dy, dpsi):
    """Both feet translated by (dx, dy) in the heading frame and turned by dpsi about mid."""
    c, s_ = math.cos(heading), math.sin(heading)
    shift = np.array([c * dx - s_ * dy, s_ * dx + c * dy])
    cr, sr = math.cos(dpsi), math.sin(dpsi)
    out = []
    for G in feet:
        r = G[:2] - mid
        p = mid + np.array([cr * r[0] - sr * r[1], sr * r[0] + cr * r[1]]) + shift
        out.append(np.array([p[0], p[1], G[2] + dpsi]))
    return out


def seg_jump(plan: Plan):
    """Jumps on both feet: vertical, broad, lateral, turning; single or repeated hops. The
    pelvis follows a g-parabola in flight."""
    ch, rng = plan.ch, plan.rng
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    n = 1 if rng.uniform() < 0.6 else int(rng.integers(2, 4))
    hop = n > 1
    phi_to = float(rng.uniform(0.5, 0.8))
    phi_land = float(rng.uniform(0.25, 0.45))
    # pelvis heights at take-off / landing from the leg geometry (legs nearly straight)
    ank_to = ch.stance_pose(0, np.zeros(3), phi_to)[1][2]
    ank_land = ch.stance_pose(0, np.zeros(3), phi_land)[1][2]
    hip_drop = -ch.legs[0].hip_offset[2]
    z_to = ank_to + 0.93 * ch.reach + hip_drop
    z_land = ank_land + 0.92 * ch.reach + hip_drop
    z_rest = plan.z_rest
    Z = _Piecewise()
    t = t0 + float(rng.uniform(0.2, 0.4))
    Z.add(t0, t, _const(z_rest))
    d_c = float(rng.uniform(0.10, 0.22)) * s
    T_cm = float(rng.uniform(0.45, 0.7))
    t = Z.add(t, t + T_cm, _ramp(t, t + T_cm, z_rest, z_rest - d_c))
    z_low = z_rest - d_c
    arm_keys = [(t0, 0.0), (t - 0.05, -0.8)]  # arm swing (fwd) knots
    lean_keys = [(t0, 0.0), (t, float(rng.uniform(0.2, 0.45)))]
    jumps = []
    cur_feet = feet
    for i in range(n):
        T_po = float(rng.uniform(0.2, 0.3))
        T_f = float(rng.uniform(0.22, 0.35) if hop else rng.uniform(0.3, 0.5))
        v0 = (z_land - z_to) / T_f + GRAVITY * T_f / 2
        v1 = v0 - GRAVITY * T_f
        t_to = t + T_po
        Z.add(t, t_to, lambda tt, a=t, b=t_to, zl=z_low, v=v0: _hermite(tt, a, b, zl, 0.0, z_to, v))
        t_land = t_to + T_f
        Z.add(t_to, t_land, lambda tt, a=t_to, v=v0: z_to + v * (tt - a) - 0.5 * GRAVITY * (tt - a) ** 2)
        kind = rng.choice(["up", "broad", "side", "turn"], p=[0.3, 0.35, 0.15, 0.2])
        dx = dy = dpsi = 0.0
        if kind == "broad":
            dx = float(rng.uniform(0.2, 0.7 if not hop else 0.4)) * s
        elif kind == "side":
            dy = float(rng.choice([-1, 1]) * rng.uniform(0.15, 0.4)) * s
        elif kind == "turn":
            dpsi = float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.2))
        mid = (cur_feet[0][:2] + cur_feet[1][:2]) / 2
        new_feet = _moved_feet(cur_feet, mid, heading, dx, dy, dpsi)
        tuck = float(rng.uniform(0.0, 0.12 if hop else 0.25)) * s
        for f in (0, 1):
            plan.step(f, new_feet[f], t_to, t_land, phi_off=phi_to, r_off=T_po, phi_on=phi_land,
                      r_on=float(rng.uniform(0.08, 0.14)), swing={"mode": "rel", "tuck": tuck},
                      alpha_flat_off=0.7, alpha_flat_on=0.5)
        heading_new = heading + dpsi
        jumps.append(dict(t_to=t_to, t_land=t_land, kind=str(kind), dx=dx, dy=dy, dpsi=dpsi,
                          h_old=heading, h_new=heading_new))
        heading = heading_new
        cur_feet = new_feet
        arm_keys += [(t_to, 1.6), (t_land, 1.0)]
        lean_keys += [(t_to, 0.05), (t_land, 0.05)]
        last = i == n - 1
        d_a = float(rng.uniform(0.08, 0.2 if last else 0.12)) * s
        T_ab = float(rng.uniform(0.25, 0.4) if last else rng.uniform(0.15, 0.22))
        t = Z.add(t_land, t_land + T_ab, lambda tt, a=t_land, b=t_land + T_ab, zz=z_rest - d_a, v=v1:
                  _hermite(tt, a, b, z_land, v, zz, 0.0))
        z_low = z_rest - d_a
        lean_keys.append((t, float(rng.uniform(0.15, 0.35))))
        arm_keys.append((t, 0.6 if not last else 0.3))
    T_rise = float(rng.uniform(0.5, 0.8))
    t_end = Z.add(t, t + T_rise, _ramp(t, t + T_rise, z_low, z_rest))
    t_end = Z.add(t_end, t_end + float(rng.uniform(0.2, 0.4)), _const(z_rest))
    arm_keys += [(t_end - 0.2, 0.0), (t_end, 0.0)]
    lean_keys += [(t_end - 0.2, 0.0), (t_end, 0.0)]
    plan.lam_pins.append((t_end, 0.5))
    yaw_keys = [(t0, jumps[0]["h_old"])]
    for j in jumps:
        yaw_keys += [(j["t_to"], j["h_old"]), (j["t_land"], j["h_new"])]
    yaw_keys.append((t_end, heading))
    arms_up = rng.uniform() < 0.5

    def fn(tt):
        P = _neutral(plan, len(tt))
        fwd = _keys(tt, arm_keys)
        for sd in SIDES:
            P.arm(sd, fwd=np.clip(fwd, -0.9, 1.6) * (1.0 if not arms_up else 0.6),
                  down=-(np.clip(fwd, 0, 2) * 0.6 if arms_up else 0.0),
                  elbow=0.2 * np.abs(fwd))
        lean = _keys(tt, lean_keys)
        P.spine(flex=0.5 * lean)
        P.neck(flex=-0.6 * lean)
        return dict(z=Z(tt), yaw=_keys(tt, yaw_keys), pitch=lean, upper=P.array())

    plan.add_segment("jump", t0, t_end, fn, jumps=len(jumps))
    plan.heading = heading


def _step_to(plan: Plan, foot, G, t_lift, dur=0.45, clear=0.05, phi_off=0.15, r_off=0.15):
    return plan.step(foot, G, t_lift, t_lift + dur, phi_off=phi_off, r_off=r_off,
                     swing={"mode": "world", "clear": clear * plan.ch.scale})


def seg_squat(plan: Plan):
    """Squats (1-4 repetitions) on a widened stance, arms forward / crossed / behind the head."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    mid = plan.mid()
    width = float(rng.uniform(0.25, 0.42)) * s
    toe = float(rng.uniform(0.1, 0.4))
    first = int(rng.integers(2))
    t = t0 + 0.5
    for f in (first, 1 - first):
        _step_to(plan, f, _place(mid, heading, _sgn(f), width, toe), t)
        t += 0.45 + 0.45
    reps = int(rng.integers(1, 5))
    depth = float(rng.uniform(0.15, 0.36)) * s
    T_rep = float(rng.uniform(1.6, 3.0))
    t_sq0 = t + 0.2
    knots = [(t0, 0.0), (t_sq0, 0.0)]
    for r in range(reps):
        a = t_sq0 + r * T_rep
        knots += [(a + 0.45 * T_rep, 1.0), (a + 0.55 * T_rep, 1.0), (a + T_rep, 0.0)]
    t_sq1 = t_sq0 + reps * T_rep
    t = t_sq1 + 0.3
    for f in (first, 1 - first):
        _step_to(plan, f, _place(mid, heading, _sgn(f), st["width"], st["toe_out"]), t)
        t += 0.9
    t_end = t + 0.3
    plan.lam_pins.append((t_end, 0.5))
    style = rng.choice(["forward", "cross", "head", "free"])
    lean = float(rng.uniform(0.5, 0.9))
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, knots), 0, 1)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if style == "forward":
                P.arm(sd, fwd=prof * (1.45 - st["arm_fwd"]), elbow=-prof * st["elbow"])
            elif style == "cross":
                P.arm(sd, fwd=prof * (1.3 - st["arm_fwd"]), elbow=prof * (1.8 - st["elbow"]), twist=0.3 * prof)
            elif style == "head":
                P.arm(sd, down=prof * (-0.1 - st["arm_down"]), elbow=prof * (2.2 - st["elbow"]),
                      fwd=prof * 0.3, twist=-prof * 0.8)
            else:
                P.arm(sd, fwd=prof * 0.5, elbow=prof * 0.4)
        P.spine(flex=prof * 0.25 * lean)
        P.neck(flex=-prof * 0.5 * lean)
        return dict(z=z_rest - depth * prof, yaw=np.full(len(tt), heading),
                    pitch=prof * lean * 0.8, upper=P.array())

    plan.add_segment("squat", t0, t_end, fn, reps=reps, depth=depth)


def seg_lunge(plan: Plan):
    """Forward or reverse lunges with either leg."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    A = int(rng.integers(2))  # the stepping foot
    B = 1 - A
    reverse = rng.uniform() < 0.4
    L = float(rng.uniform(0.4, 0.6) if reverse else rng.uniform(0.5, 0.75)) * s
    depth = float(rng.uniform(0.12, 0.24)) * s
    GA = feet[A].copy()
    c, sn = math.cos(heading), math.sin(heading)
    sign = -1.0 if reverse else 1.0
    G_new = GA + np.array([sign * L * c, sign * L * sn, 0.0])
    G_new[2] = heading + _sgn(A) * 0.05
    t_lift = t0 + float(rng.uniform(0.35, 0.55))
    T_sw = float(rng.uniform(0.4, 0.55))
    t_land = t_lift + T_sw
    if reverse:
        sA = plan.step(A, G_new, t_lift, t_land, phi_off=0.1, r_off=0.15, phi_on=0.6, r_on=0.1,
                       swing={"mode": "world", "clear": 0.06 * s})
    else:
        sA = plan.step(A, G_new, t_lift, t_land, phi_off=0.25, r_off=0.2, phi_on=-0.15, r_on=0.1,
                       swing={"mode": "world", "clear": 0.06 * s})
    T_down = float(rng.uniform(0.6, 1.0))
    T_hold = float(rng.uniform(0.1, 0.6))
    T_up = float(rng.uniform(0.6, 1.0))
    a = t_land + 0.15
    b = a + T_down
    c_ = b + T_hold
    d = c_ + T_up
    heel = float(rng.uniform(0.6, 0.9))
    if reverse:
        sA.phi = [(t_land, 0.6), (a, 0.6), (b, heel), (c_, heel), (d, 0.6)]
    else:
        sB = plan.stance(B)
        sB.phi += [(a - 0.1, 0.0), (b, heel), (c_, heel), (d, 0.5)]
    t_back = d + 0.1
    T_sw2 = float(rng.uniform(0.4, 0.55))
    if reverse:
        plan.step(A, GA, t_back, t_back + T_sw2, phi_off=0.0, r_off=0.0, phi_on=0.0,
                  swing={"mode": "world", "clear": 0.06 * s})
        sA.phi.append((t_back, 0.75))
    else:
        plan.step(A, GA, t_back, t_back + T_sw2, phi_off=0.25, r_off=0.15, phi_on=0.2, r_on=0.1,
                  swing={"mode": "world", "clear": 0.05 * s})
        sB = plan.stance(B)
        sB.phi += [(t_back + T_sw2 + 0.1, 0.0)]
    t_end = t_back + T_sw2 + float(rng.uniform(0.4, 0.7))
    front = B if reverse else A
    share = float(rng.uniform(0.6, 0.7))
    lamL = share if front == 0 else 1 - share
    plan.lam_pins += [(b, lamL), (c_, lamL), (t_end, 0.5)]
    if reverse:  # sink on the front leg while reaching back, pelvis tilted forward
        prof_knots = [(t0, 0.0), (t_lift, 0.0), (t_land, 0.35), (b, 1.0), (c_, 1.0), (d, 0.0),
                      (t_back + T_sw2, 0.0), (t_end, 0.0)]
        tilt_knots = [(t0, 0.0), (t_lift - 0.2, 0.0), (t_land, 1.0), (t_back + T_sw2, 1.0), (t_end, 0.0)]
    else:
        prof_knots = [(t0, 0.0), (a, 0.0), (b, 1.0), (c_, 1.0), (d, 0.0), (t_end, 0.0)]
        tilt_knots = [(t0, 0.0), (t_end, 0.0)]
    tilt = float(rng.uniform(0.25, 0.35))
    style = rng.choice(["hips", "free", "forward"])
    z_rest = plan.z_rest

    def fn(tt):
        prof = np.clip(_keys(tt, prof_knots), 0, 1)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if style == "hips":
                P.arm(sd, down=prof * (0.95 - st["arm_down"]), fwd=prof * (-0.35 - st["arm_fwd"]),
                      twist=prof * 0.9, elbow=prof * (1.6 - st["elbow"]))
            elif style == "forward":
                P.arm(sd, fwd=prof * 1.2, elbow=prof * 0.2)
        tl = tilt * np.clip(_keys(tt, tilt_knots), 0, 1)
        P.spine(flex=-0.05 * prof - 0.9 * tl)
        return dict(z=z_rest - depth * prof, yaw=np.full(len(tt), heading), pitch=0.05 * prof + tl,
                    upper=P.array())

    plan.add_segment("lunge", t0, t_end, fn, reverse=bool(reverse))


def seg_kick(plan: Plan):
    """Front, side or back kicks from a single-leg stance."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    feet = plan.feet()
    heading = _heading_of(feet)
    A = int(rng.integers(2))
    sg = _sgn(A)
    kind = str(rng.choice(["front", "side", "back"], p=[0.5, 0.3, 0.2]))
    L = ch.reach
    hip = np.array([0.0, ch.legs[A].hip_offset[1], ch.legs[A].hip_offset[2]])
    chamber_p = hip + np.array([0.36, 0.0, -0.5]) * s
    chamber_R = _ry(np.array(-0.3))
    pf = float(rng.uniform(0.2, 0.6))
    if kind == "front":
        e = float(rng.uniform(-0.6, 0.0))
        d = np.array([math.cos(e), 0.0, math.sin(e)])
        ext_R = _ry(np.array(-(math.pi / 2 + e) + pf))
        pitch_k, roll_k = -float(rng.uniform(0.05, 0.2)), 0.0
    elif kind == "side":
        a = float(rng.uniform(0.5, 0.8))
        d = np.array([0.1, sg * math.sin(a), -math.cos(a)])
        d /= np.linalg.norm(d)
        ext_R = _rx(np.array(-sg * a))
        pitch_k, roll_k = 0.0, sg * float(rng.uniform(0.1, 0.22))
        chamber_p = hip + np.array([0.25, sg * 0.15, -0.5]) * s
    else:
        b = float(rng.uniform(0.5, 0.8))
        d = np.array([-math.sin(b), 0.0, -math.cos(b)])
        ext_R = _ry(np.array(b + 0.3))
        pitch_k, roll_k = float(rng.uniform(0.25, 0.4)), 0.0
        chamber_p = hip + np.array([-0.1, 0.0, -0.45]) * s
        chamber_R = _ry(np.array(0.6))
    ext_p = hip + 0.94 * L * d
    t_lift = t0 + float(rng.uniform(0.7, 1.0))
    T = float(rng.uniform(0.9, 1.4))
    keys = [dict(s=0.3, R=chamber_R, p=chamber_p, toe=0.0),
            dict(s=0.5, R=ext_R, p=ext_p, toe=0.0),
            dict(s=0.62, R=ext_R, p=ext_p, toe=0.0),
            dict(s=0.8, R=chamber_R, p=chamber_p, toe=0.0)]
    plan.step(A, feet[A], t_lift, t_lift + T, phi_off=0.3, r_off=0.2, phi_on=0.2, r_on=0.1,
              swing={"mode": "rel", "keys": keys})
    t_end = t_lift + T + float(rng.uniform(0.5, 0.8))
    plan.lam_pins.append((t_end, 0.5))
    prof_knots = [(t0, 0.0), (t_lift - 0.3, 0.0), (t_lift + 0.45 * T, 1.0), (t_lift + 0.65 * T, 1.0),
                  (t_lift + T, 0.0), (t_end, 0.0)]
    guard = rng.uniform() < 0.5
    bend = float(rng.uniform(0.02, 0.05)) * s
    z_rest = plan.z_rest
    kick_window = [(t0, 0.0), (t_lift - 0.2, 0.0), (t_lift, 1.0), (t_lift + T, 1.0), (t_end - 0.1, 0.0)]

    def fn(tt):
        prof = np.clip(_keys(tt, prof_knots), 0, 1)
        win = np.clip(_keys(tt, kick_window), 0, 1)
        P = _neutral(plan, len(tt))
        for sd in SIDES:
            if guard:
                P.arm(sd, down=win * (0.9 - st["arm_down"]), fwd=win * 1.0, elbow=win * (2.0 - st["elbow"]))
            else:
                P.arm(sd, down=win * (0.4 - st["arm_down"]), elbow=win * 0.2)
        P.spine(flex=-0.5 * pitch_k * prof, lat=0.0)
        P.neck(flex=-0.5 * pitch_k * prof)
        return dict(z=z_rest - bend * win, yaw=np.full(len(tt), heading), pitch=pitch_k * prof,
                    roll=roll_k * prof, upper=P.array())

    plan.add_segment("kick", t0, t_end, fn, kick=kind)


def seg_dance(plan: Plan):
    """Dance-like stepping to a beat: side steps, marching, forward/back steps and turning
    steps, with a knee bounce and rhythmic arm patterns."""
    ch, rng, st = plan.ch, plan.rng, plan.style
    s = ch.scale
    t0 = plan.t
    Tb = float(rng.uniform(0.45, 0.65))
    n_moves = int(rng.integers(3, 7))
    feet = plan.feet()
    heading = _heading_of(feet)
    width = st["width"]
    t = t0 + Tb
    yaw_keys = [(t0, heading)]
    for _ in range(n_moves):
        move = str(rng.choice(["side", "march", "fwd_back", "turn"]))
        feet = plan.feet()
        heading = _heading_of(feet)
        mid = plan.mid()
        A = int(rng.integers(2))
        B = 1 - A
        clear = float(rng.uniform(0.05, 0.1))
        if move == "side":
            d = float(rng.uniform(0.2, 0.4)) * s * _sgn(A)
            G_A = _place(mid, heading, _sgn(A), width, st["toe_out"])
            c, sn = math.cos(heading), math.sin(heading)
            G_A[:2] += d * np.array([-sn, c])
            mid2 = mid + d * np.array([-sn, c])
            G_B = _place(mid2, heading, _sgn(B), width, st["toe_out"])
            seq = [(A, G_A), (B, G_B)]
        elif move == "march":
            clear = float(rng.uniform(0.12, 0.25))
            seq = [(A, feet[A]), (B, feet[B]), (A, feet[A]), (B, feet[B])]
        elif move == "fwd_back":
            L = float(rng.uniform(0.2, 0.35)) * s
            c, sn = math.cos(heading), math.sin(heading)
            G_f = feet[A] + np.array([L * c, L * sn, 0.0])
            seq = [(A, G_f), (A, feet[A])]
        else:
            dpsi = float(rng.choice([-1, 1]) * rng.uniform(0.4, 0.9))
            new = _moved_feet(feet, mid, heading, 0.0, 0.0, dpsi)
            first = 0 if dpsi > 0 else 1  # turn left: the left foot leads
            seq = [(first, new[first]), (1 - first, new[1 - first])]
        for foot, G in seq:
            plan.step(foot, G, t + 0.05 * Tb, t + 0.6 * Tb, phi_off=0.15, r_off=0.12,
                      phi_on=0.1 if move == "march" else 0.0, r_on=0.08 if move == "march" else 0.0,
                      swing={"mode": "world", "clear": clear * s})
            t += Tb
        yaw_keys.append((t, _heading_of(plan.feet()) + 0.0))
    t_end = t + Tb
    for i in range(1, len(yaw_keys)):
        prev = yaw_keys[i - 1][1]
        yaw_keys[i] = (yaw_keys[i][0], prev + _wrap(yaw_keys[i][1] - prev))
    yaw_keys.append((t_end, yaw_keys[-1][1]))
    plan.lam_pins.append((t_end, 0.5))
    bounce = float(rng.uniform(0.015, 0.05)) * s
    pattern = str(rng.choice(["pump", "updown", "punch", "sway", "clap"]))
    z_rest = plan.z_rest
    end_heading = yaw_keys[-1][1]

    def fn(tt):
        env = _window(tt, t0, t_end, Tb)
        ph = 2 * np.pi * (tt - t0) / Tb
        P = _neutral(plan, len(tt))
        if pattern == "pump":
            P.arm("left", elbow=env * (1.5 - st["elbow"]), fwd=env * (0.3 + 0.4 * np.sin(ph)))
            P.arm("right", elbow=env * (1.5 - st["elbow"]), fwd=env * (0.3 - 0.4 * np.sin(ph)))
        elif pattern == "updown":
            for sd in SIDES:
                P.arm(sd, down=env * (-0.6 - st["arm_down"]) * (0.5 + 0.5 * np.cos(ph / 2)),
                      elbow=env * 0.4)
        elif pattern == "punch":
            P.arm("left", fwd=env * 1.4 * (0.5 + 0.5 * np.sin(ph / 2)),
                  elbow=env * 1.6 * (0.5 - 0.5 * np.sin(ph / 2)))
            P.arm("right", fwd=env * 1.4 * (0.5 - 0.5 * np.sin(ph / 2)),
                  elbow=env * 1.6 * (0.5 + 0.5 * np.sin(ph / 2)))
        elif pattern == "sway":
            for sd in SIDES:
                P.arm(sd, down=env * (0.7 - st["arm_down"]), elbow=env * 0.3)
            P.spine(lat=env * 0.15 * np.sin(ph / 2))
        else:
            osc = 0.5 - 0.5 * np.cos(ph)
            for sd in SIDES:
                P.arm(sd, fwd=env * (1.2 + 0.25 * osc), elbow=env * (0.4 + 0.4 * osc), twist=env * 0.8)
        z = z_rest - env * (0.01 * s + bounce * (0.5 + 0.5 * np.cos(ph)))
        return dict(z=z, yaw=_keys(tt, yaw_keys), roll=env * 0.04 * np.sin(ph / 2), upper=P.array())

    plan.add_segment("dance", t0, t_end, fn, beat=Tb, pattern=pattern)
    plan.heading = end_heading


SEGMENTS: dict[str, Callable[[Plan], None]] = {
    "stand": lambda plan: seg_stand(plan),
    "walk": lambda plan: seg_locomotion(plan, backward=plan.rng.uniform() < 0.25),
    "run": lambda plan: seg_locomotion(plan, run=True),
    "jump": seg_jump,
    "squat": seg_squat,
    "lunge": seg_lunge,
    "kick": seg_kick,
    "dance": seg_dance,
}


def generate_motion(
    height_m: float, rng: np.random.Generator, duration: float, fps: float = 30.0,
    kinds: Sequence[str] | None = None,
) -> Motion:
    """Plan and solve one kinematic motion of at least ``duration`` seconds (uncropped)."""
    ch = character(height_m)
    style = _style(rng, ch)
    plan = Plan(ch, rng, style)
    plan.upper_names = _upper_names(ch)
    heading = float(rng.uniform(-np.pi, np.pi))
    x0, y0 = rng.uniform(-1.0, 1.0, 2)
    feet = [_place((x0, y0), heading, _sgn(f), style["width"], style["toe_out"]) for f in (0, 1)]
    plan.start(feet, heading, style["alpha"])
    seg_stand(plan, float(rng.uniform(0.4, 0.9)), gestures=False)
    kinds = list(kinds or [k for k in MOTION_KINDS if k in SEGMENTS])
    while plan.t < duration:
        kind = kinds[int(rng.integers(len(kinds)))]
        SEGMENTS[kind](plan)
        seg_stand(plan, float(rng.uniform(0.3, 0.8)), gestures=False)
    return _realize(plan, fps)


# =========================================================================================
# validation
# =========================================================================================


def site_trajectories(ch: Character, q: np.ndarray, sites) -> np.ndarray:
    """World positions (T, n, 3) of the given site ids along a trajectory (MuJoCo C FK)."""
    out = np.zeros((len(q), len(sites), 3))
    d = ch.d
    for k in range(len(q)):
        d.qpos[:] = q[k]
        mujoco.mj_kinematics(ch.mj, d)
        out[k] = d.site_xpos[sites]
    return out


def motion_report(m: Motion) -> dict:
    """Kinematic quality numbers of a motion (what :func:`check_motion` bounds)."""
    ch = m.character
    q = m.q
    hinge = np.arange(7, ch.nq)
    viol = np.maximum(q[:, hinge] - ch.upper[hinge], 0) + np.maximum(ch.lower[hinge] - q[:, hinge], 0)
    pos = site_trajectories(ch, q, ch.check_sites)
    csite = pos[:, -4:]  # check_sites ends with the four contact sites
    drift = 0.0
    for i in range(4):
        for a, b in _runs(m.planted[:, i]):
            drift = max(drift, float(np.max(np.abs(csite[a:b, i] - csite[a, i]))))
    return dict(
        limit_violation=float(viol.max()) if viol.size else 0.0,
        min_height=float(pos[..., 2].min()),
        planted_drift=drift,
        ik_err=float(m.info.get("ik_err", 0.0)),
        root_speed_max=float(np.max(np.linalg.norm(np.diff(q[:, :3], axis=0), axis=1)) * m.fps) if len(q) > 1 else 0.0,
    )


def check_motion(m: Motion) -> dict:
    """Raise :class:`GenerationError` unless the motion is kinematically clean."""
    r = motion_report(m)
    if r["limit_violation"] > 1e-9:
        raise GenerationError(f"joint limit violated by {r['limit_violation']:.2e} rad")
    if r["min_height"] < -1e-6:
        raise GenerationError(f"floor penetration {r['min_height']:.2e} m")
    if r["planted_drift"] > 1e-4:
        raise GenerationError(f"planted foot moved {r['planted_drift']:.2e} m")
    return r


# =========================================================================================
# ground truth: velocities, keypoints, contact labels
# =========================================================================================


def velocities(mj: mujoco.MjModel, q: np.ndarray, fps: float) -> np.ndarray:
    """qd (T, nv) by ``mj_differentiatePos``: central differences inside the clip, one-sided at
    the first and last frame (MuJoCo conventions: root angular velocity in the body frame)."""
    T = len(q)
    qd = np.zeros((T, mj.nv))
    if T < 2:
        return qd
    dt = 1.0 / fps
    for t in range(T):
        a, b = max(t - 1, 0), min(t + 1, T - 1)
        mujoco.mj_differentiatePos(mj, qd[t], (b - a) * dt, q[a], q[b])
    return qd


def contact_labels(points: np.ndarray, max_step: float = CONTACT_MAX_STEP_M,
                   max_height: float = CONTACT_MAX_HEIGHT_M) -> np.ndarray:
    """Rempe et al.'s rule: a point (T, 4, 3) is in contact at frame t when it moved less than
    ``max_step`` since frame t-1 and is less than ``max_height`` above the floor. Frame 0 has
    no previous frame and uses its displacement to frame 1 (the same one frame 1 uses)."""
    T = len(points)
    step = np.zeros(points.shape[:2])
    if T > 1:
        step[1:] = np.linalg.norm(np.diff(points, axis=0), axis=-1)
        step[0] = step[1]
    return ((step < max_step) & (points[..., 2] < max_height)).astype(np.float32)


def _ground_truth(ch: Character, q: np.ndarray, layout, fps: float):
    sites = np.array([ch.mj.site(s).id for s in layout.sites] + list(ch.contact_sites))
    pos = site_trajectories(ch, q, sites)
    kp3d = pos[:, : layout.num_joints]
    contacts = contact_labels(pos[:, layout.num_joints:])
    return kp3d, contacts


# =========================================================================================
# cameras and 2D keypoints
# =========================================================================================


@dataclass(frozen=True)
class CameraConfig:
    """Static pinhole cameras looking at the subject (OpenCV axes, no distortion)."""

    focal_px: tuple[float, float] = (500.0, 2000.0)
    image_sizes: tuple[tuple[int, int], ...] = ((1920, 1080), (1280, 720), (1080, 1920), (1000, 1000))
    distance_m: tuple[float, float] = (3.0, 8.0)
    height_m: tuple[float, float] = (0.3, 2.0)
    principal_jitter: float = 0.02  # principal point offset, fraction of the image size
    min_visible: float = 0.95  # fraction of joint-frames that must project inside the image
    min_depth_m: float = 1.0  # closest any joint may come to the camera
    tries: int = 30


@dataclass(frozen=True)
class Corruption:
    """Detector-like corruption of the projected 2D keypoints.

    Pixel noise is Gaussian with std ``noise_px + noise_rel * person height in pixels``
    (times a per-joint factor: ``joint_scale`` for wrists/ankles/feet), temporally correlated
    (AR(1) coefficient ``noise_corr``). Per joint and frame: an *outlier* (probability
    ``outlier_prob``) jumps by ``outlier_scale`` * person height; a *dropped* joint
    (fraction ``drop_prob`` of joint-frames, in bursts of mean length ``drop_burst`` frames)
    gets confidence 0 and coordinates 0. A left/right *swap* event starts at a frame with
    probability ``swap_prob`` and lasts ``swap_burst`` frames on average; it exchanges one
    random left/right pair (``layout.flip_pairs``), or all of them with probability
    ``swap_all``. Joints projecting outside the image are dropped when ``drop_outside``.
    Confidences: clean joints draw from ``conf_clean`` and lose up to 0.3 with their noise
    (relative to 3 std); outliers draw from ``conf_outlier``, swapped joints from
    ``conf_swap``.
    """

    noise_px: float = 1.5
    noise_rel: float = 0.005
    joint_scale: float = 1.5
    noise_corr: float = 0.5
    outlier_prob: float = 0.01
    outlier_scale: float = 0.15
    drop_prob: float = 0.03
    drop_burst: float = 3.0
    swap_prob: float = 0.005
    swap_burst: float = 4.0
    swap_all: float = 0.2
    drop_outside: bool = True
    conf_clean: tuple[float, float] = (0.75, 0.98)
    conf_outlier: tuple[float, float] = (0.1, 0.5)
    conf_swap: tuple[float, float] = (0.3, 0.7)

    @classmethod
    def none(cls) -> Corruption:
        """No corruption: exact projections with confidence 1."""
        return cls(noise_px=0.0, noise_rel=0.0, outlier_prob=0.0, drop_prob=0.0, swap_prob=0.0,
                   drop_outside=False, conf_clean=(1.0, 1.0))


def look_at_extrinsics(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World->camera [R t; 0 1] (OpenCV axes) of a camera at ``eye`` looking at ``target``
    (the numpy twin of :meth:`jmocap.camera.Camera.look_at`)."""
    eye = np.asarray(eye, float)
    fwd = np.asarray(target, float) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, float))
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    E = np.eye(4)
    E[:3, :3] = np.stack([right, down, fwd])
    E[:3, 3] = -E[:3, :3] @ eye
    return E


def project_points(intrinsics, extrinsics, X):
    """Pinhole projection of world points (..., 3): pixels (..., 2) and depth (...,)."""
    fx, fy, cx, cy = intrinsics
    Xc = X @ extrinsics[:3, :3].T + extrinsics[:3, 3]
    z = Xc[..., 2]
    uv = np.stack([fx * Xc[..., 0] / z + cx, fy * Xc[..., 1] / z + cy], axis=-1)
    return uv, z


def sample_camera(rng: np.random.Generator, points: np.ndarray, cfg: CameraConfig = CameraConfig()):
    """A static camera looking at the subject whose world joints over the clip are ``points``
    (T, J, 3). Resamples until ``min_visible`` of the joint-frames project inside the image and
    nothing comes closer than ``min_depth_m``; the last resort shortens the focal length until
    the subject fits. Returns (intrinsics (4,), image_size (2,), extrinsics (4, 4), info)."""
    flat = points.reshape(-1, 3)
    centre = (flat.min(axis=0) + flat.max(axis=0)) / 2
    best = None
    for attempt in range(cfg.tries):
        W, H = cfg.image_sizes[int(rng.integers(len(cfg.image_sizes)))]
        f = float(np.exp(rng.uniform(np.log(cfg.focal_px[0]), np.log(cfg.focal_px[1]))))
        dist = float(rng.uniform(*cfg.distance_m))
        cam_h = float(rng.uniform(*cfg.height_m))
        az = float(rng.uniform(-np.pi, np.pi))
        eye = np.array([centre[0] + dist * math.cos(az), centre[1] + dist * math.sin(az), cam_h])
        target = np.array([centre[0], centre[1], float(rng.uniform(0.35, 0.6)) * (flat[:, 2].max())])
        if abs(np.dot((target - eye) / np.linalg.norm(target - eye), [0, 0, 1])) > 0.98:
            continue
        E = look_at_extrinsics(eye, target)
        cx = W / 2 + float(rng.uniform(-1, 1)) * cfg.principal_jitter * W
        cy = H / 2 + float(rng.uniform(-1, 1)) * cfg.principal_jitter * H
        K = np.array([f, f, cx, cy])
        uv, z = project_points(K, E, flat)
        if z.min() < cfg.min_depth_m:
            continue
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        frac = float(inside.mean())
        cand = (K, np.array([W, H]), E, dict(distance_m=dist, height_m=cam_h, azimuth=az, attempts=attempt + 1))
        if frac >= cfg.min_visible:
            return cand
        if best is None or frac > best[0]:
            best = (frac, cand)
    if best is None:
        raise GenerationError("no camera placement keeps the subject in front of the camera")
    K, size, E, info = best[1]
    # shrink the focal length around the principal point until the subject fits
    for _ in range(40):
        uv, _z = project_points(K, E, flat)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[1])
        if inside.mean() >= cfg.min_visible:
            break
        K = K.copy()
        K[:2] *= 0.9
    info["focal_shrunk"] = True
    return K, size, E, info


def _bursts(rng, T, p_frac, mean_len, shape):
    """Boolean (T, *shape) masks of random bursts covering about ``p_frac`` of the entries."""
    out = np.zeros((T,) + shape, bool)
    if p_frac <= 0 or T == 0:
        return out
    mean_len = max(1.0, mean_len)
    p_start = p_frac / mean_len
    starts = rng.uniform(size=(T,) + shape) < p_start
    lengths = rng.geometric(1.0 / mean_len, size=(T,) + shape)
    idx = np.argwhere(starts)
    for i in idx:
        t = i[0]
        L = lengths[tuple(i)]
        out[(slice(t, t + L),) + tuple(i[1:])] = True
    return out


def corrupt_keypoints(rng: np.random.Generator, uv: np.ndarray, layout, image_size,
                      corruption: Corruption = Corruption()) -> tuple[np.ndarray, dict]:
    """Detector-like 2D keypoints (T, J, 3) = (x, y, confidence) from clean projections
    ``uv`` (T, J, 2). Returns the keypoints and counts of what was done."""
    c = corruption
    T, J, _ = uv.shape
    W, H = float(image_size[0]), float(image_size[1])
    kp = np.zeros((T, J, 3))
    kp[..., :2] = uv
    # person height in pixels per frame
    ph = np.maximum(uv[..., 1].max(axis=1) - uv[..., 1].min(axis=1), 1.0)
    names = [n.lower() for n in layout.joints]
    jscale = np.array([c.joint_scale if any(k in n for k in ("wrist", "ankle", "foot", "toe", "heel"))
                       else 1.0 for n in names])
    sigma = (c.noise_px + c.noise_rel * ph)[:, None] * jscale[None, :]  # (T, J)
    noise = np.zeros((T, J, 2))
    if np.any(sigma > 0):
        white = rng.normal(size=(T, J, 2))
        rho = float(np.clip(c.noise_corr, 0.0, 0.99))
        noise[0] = white[0]
        for t in range(1, T):
            noise[t] = rho * noise[t - 1] + math.sqrt(1 - rho * rho) * white[t]
        noise *= sigma[..., None]
    kp[..., :2] += noise
    lo, hi = c.conf_clean
    base = rng.uniform(lo, hi, size=(T, J))
    mag = np.linalg.norm(noise, axis=-1) / np.maximum(3 * sigma, 1e-9)
    conf = base - 0.3 * np.clip(mag, 0, 1) * (sigma > 0)
    # outliers
    out_mask = rng.uniform(size=(T, J)) < c.outlier_prob
    if out_mask.any():
        n = int(out_mask.sum())
        ang = rng.uniform(0, 2 * np.pi, n)
        r = np.abs(rng.normal(size=n)) * c.outlier_scale * ph[np.nonzero(out_mask)[0]] + 5.0
        kp[out_mask, 0] += r * np.cos(ang)
        kp[out_mask, 1] += r * np.sin(ang)
        conf[out_mask] = rng.uniform(*c.conf_outlier, size=n)
    # left/right swaps
    swapped = np.zeros((T, J), bool)
    n_swaps = 0
    if c.swap_prob > 0 and layout.flip_pairs:
        t = 0
        while t < T:
            if rng.uniform() < c.swap_prob:
                L = int(rng.geometric(1.0 / max(c.swap_burst, 1.0)))
                pairs = list(layout.flip_pairs) if rng.uniform() < c.swap_all else \
                    [layout.flip_pairs[int(rng.integers(len(layout.flip_pairs)))]]
                sl = slice(t, min(T, t + L))
                for a, b in pairs:
                    kp[sl, a, :2], kp[sl, b, :2] = kp[sl, b, :2].copy(), kp[sl, a, :2].copy()
                    swapped[sl, a] = swapped[sl, b] = True
                n_swaps += 1
                t += L
            else:
                t += 1
        if swapped.any():
            conf[swapped] = rng.uniform(*c.conf_swap, size=int(swapped.sum()))
    # drops
    drop = _bursts(rng, T, c.drop_prob, c.drop_burst, (J,))
    if c.drop_outside:
        x, y = kp[..., 0], kp[..., 1]
        drop |= (x < 0) | (x >= W) | (y < 0) | (y >= H)
    conf = np.clip(conf, 0.01, 1.0)
    conf[drop] = 0.0
    kp[..., 2] = conf
    kp[drop, :2] = 0.0
    stats = dict(dropped=float(drop.mean()), outliers=int(out_mask.sum()), swap_events=n_swaps,
                 noise_std_px=float(np.mean(sigma)))
    return kp.astype(np.float32), stats


def clean_keypoints2d(clip: Clip) -> np.ndarray:
    """The exact projection (T, J, 2) of a synthetic clip's ``gt_keypoints3d`` with its camera
    (what the 2D keypoints are before corruption)."""
    if clip.gt_keypoints3d is None or clip.extrinsics is None:
        raise ValueError(f"clip {clip.name!r} has no 3D ground truth or no extrinsics")
    uv, _ = project_points(clip.intrinsics, clip.extrinsics, clip.gt_keypoints3d.astype(np.float64))
    return uv


# =========================================================================================
# physics variant: track the kinematic motion in MuJoCo C
# =========================================================================================


@dataclass(frozen=True)
class PhysicsConfig:
    """Tracking controller of the physics variant (see ``docs/data.md``).

    Hinges: ``tau = tau_ff + kp (q_ref - q) + kd (qd_ref - qd)`` with ``kp = M_jj w^2``,
    ``kd = 2 zeta M_jj w`` (``M_jj``: the joint-space inertia at the standing pose), the damping
    part integrated implicitly (as MuJoCo ``dof_damping`` with the ``implicitfast``
    integrator); ``tau_ff`` is inverse dynamics of the reference with the contact forces
    distributed over the planted contact points (non-negative least squares in a friction
    pyramid). Root: the part of the reference's root wrench the contacts cannot explain, plus a
    weak PD on the root pose (``root_freq_hz``); both are the *residual* force / torque.
    """

    substeps_per_frame: int = 0  # 0: as many as make the step <= max_dt
    max_dt: float = 0.004
    joint_freq_hz: float = 6.0
    joint_zeta: float = 1.0
    min_inertia: float = 0.02
    root_freq_hz: float = 1.0
    root_zeta: float = 1.0
    friction: float = 0.9
    contact_timeconst: float = 0.008  # MuJoCo solref time constant of the contacts (s)
    fall_height: float = 0.5  # fraction of the standing pelvis height
    fall_tilt_deg: float = 60.0


def _pyramid(mu):
    d = np.array([[mu, 0, 1], [-mu, 0, 1], [0, mu, 1], [0, -mu, 1]], float)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _feedforward(ch: Character, mj, q, qd, qdd, planted, mu):
    """Inverse dynamics of the reference (T frames): hinge feed-forward torques (T, nv) and the
    root wrench the planted contacts cannot supply (T, 6)."""
    T = len(q)
    mj = copy.deepcopy(mj)  # rigid-body inverse dynamics only: no contacts, limits, damping
    mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    mj.dof_damping[:] = 0.0
    d = mujoco.MjData(mj)
    ff = np.zeros((T, mj.nv))
    res = np.zeros((T, 6))
    jp = np.zeros((3, mj.nv))
    D = _pyramid(mu)
    w, l = 0.035 * ch.scale, 0.03 * ch.scale
    patch = ([np.array([0.0, w, 0.0]), np.array([0.0, -w, 0.0]), np.array([l, 0.0, 0.0])],  # heel
             [np.array([0.0, w, 0.0]), np.array([0.0, -w, 0.0]), np.array([l, 0.0, 0.0]),
              np.array([-l, 0.0, 0.0])])  # toe
    for k in range(T):
        d.qpos[:], d.qvel[:], d.qacc[:] = q[k], qd[k], qdd[k]
        mujoco.mj_inverse(mj, d)
        tau = d.qfrc_inverse.copy()
        pts = np.nonzero(planted[k])[0]
        force_gen = np.zeros(mj.nv)
        if len(pts):
            mujoco.mj_kinematics(mj, d)
            mujoco.mj_comPos(mj, d)
            cols = []
            for i in pts:
                sid = int(ch.contact_sites[i])
                body = int(mj.site_bodyid[sid])
                R = d.xmat[body].reshape(3, 3)
                for off in patch[i % 2]:  # a small sole patch around the contact site
                    p = d.site_xpos[sid] + R @ off
                    mujoco.mj_jac(mj, d, jp, None, p, body)
                    cols.append(jp.T @ D.T)  # (nv, 4)
            A = np.concatenate(cols, axis=1)  # (nv, 4n)
            n = A.shape[1]
            Aw = np.vstack([A[:6], 1e-2 * np.eye(n)])
            bw = np.concatenate([tau[:6], np.zeros(n)])
            c, _ = nnls(Aw, bw, maxiter=50 * n)
            force_gen = A @ c
        ff[k] = tau - force_gen
        res[k] = ff[k, :6]
        ff[k, :6] = 0.0
    return ff, res


def simulate_tracking(ch: Character, q_ref: np.ndarray, fps: float, planted: np.ndarray,
                      cfg: PhysicsConfig = PhysicsConfig()) -> dict:
    """Track a kinematic motion in MuJoCo C (floor contact, PD + feed-forward hinges, residual
    root wrench). Returns q, qd (T, nq/nv) of the simulated motion sampled at the frames,
    ``tau`` (T, nv) applied generalised forces and ``grf`` (T, 4, 3) world-frame foot contact
    forces (each averaged over the frame's substeps), and residual / tracking statistics."""
    T = len(q_ref)
    mj = copy.deepcopy(ch.mj)
    frame_dt = 1.0 / fps
    n = cfg.substeps_per_frame or max(1, int(math.ceil(frame_dt / cfg.max_dt - 1e-9)))
    dt = frame_dt / n
    mj.opt.timestep = dt
    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # stiffer contacts than MuJoCo's default (time constant 0.02 s): less sinking on impact
    mj.geom_solref[:, 0] = max(cfg.contact_timeconst, 2 * dt)
    mj.geom_solref[:, 1] = 1.0
    nv = mj.nv
    qd_ref = velocities(mj, q_ref, fps)
    qdd_ref = np.zeros_like(qd_ref)
    if T > 1:
        qdd_ref[1:-1] = (qd_ref[2:] - qd_ref[:-2]) * fps / 2
        qdd_ref[0], qdd_ref[-1] = (qd_ref[1] - qd_ref[0]) * fps, (qd_ref[-1] - qd_ref[-2]) * fps
    ff, id_res = _feedforward(ch, mj, q_ref, qd_ref, qdd_ref, planted, cfg.friction)
    # gains from the joint-space inertia at the standing pose
    d0 = mujoco.MjData(mj)
    d0.qpos[:] = ch.q_stand
    mujoco.mj_forward(mj, d0)
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(mj, d0, M)
    Mjj = np.maximum(np.diag(M)[6:], cfg.min_inertia)
    w = 2 * np.pi * cfg.joint_freq_hz
    kp = Mjj * w * w
    kd = 2 * cfg.joint_zeta * Mjj * w
    mj.dof_damping[6:] = kd
    mass = float(np.sum(mj.body_mass))
    weight = mass * GRAVITY
    wr = 2 * np.pi * cfg.root_freq_hz
    I_root = np.diag(M)[3:6].copy()
    # foot geoms -> which foot; contact sites
    foot_bodies = {ch.legs[0].ankle_body, ch.legs[0].toe_body, ch.legs[1].ankle_body, ch.legs[1].toe_body}
    floor = [g for g in range(mj.ngeom) if mj.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    if not floor:
        raise ValueError("the model has no floor plane")
    floor = set(floor)
    d = mujoco.MjData(mj)
    d.qpos[:] = q_ref[0]
    d.qvel[:] = qd_ref[0]
    mujoco.mj_forward(mj, d)
    q_out = np.zeros((T, mj.nq))
    qd_out = np.zeros((T, nv))
    tau_out = np.zeros((T, nv))
    grf_out = np.zeros((T, 4, 3))
    resid = np.zeros((T, 6))
    f6 = np.zeros(6)
    nonfoot = 0
    z_fall = cfg.fall_height * ch.z_stand
    cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg))
    foot_geom = np.array([mj.geom_bodyid[g] in foot_bodies for g in range(mj.ngeom)])
    is_floor = np.zeros(mj.ngeom, bool)
    is_floor[list(floor)] = True
    e_rot = np.zeros(3)
    quat = np.zeros(4)
    qfrc = np.zeros(nv)
    for k in range(T):
        q_out[k], qd_out[k] = d.qpos, d.qvel
        k1 = min(k + 1, T - 1)
        qa_ref, qb_ref = q_ref[k], q_ref[k1]
        if np.dot(qa_ref[3:7], qb_ref[3:7]) < 0:
            qb_ref = qb_ref.copy()
            qb_ref[3:7] *= -1
        acc_tau = np.zeros(nv)
        acc_grf = np.zeros((4, 3))
        for i in range(n):
            a = i / n
            qr = (1 - a) * qa_ref + a * qb_ref
            qdr = (1 - a) * qd_ref[k] + a * qd_ref[k1]
            quat[:] = qr[3:7] / np.linalg.norm(qr[3:7])
            qfrc[6:] = ((1 - a) * ff[k, 6:] + a * ff[k1, 6:] + kp * (qr[7:] - d.qpos[7:])
                        + kd * qdr[6:])
            mujoco.mju_subQuat(e_rot, quat, d.qpos[3:7])  # body-frame rotation to the reference
            qfrc[:3] = ((1 - a) * id_res[k, :3] + a * id_res[k1, :3]
                        + mass * (wr * wr * (qr[:3] - d.qpos[:3])
                                  + 2 * cfg.root_zeta * wr * (qdr[:3] - d.qvel[:3])))
            qfrc[3:6] = ((1 - a) * id_res[k, 3:] + a * id_res[k1, 3:]
                         + I_root * (wr * wr * e_rot + 2 * cfg.root_zeta * wr * (qdr[3:6] - d.qvel[3:6])))
            d.qfrc_applied[:] = qfrc
            mujoco.mj_step(mj, d)
            acc_tau += qfrc
            acc_tau[6:] -= kd * d.qvel[6:]  # the implicit damping acted with the new velocity
            if d.ncon:
                g1 = d.contact.geom1[: d.ncon]
                g2 = d.contact.geom2[: d.ncon]
                sp = None
                for c in range(d.ncon):
                    if is_floor[g1[c]]:
                        other, sign = g2[c], 1.0
                    elif is_floor[g2[c]]:
                        other, sign = g1[c], -1.0
                    else:
                        continue
                    if not foot_geom[other]:
                        nonfoot += 1
                        continue
                    mujoco.mj_contactForce(mj, d, c, f6)
                    con = d.contact[c]
                    fw = sign * (con.frame.reshape(3, 3).T @ f6[:3])
                    if sp is None:
                        sp = d.site_xpos[ch.contact_sites]
                    j = int(np.argmin(((sp - con.pos) ** 2).sum(axis=1)))
                    acc_grf[j] += fw
        tau_out[k] = acc_tau / n
        grf_out[k] = acc_grf / n
        resid[k] = tau_out[k, :6]
        z = d.qpos[2]
        up = d.xmat[ch.pelvis].reshape(3, 3)[2, 2]
        if not np.all(np.isfinite(d.qpos)) or z < z_fall or up < cos_tilt:
            raise GenerationError(f"the simulated character fell at frame {k}")
    F = np.linalg.norm(resid[:, :3], axis=1) / weight
    Tq = np.linalg.norm(resid[:, 3:], axis=1) / (weight * ch.height)
    hinge_err = np.abs(_wrap(q_out[:, 7:] - q_ref[:, 7:]))
    stats = dict(
        substeps=n,
        timestep=dt,
        residual_force_mean=float(F.mean()),
        residual_force_max=float(F.max()),
        residual_torque_mean=float(Tq.mean()),
        residual_torque_max=float(Tq.max()),
        feedforward_residual_force_mean=float(np.mean(np.linalg.norm(id_res[:, :3], axis=1)) / weight),
        tracking_root_mm=float(np.mean(np.linalg.norm(q_out[:, :3] - q_ref[:, :3], axis=1)) * 1000),
        tracking_joint_deg=float(np.degrees(hinge_err.mean())),
        grf_vertical_mean_over_weight=float(grf_out[..., 2].sum(axis=1).mean() / weight),
        nonfoot_contacts=int(nonfoot),
    )
    return dict(q=q_out, qd=qd_out, tau=tau_out, grf=grf_out, stats=stats)


# =========================================================================================
# clips
# =========================================================================================


@dataclass(frozen=True)
class SynthConfig:
    """What :func:`generate_clip` makes. ``frames`` is a clip length or a (min, max) range."""

    frames: int | tuple[int, int] = (150, 300)
    fps: float = 30.0
    layout: str = "body25"
    physics: bool = False
    kinds: tuple[str, ...] | None = None  # motion kinds to draw from (default: all)
    height_m: tuple[float, float] = (1.5, 1.95)
    camera: CameraConfig = field(default_factory=CameraConfig)
    corruption: Corruption = field(default_factory=Corruption)
    physics_cfg: PhysicsConfig = field(default_factory=PhysicsConfig)
    max_attempts: int = 12

    def to_json(self) -> dict:
        return _jsonable(dataclasses.asdict(self))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def _stance_runs(planted: np.ndarray) -> dict:
    return {name: [[int(a), int(b)] for a, b in _runs(planted[:, i])]
            for i, name in enumerate(CONTACT_SITES)}


def clip_name(index: int) -> str:
    return f"synth_{index:06d}"


def generate_clip(seed: int, index: int = 0, config: SynthConfig = SynthConfig(),
                  name: str | None = None) -> Clip:
    """One synthetic clip, deterministic in ``(seed, index, config)``.

    Draws a subject height, plans and solves a motion (retrying with fresh draws when a
    motion fails its kinematic checks, or falls in the physics variant), crops a window of the
    requested length, optionally tracks it in simulation, samples a camera and projects and
    corrupts the 2D keypoints.
    """
    layout = get_layout(config.layout)
    kinds = tuple(config.kinds) if config.kinds else tuple(SEGMENTS)
    for k in kinds:
        if k not in SEGMENTS:
            raise ValueError(f"unknown motion kind {k!r}; known: {sorted(SEGMENTS)}")
    fr = config.frames
    errors = []
    for attempt in range(config.max_attempts):
        rng = np.random.default_rng([int(seed), int(index), attempt])
        T = int(fr) if np.isscalar(fr) else int(rng.integers(int(fr[0]), int(fr[1]) + 1))
        if T < 2:
            raise ValueError(f"frames per clip must be >= 2, got {T}")
        height = round(float(rng.uniform(*config.height_m)), 2)
        try:
            motion = generate_motion(height, rng, T / config.fps + 0.5, config.fps, kinds)
            check_motion(motion)
            if motion.num_frames < T:
                raise GenerationError("motion shorter than the clip")
            start = int(rng.integers(0, motion.num_frames - T + 1))
            motion = motion.slice(start, start + T)
            ch = motion.character
            meta: dict[str, Any] = {}
            q = motion.q
            tau = grf = None
            if config.physics:
                sim = simulate_tracking(ch, q, config.fps, motion.planted, config.physics_cfg)
                q, qd, tau, grf = sim["q"], sim["qd"], sim["tau"], sim["grf"]
                meta["physics"] = sim["stats"]
            else:
                qd = velocities(ch.mj, q, config.fps)
            kp3d, contacts = _ground_truth(ch, q, layout, config.fps)
            if config.physics:
                heights = site_trajectories(ch, q, ch.check_sites)[..., 2]
                meta["physics"]["min_site_height"] = float(heights.min())
            K, size, E, cam_info = sample_camera(rng, kp3d, config.camera)
            uv, _ = project_points(K, E, kp3d)
            kp2d, corr = corrupt_keypoints(rng, uv, layout, size, config.corruption)
        except GenerationError as e:
            errors.append(f"attempt {attempt}: {e}")
            continue
        counts = np.bincount(motion.kind, minlength=len(MOTION_KINDS))
        present = [MOTION_KINDS[i] for i in np.nonzero(counts)[0]]
        main = [MOTION_KINDS[i] for i in np.argsort(-counts) if counts[i] > 0 and MOTION_KINDS[i] != "stand"]
        kind = main[0] if main else "stand"
        meta.update(
            generator=GENERATOR,
            seed=int(seed),
            index=int(index),
            attempt=attempt,
            kind=kind,
            kinds=present,
            kind_per_frame=[[MOTION_KINDS[int(motion.kind[a])], int(a), int(b)]
                            for a, b in _kind_runs(motion.kind)],
            physics_variant=bool(config.physics),
            planned_contacts=_stance_runs(motion.planted),
            flight_frames=int(motion.flight.sum()),
            camera=_jsonable(cam_info),
            corruption=_jsonable(dataclasses.asdict(config.corruption)),
            corruption_stats=corr,
            contact_rule=dict(max_step_m=CONTACT_MAX_STEP_M, max_height_m=CONTACT_MAX_HEIGHT_M,
                              frame0="displacement to frame 1"),
            clean_keypoints2d="project gt_keypoints3d with intrinsics/extrinsics "
                              "(jmocap.data.synthetic.clean_keypoints2d)",
            kinematic=_jsonable({k: v for k, v in motion.info.items() if k in ("passes", "ik_err")}),
        )
        return Clip(
            name=name or clip_name(index),
            layout=layout.name,
            fps=config.fps,
            keypoints=kp2d,
            intrinsics=K,
            image_size=size,
            extrinsics=E,
            gt_q=q,
            gt_qd=qd,
            gt_keypoints3d=kp3d,
            gt_contacts=contacts,
            gt_tau=tau,
            gt_grf=grf,
            height_m=round(ch.height, 6),
            mass_kg=round(ch.mass, 6),
            meta=meta,
        )
    raise GenerationError(f"clip {index} (seed {seed}): no valid motion in {config.max_attempts} "
                          f"attempts: " + "; ".join(errors[-3:]))


def _kind_runs(kind):
    out = []
    a = 0
    for i in range(1, len(kind) + 1):
        if i == len(kind) or kind[i] != kind[a]:
            out.append((a, i))
            a = i
    return out


def synthesize(n: int, seed: int, config: SynthConfig = SynthConfig(), start: int = 0) -> Iterator[Clip]:
    """Clips ``start .. start + n - 1`` of the stream for ``seed``."""
    for i in range(start, start + n):
        yield generate_clip(seed, i, config)


__all__ = [
    "CONTACT_MAX_HEIGHT_M",
    "CONTACT_MAX_STEP_M",
    "MOTION_KINDS",
    "CameraConfig",
    "Character",
    "Corruption",
    "GenerationError",
    "Motion",
    "PhysicsConfig",
    "SynthConfig",
    "character",
    "check_motion",
    "clean_keypoints2d",
    "contact_labels",
    "corrupt_keypoints",
    "generate_clip",
    "generate_motion",
    "look_at_extrinsics",
    "motion_report",
    "project_points",
    "sample_camera",
    "simulate_tracking",
    "site_trajectories",
    "synthesize",
    "velocities",
]
