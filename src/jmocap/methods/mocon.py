r"""``mocon``: track the fitted motion with a simulated character by sampling-based control (Neural
MoCon, Huang et al. 2022, Sec. 3.1, 3.4), on the clip's terrain.

The reference is ``trajopt``'s fit (this config's fields are ``trajopt``'s, so the reference
carries MoCon's interaction constraint, Sec. 3.2: every contact height is the signed distance to
the clip's scene). A character with jmocap's body is then simulated in MuJoCo C
(:mod:`jmocap.simulator`: the same model and contact model as the synthetic ground truth; the
scene's boxes are geoms of the model), moved only by PD servos on its hinges, feed-forward hinge
torques and its contacts with the floor and the terrain. The root is never actuated, so the
result obeys the equations of motion with the simulator's contact forces exactly (a zero residual
root wrench), and no body point passes through the terrain further than MuJoCo's soft contacts
allow.

Control, window by window (``window_frames``, the paper's "per frame" at ``window_frames = 1``):

* ``samples`` corrections :math:`\Delta\tilde q` of the reference's hinge angles are drawn
  (``sampling="gaussian"``: around ``carry`` times the last window's correction with standard
  deviation ``sigma_rad``, legs and trunk full, arms and head ``other_sigma`` of it;
  ``"uniform"``: the same spread, uniform: the ablation of the paper's Tab. 3), in ``iterations``
  rounds: each later round draws from the weighted mean and spread of the last round's
  ``elites`` best (CMA-ES's ``(mu_W, lambda)`` recombination weights with a diagonal covariance:
  the cross-entropy method, the paper's "Gaussian CMA" distribution without its learned
  prior). The servo targets :math:`\bar q_t = \tilde q_t + \Delta\tilde q_t` blend from the
  correction in force over the window's first frame;
* every sample is simulated over the window and ``lookahead_frames`` more (the correction then
  kept at ``lookahead_gain``) by ``mujoco.rollout`` (MuJoCo C, multi-threaded; ``backend="mjx"``
  simulates them with MJX instead, for an accelerator);
* each is scored at every simulated frame by the paper's sampling losses (Eq. 10-14), each
  residual divided by its scale: :math:`L_{tra}` (hinge angles and root orientation; 3D joints),
  :math:`L_{dyn}` (joint velocities; 3D joint velocities), :math:`L_{ban}` (each foot's planar
  offset from the centre of mass; the centre of mass's velocity), :math:`L_{reproj}` (confidence
  weighted, in the image, scaled by the person's height in pixels), plus the interaction term of
  the reference's contacts (a contact site the reference holds in contact is on the scene:
  its signed distance) and a regulariser on the correction;
* the best sample's window is committed by stepping MuJoCo C with its controls while the contact
  forces are recorded (:func:`jmocap.simulator.record_foot_forces`: each foot's contacts split
  between its heel and toe sites, frame values by the tent average that matches Newton's law at
  the frames).

When the pelvis tilts more than ``backtrack_tilt_deg`` from the reference or drops below
``fall_height`` of the reference's height above the ground, the search goes back
``backtrack_windows`` windows and draws ``backtrack_factor`` times more samples with
``backtrack_sigma`` times the spread; after ``max_backtracks`` failed windows ending at one
frame the character is put back on the reference at that frame (a *reset*, counted in the result's diagnostics: the frames
before and after it are each physical, the jump between them is not).

The result: the simulated ``q``, ``qd``; ``tau`` the servos' and feed-forward hinge torques
(root rows 0); ``grf`` the simulator's contact forces at the four contact sites; ``contact_prob``
1 where a site carries more than ``contact_force_share`` of the body weight; ``target_q`` the
servo targets. Not a pure JAX function: MuJoCo C runs on the host (``Method.host``), so
``jmocap reconstruct`` and ``jmocap eval`` call it clip by clip; the reference and the losses are
jitted JAX. Deterministic in ``seed`` (the MuJoCo C backend).

``sampling="prior"`` (variant ``mocon_prior``) draws each window's first round from the paper's
learned distribution prior instead (Sec. 3.3, :mod:`jmocap.methods.mocon_prior`): an encoder of
the character's state and the reference, trained on the cross-entropy distributions and through
the two-branch decoder with MuJoCo in the loop (``experiments/train_mocon_prior.py``).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import rollout

from jmocap import physics as P
from jmocap.constants import FRICTION_MU, GRAVITY
from jmocap.inputs import ClipInputs
from jmocap.methods import mocon_prior as MP
from jmocap.methods import trajopt as TO
from jmocap.methods.base import Method, Variant, register, register_variant, static, whole_clip
from jmocap.methods.kinematic import LEARNED_STAGE_FIELDS
from jmocap.model import Model, nominal_height, scaled_spec
from jmocap.motion import Motion
from jmocap.scene import Scene, add_to_spec, boxes, height_above
from jmocap.simulator import (
    add_servos,
    foot_contacts,
    foot_geom_map,
    record_foot_forces,
    rewind,
    simulation_model,
    snapshot,
    substep_records,
    tent_average,
    tilt,
)

Array = jnp.ndarray

#: the hinges sampled with the full spread (names containing one of these: legs and trunk, which
#: balance the body); the others (arms, head) with ``other_sigma`` of it
BALANCE_JOINTS = ("hip", "knee", "ankle", "foot", "spine")
BACKENDS = ("mujoco", "mjx")
#: where a window's first round of corrections comes from: the fixed Gaussian around the last
#: correction, the same spread uniform (ablation), or the learned prior (mocon_prior)
SAMPLINGS = ("gaussian", "uniform", "prior")
#: a contact site this high or lower above the ground may take its foot's force (the synthetic
#: ground truth's ``PhysicsConfig.site_floor_m``: the forces are split the same way)
SITE_FLOOR_M = 0.02


@struct.dataclass
class MoconConfig(TO.TrajOptConfig):
    """``trajopt``'s fields (the reference) and the sampling controller's. The controller's fields
    are static: the host loop reads them as Python numbers. Loss scales are in metres, radians,
    seconds and fractions of the person's height in the image; weights multiply the squared
    scaled residuals (means over joints, sums over the simulated frames)."""

    samples: int = static(32)  # per round
    window_frames: int = static(2)  # one control interval
    lookahead_frames: int = static(4)  # simulated past the window to score a sample
    # the simulation step is at most this (s): whole substeps per frame. 2 ms and contacts of 4 ms
    # since stop 52 (3.7 ms and 8 ms before: the feet sank into the boxes; docs/evaluation.md)
    max_dt: float = static(0.002)
    contact_timeconst: float = static(0.004)  # MuJoCo solref time constant of the contacts (s)
    pd_freq_hz: float = static(8.0)  # servo bandwidth (critically damped, per hinge)
    feedforward: bool = static(True)  # the reference's own hinge torques (trajopt's) added to the servos
    # the first round's distribution (SAMPLINGS): "gaussian" (around carry x the last correction,
    # spread sigma_rad), "uniform" (ablation) or "prior" (the learned prior's, mocon_prior)
    sampling: str = static("gaussian")
    # rounds of sampling per window: after each, the next round's Gaussian is the weighted mean
    # and spread of its ``elites`` best samples (CMA-ES's (mu_W, lambda) weights, diagonal: the
    # cross-entropy method); 1: a single draw
    iterations: int = static(3)
    elites: int = static(8)
    min_spread: float = static(0.2)  # the spread never shrinks below this share of the first round's
    sigma_rad: float = static(0.1)
    other_sigma: float = static(0.3)
    carry: float = static(0.7)  # a window's mean correction, times the last window's
    lookahead_gain: float = static(0.5)
    # --- the sampling losses (Eq. 10-13 and the interaction term) ---
    w_tra: float = static(1.0)
    pose_sigma_rad: float = static(0.15)
    joint_sigma_m: float = static(0.05)
    w_dyn: float = static(0.2)
    qd_sigma: float = static(2.0)  # rad/s (root: m/s)
    joint_vel_sigma: float = static(0.5)  # m/s
    w_balance: float = static(1.0)
    balance_sigma_m: float = static(0.05)
    com_vel_sigma: float = static(0.2)  # m/s
    w_image: float = static(1.0)
    image_sigma: float = static(0.02)  # of the person's height in the image
    w_interaction: float = static(1.0)
    interaction_sigma_m: float = static(0.02)
    w_regular: float = static(0.1)  # the correction, in units of sigma_rad
    # --- failures ---
    fall_height: float = static(0.6)  # of the reference pelvis height above the ground
    backtrack_tilt_deg: float = static(30.0)
    backtrack_windows: int = static(2)
    backtrack_factor: int = static(4)
    backtrack_sigma: float = static(2.0)
    max_backtracks: int = static(4)  # failed windows ending at one frame; then a reset onto the reference
    contact_force_share: float = static(0.01)  # of body weight: a site in contact
    backend: str = static("mujoco")  # "mujoco" (MuJoCo C rollouts) or "mjx"
    threads: int = static(0)  # rollout threads (0: one per CPU core)
    seed: int = static(0)


def check_config(config: MoconConfig) -> None:
    if config.backend not in BACKENDS:
        raise ValueError(f"mocon backend must be one of {BACKENDS}, got {config.backend!r}")
    if config.sampling not in SAMPLINGS:
        raise ValueError(f"mocon sampling must be one of {SAMPLINGS}, got {config.sampling!r}")
    if min(config.samples, config.window_frames) < 1 or config.lookahead_frames < 0:
        raise ValueError("mocon needs samples >= 1, window_frames >= 1 and lookahead_frames >= 0")


# ---------------------------------------------------------------------------------------
# the simulated character
# ---------------------------------------------------------------------------------------


class Simulation:
    """A clip's character in MuJoCo C: jmocap's humanoid at the model's size with the clip's
    terrain, hinge servos and the simulation settings (:mod:`jmocap.simulator`)."""

    def __init__(self, model: Model, scene: Scene | None, fps: float, config: MoconConfig):
        self.n = max(1, int(math.ceil(1.0 / fps / config.max_dt - 1e-9)))
        self.dt = 1.0 / fps / self.n
        spec = scaled_spec(None, nominal_height(model.mj), model.total_mass)
        if scene is not None and boxes(scene):
            add_to_spec(spec, scene, friction=FRICTION_MU)
        base = simulation_model(spec.compile(), self.dt, config.contact_timeconst)
        if base.nq != model.nq or not np.allclose(base.body_mass, model.mj.body_mass) \
                or not np.allclose(base.body_pos, model.mj.body_pos):
            raise ValueError("mocon's simulated character differs from the reconstruction's model")
        self.q_stand = model.keyframe("stand")
        self.mj, self.kv = add_servos(spec, base, self.q_stand, config.pd_freq_hz)
        mj = self.mj
        self.hinge_q = np.array([mj.jnt_qposadr[mj.actuator_trnid[a, 0]] for a in range(mj.nu)])
        names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, int(mj.actuator_trnid[a, 0])) for a in range(mj.nu)]
        self.spread = np.array([1.0 if any(p in nm for p in BALANCE_JOINTS) else config.other_sigma for nm in names])
        sites = model.topo.contact_sites
        self.sites = list(sites)
        feet = (tuple({model.topo.site_body[s] for s in sites[:2]}), tuple({model.topo.site_body[s] for s in sites[2:]}))
        # each foot: the bodies carrying its sites and their children (the toes)
        feet = tuple(tuple(b for b in range(mj.nbody) if b in f or mj.body_parentid[b] in f) for f in feet)
        self.ground, self.geom_foot, self.geom_body = foot_geom_map(mj, feet)
        self.scene = scene
        self.weight = float(np.sum(mj.body_mass)) * GRAVITY


# ---------------------------------------------------------------------------------------
# the sampling losses (jitted JAX over samples x frames)
# ---------------------------------------------------------------------------------------


def _frame_quantities(model: Model, q: Array, layout: str):
    """Per configuration (..., nq): 3D joints (..., J, 3), centre of mass (..., 3) and the contact
    sites (..., 4, 3)."""

    def one(x):
        kin = P.forward_kinematics(model, x)
        mass = jnp.asarray(model.body_mass, x.dtype)
        com = jnp.sum(kin.xipos * mass[:, None], 0) / jnp.sum(mass)
        sites = P.site_positions(model, x, model.topo.contact_sites, kin=kin)
        return P.keypoints(model, x, layout, kin=kin), com, sites

    flat = q.reshape(-1, q.shape[-1])
    j, c, s = jax.vmap(one)(flat)
    lead = q.shape[:-1]
    return j.reshape(*lead, *j.shape[1:]), c.reshape(*lead, 3), s.reshape(*lead, 4, 3)


@functools.partial(jax.jit, static_argnames=("layout",))
def reference_quantities(model: Model, q: Array, layout: str):
    return _frame_quantities(model, q, layout)


def _wrap(a: Array) -> Array:
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


@functools.partial(jax.jit, static_argnames=("layout", "weights"))
def sample_losses(model: Model, q: Array, qd: Array, start: tuple, ref: dict, frame_ok: Array, offsets: Array,
                  scene: Scene | None, *, layout: str, weights: tuple) -> Array:
    """The sampling loss (S,) of ``S`` simulated samples: ``q`` (S, K, nq) and ``qd`` (S, K, nv)
    at the ends of K frames, ``start`` the (joints, com, sites) of the window's start state
    (shared by the samples; velocities are the frames' differences), ``ref`` the reference's
    per-frame arrays (K, ...), ``frame_ok`` (K,) the frames that count, ``offsets`` (S, nu) the
    corrections in units of the spread. ``weights``: the config's weights and scales
    (:func:`_weights`)."""
    (w_tra, s_q, s_j, w_dyn, s_qd, s_jd, w_ban, s_b, s_cv, w_img, s_img, w_int, s_int, w_reg, fps) = weights
    j, com, sites = _frame_quantities(model, q, layout)  # (S, K, ...)
    j0, com0, _ = start
    jp = jnp.concatenate([jnp.broadcast_to(j0, (j.shape[0], 1, *j.shape[2:])), j], 1)
    cp = jnp.concatenate([jnp.broadcast_to(com0, (com.shape[0], 1, 3)), com], 1)
    jd = (jp[:, 1:] - jp[:, :-1]) * fps
    cd = (cp[:, 1:] - cp[:, :-1]) * fps
    # L_tra (Eq. 10)
    dq = _wrap(q[..., 7:] - ref["q"][None, :, 7:])
    dot = jnp.abs(jnp.sum(q[..., 3:7] * ref["q"][None, :, 3:7], -1)) / jnp.linalg.norm(q[..., 3:7], axis=-1)
    rot = 2 * jnp.arccos(jnp.clip(dot, 0.0, 1.0))
    pose = (jnp.sum(dq**2, -1) + rot**2) / (dq.shape[-1] + 1) / s_q**2
    joints = jnp.mean(jnp.sum((j - ref["joints"][None]) ** 2, -1), -1) / s_j**2
    tra = pose + joints
    # L_dyn (Eq. 11)
    dyn = jnp.mean((qd - ref["qd"][None]) ** 2, -1) / s_qd**2 \
        + jnp.mean(jnp.sum((jd - ref["joints_vel"][None]) ** 2, -1), -1) / s_jd**2
    # L_ban (Eq. 12): each foot site's planar offset from the centre of mass, and its velocity
    d = (sites - com[..., None, :])[..., :2]
    ban = jnp.mean(jnp.sum((d - ref["offsets"][None]) ** 2, -1), -1) / s_b**2 \
        + jnp.sum((cd - ref["com_vel"][None]) ** 2, -1) / s_cv**2
    # L_reproj (Eq. 13), through each frame's camera, in units of the person's image height
    E = ref["camera"]  # (K, 4, 4)
    xc = jnp.einsum("kij,skpj->skpi", E[:, :3, :3], j) + E[None, :, None, :3, 3]
    z = jnp.maximum(xc[..., 2], 1e-3)
    f, c = ref["intrinsics"][:2], ref["intrinsics"][2:]
    uv = xc[..., :2] / z[..., None] * f + c
    conf = ref["keypoints"][None, ..., 2]
    r2 = jnp.sum((uv - ref["keypoints"][None, ..., :2]) ** 2, -1) / (s_img * ref["height_px"]) ** 2
    img = jnp.sum(conf * r2, -1) / jnp.maximum(jnp.sum(conf, -1), 1e-6)
    # the interaction term: the reference's contact sites on the scene
    h = TO.surface_heights(scene, sites)
    inter = jnp.sum(ref["contact"][None] * h**2, -1) / s_int**2
    per_frame = w_tra * tra + w_dyn * dyn + w_ban * ban + w_img * img + w_int * inter
    total = jnp.sum(jnp.where(frame_ok[None], per_frame, 0.0), -1) + w_reg * jnp.mean(offsets**2, -1)
    return jnp.where(jnp.isfinite(total), total, jnp.inf)


def _weights(config: MoconConfig, fps: float) -> tuple:
    c = config
    return (c.w_tra, c.pose_sigma_rad, c.joint_sigma_m, c.w_dyn, c.qd_sigma, c.joint_vel_sigma, c.w_balance,
            c.balance_sigma_m, c.com_vel_sigma, c.w_image, c.image_sigma, c.w_interaction, c.interaction_sigma_m,
            c.w_regular, float(fps))


# ---------------------------------------------------------------------------------------
# rollouts: MuJoCo C or MJX
# ---------------------------------------------------------------------------------------


_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED


class MujocoRollouts:
    """Samples simulated by ``mujoco.rollout`` (MuJoCo C, one thread per core)."""

    def __init__(self, mj: mujoco.MjModel, threads: int):
        self.mj = mj
        self.datas = [mujoco.MjData(mj) for _ in range(max(1, threads or os.cpu_count() or 1))]

    def __call__(self, d: mujoco.MjData, controls: np.ndarray, frame_ends: np.ndarray):
        """``(qpos (S, K, nq), qvel (S, K, nv))`` after the substeps ``frame_ends`` (K,) of the
        rollouts from ``d``'s state under ``controls`` (S, steps, nu + nv)."""
        mj = self.mj
        state = np.zeros(mujoco.mj_stateSize(mj, _FULL))
        mujoco.mj_getState(mj, d, state, _FULL)
        states, _ = rollout.rollout(mj, self.datas, state[None], controls, control_spec=_CONTROL,
                                    nstep=controls.shape[1], initial_warmstart=d.qacc_warmstart[None].copy())
        s = states[:, frame_ends]
        return s[..., 1:1 + mj.nq], s[..., 1 + mj.nq:1 + mj.nq + mj.nv]


class MjxRollouts:
    """The same rollouts with MJX (``jax.vmap`` over samples of a ``lax.scan`` of ``mjx.step``;
    ``lax.map`` on a CPU): for an accelerator. Agrees with :class:`MujocoRollouts` to the differences of the two
    constraint solvers (tests/test_mocon.py measures it)."""

    def __init__(self, mj: mujoco.MjModel, threads: int = 0):
        from mujoco import mjx

        self.mj = mj
        self.mjx = mjx
        self.model = mjx.put_model(mj)

        def run(model, data, controls, ends):
            nu = model.nu

            def step(dd, u):
                new = mjx.step(model, dd.replace(ctrl=u[:nu], qfrc_applied=u[nu:]))
                # MJX's contact indices come back int64 under float64 (put_data makes int32)
                new = jax.tree.map(lambda a, b: a.astype(b.dtype), new, dd)
                return new, (new.qpos, new.qvel)

            def one(c):
                _, (qs, vs) = jax.lax.scan(step, data, c)
                return qs[ends], vs[ends]

            if jax.default_backend() == "cpu":
                # one sample at a time: MJX's constraint solver factors with jnp.linalg
                # (LAPACK on a CPU), and batched LAPACK calls can deadlock XLA's CPU thread
                # pool on a 2-core machine (jmocap.physics.linalg says why)
                return jax.lax.map(one, controls)
            return jax.vmap(one)(controls)

        self._run = jax.jit(run)

    def __call__(self, d: mujoco.MjData, controls: np.ndarray, frame_ends: np.ndarray):
        data = self.mjx.put_data(self.mj, d)
        q, v = self._run(self.model, data, jnp.asarray(controls, data.qpos.dtype), jnp.asarray(frame_ends))
        return np.asarray(q, np.float64), np.asarray(v, np.float64)


def rollouts(sim: Simulation, config: MoconConfig):
    return (MjxRollouts if config.backend == "mjx" else MujocoRollouts)(sim.mj, config.threads)


# ---------------------------------------------------------------------------------------
# one clip
# ---------------------------------------------------------------------------------------


def _settle_height(sim: Simulation, d: mujoco.MjData) -> None:
    """Lift the character out of the ground where its first pose penetrates it."""
    mujoco.mj_forward(sim.mj, d)
    depth = min((d.contact.dist[i] for i in range(d.ncon)), default=0.0)
    if depth < 0:
        d.qpos[2] -= depth
        mujoco.mj_forward(sim.mj, d)


def _start_velocity(mj: mujoco.MjModel, q: np.ndarray, fps: float, frames: int = 3) -> np.ndarray:
    """The mean velocity (nv,) over the reference's first ``frames`` frames: a fitted clip's
    first frame-to-frame difference carries the fit's noise (metres and radians per second at
    30 fps), and the simulation starts from it."""
    m = min(frames, len(q) - 1)
    v = np.zeros(mj.nv)
    if m > 0:
        mujoco.mj_differentiatePos(mj, v, m / fps, q[0], q[m])
    return v


def window_controls(q_ref: np.ndarray, ff: np.ndarray, hinge_q: np.ndarray, n: int, prev: np.ndarray,
                    off: np.ndarray, k0: int, k1: int, k2: int, lookahead_gain: float) -> np.ndarray:
    """Servo targets and feed-forward (S, steps, nu + nv) of the corrections ``off`` (S, nu) over
    frames k0..k2-1 (``n`` substeps each; the window ends at k1): blended from ``prev`` over the
    first frame, kept at ``lookahead_gain`` after the window; substeps interpolate the reference
    ``q_ref`` (Te, nq) and its feed-forward ``ff`` (Te, nv) linearly between frames."""
    Te, nu, nv = len(q_ref), len(hinge_q), ff.shape[1]
    a = np.arange(n) / n
    ks = np.arange(k0, k2)
    nxt = np.minimum(ks + 1, Te - 1)
    base = (q_ref[ks][:, None, hinge_q] * (1 - a)[None, :, None]
            + q_ref[nxt][:, None, hinge_q] * a[None, :, None]).reshape(-1, nu)
    fw = (ff[ks][:, None] * (1 - a)[None, :, None] + ff[nxt][:, None] * a[None, :, None]).reshape(-1, nv)
    steps = (k1 - k0) * n
    blend = np.minimum((np.arange(len(base)) + 1.0) / n, 1.0)
    gain = np.where(np.arange(len(base)) < steps, 1.0, lookahead_gain)
    corr = (prev[None, None] * (1 - blend)[None, :, None] + off[:, None] * blend[None, :, None]) * gain[None, :, None]
    ctrl = base[None] + corr
    return np.concatenate([ctrl, np.broadcast_to(fw[None], (len(off),) + fw.shape)], -1)


def track(model: Model, inputs: ClipInputs, ref: Motion, config: MoconConfig, prior: dict | None = None,
          record: dict | None = None) -> Motion:
    """Track one clip's reference (``ref``, ``trajopt``'s result; numpy arrays of one clip, padded
    frames marked by ``inputs.mask``) by sampling-based control (module docstring).

    ``prior``: the learned prior's variables (:mod:`jmocap.methods.mocon_prior`), needed with
    ``config.sampling == "prior"``. ``record``: a dict that receives what the prior's training
    recipe needs (``"clip"``: the reference, feed-forward and substeps; ``"windows"``: per
    searched window, in order (a window searched again after a backtrack is recorded again),
    its start state, features, the correction in force and the cross-entropy distribution of
    its last round and best sample, in base-spread units)."""
    check_config(config)
    mask = np.asarray(inputs.mask, bool)
    T = int(mask.sum())
    L = len(mask)
    fps = float(inputs.fps)
    scene = inputs.scene if inputs.scene is not None and boxes(inputs.scene) else None
    sim = Simulation(model, scene, fps, config)
    mj, n = sim.mj, sim.n
    nq, nv, nu = mj.nq, mj.nv, mj.nu
    rng = np.random.default_rng(config.seed)
    run = rollouts(sim, config)

    # the reference, one frame past the end held (the last frame's forces need its substeps)
    q_ref = np.concatenate([np.asarray(ref.q[:T], np.float64), np.asarray(ref.q[T - 1:T], np.float64)])
    qd_ref = np.concatenate([np.asarray(ref.qd[:T], np.float64), np.zeros((1, nv))])
    Te = T + 1
    ff = np.zeros((Te, nv))
    if config.feedforward:
        ff[:T, 6:] = np.asarray(ref.tau[:T, 6:], np.float64)
        ff[T] = ff[T - 1]
    joints, com, sites = jax.device_get(reference_quantities(model, jnp.asarray(q_ref, jnp.float32), config.layout))
    joints_vel = np.zeros_like(joints)
    joints_vel[1:] = (joints[1:] - joints[:-1]) * fps
    com_vel = np.zeros_like(com)
    com_vel[1:] = (com[1:] - com[:-1]) * fps
    kp = np.concatenate([np.asarray(inputs.keypoints[:T]), np.asarray(inputs.keypoints[T - 1:T]) * [1, 1, 0]])
    cams = np.asarray(inputs.world_to_camera())[:T]
    cams = np.concatenate([cams, cams[-1:]])
    contact = np.concatenate([np.asarray(ref.contact_prob[:T]) > config.contact_threshold, np.zeros((1, 4), bool)])
    reference = dict(q=q_ref, qd=qd_ref, joints=joints, joints_vel=joints_vel, offsets=(sites - com[:, None])[..., :2],
                     com_vel=com_vel, keypoints=kp, camera=cams, contact=contact.astype(np.float64))
    height_px = float(TO.person_height_px(jnp.asarray(inputs.keypoints), jnp.asarray(mask)))
    intrinsics = np.asarray(inputs.intrinsics, np.float64)
    weights = _weights(config, fps)
    jscene = None if scene is None else jax.tree.map(jnp.asarray, inputs.scene)
    pelvis_ref = height_above(scene, q_ref[:, :3])

    d = mujoco.MjData(mj)
    d.qpos[:] = q_ref[0]
    d.qvel[:] = _start_velocity(mj, q_ref, fps)
    _settle_height(sim, d)

    W, A = config.window_frames, config.lookahead_frames
    K = W + A
    sub = substep_records(Te * n, nv)
    q_out, qd_out = np.zeros((Te, nq)), np.zeros((Te, nv))
    target = np.zeros((Te, nq))
    spread = sim.spread * config.sigma_rad

    def controls(prev, off, k0, k1, k2):
        return window_controls(q_ref, ff, sim.hinge_q, n, prev, off, k0, k1, k2, config.lookahead_gain)

    def commit(k0, k1, ctrl):
        """Step MuJoCo C over frames k0..k1-1 with the chosen controls, recording the forces."""
        for k in range(k0, k1):
            q_out[k], qd_out[k] = d.qpos, d.qvel
            for i in range(n):
                j, s = (k - k0) * n + i, k * n + i
                mujoco.mj_step1(mj, d)
                con, _ = foot_contacts(d, sim.ground, sim.geom_foot, sim.geom_body)
                sp = d.site_xpos[sim.sites].copy()
                d.ctrl[:] = ctrl[j, :nu]
                d.qfrc_applied[:] = ctrl[j, nu:]
                mujoco.mj_step2(mj, d)
                # the servos' effective force at the new velocity (implicitfast integrates their
                # damping implicitly), plus the feed-forward
                sub["tau"][s] = d.qfrc_actuator + d.qfrc_applied - sim.dt * sim.kv * d.qacc
                record_foot_forces(mj, d, con, sp, sub, s, SITE_FLOOR_M, height_above(scene, sp))
            target[k] = q_ref[k]
            target[k, sim.hinge_q] = ctrl[(k - k0) * n, :nu]

    def score(off, prev, k0, k1, k2, ends, start, frame_ref, ok):
        """Controls (S, steps, nu + nv) and losses (S,) of the corrections ``off`` (S, nu) over
        frames k0..k2 from the current state."""
        ctrl = controls(prev, off, k0, k1, k2)
        qs, vs = run(d, ctrl, ends)
        pad = K - qs.shape[1]
        if pad:
            qs = np.concatenate([qs, np.repeat(qs[:, -1:], pad, 1)], 1)
            vs = np.concatenate([vs, np.repeat(vs[:, -1:], pad, 1)], 1)
        loss = np.asarray(sample_losses(model, jnp.asarray(qs, jnp.float32), jnp.asarray(vs, jnp.float32), start,
                                        frame_ref, ok, jnp.asarray(off / np.maximum(spread, 1e-9), jnp.float32),
                                        jscene, layout=config.layout, weights=weights))
        return ctrl, loss

    if config.sampling == "prior" and prior is None:
        raise ValueError("mocon sampling='prior' needs the prior's variables (jmocap.methods.mocon_prior)")
    if prior is not None and MP.nu_of(prior) != nu:
        raise ValueError(f"the mocon prior was made for {MP.nu_of(prior)} hinges; this character has {nu}")
    windows: list[dict] = []
    if record is not None:
        record["clip"] = dict(q_ref=q_ref, qd_ref=qd_ref, ff=ff, contact=reference["contact"], n=n,
                              spread=spread, hinge_q=sim.hinge_q)
        record["windows"] = windows
    snapshots: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    prev = np.zeros(nu)
    k0, retry_until = 0, -1
    failures: dict[int, int] = {}  # frame -> the failed windows that ended there
    backtracks = resets = simulated = 0
    while k0 < Te - 1:
        snapshots[k0] = (snapshot(mj, d), prev.copy())
        k1 = min(k0 + W, Te - 1)
        k2 = min(k1 + A, Te - 1)
        retry = k0 < retry_until
        S = config.samples * (config.backtrack_factor if retry else 1)
        scale = spread * (config.backtrack_sigma if retry else 1.0)
        ends = (np.arange(1, k2 - k0 + 1) * n) - 1
        # pad to K frames (one program per sample count), the padding not counted
        ks = np.arange(k0 + 1, k0 + 1 + K).clip(max=Te - 1)
        ok = jnp.asarray(np.arange(K) < (k2 - k0))
        start = reference_quantities(model, jnp.asarray(d.qpos[None], jnp.float32), config.layout)
        start = tuple(x[0] for x in start)
        frame_ref = {k: jnp.asarray(v[ks], jnp.float32) for k, v in reference.items()}
        frame_ref["intrinsics"] = jnp.asarray(intrinsics, jnp.float32)
        frame_ref["height_px"] = jnp.float32(height_px)

        features = None
        if prior is not None or record is not None:
            features = MP.window_features(d.qpos, d.qvel, q_ref[[k0, k1, k2]], qd_ref[k0], reference["contact"][k1],
                                          prev / spread)
        if config.sampling == "prior":
            mu, sig = jax.device_get(MP.encode_jit(prior, jnp.asarray(features[None])))
            mean, std = mu[0].astype(np.float64) * spread, sig[0].astype(np.float64) * scale
        else:
            mean, std = config.carry * prev, scale
        if record is not None:
            start_state = np.zeros(mujoco.mj_stateSize(mj, _FULL))
            mujoco.mj_getState(mj, d, start_state, _FULL)
        best_loss, best_off, best_ctrl = np.inf, None, None
        for it in range(config.iterations):
            if config.sampling == "uniform":
                noise = rng.uniform(-math.sqrt(3.0), math.sqrt(3.0), size=(S, nu))
            else:
                noise = rng.normal(size=(S, nu))
            off = mean[None] + noise * std
            off[0] = mean
            ctrl, loss = score(off, prev, k0, k1, k2, ends, start, frame_ref, ok)
            simulated += S * ctrl.shape[1]
            b = int(np.argmin(loss))
            if loss[b] < best_loss:
                best_loss, best_off, best_ctrl = loss[b], off[b], ctrl[b]
            if it + 1 < config.iterations or record is not None:  # the elites' mean and spread (cross-entropy)
                order = np.argsort(loss)[:config.elites]
                w = np.log(config.elites + 0.5) - np.log(np.arange(1, len(order) + 1))
                w /= w.sum()
                mean = w @ off[order]
                std = np.maximum(np.sqrt(w @ (off[order] - mean) ** 2), config.min_spread * scale)
        if record is not None:
            windows.append(dict(k0=k0, k1=k1, k2=k2, retry=retry, state=start_state, features=features, prev=prev / spread,
                                mu=mean / spread, sigma=std / spread, best=best_off / spread, loss=best_loss))
        off, ctrl, best = best_off[None], best_ctrl[None], 0
        prev = off[best]
        commit(k0, k1, ctrl[best])
        pelvis = float(height_above(scene, d.qpos[None, :3])[0])
        bad = (not np.all(np.isfinite(d.qpos)) or pelvis < config.fall_height * pelvis_ref[k1]
               or tilt(d.qpos[3:7], q_ref[k1, 3:7]) > math.radians(config.backtrack_tilt_deg))
        if bad:
            backtracks += 1
            failures[k1] = failures.get(k1, 0) + 1
            if failures[k1] > config.max_backtracks:  # a reset onto the reference
                resets += 1
                mujoco.mj_resetData(mj, d)
                d.qpos[:], d.qvel[:] = q_ref[k1], _start_velocity(mj, q_ref[k1:], fps)
                _settle_height(sim, d)
                prev = np.zeros(nu)
                k0 = k1
                continue
            k0, prev = rewind(mj, d, snapshots, k0, config.backtrack_windows, W)
            retry_until = k1 + W
            continue
        k0 = k1
    q_out[Te - 1], qd_out[Te - 1] = d.qpos, d.qvel

    tau = tent_average(sub["tau"], n)[:T]
    grf = tent_average(sub["grf"], n)[:T]
    contact = (grf[..., 2] > config.contact_force_share * sim.weight).astype(np.float32)

    def padded(x):
        x = np.asarray(x[:T], np.float32)
        return np.concatenate([x, np.repeat(x[-1:], L - T, 0)]) if L > T else x

    diagnostics = {"mocon_resets": np.float32(resets), "mocon_backtracks": np.float32(backtracks),
                   "mocon_samples_simulated": np.float32(simulated)}
    return Motion(padded(q_out), padded(qd_out), padded(tau), padded(grf), padded(contact), padded(target[:T]),
                  mask, diagnostics=diagnostics)


# ---------------------------------------------------------------------------------------
# the method
# ---------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _batched_reference():
    return jax.jit(jax.vmap(TO.reconstruct, in_axes=(None, 0, 0, None)))


def reconstruct_host(params: dict, models: Sequence[Model], inputs: ClipInputs, config: MoconConfig) -> Motion:
    """A batch of clips (``inputs`` stacked, ``models`` one per clip): ``trajopt``'s reference of
    all of them at once (jitted), then each clip tracked in the simulator (:func:`track`).
    Returns the batch's :class:`Motion` (numpy)."""
    check_config(config)
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *models)
    ref = jax.device_get(_batched_reference()(params, stacked, inputs, config))
    prior = MP.prior_params(params) if config.sampling == "prior" else None
    out = []
    for b, model in enumerate(models):
        one = jax.tree.map(lambda x, b=b: np.asarray(x)[b], inputs)
        out.append(track(model, one, jax.tree.map(lambda x, b=b: np.asarray(x)[b], ref), config, prior))
    return jax.tree.map(lambda *xs: np.stack(xs), *out)


