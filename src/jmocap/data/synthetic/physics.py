"""The physics variant: track a kinematic motion in a MuJoCo C simulation moved by contacts alone.

:func:`simulate_tracking` runs a whole-body tracking controller at every simulation substep
(:func:`_control`): desired accelerations for all dofs (reference acceleration + PD, root
included) are traded off, by a bounded least squares, against contact forces at the foot
points MuJoCo has on the floor (non-negative combinations of the edges of the
``FRICTION_MU`` pyramid) such that the *root rows* of the equation of motion hold with no root
force; the resulting hinge torques are applied and MuJoCo's own contact solver produces the
real contact forces, which are the ground truth. The root is moved by gravity and contacts only;
a penalised root residual is switched on only while the root pose error exceeds
:attr:`PhysicsConfig.rescue_pos_m` / :attr:`PhysicsConfig.rescue_rot_deg` (recorded as
``residual``). Forces are sampled at the frames by the tent average that matches central
differences of the frame positions (:func:`tent_average`); per-site forces come from a lever
split of each contact force between its foot's heel and toe sites on the floor
(:func:`floor_split`), per-foot force, centre of pressure and free moment from MuJoCo's contact points
(:func:`foot_cop_free_moment`). :class:`PhysicsConfig` holds the settings; ``docs/data.md``
describes the whole design.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.optimize import nnls

from jmocap.constants import FLOOR_NORMAL, FRICTION_CONE, FRICTION_MU, GRAVITY
from jmocap.data.synthetic.character import Character
from jmocap.data.synthetic.curves import _wrap
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.ground_truth import velocities
from jmocap.model import scaled_spec
from jmocap.scene import Scene, add_to_spec, boxes, height_above, surface_height
from jmocap.simulator import FootContacts as _Contacts
from jmocap.simulator import contact_forces as _contact_forces  # noqa: F401  (re-exported)
from jmocap.simulator import (  # noqa: F401  (re-exported: the synthetic physics API)
    floor_split,
    foot_geom_map,
    lever_split,
    record_foot_forces,
    simulation_model,
    substep_records,
    tent_average,
    tent_weights,
)
from jmocap.simulator import foot_contacts as _floor_contacts  # noqa: F401

#: a foot contact whose normal is more than 8 degrees off its ground geom's top-face normal (the
#: box's z axis: vertical for steps, tilted for a ramp) touches a terrain box's side or edge
#: (:func:`simulate_tracking`)
EDGE_NORMAL_Z = math.cos(math.radians(8.0))


@dataclass(frozen=True)
class SamplingConfig:
    """The sampling controller of :func:`jmocap.data.synthetic.sampling.simulate_sampling`
    (``PhysicsConfig.controller = "sampling"``). Cost weights are per frame, on errors in metres and radians."""

    # "qp": every sample is driven by the QP tracker's whole-body inverse dynamics (its hinge
    # torques solved with the contacts, the root rows with no root force) towards the plan's
    # hinge angles plus the sample's offset, re-solved every ``qp_substeps`` substeps (stop 63);
    # "servo": position servos on the hinges plus a feed-forward (stop 44), cheaper per sample
    # but pushing planted feet past friction (docs/data.md, "Why its feet skate")
    actuation: str = "qp"
    samples: int = 0  # per window; 0: the actuation's default (qp 16, servo 64)
    qp_substeps: int = 6  # "qp": the QP is solved every this many substeps, its torques held between
    # durations in seconds, rounded to whole frames at the clip's rate (3, 12 and 1 frames at 30 fps)
    window_s: float = 0.1  # one control window
    lookahead_s: float = 0.4  # simulated past the window to score a sample
    pd_freq_hz: float = 8.0  # "servo": the servos' frequency
    sigma: float = 0.1  # rad, the offsets' standard deviation
    # the hinges sampled with the full ``sigma`` (names containing one of these: the legs and
    # the trunk, which balance the body); the others (arms, head) with ``other_sigma`` x sigma
    sampled: tuple[str, ...] = ("hip", "knee", "ankle", "foot", "spine")
    other_sigma: float = 0.3
    # offsets blend linearly from the one in force to the sample's over the window's first
    # ``ramp_s`` (continuous servo targets; 0: switched at the window's start)
    ramp_s: float = 1 / 30
    carry: float = 0.7  # the next window's mean offset, times the chosen one
    # sample i is drawn with sigma x sigma_scales[i % len]: small changes to choose from as well
    # as large ones
    sigma_scales: tuple[float, ...] = (1.0,)
    w_change: float = 0.0  # cost of the offset's change, per mean squared radian over the hinges
    lookahead_gain: float = 0.5  # the offset kept over the lookahead
    elite: int = 1  # > 1: the mean of this many best samples is tried too (measured, not taken: docs/data.md)
    w_support: float = 10.0  # root - feet (horizontal), against the plan's
    w_height: float = 10.0
    w_rot: float = 2.0
    w_pose: float = 5.0  # mean squared hinge error
    w_vel: float = 1.0  # root linear velocity
    w_pos: float = 0.3  # root world position
    feedforward_margin_m: float = 0.005  # "servo": plan foot geoms this near the floor support it (feed-forward)
    backtrack_tilt_deg: float = 25.0
    backtrack_windows: int = 2
    backtrack_factor: int = 4  # samples x this after a backtrack
    backtrack_sigma: float = 2.0  # and sigma x this
    max_backtracks: int = 8  # without the rescue: backtracks of a clip before it fails
    # the rescue (0: off): after this many backtracks at one place (each failure within a window
    # of the first), the windows from the backtrack's start through ``rescue_s`` past the failed
    # window are stepped with a root wrench, a PD towards the plan's root at ``rescue_freq_hz``
    # (critically damped, through the root block of the mass matrix) recorded as ``residual``,
    # and the servos at the plan (the offset decaying by ``carry`` per window); the search then
    # resumes. The clip fails only where a rescued window loses its balance too
    rescue_after: int = 5
    rescue_s: float = 0.0
    rescue_freq_hz: float = 1.0
    threads: int = 2  # rollout threads

    def __post_init__(self):
        if self.actuation not in ("qp", "servo"):
            raise ValueError(f"SamplingConfig.actuation must be 'qp' or 'servo', got {self.actuation!r}")
        if self.samples < 0 or self.qp_substeps < 1:
            raise ValueError("SamplingConfig needs samples >= 0 and qp_substeps >= 1")

    @property
    def num_samples(self) -> int:
        """Samples per window: ``samples``, or the actuation's default when 0."""
        return self.samples or (16 if self.actuation == "qp" else 64)


