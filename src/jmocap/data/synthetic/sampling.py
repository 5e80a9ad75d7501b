"""Sampling-based tracking: ground truth moved by joint torques and contacts alone (a root force only in rescues).

The QP tracker of :mod:`jmocap.data.synthetic.physics` follows the kinematic plan frame by frame
and needs a root residual (the "rescue") wherever the plan is not dynamically feasible: its
centre of mass comes from a linear inverted pendulum, so in parts of single support its
zero-moment point lies outside the supporting foot, and a fixed plan tracked with joint PD and
contacts falls (docs/data.md). :func:`simulate_sampling` instead searches, window by window, for
the joint targets that keep a simulated character *balanced* close to the plan, in the spirit
of SAMCON (Liu et al. 2010, "Sampling-based contact-rich motion control") and of Neural MoCon's
sampling control (Huang et al. 2022, Sec. 3.1):

* every sample is driven towards the plan's hinge angles plus a per-window offset, and the root
  is never actuated. ``SamplingConfig.actuation`` says how:

  - ``"qp"`` (the default, stop 63): the QP tracker's whole-body inverse dynamics
    (:func:`jmocap.data.synthetic.physics._control`: hinge torques solved together with the
    friction-pyramid forces of the contacts MuJoCo has, the root rows with no root force,
    touching points held still), re-solved from the sample's own state every ``qp_substeps``
    substeps and held between. Its torques respect the contacts, so planted feet stay planted;
  - ``"servo"`` (stop 44): PD servos on every hinge (MuJoCo position actuators, stiffness
    ``I_i (2 pi f)^2`` and damping ``2 I_i (2 pi f)``, ``I_i`` the standing pose's joint-space
    inertia diagonal) and a feed-forward hinge torque (the QP tracker's torques at the plan's
    own state). Cheaper per sample, but the independent servos push planted feet harder than
    friction holds them (docs/data.md, "Why its feet skate");
* per control window (``window_s`` seconds, in whole frames) ``samples`` offsets are drawn (Gaussian, standard
  deviation ``sigma`` rad, around ``carry`` times the previous window's offset), blended from
  the offset in force over the window's first ``ramp_s``, each is rolled out by ``mujoco.rollout`` (MuJoCo C,
  multi-threaded; the QP actuation in chunks of ``qp_substeps`` substeps, each sample's QP solved
  between them, from a zero solver warm start) over the window and a ``lookahead_s`` of
  further time (the offset then decayed to ``lookahead_gain`` of itself), and scored against
  the plan frame by frame: the root's horizontal position *relative to the feet* (balance
  over the support, not the plan's world path: a walk may lag its plan), its height, its
  orientation, the hinge angles, the root velocity and, weakly, the world position;
* the best sample's window is committed by stepping MuJoCo C itself (the same model, state and
  controls, so the committed motion is exactly the rollout's: ``stats["commit_mismatch"]`` is
  the largest difference, 0) while recording the contact forces as
  :func:`jmocap.data.synthetic.physics.simulate_tracking` does;
* when the pelvis tilts more than ``backtrack_tilt_deg`` from the plan's, the search returns
  ``backtrack_windows`` windows and draws ``backtrack_factor`` times more samples with
  ``backtrack_sigma`` times the spread;
* where the search fails ``rescue_after`` times at one place, the *rescue* steps the windows
  from the backtrack's start through ``rescue_s`` past the failed window with the servos at the
  plan and a root wrench (a critically damped PD towards the plan's root height, orientation
  and place relative to the feet), recorded per frame as the ``residual``; then the search
  resumes. So a motion the search cannot balance keeps its kind (a redrawn clip would select the
  motions that are easy to balance) and its residual says where it was pushed. Without the
  rescue (``rescue_after=0``) the simulation fails after ``max_backtracks``
  (:class:`GenerationError`, the clip is redrawn).

The residual root wrench is zero on every frame outside the rescues. See docs/data.md.
"""

from __future__ import annotations

import copy
import math

import mujoco
import numpy as np
from mujoco import rollout

