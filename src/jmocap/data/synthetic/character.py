"""The character: a scaled humanoid, its legs' geometry, leg inverse kinematics.

:class:`Character` wraps a :class:`jmocap.Model` (``jmocap.model.character``) and precomputes
what the generator needs about it: the standing pose, joint ranges, each leg's hinge chain and
foot geometry in the foot's ground frame (contact sites, toe hinge, sole points). The legs are
solved by damped Gauss-Newton on a numpy transcription of MuJoCo's kinematics for the hinge
chain (checked against MuJoCo C in the tests); :func:`_solve_all` solves every frame of a
motion and returns the whole-body centre of mass. :func:`character` caches one per height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from jmocap.constants import DEFAULT_HEIGHT_M
from jmocap.data.synthetic.rotations import _exp_rot, _log_rot, _quat2mat, _ry, _rz
from jmocap.layouts import CONTACT_SITES
from jmocap.model import character as scaled_character
from jmocap.model import site_trajectory

_DEBUG = False

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

    Wraps a :class:`jmocap.Model` (``jmocap.model.character(height_m, mass_kg)``) and a scratch
    ``MjData``. Joint names follow ``jmocap/assets/mjcf/humanoid.xml`` (SMPL bodies,
    ``<body>_x/_y/_z`` hinges).
    """

    def __init__(self, model):
        self.model = model
        self.spec_args = None  # (height, mass) of jmocap.model.scaled_spec, set by character()
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
        self.scale = self.height / DEFAULT_HEIGHT_M
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
        -> knee -> ankle (``tests/test_synthetic_character.py`` checks it against MuJoCo C).
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
    """A cached :class:`Character` for a height (rounded to 1 cm; mass for a BMI of 22), on the
    package's one model cache (:func:`jmocap.model.character`)."""
    h = round(float(height_m), 2)
    ch = _CHAR_CACHE.get(h)
    if ch is None:
        mass = 22.0 * h * h  # BMI 22
        ch = Character(scaled_character(h, mass))
        ch.spec_args = (h, mass)  # jmocap.model.scaled_spec's arguments (the terrain's simulation model)
        if len(_CHAR_CACHE) > 64:
            _CHAR_CACHE.pop(next(iter(_CHAR_CACHE)))
        _CHAR_CACHE[h] = ch
    return ch


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


def site_trajectories(ch: Character, q: np.ndarray, sites) -> np.ndarray:
    """World positions (T, n, 3) of the given site ids along a trajectory (MuJoCo C FK)."""
    return site_trajectory(ch.mj, q, sites)