@dataclass(frozen=True)
class PhysicsConfig:
    """Tracking controller of the physics variant (see ``docs/data.md``).

    Desired accelerations ``qdd_ref + w^2 (q_ref - q) + 2 zeta w (qd_ref - qd)`` (hinges:
    ``joint_freq_hz``; root: ``root_freq_hz``), weighted by the standing pose's joint-space
    inertia (``sqrt(M_ii)`` per row, times ``w_root`` / ``w_joint``); planted contact points
    held still (``w_contact``, a velocity damping at ``contact_damping_hz``); edge coefficients
    regularised by ``w_force`` (per newton, relative to ``sqrt(mass)``). The rescue residual is
    on while the root is more than ``rescue_pos_m`` or ``rescue_rot_deg`` off the reference and
    off again below ``rescue_off`` times both; it costs ``w_residual`` per newton. ``settle_s``:
    the settled start, seconds of the motion before the clip (a standing hold where the motion
    has fewer) simulated and dropped, so the clip starts in equilibrium with the floor.
    """

    substeps_per_frame: int = 0  # 0: as many as make the step <= max_dt
    max_dt: float = 0.002
    joint_freq_hz: float = 6.0
    root_freq_hz: float = 2.0
    zeta: float = 1.0
    w_root: float = 1.0
    w_joint: float = 1.0
    w_contact: float = 10.0
    contact_damping_hz: float = 5.0
    w_force: float = 1e-3
    rescue_pos_m: float = 0.10
    rescue_rot_deg: float = 15.0
    rescue_off: float = 0.5
    w_residual: float = 1.0
    contact_force_threshold: float = 0.01  # fraction of body weight: force contact label, CoP
    site_floor_m: float = 0.02  # a contact site this high or lower may take force (floor_split)
    contact_timeconst: float = 0.008  # MuJoCo solref time constant of the contacts (s)
    fall_height: float = 0.5  # fraction of the standing pelvis height
    fall_tilt_deg: float = 60.0
    # terrain: a simulation whose feet touch a box's side or edge on more than this share of the
    # frames (a foot caught on a step) fails, and the clip is drawn again
    max_edge_contact_share: float = 0.05
    settle_s: float = 0.5  # lead-in simulated before the clip's first frame and dropped
    # "qp": the QP tracker with the rescue residual (simulate_tracking); "sampling": sampling-based
    # control, a root force only in its rescues (jmocap.data.synthetic.sampling.simulate_sampling)
    controller: str = "qp"
    sampling: SamplingConfig = field(default_factory=SamplingConfig)

    def settle_frames(self, fps: float) -> int:
        """Frames of lead-in (``settle_s`` at ``fps``) that :func:`simulate_tracking`'s caller
        puts before the clip (docs/data.md, "The first frame")."""
        return int(round(self.settle_s * fps))