from jmocap.constants import GRAVITY
from jmocap.data.synthetic.character import Character
from jmocap.data.synthetic.curves import _wrap
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.physics import (
    PhysicsConfig,
    _contact_jacobians,
    _control,
    _floor_contacts,
    foot_geoms,
    frames_from_substeps,
    pyramid_edges,
    record_foot_forces,
    reference_derivatives,
    simulation_model,
    substep_records,
)
from jmocap.model import scaled_spec
from jmocap.simulator import add_servos, rewind, snapshot, tilt


def sampling_model(ch: Character, dt: float, contact_timeconst: float, freq_hz: float):
    """The tracking simulation's model (:func:`~jmocap.data.synthetic.physics.simulation_model`)
    with a position servo on every hinge (:func:`jmocap.simulator.add_servos`); returns
    ``(model, kv)`` with ``kv`` (nv,) each dof's servo damping (0 on the root)."""
    base = simulation_model(ch.mj, dt, contact_timeconst)
    spec = scaled_spec(None, round(ch.height, 2), float(np.sum(ch.mj.body_mass)))
    return add_servos(spec, base, ch.q_stand, freq_hz)


def feedforward(ch: Character, mj, q_ref, qd_ref, qdd_ref, cfg) -> np.ndarray:
    """(T, nv) hinge torques (root entries 0) of the QP tracker at the plan's own states, its
    contacts those foot geoms within ``feedforward_margin_m`` of the floor: the torques that
    would realise the plan's accelerations where its contacts can balance them."""
    m = copy.deepcopy(mj)
    m.geom_margin[:] = cfg.sampling.feedforward_margin_m
    d = mujoco.MjData(m)
    d.qpos[:] = ch.q_stand
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    sw = np.sqrt(np.diag(M)) * np.r_[np.full(6, cfg.w_root), np.full(m.nv - 6, cfg.w_joint)]
    mass = float(np.sum(m.body_mass))
    floor, geom_foot, geom_body = foot_geoms(ch, m)
    E = pyramid_edges()
    jp = np.zeros((3, m.nv))
    out = np.zeros((len(q_ref), m.nv))
    for k in range(len(q_ref)):
        d.qpos[:], d.qvel[:] = q_ref[k], qd_ref[k]
        mujoco.mj_forward(m, d)
        con, _ = _floor_contacts(d, floor, geom_foot, geom_body)
        A, Jc = _contact_jacobians(m, d, con, E, jp)
        mujoco.mj_fullM(m, d, M)
        out[k] = _control(M, d.qfrc_bias.copy(), A, Jc, Jc @ d.qvel, qdd_ref[k], sw, cfg, mass, False)
    out[:, :6] = 0.0
    return out


def _support_points(mj, q, sites) -> np.ndarray:
    """(len(q), 2) the mean horizontal position of the contact sites of each configuration."""
    d = mujoco.MjData(mj)
    out = np.zeros((len(q), 2))
    for i, x in enumerate(q):
        d.qpos[:] = x
        mujoco.mj_kinematics(mj, d)
        out[i] = d.site_xpos[sites, :2].mean(0)
    return out