def reconstruct(params: dict, model: Model, inputs: ClipInputs, config: MoconConfig = MoconConfig()) -> Motion:  # noqa: B008
    """One clip (numpy in, numpy out): :func:`reconstruct_host` of a batch of one. Not traceable
    (MuJoCo C runs on the host): do not ``jax.jit`` or ``jax.vmap`` it."""
    if isinstance(inputs.mask, jax.core.Tracer):
        raise TypeError("mocon simulates in MuJoCo C on the host and cannot be traced (jax.jit/vmap): call "
                        "jmocap.methods.mocon.reconstruct on concrete arrays, or reconstruct_host for a batch")
    batch = jax.tree.map(lambda x: np.asarray(x)[None], inputs)
    return jax.tree.map(lambda x: x[0], reconstruct_host(params, [model], batch, config))


METHOD = register(
    Method(
        name="mocon",
        summary="offline: trajopt's fit on the clip's terrain tracked by a simulated character "
        "(MuJoCo C) with sampling-based control: no residual force, the simulator's contact forces",
        paper="004 (Neural MoCon, Huang et al. 2022), Sec. 3.1-3.4 (the learned prior of Sec. 3.3: variant mocon_prior)",
        config_type=MoconConfig,
        reconstruct=reconstruct,
        init_params=TO.init_params,
        **whole_clip(reconstruct),
        from_weights=LEARNED_STAGE_FIELDS,
        host=reconstruct_host,
    )
)

register_variant(Variant("mocon_uniform", "mocon", {"sampling": "uniform"},
                         "mocon sampling uniformly instead of from the Gaussian (ablation, Tab. 3 of the paper)"))
register_variant(Variant("mocon_prior", "mocon", {"sampling": "prior"},
                         "mocon drawing each window's first round from the learned distribution prior (Sec. 3.3: "
                         "an encoder of the character's state and the reference, trained on the cross-entropy "
                         "distributions and through a two-branch decoder with MuJoCo in the loop)"))
register_variant(Variant("mocon_no_interaction", "mocon", {"use_scene": False, "w_interaction": 0.0},
                         "mocon without the interaction term: its reference fitted on the floor z = 0 "
                         "and no contact term in the sampling loss (ablation, Tab. 3 of the paper)"))
register_variant(Variant("mocon_no_image", "mocon", {"w_image": 0.0},
                         "mocon without the image-level loss (Eq. 13) in the sampling loss (ablation, Tab. 3 of the paper)"))

__all__ = ["METHOD", "SAMPLINGS", "MoconConfig", "Simulation", "MjxRollouts", "MujocoRollouts", "reconstruct",
           "reconstruct_host", "sample_losses", "track", "window_controls"]