@functools.cache
def pyramid_edges() -> np.ndarray:
    """The 4 edges (4, 3) of the floor's friction pyramid: ``jmocap.physics.friction_pyramid_edges``
    for the floor normal and ``FRICTION_MU`` (MuJoCo's pyramidal cone: ``n +- mu t1``,
    ``n +- mu t2``; the floor's tangent axes are world x and y)."""
    from jmocap.physics.qp import friction_pyramid_edges

    return np.asarray(friction_pyramid_edges(np.asarray(FLOOR_NORMAL, float), FRICTION_MU, 4), float)


def terrain_model(ch: Character, scene: Scene | None) -> mujoco.MjModel:
    """The character's model with the terrain's boxes as static world geoms
    (:func:`jmocap.scene.add_to_spec`); ``ch.mj`` itself without a scene. The character's bodies,
    joints and sites are unchanged (the boxes are geoms of the world body)."""
    if scene is None or not boxes(scene):
        return ch.mj
    if ch.spec_args is None:
        raise ValueError("a terrain simulation needs a character made by character(height)")
    spec = scaled_spec(None, *ch.spec_args)
    add_to_spec(spec, scene, friction=FRICTION_MU)
    mj = spec.compile()
    if mj.nq != ch.mj.nq or not np.allclose(mj.body_mass, ch.mj.body_mass) or not np.allclose(mj.body_pos, ch.mj.body_pos):
        raise ValueError("the terrain model's character differs from the generator's")
    return mj


def reference_derivatives(mj: mujoco.MjModel, q_ref: np.ndarray, fps: float):
    """Velocities (``mj_differentiatePos`` central differences) and accelerations (central
    differences of those, one-sided at the ends) of a reference motion."""
    qd = velocities(mj, q_ref, fps)
    qdd = np.zeros_like(qd)
    if len(q_ref) > 1:
        qdd[1:-1] = (qd[2:] - qd[:-2]) * fps / 2
        qdd[0], qdd[-1] = (qd[1] - qd[0]) * fps, (qd[-1] - qd[-2]) * fps
    return qd, qdd


def foot_cop_free_moment(force: np.ndarray, moment: np.ndarray, fallback: np.ndarray, threshold: float,
                         plane_z: np.ndarray | float = 0.0):
    """Centre of pressure (..., 3) on the horizontal surface at height ``plane_z`` (the floor, 0,
    or a box top under the foot) and free moment (...) of a foot's force (..., 3) and moment
    about the world origin (..., 3): the force-plate formulas for a plate at height ``h``,
    ``x = (h F_x - M_y) / F_z``, ``y = (M_x + h F_y) / F_z``, ``tau = M_z - (x F_y - y F_x)``.
    Where ``F_z <= threshold`` the CoP is ``fallback`` (..., 3) put on the surface and the free
    moment 0."""
    fz = force[..., 2]
    h = np.broadcast_to(np.asarray(plane_z, float), fz.shape)
    loaded = fz > threshold
    safe = np.where(loaded, fz, 1.0)
    x = np.where(loaded, (h * force[..., 0] - moment[..., 1]) / safe, fallback[..., 0])
    y = np.where(loaded, (moment[..., 0] + h * force[..., 1]) / safe, fallback[..., 1])
    tau = np.where(loaded, moment[..., 2] - (x * force[..., 1] - y * force[..., 0]), 0.0)
    return np.stack([x, y, h.copy()], axis=-1), tau