def simulate_sampling(ch: Character, q_ref: np.ndarray, fps: float, cfg: PhysicsConfig, lead: int = 0,
                      rng: np.random.Generator | None = None) -> dict:
    """Track a kinematic motion in MuJoCo C by sampling-based control (module docstring): hinge
    torques (the QP actuation's, or servos and a feed-forward) and contacts, a root force only
    in the rescues. ``cfg`` is a
    :class:`~jmocap.data.synthetic.physics.PhysicsConfig` (its ``sampling`` settings, substeps,
    contact model, labels); ``lead`` as :func:`~jmocap.data.synthetic.physics.simulate_tracking`,
    whose return value this has (``residual`` zero outside the rescues; ``stats`` adds
    ``controller``, ``actuation``, ``backtracks``, ``samples_simulated``, ``rescues`` and
    ``commit_mismatch``). Deterministic in ``rng`` (default seed 0)."""
    sc = cfg.sampling
    rng = np.random.default_rng(0) if rng is None else rng
    T = len(q_ref)
    if not 0 <= lead < T:
        raise ValueError(f"lead-in of {lead} frames needs 0 <= lead < len(q_ref) = {T}")
    n = cfg.substeps_per_frame or max(1, int(math.ceil(1.0 / fps / cfg.max_dt - 1e-9)))
    dt = 1.0 / fps / n
    qp = sc.actuation == "qp"
    if qp:
        # no actuators: the QP's torques go through qfrc_applied
        mj, kv = simulation_model(ch.mj, dt, cfg.contact_timeconst), np.zeros(ch.mj.nv)
        joints = [j for j in range(mj.njnt) if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    else:
        mj, kv = sampling_model(ch, dt, cfg.contact_timeconst, sc.pd_freq_hz)
        joints = [int(mj.actuator_trnid[a, 0]) for a in range(mj.nu)]
    nv = mj.nv
    nu = len(joints)  # one offset per hinge
    hinge_q = np.array([mj.jnt_qposadr[j] for j in joints])
    if qp and not np.array_equal(hinge_q, np.arange(7, mj.nq)):
        raise ValueError("the QP actuation needs the hinges to be the dofs after the free root")
    names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) for j in joints]
    free = np.array([1.0 if any(p in nm for p in sc.sampled) else sc.other_sigma for nm in names])
    # one frame past the end, the last held, so that the last frame's forces have their substeps
    qr = np.concatenate([q_ref, q_ref[-1:]])
    Te = T + 1
    qd_ref, qdd_ref = reference_derivatives(mj, qr, fps)
    qd_ref[-1], qdd_ref[-1] = 0.0, 0.0
    ff = None if qp else feedforward(ch, mj, qr, qd_ref, qdd_ref, cfg)
    sites = list(ch.contact_sites)
    support_ref = _support_points(mj, qr, sites)
    mass = float(np.sum(mj.body_mass))
    weight = mass * GRAVITY
    floor, geom_foot, geom_body = foot_geoms(ch, mj)
    z_fall = cfg.fall_height * ch.z_stand
    cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg))

    window = max(1, round(sc.window_s * fps))
    lookahead = max(0, round(sc.lookahead_s * fps))
    ramp = max(0, round(sc.ramp_s * fps))
    sub = substep_records(Te * n, nv)
    q_out = np.zeros((Te, mj.nq))
    qd_out = np.zeros((Te, nv))
    site_z = np.zeros((Te, 4))
    root_err = np.zeros((Te, 2))
    nonfoot = np.zeros(Te, int)

    def targets(k0: int, k1: int):
        """Servo targets (steps, nu) and feed-forward (steps, nv) of the substeps of frames k0..k1-1
        (the QP actuation: zero targets, to which the offsets are added, and no feed-forward)."""
        if qp:
            return np.zeros(((k1 - k0) * n, nu)), None
        a = np.arange(n) / n
        tq = [qr[k, hinge_q][None] * (1 - a[:, None]) + qr[min(k + 1, Te - 1), hinge_q][None] * a[:, None]
              for k in range(k0, k1)]
        tf = [ff[k][None] * (1 - a[:, None]) + ff[min(k + 1, Te - 1)][None] * a[:, None] for k in range(k0, k1)]
        return np.concatenate(tq), np.concatenate(tf)

    full_spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    control_spec = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED
    state = np.zeros(mujoco.mj_stateSize(mj, full_spec))
    d = mujoco.MjData(mj)
    d.qpos[:] = qr[0]
    d.qvel[:] = qd_ref[0]
    mujoco.mj_forward(mj, d)
    datas = [mujoco.MjData(mj) for _ in range(max(1, sc.threads))]
    nq = mj.nq

    def cost(states: np.ndarray, k: int) -> np.ndarray:
        """Cost (N,) of the sampled states (N, nstate) at frame k."""
        q = states[:, 1:1 + nq]
        v = states[:, 1 + nq:1 + nq + nv]
        ref = qr[k]
        rel = (q[:, :2] - _support_points(mj, q, sites)) - (ref[:2] - support_ref[k])
        dot = np.abs(q[:, 3:7] @ ref[3:7]) / np.linalg.norm(q[:, 3:7], axis=1)
        rot = 2 * np.arccos(np.clip(dot, 0.0, 1.0))
        return (sc.w_support * np.sum(rel**2, 1) + sc.w_height * (q[:, 2] - ref[2]) ** 2 + sc.w_rot * rot**2
                + sc.w_pose * np.mean(_wrap(q[:, 7:] - ref[7:]) ** 2, 1)
                + sc.w_vel * np.sum((v[:, :3] - qd_ref[k, :3]) ** 2, 1)
                + sc.w_pos * np.sum((q[:, :3] - ref[:3]) ** 2, 1))

    M = np.zeros((nv, nv))
    kp = (2 * math.pi * sc.rescue_freq_hz) ** 2
    kd = 2 * math.sqrt(kp)

    def plan_at(k: int, a: float, feet_xy: np.ndarray):
        """The plan at substep ``a`` (0..1) of frame k, linearly interpolated: ``q`` (nq,), its
        root's horizontal place taken *relative to the feet* (the mean of the contact sites now at
        ``feet_xy``), as the search scores it (a walk that lags its plan is not pulled back);
        ``qd`` and ``qdd`` (nv,)."""
        kb = min(k + 1, Te - 1)
        qa, qb = qr[k], qr[kb].copy()
        if np.dot(qa[3:7], qb[3:7]) < 0:
            qb[3:7] *= -1
        q = (1 - a) * qa + a * qb
        q[:2] += feet_xy - ((1 - a) * support_ref[k] + a * support_ref[kb])
        return q, (1 - a) * qd_ref[k] + a * qd_ref[kb], (1 - a) * qdd_ref[k] + a * qdd_ref[kb]

    def rescue_wrench(k: int, a: float) -> np.ndarray:
        """The rescue's root wrench (6,) at the substep ``a`` (0..1) of frame k: a critically
        damped PD (free-joint coordinates: world force, body-frame torque) through the root
        block of the mass matrix (``d`` after ``mj_step1``) towards the plan's root as the
        search scores it (:func:`plan_at`): its height, orientation and place relative to the feet."""
        ref, qd, _ = plan_at(k, a, d.site_xpos[sites, :2].mean(0))
        vref = qd[:6]
        e = np.zeros(6)
        e[:3] = ref[:3] - d.qpos[:3]
        mujoco.mju_subQuat(e[3:], ref[3:7] / np.linalg.norm(ref[3:7]), d.qpos[3:7])
        mujoco.mj_fullM(mj, d, M)
        return M[:6, :6] @ (kp * e + kd * (vref - d.qvel[:6]))

    # the QP actuation: the QP tracker's gains and weights (PhysicsConfig), no root force
    sw = np.zeros(nv)
    kp_qp = (2 * math.pi * np.r_[np.full(6, cfg.root_freq_hz), np.full(nv - 6, cfg.joint_freq_hz)]) ** 2
    kd_qp = 2 * cfg.zeta * np.sqrt(kp_qp)
    if qp:
        ds = mujoco.MjData(mj)
        ds.qpos[:] = ch.q_stand
        mujoco.mj_forward(mj, ds)
        mujoco.mj_fullM(mj, ds, M)
        sw = np.sqrt(np.diag(M)) * np.r_[np.full(6, cfg.w_root), np.full(nv - 6, cfg.w_joint)]
    E = pyramid_edges()
    jp = np.zeros((3, nv))
    e_qp = np.zeros(nv)
    MM = np.zeros((nv, nv))

    def qp_torque(dd: mujoco.MjData, k: int, a: float, off: np.ndarray) -> np.ndarray:
        """The QP actuation's generalised force (nv,; root entries 0) at ``dd`` (after
        ``mj_step1``), substep ``a`` (0..1) of frame k: :func:`~jmocap.data.synthetic.physics._control`
        (the QP tracker's whole-body inverse dynamics with the contacts MuJoCo has, the root rows
        with no root force) towards the plan's hinge angles plus ``off`` (nu,) and the plan's root
        height and orientation, its horizontal place taken relative to the feet (:func:`plan_at`)."""
        ref, qd, qdd = plan_at(k, a, dd.site_xpos[sites, :2].mean(0))
        rot = np.zeros(3)
        mujoco.mju_subQuat(rot, ref[3:7] / np.linalg.norm(ref[3:7]), dd.qpos[3:7])
        e_qp[:3], e_qp[3:6], e_qp[6:] = ref[:3] - dd.qpos[:3], rot, _wrap(ref[7:] + off - dd.qpos[7:])
        a_des = qdd + kp_qp * e_qp + kd_qp * (qd - dd.qvel)
        con, _ = _floor_contacts(dd, floor, geom_foot, geom_body)
        A, Jc = _contact_jacobians(mj, dd, con, E, jp)
        mujoco.mj_fullM(mj, dd, MM)
        return _control(MM, dd.qfrc_bias, A, Jc, Jc @ dd.qvel, a_des, sw, cfg, mass, False)

    def commit(k0: int, k1: int, ctrl: np.ndarray, force: np.ndarray | None, rescue: bool = False) -> None:
        """Step MuJoCo C over frames k0..k1-1 with the chosen controls, recording the forces;
        ``rescue``: with the rescue's root wrench (:func:`rescue_wrench`) as well. The QP
        actuation: ``ctrl`` holds the offsets per substep and ``force`` is None; the QP is solved
        every ``qp_substeps`` substeps from a zero solver warm start, as in :func:`evaluate`."""
        e_rot = np.zeros(3)
        for k in range(k0, k1):
            q_out[k], qd_out[k] = d.qpos, d.qvel
            mujoco.mju_subQuat(e_rot, qr[k, 3:7] / np.linalg.norm(qr[k, 3:7]), d.qpos[3:7])
            root_err[k] = np.linalg.norm(qr[k, :3] - d.qpos[:3]), np.linalg.norm(e_rot)
            nonfoot[k] = 0
            for i in range(n):
                j = (k - k0) * n + i
                s = k * n + i
                mujoco.mj_step1(mj, d)
                con, other = _floor_contacts(d, floor, geom_foot, geom_body)
                nonfoot[k] += other
                sp = d.site_xpos[sites].copy()
                if i == 0:
                    site_z[k] = sp[:, 2]
                if not qp:
                    d.ctrl[:] = ctrl[j]
                    d.qfrc_applied[:] = force[j]
                elif i % sc.qp_substeps == 0:
                    # a zero warm start where each rollout starts, so the commit is the rollout
                    d.qacc_warmstart[:] = 0.0
                    d.qfrc_applied[:] = qp_torque(d, k, i / n, ctrl[j])
                if rescue:
                    d.qfrc_applied[:6] = rescue_wrench(k, i / n)
                    sub["rescue"][s] = True
                mujoco.mj_step2(mj, d)
                # the generalised force the servos and the feed-forward applied: implicitfast
                # integrates the servos' damping implicitly, so its effective force is taken at
                # the new velocity (qacc the step's acceleration)
                sub["tau"][s] = d.qfrc_actuator + d.qfrc_applied - dt * kv * d.qacc
                record_foot_forces(mj, d, con, sp, sub, s, cfg.site_floor_m)

    def servo_targets(offsets, prev, base_q, a, steps):
        """Servo targets (m, steps + lookahead, nu) of the offsets (m, nu), blended from ``prev``
        by ``a`` over the window's ``steps`` substeps (``lookahead_gain`` of them after)."""
        ctrl = np.repeat(base_q[None], len(offsets), axis=0)
        ctrl[:, :steps] += prev[None, None, :] * (1 - a)[None, :, None] + offsets[:, None, :] * a[None, :, None]
        ctrl[:, steps:] += sc.lookahead_gain * offsets[:, None, :]
        return ctrl

    chunks = [(i, min(i + sc.qp_substeps, n)) for i in range(0, n, sc.qp_substeps)]
    scratch = mujoco.MjData(mj)

    def evaluate_qp(ctrl, k0, k1, k2):
        """The QP actuation's rollouts of the per-substep offsets ``ctrl`` (m, steps, nu) from the
        state in ``state``: per chunk of ``qp_substeps`` substeps, each sample's QP torques at its
        own state, then ``mujoco.rollout`` of all samples over the chunk with those torques held
        (zero solver warm start, as :func:`commit`). Returns the costs (m,) over frames k0+1 .. k2
        and the states (m, nstate) at frame k1, the window's end."""
        m = len(ctrl)
        st = np.repeat(state[None], m, axis=0)
        total = np.zeros(m)
        alive = np.ones(m, bool)
        tau = np.zeros((m, nv))
        end = st
        for j, k in enumerate(range(k0, k2)):
            for i0, i1 in chunks:
                for s in np.flatnonzero(alive):
                    mujoco.mj_setState(mj, scratch, st[s], full_spec)
                    mujoco.mj_step1(mj, scratch)
                    tau[s] = qp_torque(scratch, k, i0 / n, ctrl[s, j * n + i0])
                out, _ = rollout.rollout(mj, datas, st, np.repeat(tau[:, None], i1 - i0, axis=1),
                                         control_spec=mujoco.mjtState.mjSTATE_QFRC_APPLIED, nstep=i1 - i0,
                                         initial_warmstart=np.zeros((m, nv)))
                st = out[:, -1].copy()
                alive &= np.all(np.isfinite(st), axis=1)
                st[~alive] = state  # a diverged sample is scored inf and no longer simulated
            c = cost(st, k + 1)
            total += np.where(alive & np.isfinite(c), c, np.inf)
            alive &= np.isfinite(total)
            st[~alive] = state
            if k + 1 == k1:
                end = st.copy()
        return total, end

    def evaluate(offsets, prev, base_q, base_f, a, steps, k0, k2):
        """Servo targets of the offsets (:func:`servo_targets`; the QP actuation: the offsets per
        substep) and their costs (m,) over frames k0+1 .. k2, rolled out from the state in
        ``state``; and the rolled-out states (m, nstate) at the window's end (frame k0 + steps / n)."""
        m = len(offsets)
        ctrl = servo_targets(offsets, prev, base_q, a, steps)
        if qp:
            total, end = evaluate_qp(ctrl, k0, k0 + steps // n, k2)
            total += sc.w_change * np.mean((offsets - prev[None]) ** 2, axis=1)
            return ctrl, total, end
        controls = np.concatenate([ctrl, np.broadcast_to(base_f[None], (m,) + base_f.shape)], axis=-1)
        states, _ = rollout.rollout(mj, datas, state[None], controls, control_spec=control_spec,
                                    nstep=(k2 - k0) * n, initial_warmstart=d.qacc_warmstart[None].copy())
        # the offset's change from the one in force: each change jerks the servos' targets
        total = sc.w_change * np.mean((offsets - prev[None]) ** 2, axis=1)
        for j, k in enumerate(range(k0 + 1, k2 + 1)):
            c = cost(states[:, (j + 1) * n - 1], k)
            total += np.where(np.isfinite(c), c, np.inf)
        return ctrl, total, states[:, steps - 1]

    def fallen() -> bool:
        """The simulated state is not finite, or the pelvis is below the fall height or tilted past
        the fall angle (``PhysicsConfig.fall_height`` / ``fall_tilt_deg``)."""
        return (not np.all(np.isfinite(d.qpos)) or d.qpos[2] < z_fall
                or d.xmat[ch.pelvis].reshape(3, 3)[2, 2] < cos_tilt)

    snapshots: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    prev = np.zeros(nu)
    k0, backtracks, retry_until, simulated, mismatch = 0, 0, -1, 0, 0.0
    rescue_frames = max(0, round(sc.rescue_s * fps))
    rescue_until, rescues, fail_at, fails_here = -1, 0, -(10 ** 9), 0
    while k0 < Te - 1:
        snapshots[k0] = (snapshot(mj, d), prev.copy())
        k1 = min(k0 + window, Te - 1)
        k2 = min(k1 + lookahead, Te - 1)
        base_q, base_f = targets(k0, k2)
        steps = (k1 - k0) * n
        # from the offset in force (the last window's) to the next
        a = np.minimum((np.arange(steps) + 1.0) / max(ramp * n, 1), 1.0)
        if k0 < rescue_until:
            # the rescue: the servos (or the QP) at the plan (the offset in force decaying) and a
            # root wrench
            off = sc.carry * prev
            commit(k0, k1, servo_targets(off[None], prev, base_q, a, steps)[0, :steps],
                   None if qp else base_f[:steps], rescue=True)
            prev = off
            if fallen():
                raise GenerationError(f"the sampling controller's rescue lost balance at frame {k1}")
            k0 = k1
            continue
        retry = k0 < retry_until
        N = sc.num_samples * (sc.backtrack_factor if retry else 1)
        sigma = sc.sigma * (sc.backtrack_sigma if retry else 1.0)
        scale = np.asarray(sc.sigma_scales, float)[np.arange(N) % len(sc.sigma_scales)]
        off = sc.carry * prev[None] + rng.normal(size=(N, nu)) * (sigma * free) * scale[:, None]
        off[0] = sc.carry * prev
        mujoco.mj_getState(mj, d, state, full_spec)

        ctrl, total, ends = evaluate(off, prev, base_q, base_f, a, steps, k0, k2)
        simulated += N * (k2 - k0) * n
        best = int(np.argmin(total))
        if sc.elite > 1:
            # the mean of the best few samples: the noise of any one draw averages out (smoother
            # servo targets); taken when it scores at least as well as the best draw
            mean = off[np.argsort(total)[:sc.elite]].mean(0, keepdims=True)
            ctrl_m, total_m, ends_m = evaluate(mean, prev, base_q, base_f, a, steps, k0, k2)
            simulated += (k2 - k0) * n
            if total_m[0] <= total[best]:
                off, ctrl, ends, best = mean, ctrl_m, ends_m, 0
        prev = off[best]
        commit(k0, k1, ctrl[best, :steps], None if qp else base_f[:steps])
        # the committed window is the chosen rollout (bit for bit; recorded, tested), unless every
        # sample diverged (then the window fails below and is searched again)
        if np.isfinite(total[best]):
            mujoco.mj_getState(mj, d, state, full_spec)
            mismatch = max(mismatch, float(np.max(np.abs(state - ends[best]))))
        bad = fallen() or tilt(d.qpos[3:7], qr[k1, 3:7]) > math.radians(sc.backtrack_tilt_deg)
        if bad:
            backtracks += 1
            if sc.rescue_after > 0:
                # a failure within a window of the place the last ones happened counts there
                fails_here = fails_here + 1 if k1 <= fail_at + window else 1
                fail_at = k1 if fails_here == 1 else fail_at
                if fails_here >= sc.rescue_after:
                    rescue_until, fails_here, rescues = max(k1, fail_at) + rescue_frames, 0, rescues + 1
            elif backtracks > sc.max_backtracks:
                raise GenerationError(f"the sampling controller lost balance at frame {k1} after "
                                      f"{sc.max_backtracks} backtracks")
            k0, prev = rewind(mj, d, snapshots, k0, sc.backtrack_windows, window)
            retry_until = k1 + window
            continue
        k0 = k1
    q_out[Te - 1], qd_out[Te - 1] = d.qpos, d.qvel
    sim = frames_from_substeps(ch, q_ref, q_out[:T], qd_out[:T], fps, n, lead, cfg, weight,
                               {k: v[:T * n] for k, v in sub.items()}, site_z[:T], root_err[:T],
                               int(nonfoot[:T].sum()))
    sim["stats"].update(controller="sampling", actuation=sc.actuation, backtracks=int(backtracks),
                        samples_simulated=int(simulated), rescues=int(rescues), commit_mismatch=mismatch)
    return sim
