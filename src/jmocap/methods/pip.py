"""``pip``: physical dynamics by PIP's dual PD controller and motion-tracking QP (Yi et al. 2022,
Sec. 3.2), tracking a reference fitted to the 2D evidence.

The reference (``reference_source``): TPNet's target pose (:func:`~jmocap.methods.stages.target_pose`)
fitted frame by frame to the clip's 2D keypoints through its camera (``"fit"``: the per-frame
Levenberg-Marquardt stage of ``trajopt``, :func:`jmocap.methods.trajopt.per_frame_fit`, with
TPNet's root-relative 3D joints as its prior), then smoothed by a centred Gaussian of
``smoothing_radius`` frames each side (:func:`smooth_poses`); or TPNet's pose as it is
(``"tpnet"``, the variant ``pip_tpnet``: PIP tracks a kinematic estimate as given). Contact
probabilities (``contact_source``): Rempe et al.'s estimator over 2D windows (``"mlp"``,
:mod:`jmocap.methods.contact_estimation`) or TPNet's contact head (``"tpnet"``).

Per frame, ``iterations`` steps of ``dt = 1 / (fps iterations)``, each:

1. rigid-body terms ``M``, ``h`` and the contact points: each foot site widened to a pair of
   sole points (:func:`sole_points`);
2. the contact state as PIP decides it (:func:`jmocap.physics.tracking.contact_state`): a point
   is in contact when it is near the floor (< 3 cm) and the contact estimate says so (PIP also
   counts any point < 0.5 cm above the floor, ``contact_touch_m``; off by default, see
   :class:`PIPConfig`);
3. the dual PD controller (PIP eqs. 3, 5): desired accelerations of the rotational dofs (root
   orientation and hinges, towards the reference pose) and of every body origin (towards the
   reference's root-relative body positions, plus a horizontal anchor of the root and its
   filtered reference velocity; the body's height comes from gravity and the contacts, not
   from the reference);
4. the motion-tracking QP (PIP eq. 7, :func:`jmocap.physics.tracking.tracking_qp`) over the
   acceleration and the contact forces: tracking + residual, torque, Signorini and
   sticking-contact penalties, subject to the friction pyramid at points in contact and to
   *unconditional* non-penetration of every sole point;
5. the semi-implicit Euler step (PIP eq. 13 with the new velocity in the position update).

The root therefore moves only by gravity, the contact forces and a heavily penalised residual
root wrench; the joint torques are ``M qdd + h - J_c^T lambda``. ``lax.scan`` over frames,
chunked with the state carried like ``physcap``. Frame t depends on frames <= t + ``lookahead``
(12 frames, 0.4 s at 30 fps, with the defaults: the smoothing radius; 0 for ``pip_tpnet``, which
is causal).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap import physics as P
from jmocap.constants import FRICTION_MU
from jmocap.inputs import ClipInputs
from jmocap.methods import stages as S
from jmocap.methods.base import Method, Variant, register, register_variant, static
from jmocap.methods.kinematic import LEARNED_STAGE_FIELDS, KinematicConfig
from jmocap.methods.kinematic import init_params as init_tpnet_params
from jmocap.methods.physcap import CycleState, rest_state
from jmocap.methods.physcap import init_carry as physcap_init_carry
from jmocap.methods.stages import on_floor, sole_points
from jmocap.model import Model
from jmocap.motion import Motion
from jmocap.physics.tracking import TrackingWeights, contact_state, solve_qp, tracking_qp

Array = jnp.ndarray


@struct.dataclass
class PIPConfig(KinematicConfig):
    """Structure (static) and physical parameters (traced) of the ``pip`` method."""

    iterations: int = static(2)  # steps per frame (PIP: one step at 60 fps)
    # --- the reference and the contact estimate ---
    # where the reference pose comes from: "fit" (TPNet's pose fitted frame by frame to the 2D
    # keypoints through the camera: trajopt's per-frame Levenberg-Marquardt stage) or "tpnet"
    # (TPNet's target pose as it is, the PIP paper's setting: a kinematic estimate tracked as given)
    reference_source: str = static("fit")
    # where the contact probabilities come from: "mlp" (Rempe et al.'s estimator over 2D windows,
    # jmocap.methods.contact_estimation; reads 6 frames ahead; BODY_25 only: it reads heels and
    # toes), "tpnet" (TPNet's contact head), or "auto": "mlp" where the layout is BODY_25, else "tpnet"
    contact_source: str = static("auto")
    # frames of each clip per tile of the per-frame fit (trajopt.per_frame_fit's ``tile``: a tile
    # holds this many frames of every clip of a vmapped batch; 0: all frames at once). The same
    # result; 4 was the fastest at 128 clips per device (docs/performance.md)
    fit_tile: int = static(4)
    fit_iterations: int = static(15)  # Levenberg-Marquardt iterations per frame ("fit"; 30 gave the same accuracy on the validation archive)
    # the fit's pull towards TPNet's root-relative joints (trajopt's w_pose, 2 there). 1 since the
    # fine-tuned TPNet, on data/val: MPJPE 91.4 -> 90.5 mm (0.5: 89.8, root +4 mm; 5: 93.1; 10: 95.3)
    fit_w_pose: float = 1.0
    # the fit holds the feet labelled in contact on the floor (trajopt's frame_contacts): with
    # the camera known, a foot on the floor fixes the frame's depth. On data/val: MPJPE 90.5 ->
    # 89.2 mm, root 181 -> 170 mm, residual 7.2 -> 6.9 % BW, GRF error 22.3 -> 21.9 % BW
    fit_contacts: bool = static(True)
    # the reference's centred Gaussian smoothing: radius (frames each side; 0: none, causal) and
    # standard deviation (frames). The per-frame fit follows the keypoints' noise; tracked as it
    # is, that noise becomes force noise (net GRF error 64 % BW instead of 28 on 12 held-out clips).
    # sigma 6 frames (0.2 s at 30 fps) since the retrained TPNet, on the validation archive against
    # sigma 3: residual 9.7 -> 7.7 % BW, cone violations 2.8 -> 0.9 %, GRF error 27 -> 23 % BW,
    # at +2 mm MPJPE; sigma 8: MPJPE +4 mm, PA-MPJPE +4 mm for residual 7.0 (docs/evaluation.md)
    smoothing_radius: int = static(12)
    smoothing_sigma: float = 6.0
    # --- dual PD controller (PIP eqs. 3, 5; gains in 1/s^2 and 1/s) ---
    kp_rot: float = 1600.0  # PIP k_p_theta = 2400
    kd_rot: float = 80.0  # PIP k_d_theta = 60
    kp_pos: float = 400.0  # PIP k_p_r = 3600
    kd_pos: float = 40.0  # PIP k_d_r = 60
    # weight of the target's velocity in the D terms (0: damp to rest; 1: track the reference's
    # velocity). 1 since stop 35: with the smoothed, fitted reference its velocity is clean, and
    # damping to rest made the body lag fast motion (runs). On data/val: MPJPE 92.2 -> 86.9 mm,
    # PA-MPJPE 54.0 -> 51.6, residual 7.8 -> 7.6 % BW, GRF error 22.4 -> 23.1, ballistic 97 ->
    # 112 % BW, cone violations 1.30 -> 1.38 % (0.5: 89.3 mm; 1.5: 85.3 mm, cone 1.51 %)
    feedforward: float = 1.0
    # horizontal pull of the root towards the target's (1/s^2); the position PD itself acts on
    # root-relative body positions, so the global height and translation come from the contacts,
    # gravity and the velocity terms (as in PIP), not from TPNet's absolute depth. 100 / 20 since
    # the fit's contact rows (50 / 15 before): held-out root error 172 -> 134 mm, residual 8.4 ->
    # 9.1 % BW, cone violations 1.27 -> 1.29 % (docs/evaluation.md)
    kp_anchor: float = 100.0
    kd_anchor: float = 20.0
    velocity_smoothing_s: float = 0.2  # time constant of the causal filter of the root's target velocity
    # --- contact state (PIP Sec. 3.2.3: in contact when < contact_touch_m above the floor, or
    # < contact_near_m and the estimate says so). PIP's touch rule (0.5 cm) is off by default:
    # with an evidence-fitted reference a swing foot skims the floor, and the rule would put
    # forces on it whatever the estimator says (per-foot GRF correlation 0.20 -> 0.33 without it)
    # the estimate a site needs (the contact MLP's vote fraction: 0.6 = 4 of its 5 windows). A
    # false contact pins and loads a swinging foot, so pip asks for more than the classifier's
    # own best-F1 point (0.5). Since stop 40, on data/val / the walking archive data/val_walk
    # (w_slip 4): MPJPE 79.5 -> 79.2 / 86.7 -> 84.9 mm, walking per-foot GRF correlation 0.46 ->
    # 0.50 / 0.57 -> 0.59, skate 9.96 -> 10.5 / 19.7 -> 19.5 %
    contact_threshold: float = 0.6
    contact_touch_m: float = 0.0
    contact_near_m: float = 0.03
    # support per foot: a foot whose heel or toe the estimate puts in contact may push on both
    # (each where it is within contact_near_m of the floor); the QP decides where the load goes
    contact_per_foot: bool = static(False)
    # the net external force (contacts + residual) in the friction pyramid too (tracking_qp's
    # net_force_cone): the residual cannot pull the body down nor push it beyond friction. On
    # data/val (stop 40, at 6 steps): cone violations 1.11 -> 0.14 %, residual 7.26 -> 6.87 % BW, skate
    # 9.20 -> 9.03 %, MPJPE 83.25 -> 83.24 mm; pip_imu (imu_val_phys): residual 5.15 -> 5.04
    net_force_cone: bool = static(True)
    # --- tracking QP (PIP eq. 7; see jmocap.physics.tracking) ---
    mu: float = FRICTION_MU
    w_rotation: float = 1.0
    w_position: float = 1.0
    w_residual: float = 300.0
    w_torque: float = 0.01
    w_signorini: float = 100.0
    w_regularisation: float = 0.1
    # the sticking penalty stops a sliding contact within one step, so per frame it weakens as
    # the steps grow: 2 at the 6 steps per frame pip ran until stop 40 (docs/method.md) is 6 at
    # 2 steps (the same results on data/val). 4 trades skate for pose: on data/val 6 -> 4:
    # MPJPE 81.4 -> 79.5 mm, residual 6.97 -> 6.57 % BW, skate 8.0 -> 10.0 % (2: 76.9 mm, 12.7 %)
    w_slip: float = 4.0
    # --- failure recovery ---
    # a frame that ends with the simulated root more than this far (m) from the reference's is a
    # tracking failure: the state restarts at rest at the reference pose (lifted out of the
    # floor), and the clip's result counts it (Motion.diagnostics["resets"]). Without it one
    # failure ruins the rest of a clip: a reference whose root orientation flips by 180 deg between
    # frames once demanded thousands of N m of residual torque, the body spun and took off, and the
    # net-force pyramid then let the residual hold it 10 m up while the horizontal anchor pulled it
    # back (docs/method.md). 0 turns the check off
    reset_m: float = 1.0

    def weights(self) -> TrackingWeights:
        return TrackingWeights(self.w_rotation, self.w_position, self.w_residual, self.w_torque,
                               self.w_signorini, self.w_regularisation, self.w_slip)


def init_params(key: Array, model: Model, config: PIPConfig = PIPConfig()) -> dict:
    """Fresh parameters: TPNet only (the dynamics have no network)."""
    return init_tpnet_params(key, model, config)


def tracked_bodies(model: Model) -> np.ndarray:
    """The bodies whose world origins the position PD tracks: every body but the world."""
    return np.arange(1, model.topo.nbody)


@struct.dataclass
class Reference:
    """One frame of the kinematic reference."""

    q: Array  # (nq,) target pose
    qd: Array  # (nv,) its backward-difference velocity
    pos: Array  # (B, 3) world origins of the tracked bodies
    vel: Array  # (B, 3) their backward-difference velocities
    root_vel: Array  # (3,) the root's target velocity, causally low-pass filtered
    prob: Array  # (4,) contact probabilities


def reference(model: Model, q_hat: Array, prob: Array, fps, smoothing_s=0.2, *, skip: int = 0,
              init_vel=None, restart=True) -> Reference:
    """The per-frame reference from the target poses (T, nq): backward differences and a
    first-order low-pass filter of the root velocity with time constant ``smoothing_s``, both
    causal. The filter runs over frames ``skip:`` only (a chunk's history frames are skipped,
    their entries are zero), starting from that frame's own velocity where ``restart`` (a
    clip's first chunk) and from ``init_vel`` (the filter's carried state) elsewhere."""
    bodies = tracked_bodies(model)
    pos = jax.vmap(lambda q: P.forward_kinematics(model, q).xpos[bodies])(q_hat)
    fps = jnp.asarray(fps, q_hat.dtype)
    vel = jnp.concatenate([jnp.zeros_like(pos[:1]), pos[1:] - pos[:-1]]) * fps
    a = 1.0 - jnp.exp(-1.0 / (fps * jnp.maximum(smoothing_s, 1e-6)))

    def lowpass(v, x):
        v = v + a * (x - v)
        return v, v

    root = vel[skip:, 0]
    start = root[0] if init_vel is None else jnp.where(restart, root[0], init_vel)
    _, root_vel = jax.lax.scan(lowpass, start, root)
    root_vel = jnp.concatenate([jnp.zeros((skip, 3), root_vel.dtype), root_vel])
    return Reference(q_hat, P.finite_difference_velocity(model, q_hat, fps), pos, vel, root_vel, prob)


@struct.dataclass
class StepOutput:
    tau: Array  # (nv,)
    grf: Array  # (4, 3)
    certified: Array  # () bool
    in_contact: Array  # (4,) bool


def step_qp(model: Model, state: CycleState, ref: Reference, dt, config: PIPConfig, in_contact=None):
    """The tracking QP of one step (:func:`jmocap.physics.tracking.tracking_qp`) and the contact
    state it used (PIP's rule, or ``in_contact`` (8,) when given)."""
    q, qd = state.q, state.qd
    body = S.rigid_body_terms(model, q, qd)
    kin = body.kin
    pts, bodies_c, height = sole_points(model, kin)
    if in_contact is None:
        prob = ref.prob  # (4,) left heel, left toe, right heel, right toe
        if config.contact_per_foot:
            prob = jnp.repeat(jnp.maximum(prob[0::2], prob[1::2]), 2)
        in_contact = contact_state(height, jnp.repeat(prob, 2), touch=config.contact_touch_m,
                                   near=config.contact_near_m, threshold=config.contact_threshold)

    # dual PD (PIP eqs. 3, 5): rotations towards the target pose; body positions towards the
    # target's root-relative ones; the root's translation by a horizontal anchor and the
    # filtered target velocity (TPNet's absolute height and depth are not tracked)
    ff = config.feedforward
    e = S.pd_error(model, ref.q, q)
    acc_rot = config.kp_rot * e[3:] + config.kd_rot * (ff * ref.qd[3:] - qd[3:])
    bodies = tracked_bodies(model)
    Jb, _ = P.point_jacobian(model, kin, kin.xpos[bodies], bodies)
    r, rd = kin.xpos[bodies], Jb @ qd
    horizontal = jnp.asarray([1.0, 1.0, 0.0], r.dtype)
    acc_pos = (config.kp_pos * ((ref.pos - ref.pos[:1]) - (r - r[:1]))
               + config.kd_pos * (ff * (ref.vel - ref.vel[:1]) - (rd - rd[:1]))
               + horizontal * config.kp_anchor * (ref.pos[:1] - r[:1])
               + config.kd_anchor * (ref.root_vel - rd[:1]))
    qp = tracking_qp(model, kin, body.M, body.h, qd, acc_rot, bodies, acc_pos, pts, bodies_c, height,
                     in_contact, dt, mu=config.mu, weights=config.weights(),
                     net_force_cone=config.net_force_cone)
    return qp, in_contact


def step(model: Model, state: CycleState, ref: Reference, dt, config: PIPConfig) -> tuple[CycleState, StepOutput]:
    """One step of the dual PD controller and the tracking QP (see the module docstring)."""
    qp, in_contact = step_qp(model, state, ref, dt, config)
    sol = solve_qp(qp)
    q_new, qd_new = P.integrate(model, state.q, state.qd, sol.qdd, dt)
    grf = sol.grf.reshape(-1, 2, 3).sum(1)  # each site's pair of sole points
    return CycleState(q_new, qd_new, grf), StepOutput(sol.tau, grf, sol.certified, in_contact.reshape(-1, 2).any(1))


@struct.dataclass
class FrameOutput:
    q: Array
    qd: Array
    tau: Array  # mean over the frame's steps
    grf: Array  # mean over the frame's steps
    certified: Array  # () bool: every QP of the frame was certified
    reset: Array  # () bool: the frame ended in a tracking failure and the state restarted (reset_m)


def restart_state(model: Model, r: Reference) -> CycleState:
    """The state a tracking failure restarts from: the reference pose, lifted so that no sole
    point is below the floor, at rest (the reference's velocity is the least trustworthy part
    of it where tracking failed: a jump of the reference is a huge finite difference)."""
    return rest_state(r.q.at[2].max(on_floor(model, r.q)[2]), model.nv)


def simulate(model: Model, ref: Reference, mask: Array, fps, config: PIPConfig = PIPConfig(), *,
             init: CycleState | None = None) -> tuple[CycleState, FrameOutput]:
    """The tracking dynamics over frames (``lax.scan``), ``iterations`` steps per frame; padding
    frames (mask False) leave the state unchanged. A real frame that ends with the root more than
    ``config.reset_m`` from the reference's restarts from the reference (:func:`restart_state`)
    and is flagged in :attr:`FrameOutput.reset`."""
    dtype = ref.q.dtype
    k = config.iterations
    dt = (1.0 / jnp.asarray(fps, dtype)) / k
    if init is None:
        init = rest_state(on_floor(model, ref.q[0]), model.nv)

    def frame(state, xs):
        r, real = xs

        def iteration(s, _):
            return step(model, s, r, dt, config)

        new, steps = jax.lax.scan(iteration, state, None, length=k)
        away = jnp.linalg.norm(new.q[:3] - r.q[:3])
        failed = real & (config.reset_m > 0) & ~(away <= config.reset_m)  # NaN is a failure too
        # (a cond: one clip skips the restart's kinematics; under vmap it becomes a select)
        new = jax.lax.cond(failed, lambda: restart_state(model, r), lambda: new)
        new = jax.tree.map(lambda a, b: jnp.where(real, a, b), new, state)
        out = FrameOutput(new.q, new.qd, steps.tau.mean(0), steps.grf.mean(0), jnp.all(steps.certified) | ~real,
                          failed)
        return new, out

    return jax.lax.scan(frame, init, (ref, mask))


def to_motion(out: FrameOutput, ref: Reference, mask, resets=None) -> Motion:
    """The result; ``diagnostics["resets"]``: the tracking failures so far (``resets``, a chunk's
    running count over its clip, else this run's)."""
    resets = jnp.sum(out.reset & mask).astype(out.q.dtype) if resets is None else resets
    return Motion(out.q, out.qd, out.tau, out.grf, ref.prob, ref.q, mask, certified=out.certified,
                  diagnostics={"resets": resets})


#: frames before a frame over which the per-frame fit's image scale is taken (a causal median)
SCALE_FRAMES = 12


def contact_source(config: PIPConfig) -> str:
    """The contact estimator ``config`` uses: ``"mlp"`` or ``"tpnet"`` (``"auto"`` resolved by the
    layout: the MLP reads BODY_25's heels and toes)."""
    if config.contact_source == "auto":
        from jmocap.methods import contact_estimation as CE

        return "mlp" if config.layout in CE.SUPPORTED_LAYOUTS else "tpnet"
    if config.contact_source not in ("mlp", "tpnet"):
        raise ValueError(f"unknown contact_source {config.contact_source!r} (auto, mlp, tpnet)")
    return config.contact_source


def contact_probabilities(params: dict, inputs: ClipInputs, tp, config: PIPConfig) -> Array:
    """(T, 4) contact probabilities of the configured source (:func:`contact_source`)."""
    tpnet = S.contact_probability(tp.contact_logits)
    source = contact_source(config)
    if source == "tpnet":
        return tpnet
    if source == "mlp":
        from jmocap.methods import contact_estimation as CE

        return CE.estimate_contacts(CE.contact_params(params), inputs, config.layout, depth=tp.trans_cam[:, 2])
    raise AssertionError(source)


def reference_poses(model: Model, inputs: ClipInputs, tp, prob: Array, config: PIPConfig) -> Array:
    """(T, nq) reference poses of ``config.reference_source``."""
    if config.reference_source == "tpnet":
        return tp.q_hat
    if config.reference_source == "fit":
        from jmocap.methods import trajopt as TO

        # the prior on TPNet's orientation too (trajopt turns it to the fit's since stop 57; pip's
        # reference was not measured that way), and the limits on the Euler angles as written:
        # trajopt's judged triples (stop 58) leave neighbouring frames of a per-frame fit in
        # different triples, which the smoothing and the tracker's PD would read as 180-degree
        # jumps (the demo's run diverged)
        tcfg = TO.TrajOptConfig(layout=config.layout, nets=config.nets, w_accel=0.0, w_contact_vel=0.0,
                                w_pose=config.fit_w_pose, prior_rotation="tpnet", limit_branches=False)
        prob_t = TO.problem(model, inputs, tp.q_hat, prob, tcfg)
        # the image scale of the robust reprojection: per frame, over it and the 12 frames
        # before it (trajopt uses the whole clip's; a chunk must see what the whole clip sees)
        prob_t = prob_t.replace(unit_px=TO.person_height_px_causal(prob_t.keypoints, prob_t.mask, SCALE_FRAMES) / 100.0)
        return TO.per_frame_fit(model, tp.q_hat, prob_t, tcfg, config.fit_iterations, tcfg.gm_scale_initial,
                                tcfg.gm_scale, contacts=prob_t.contacts if config.fit_contacts else None,
                                tile=config.fit_tile)
    raise ValueError(f"unknown reference_source {config.reference_source!r} (tpnet, fit)")


def smooth_poses(q: Array, mask: Array, radius: int, sigma) -> Array:
    """Poses (T, nq) smoothed by a centred Gaussian window of ``2 radius + 1`` frames (standard
    deviation ``sigma`` frames) over the real frames (``mask``): root position and hinge angles
    averaged, the root quaternion averaged after aligning each neighbour's sign with the centre
    frame's, then normalised; a frame that is not real takes the nearest earlier real frame's
    value (else the nearest later one's). ``radius = 0`` returns ``q``."""
    if radius == 0:
        return q
    T = q.shape[0]
    offsets = jnp.arange(-radius, radius + 1)
    w = jnp.exp(-0.5 * (offsets / jnp.maximum(sigma, 1e-3)) ** 2).astype(q.dtype)
    idx = jnp.arange(T)[:, None] + offsets[None, :]
    ok = (idx >= 0) & (idx < T)
    idx = jnp.clip(idx, 0, T - 1)
    ww = w[None, :] * (ok & mask[idx]).astype(q.dtype)  # (T, K)
    ww = ww / jnp.maximum(jnp.sum(ww, 1, keepdims=True), 1e-12)
    nb = q[idx]  # (T, K, nq)
    quat = nb[..., 3:7]
    sign = jnp.where(jnp.sum(quat * q[:, None, 3:7], -1, keepdims=True) < 0, -1.0, 1.0)
    avg = jnp.einsum("tk,tkn->tn", ww, nb.at[..., 3:7].set(quat * sign))
    avg = avg.at[:, 3:7].set(avg[:, 3:7] / jnp.linalg.norm(avg[:, 3:7], axis=-1, keepdims=True))
    # frames that are not real take the nearest real frame's (edge replication: a chunk's history
    # before the clip's first frame then repeats that frame, as the whole clip's start does)
    t = jnp.arange(T)
    prev = jax.lax.cummax(jnp.where(mask, t, -1), axis=0)
    nxt = jax.lax.cummin(jnp.where(mask, t, T), axis=0, reverse=True)
    near = jnp.where(prev >= 0, prev, jnp.where(nxt < T, nxt, t))
    return jnp.where(jnp.any(mask), avg[near], q)


def clip_reference(params: dict, model: Model, inputs: ClipInputs, config: PIPConfig = PIPConfig()) -> Reference:
    """The whole clip's per-frame :class:`Reference`: the reference poses of
    ``config.reference_source`` (smoothed), the contact probabilities of ``config.contact_source``."""
    tp = S.target_pose(params, model, inputs, config)
    prob = contact_probabilities(params, inputs, tp, config)
    q_ref = smooth_poses(reference_poses(model, inputs, tp, prob, config), jnp.asarray(inputs.mask),
                         config.smoothing_radius, config.smoothing_sigma)
    return reference(model, q_ref, prob, inputs.fps, config.velocity_smoothing_s)


def reconstruct(params: dict, model: Model, inputs: ClipInputs, config: PIPConfig = PIPConfig()) -> Motion:
    """2D keypoints of one clip -> physically plausible :class:`Motion` (see the module doc)."""
    ref = clip_reference(params, model, inputs, config)
    mask = jnp.asarray(inputs.mask)
    _, out = simulate(model, ref, mask, inputs.fps, config)
    return to_motion(out, ref, mask)


def history(config) -> int:
    """Frames before a chunk that it needs: TPNet's receptive field (as ``kinematic``), which
    includes the frame before the chunk that the reference's backward differences read, plus the
    reference smoothing's radius; at least the contact estimator's window (6 frames)."""
    from jmocap.methods import contact_estimation as CE

    fit = SCALE_FRAMES + config.smoothing_radius if config.reference_source == "fit" else 0
    return max(2 * config.nets.window - 1 + config.smoothing_radius, CE.HALF_WINDOW + CE.HALF_OUT, fit)


def lookahead(config) -> int:
    """Frames after a chunk that it needs (the method's latency): the contact estimator's
    (``contact_source="mlp"``: a 9-frame window around each of the 5 frames it votes for, 6
    frames ahead) and the reference smoothing's radius; 0 with TPNet's contacts and no
    smoothing (then ``pip`` is causal)."""
    from jmocap.methods import contact_estimation as CE

    mlp = CE.HALF_WINDOW + CE.HALF_OUT if contact_source(config) == "mlp" else 0
    return max(mlp, config.smoothing_radius)


@struct.dataclass
class Carry:
    """What a chunk hands to the next: the dynamic state, the root-velocity filter's state and
    the clip's tracking failures so far."""

    state: CycleState
    root_vel: Array  # (3,)
    resets: Array  # ()


def init_carry(model: Model, config=None, dtype=jnp.float32) -> Carry:
    """A zero :class:`Carry` (the shapes of the state carried between chunks)."""
    return Carry(physcap_init_carry(model, config, dtype), jnp.zeros(3, dtype), jnp.zeros((), dtype))


def reconstruct_chunk(params, model: Model, inputs: ClipInputs, carry: Carry, first, config: PIPConfig,
                      history: int) -> tuple[Carry, Motion]:
    """One chunk of one clip (see :func:`jmocap.methods.physcap.reconstruct_chunk`): ``inputs``
    holds ``history + L + lookahead(config)`` frames; the carried state and filter make the chunks
    agree with :func:`reconstruct` to float rounding (except where the per-frame fit fills a
    frame without evidence from neighbours beyond the chunk's window)."""
    H, A = history, lookahead(config)
    n = inputs.mask.shape[0] - A  # history + L
    tp = S.target_pose(params, model, inputs, config)
    prob = contact_probabilities(params, inputs, tp, config)
    window_mask = jnp.asarray(inputs.mask)
    q_ref = smooth_poses(reference_poses(model, inputs, tp, prob, config), window_mask, config.smoothing_radius,
                         config.smoothing_sigma)
    ref = reference(model, q_ref[:n], prob[:n], inputs.fps, config.velocity_smoothing_s, skip=H,
                    init_vel=carry.root_vel, restart=first)
    ref = jax.tree.map(lambda a: a[H:], ref)
    mask = window_mask[H:n]
    start = CycleState(on_floor(model, ref.q[0]), jnp.zeros_like(carry.state.qd), jnp.zeros_like(carry.state.grf))
    init = jax.tree.map(lambda a, b: jnp.where(first, a, b), start, carry.state)
    state, out = simulate(model, ref, mask, inputs.fps, config, init=init)
    last = jnp.max(jnp.where(mask, jnp.arange(mask.shape[0]), 0))  # the chunk's last real frame
    resets = jnp.where(first, 0.0, carry.resets) + jnp.sum(out.reset & mask)
    return Carry(state, ref.root_vel[last], resets), to_motion(out, ref, mask, resets)


METHOD = register(
    Method(
        name="pip",
        summary="physical dynamics: PIP's dual PD controller and motion-tracking QP over "
        "accelerations and contact forces (friction pyramid, no slip, unconditional non-penetration), "
        "tracking TPNet's pose fitted to the 2D keypoints; 6 frames of latency",
        paper="002 (PIP), Sec. 3.2, on 000's (Neural PhysCap) kinematic target fitted as in 001 (Rempe et al.)",
        config_type=PIPConfig,
        reconstruct=reconstruct,
        reconstruct_chunk=reconstruct_chunk,
        init_carry=init_carry,
        history=history,
        lookahead=lookahead,
        init_params=init_params,
        from_weights=LEARNED_STAGE_FIELDS,
    )
)

register_variant(Variant(
    "pip_tpnet", "pip",
    {"reference_source": "tpnet", "contact_source": "tpnet", "smoothing_radius": 0, "contact_touch_m": 0.005,
     "kp_anchor": 25.0, "kd_anchor": 10.0, "w_slip": 3.0, "feedforward": 0.0, "contact_threshold": 0.5,
     # its weak anchor follows TPNet's noisy depth only loosely, by design: on the held-out archive
     # its root was more than 1 m from TPNet's on 47 frames of 9 clips (far runs), where restarting
     # made jumps (jitter 0.26 -> 0.83 km/s^3); 3 m catches a launch only
     "reset_m": 3.0},
    "pip as the PIP paper runs it: tracking TPNet's kinematic target as given (no 2D fit), TPNet's "
    "contacts, PIP's touch rule; causal"))

__all__ = [
    "METHOD",
    "Carry",
    "init_carry",
    "PIPConfig",
    "Reference",
    "clip_reference",
    "contact_probabilities",
    "contact_source",
    "init_params",
    "lookahead",
    "reconstruct",
    "reconstruct_chunk",
    "reference",
    "simulate",
    "smooth_poses",
    "step",
    "step_qp",
    "restart_state",
    "to_motion",
    "on_floor",
    "tracked_bodies",
]