def force_contact_labels(grf: np.ndarray, foot_force: np.ndarray, site_z: np.ndarray, threshold: float,
                         floor_m: float) -> np.ndarray:
    """Contact labels (T, 4) of the sites (L heel, L toe, R heel, R toe): a site is in contact when
    its vertical force (``grf`` (T, 4, 3), from :func:`floor_split`) exceeds ``threshold`` N, or
    when its foot's vertical force (``foot_force`` (T, 2, 3)) does and the site is on the floor
    (``site_z`` (T, 4) at most ``floor_m``: the sites that may take the foot's force).

    So every site with force is labelled in contact, and a labelled site is on the floor or
    carries force; a site of a loaded foot that rests on the floor while the load goes through
    the other site (a flat foot with the centre of pressure at the heel) is in contact with a
    small force, as Signorini's condition allows."""
    loaded = np.repeat(foot_force[..., 2] > threshold, 2, axis=-1)
    return ((grf[..., 2] > threshold) | (loaded & (site_z <= floor_m))).astype(np.float32)


def _contact_jacobians(mj, d, con: _Contacts, E: np.ndarray, jp: np.ndarray):
    """Generalised forces of the pyramid edges at the contact points, ``A`` (nv, 4k), and the
    points' Jacobians ``Jc`` (3k, nv) (``mj_jac`` on the foot bodies; ``jp``: a (3, nv) buffer)."""
    A_cols, J_rows = [], []
    for p, b in zip(con.pos, con.body, strict=True):
        mujoco.mj_jac(mj, d, jp, None, p, int(b))
        A_cols.append(jp.T @ E.T)
        J_rows.append(jp.copy())
    if not A_cols:
        return np.zeros((mj.nv, 0)), np.zeros((0, mj.nv))
    return np.hstack(A_cols), np.vstack(J_rows)


def _control(M, h, A, Jc, vc, a_des, sw, cfg: PhysicsConfig, mass: float, residual: bool):
    """One whole-body tracking step: generalised force (nv,) to apply (root entries: the residual).

    Unknowns: hinge accelerations x, edge coefficients c >= 0 and, while ``residual``, a root
    wrench r; the root acceleration is eliminated with the root rows of
    ``M qdd + h = A c + [r; tau]`` (r = 0 otherwise). Minimises ``|sw (qdd - a_des)|^2 +
    w_contact^2 mass |Jc qdd + k vc|^2 + w_force^2 mass |c|^2 + w_residual^2 |r|^2 / mass``: the
    unconstrained (x, r) are projected out (QR), the rest is a non-negative least squares in c
    (Lawson-Hanson ``nnls``)."""
    nv = len(h)
    nj = nv - 6
    nr = 6 if residual else 0
    Minv = np.linalg.inv(M[:6, :6])
    B = Minv @ M[:6, 6:]
    g0 = Minv @ h[:6]
    P = Minv @ A[:6]
    m = P.shape[1]
    # qdd_r = Kr z + P c - g0 with z = [x, r]; rows K z + H c - y
    Kr = np.hstack([-B, Minv[:, :nr]])
    blocks = [
        (sw[:6, None] * Kr, sw[:6, None] * P, sw[:6] * (g0 + a_des[:6])),
        (np.hstack([np.diag(sw[6:]), np.zeros((nj, nr))]), np.zeros((nj, m)), sw[6:] * a_des[6:]),
    ]
    if len(Jc):
        sc = cfg.w_contact * math.sqrt(mass)
        Jr = Jc[:, :6]
        kv = 2 * math.pi * cfg.contact_damping_hz
        Kc = Jr @ Kr
        Kc[:, :nj] += Jc[:, 6:]
        blocks.append((sc * Kc, sc * (Jr @ P), sc * (Jr @ g0 - kv * vc)))
    if residual:
        blocks.append((np.hstack([np.zeros((6, nj)), cfg.w_residual / math.sqrt(mass) * np.eye(6)]),
                       np.zeros((6, m)), np.zeros(6)))
    K = np.vstack([b[0] for b in blocks])
    H = np.vstack([b[1] for b in blocks])
    y = np.concatenate([b[2] for b in blocks])
    nz = nj + nr
    Q, R = np.linalg.qr(K, mode="complete")
    c = np.zeros(m)
    if m:
        Q2 = Q[:, nz:]
        Ac = np.vstack([Q2.T @ H, cfg.w_force * math.sqrt(mass) * np.eye(m)])
        bc = np.concatenate([Q2.T @ y, np.zeros(m)])
        c, _ = nnls(Ac, bc, maxiter=50 * m)
    z = np.linalg.solve(R[:nz], Q[:, :nz].T @ (y - H @ c))
    x, r = z[:nj], z[nj:]
    qdd = np.concatenate([Kr @ z + P @ c - g0, x])
    tau = M @ qdd + h - A @ c
    tau[:6] = r if residual else 0.0
    return tau


def foot_geoms(ch: Character, mj: mujoco.MjModel):
    """``(floor, geom_foot, geom_body)`` (ngeom,): the ground (the floor plane and the terrain's
    boxes: every geom of the world body), each geom's foot (0 left, 1 right, -1 none) and body
    (:func:`jmocap.simulator.foot_geom_map` of the character's legs)."""
    return foot_geom_map(mj, tuple((L.ankle_body, L.toe_body) for L in ch.legs))


def _rescue(on: bool, pos_err: float, rot_err: float, cfg: PhysicsConfig) -> bool:
    """Hysteresis of the rescue residual: on when the root is more than ``rescue_pos_m`` or
    ``rescue_rot_deg`` off the reference, off again when below ``rescue_off`` times both."""
    p, a = cfg.rescue_pos_m, math.radians(cfg.rescue_rot_deg)
    if pos_err > p or rot_err > a:
        return True
    if pos_err < cfg.rescue_off * p and rot_err < cfg.rescue_off * a:
        return False
    return on


def simulate_tracking(ch: Character, q_ref: np.ndarray, fps: float, cfg: PhysicsConfig = PhysicsConfig(),
                      lead: int = 0, scene: Scene | None = None) -> dict:
    """Track a kinematic motion in MuJoCo C, moved by hinge torques and contacts (a penalised
    root residual only while the root is far off the reference).

    ``lead``: the first ``lead`` frames of ``q_ref`` are a lead-in, simulated and dropped: the
    returned arrays start at ``q_ref[lead]`` (the settled start, ``PhysicsConfig.settle_s``), and
    their first frame's forces are the full tent average over the lead-in's last substeps. The
    character falling during the lead-in fails the simulation too.

    Returns, sampled at the frames (forces by :func:`tent_average`): ``q``, ``qd`` (T, nq/nv) the
    simulated states; ``tau`` (T, nv) the applied generalised forces (root residual, hinge
    torques); ``residual`` (T, 6) = ``tau[:, :6]``; ``grf`` (T, 4, 3) the world-frame contact
    forces on the feet, split between each foot's heel and toe sites on the floor
    (:func:`floor_split`); ``foot_force`` (T, 2, 3), ``cop`` (T, 2, 3), ``free_moment`` (T, 2) per
    foot (left, right); ``contacts`` (T, 4) contact labels by force and floor
    (:func:`force_contact_labels`); and ``stats`` (of the returned frames).

    ``scene``: the terrain (:mod:`jmocap.scene`), simulated as static boxes beside the floor
    (:func:`terrain_model`); heights (the labels' "on the floor", the split's raised sites, the
    fall test) are then measured above the terrain under each point. A foot that touches a box
    anywhere but its top (a side or an edge: a contact normal more than 8 degrees off the top
    face's) is simulated as MuJoCo has it (a scuffed step edge); its frames are counted
    (``stats["edge_contact_frames"]``): only there, and on a ramp (whose pyramid is tilted with
    its top), may a ground-truth force leave the floor's friction pyramid. More than
    ``cfg.max_edge_contact_share`` of the frames (a foot caught on a step) fails the simulation.
    """
    T = len(q_ref)
    if not 0 <= lead < T:
        raise ValueError(f"lead-in of {lead} frames needs 0 <= lead < len(q_ref) = {T}")
    frame_dt = 1.0 / fps
    n = cfg.substeps_per_frame or max(1, int(math.ceil(frame_dt / cfg.max_dt - 1e-9)))
    dt = frame_dt / n
    mj = simulation_model(terrain_model(ch, scene), dt, cfg.contact_timeconst)
    nv = mj.nv
    qd_ref, qdd_ref = reference_derivatives(mj, q_ref, fps)
    d = mujoco.MjData(mj)
    d.qpos[:] = ch.q_stand
    mujoco.mj_forward(mj, d)
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(mj, d, M)
    sw = np.sqrt(np.diag(M)) * np.r_[np.full(6, cfg.w_root), np.full(nv - 6, cfg.w_joint)]
    kp = (2 * np.pi * np.r_[np.full(6, cfg.root_freq_hz), np.full(nv - 6, cfg.joint_freq_hz)]) ** 2
    kd = 2 * cfg.zeta * np.sqrt(kp)
    mass = float(np.sum(mj.body_mass))
    weight = mass * GRAVITY
    E = pyramid_edges()
    floor, geom_foot, geom_body = foot_geoms(ch, mj)
    sites = ch.contact_sites
    z_fall = cfg.fall_height * ch.z_stand
    cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg))

    d.qpos[:] = q_ref[0]
    d.qvel[:] = qd_ref[0]
    mujoco.mj_forward(mj, d)
    q_out = np.zeros((T, mj.nq))
    qd_out = np.zeros((T, nv))
    sub = substep_records(T * n, nv)
    site_z = np.zeros((T, 4))
    edge = np.zeros(T, bool)
    root_err = np.zeros((T, 2))
    nonfoot = 0
    rescue = False
    e = np.zeros(nv)
    e_rot = np.zeros(3)
    jp = np.zeros((3, nv))
    for k in range(T):
        q_out[k], qd_out[k] = d.qpos, d.qvel
        k1 = min(k + 1, T - 1)
        qa, qb = q_ref[k], q_ref[k1].copy()
        if np.dot(qa[3:7], qb[3:7]) < 0:
            qb[3:7] *= -1
        for i in range(n):
            s = k * n + i
            a = i / n
            mujoco.mj_step1(mj, d)
            qr = (1 - a) * qa + a * qb
            qdr = (1 - a) * qd_ref[k] + a * qd_ref[k1]
            qddr = (1 - a) * qdd_ref[k] + a * qdd_ref[k1]
            mujoco.mju_subQuat(e_rot, qr[3:7] / np.linalg.norm(qr[3:7]), d.qpos[3:7])
            e[:3], e[3:6], e[6:] = qr[:3] - d.qpos[:3], e_rot, _wrap(qr[7:] - d.qpos[7:])
            err = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e_rot))
            if i == 0:
                root_err[k] = err
            rescue = sub["rescue"][s] = _rescue(rescue, *err, cfg)
            a_des = qddr + kp * e + kd * (qdr - d.qvel)
            con, other = _floor_contacts(d, floor, geom_foot, geom_body)
            nonfoot += other
            if scene is not None and len(con.index):
                # a contact off its ground geom's top face (its z axis; the floor's normal is z)
                g1 = d.contact.geom1[con.index]
                ground = np.where(floor[g1], g1, d.contact.geom2[con.index])
                top = d.geom_xmat[ground].reshape(-1, 3, 3)[:, :, 2]
                if np.min(np.abs(np.sum(d.contact.frame[con.index, :3] * top, -1))) < EDGE_NORMAL_Z:
                    edge[k] = True
            A, Jc = _contact_jacobians(mj, d, con, E, jp)
            sp = d.site_xpos[sites].copy()
            sh = height_above(scene, sp)
            if i == 0:
                site_z[k] = sh
            mujoco.mj_fullM(mj, d, M)
            tau = _control(M, d.qfrc_bias, A, Jc, Jc @ d.qvel, a_des, sw, cfg, mass, rescue)
            d.qfrc_applied[:] = tau
            mujoco.mj_step2(mj, d)
            sub["tau"][s] = tau
            # the step's contact forces (computed in mj_step2 for the contacts of mj_step1)
            record_foot_forces(mj, d, con, sp, sub, s, cfg.site_floor_m, sh)
        up = d.xmat[ch.pelvis].reshape(3, 3)[2, 2]
        if not np.all(np.isfinite(d.qpos)) or height_above(scene, d.qpos[:3]) < z_fall or up < cos_tilt:
            raise GenerationError(f"the simulated character fell at frame {k}")
    out = frames_from_substeps(ch, q_ref, q_out, qd_out, fps, n, lead, cfg, weight, sub, site_z, root_err, nonfoot,
                               scene)
    if scene is not None:
        out["stats"]["edge_contact_frames"] = int(edge[lead:].sum())
        if edge[lead:].mean() > cfg.max_edge_contact_share:
            raise GenerationError(f"a foot caught on the terrain's edges in {int(edge[lead:].sum())} of "
                                  f"{T - lead} frames")
    return out


def frames_from_substeps(ch: Character, q_ref, q_out, qd_out, fps: float, n: int, lead: int, cfg: PhysicsConfig,
                         weight: float, sub: dict, site_z, root_err, nonfoot: int, scene: Scene | None = None) -> dict:
    """The frame values and statistics of a simulation from its substep records (``sub``,
    :func:`substep_records`: ``tau`` the applied generalised forces, the foot forces of
    :func:`record_foot_forces`, ``rescue`` the substeps with a root residual), the frame states ``q_out`` / ``qd_out`` and the
    per-frame ``site_z`` (T, 4, heights above the terrain ``scene``) and ``root_err`` (T, 2); the
    first ``lead`` frames are dropped
    (:func:`simulate_tracking`'s return value)."""
    T = len(q_ref)
    sub_tau, sub_grf, sub_foot, sub_moment = sub["tau"], sub["grf"], sub["foot"], sub["moment"]
    sub_mid, rescue_sub = sub["mid"], sub["rescue"]
    dt = 1.0 / fps / n
    threshold = cfg.contact_force_threshold * weight
    keep = slice(lead, T)
    tau = tent_average(sub_tau, n)[keep]
    grf = tent_average(sub_grf, n)[keep]
    foot_force = tent_average(sub_foot, n)[keep]
    mid = sub_mid[::n][keep]
    plane = np.zeros(mid.shape[:-1]) if scene is None else surface_height(scene, mid[..., :2])
    cop, free_moment = foot_cop_free_moment(foot_force, tent_average(sub_moment, n)[keep], mid, threshold, plane)
    q_out, qd_out, q_ref = q_out[keep], qd_out[keep], q_ref[keep]
    rescue_sub, root_err, site_z = rescue_sub[lead * n:], root_err[keep], site_z[keep]
    residual = tau[:, :6].copy()
    F = np.linalg.norm(residual[:, :3], axis=1) / weight
    Tq = np.linalg.norm(residual[:, 3:], axis=1) / (weight * ch.height)
    res_frames = np.any(residual != 0, axis=1)
    hinge_err = np.abs(_wrap(q_out[:, 7:] - q_ref[:, 7:]))
    stats = dict(
        controller=cfg.controller,
        substeps=n,
        timestep=dt,
        settle_frames=int(lead),
        friction_mu=FRICTION_MU,
        friction_cone=FRICTION_CONE,
        contact_force_threshold_bw=cfg.contact_force_threshold,
        site_floor_m=cfg.site_floor_m,
        residual_frames=int(res_frames.sum()),
        residual_frame_share=float(res_frames.mean()),
        residual_substep_share=float(rescue_sub.mean()),
        residual_force_mean=float(F.mean()),
        residual_force_max=float(F.max()),
        residual_torque_mean=float(Tq.mean()),
        residual_torque_max=float(Tq.max()),
        tracking_root_mm=float(root_err[:, 0].mean() * 1000),
        tracking_root_max_mm=float(root_err[:, 0].max() * 1000),
        tracking_root_deg=float(np.degrees(root_err[:, 1].mean())),
        tracking_joint_deg=float(np.degrees(hinge_err.mean())),
        grf_vertical_mean_over_weight=float(grf[..., 2].sum(axis=1).mean() / weight),
        nonfoot_contacts=int(nonfoot),
    )
    return dict(q=q_out, qd=qd_out, tau=tau, residual=residual, grf=grf, foot_force=foot_force,
                cop=cop, free_moment=free_moment,
                contacts=force_contact_labels(grf, foot_force, site_z, threshold, cfg.site_floor_m),
                stats=stats)
