"""``dnd``: D&D (Li et al. 2022, ``../shared/papers/003``): human dynamics seen from a moving
camera whose motion is unknown.

TPNet's pose in the camera frame is the initial motion ``q_hat`` (the paper's kinematics
backbone), beside the contact estimator's probabilities (which DyNet's contact logits refine).
Only the first frame's camera is read (:func:`seen_inputs`). Two temporal networks read the whole clip (non-causal, like the paper's 16-frame
windows, wider here):

* **DyNet** (Sec. 3.3.1) predicts per frame the camera's angular velocity ``omega`` and linear
  acceleration ``a`` (both in the camera's axes), the ground reaction forces ``lambda`` at the
  four contact points, their contact probabilities ``p`` and a direct root actuation ``eta``;
* the **attentive PD controller** (Sec. 3.3.2) predicts gains ``k_p``, ``k_d``, offsets ``alpha``
  and attention weights over a window of ``2 W + 1`` frames (softmax: they sum to one), whose
  average of the initial motion is the target state ``q~`` (eq. 7).

Per frame (``iterations`` sub-steps of ``dt = 1 / (fps k)``), with the camera's orientation
``R`` (world -> camera) integrated from ``omega`` from the first frame's known camera:

1. **inertial force control** (eqs. 2-3, 9): the pose relative to the camera accelerates by
   ``M qdd = tau + J^T (b lambda) - h_g(R g) + I(omega, d omega/dt, a)`` with ``tau`` the PD
   control (eq. 8) and ``I`` jmocap's exact generalised inertial force
   (:func:`jmocap.physics.inertial_force`; linear, centripetal, Coriolis and Euler terms);
2. **probabilistic contact torque** (eq. 6): in training ``b`` is a Gumbel-softmax sample of the
   contact probabilities, so the motion error's gradient reaches the contact head; at inference
   ``b = [p > threshold]``;
3. **trajectory forward dynamics** (eq. 10): the root's world velocity changes by
   ``(R^T (eta + sum b lambda)) / m + g`` (the whole body's mass ``m``, where the paper writes the
   root body's);
4. **constrained update** (eq. 15): the velocities are projected (the pose's change weighted
   ``pose_stiffness`` times its kinetic energy, the world root's by its own) onto soft
   constraints that the contact points in contact do not move in the world and, jmocap's
   addition, come back to the known floor (``floor_recovery``);
5. integration (eqs. 11-14) of the pose, the root's world position and the camera's orientation.

The world motion is the root's world position, its orientation turned by ``R^T`` and the
joint angles; the camera track it implies (:func:`estimated_track`) places the camera so that
the root appears where the camera-frame pose has it. The reported torques are the world
motion's inverse dynamics less the forces (``tau[:6]`` is the residual root wrench that the
world motion needs, whatever the networks called ``eta``), so that every method's residual is
measured the same way.

The static switches give the paper's ablations (Tab. 3): ``camera_motion="none"`` (residual
force control: no inertial force, the camera held still, a residual root force in the camera
frame instead), ``contacts="discrete"`` (thresholded contacts in training, no PCT),
``pd="meta"`` (per-frame gains without attention). ``camera_motion="track"`` uses a known
track's motion (the clip's ``camera_track``) instead of DyNet's (issue 20, item 3).
See docs/method.md, "D&D", for the choices made where the paper is silent.
"""

from __future__ import annotations

import functools
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap import physics as P
from jmocap.constants import GRAVITY, NUM_CONTACTS
from jmocap.inputs import ClipInputs
from jmocap.layouts import get_layout
from jmocap.methods import stages as S
from jmocap.methods.base import (
    Method,
    Variant,
    load_float32_params,
    register,
    register_variant,
    static,
    whole_clip,
)
from jmocap.methods.kinematic import LEARNED_STAGE_FIELDS, KinematicConfig
from jmocap.methods.kinematic import init_params as init_tpnet_params
from jmocap.model import Model
from jmocap.motion import Motion
from jmocap.physics.rotations import mat_to_quat, quat_error, quat_exp, quat_normalize, quat_to_mat

Array = jnp.ndarray

ASSET = Path(__file__).resolve().parents[1] / "assets" / "dnd_nets.msgpack"
CAMERA_MOTIONS = ("estimated", "track", "none")
CONTACT_MODES = ("pct", "discrete")
PD_MODES = ("attentive", "meta")


@struct.dataclass
class DnDConfig(KinematicConfig):
    """Structure (static) and physical parameters (traced) of D&D."""

    # --- structure (static) ---
    camera_motion: str = static("estimated")  # "estimated" (DyNet, D&D), "track" (known), "none" (RFC)
    contacts: str = static("pct")  # "pct": Gumbel-softmax samples in training; "discrete": thresholded
    pd: str = static("attentive")  # "attentive" (eq. 7-8) or "meta" (per-frame gains, no attention)
    attention: int = static(8)  # W: the target of frame t averages frames t-W..t+W
    channels: int = static(128)  # width of the two temporal networks (paper: 256, DyNet's GRU 1024)
    depth: int = static(4)  # residual blocks, dilations 1, 2, 4, ... (receptive field 2^(depth+1) - 1)
    iterations: int = static(2)  # sub-steps per frame
    # --- physical parameters (traced) ---
    contact_threshold: float = 0.5
    gumbel_temperature: float = 1.0
    # 1/eps^2 of the soft contact-velocity constraint, per (m/s)^2 and kg: the projection's
    # penalty weight relative to the kinetic-energy metric (large: the constraint nearly holds)
    constraint_weight: float = 1e3
    kp_root_pos: float = 400.0  # base PD gains (1/s^2); the network scales them by exp([-2, 2])
    kp_root_rot: float = 400.0
    kp_joint: float = 400.0
    max_velocity: float = 30.0  # |qd| bound (rad/s, m/s) before the projection
    # share of a contact point's height above (below) the floor that the constrained update
    # takes out per step while it is in contact (jmocap's; 0: D&D's eq. 15, velocities only)
    floor_recovery: float = 0.2
    # the constrained update's cost of changing the camera-frame pose's velocity relative to the
    # world root's, per unit kinetic energy: the pose is what the camera sees, the world velocity
    # what is unknown, so the contacts move the body in the world rather than bend the legs (1:
    # the plain kinetic-energy metric, where a pinned foot mostly drags its light leg back)
    pose_stiffness: float = 100.0


def _check(config: DnDConfig) -> None:
    for name, value, allowed in (("camera_motion", config.camera_motion, CAMERA_MOTIONS),
                                 ("contacts", config.contacts, CONTACT_MODES), ("pd", config.pd, PD_MODES)):
        if value not in allowed:
            raise ValueError(f"DnDConfig.{name} must be one of {allowed}, got {value!r}")


# ---------------------------------------------------------------------------------------
# the networks
# ---------------------------------------------------------------------------------------


class ClipConvNet(nn.Module):
    """A whole clip (T, F) -> (T, out): an embedding, ``depth`` residual blocks of dilated
    convolutions over time (kernel 3, dilation 1, 2, 4, ...; replication padding, so every frame,
    first and last included, sees a full window), layer norm, and a zero-initialised linear head
    (a fresh network outputs zeros: no camera motion, no force, neutral gains)."""

    out: int
    channels: int = 128
    depth: int = 4

    @nn.compact
    def __call__(self, x: Array) -> Array:
        h = nn.Dense(self.channels)(x)
        for i in range(self.depth):
            d = 2**i
            padded = jnp.pad(h, [(d, d), (0, 0)], mode="edge")
            r = nn.Conv(self.channels, (3,), kernel_dilation=(d,), padding="VALID")(nn.gelu(nn.LayerNorm()(padded)))
            h = h + r
        return nn.Dense(self.out, kernel_init=nn.initializers.zeros)(nn.gelu(nn.LayerNorm()(h)))


def dynet_outputs() -> int:
    """omega (3), a (3), lambda (4 x 3), contact logits (4), eta (3)."""
    return 3 + 3 + 3 * NUM_CONTACTS + NUM_CONTACTS + 3


def pd_outputs(model: Model, config: DnDConfig) -> int:
    """k_p, k_d and alpha per dof, and (attentive) 2 W + 1 attention logits."""
    return 3 * model.nv + (2 * config.attention + 1 if config.pd == "attentive" else 0)


def num_features(model: Model, config: DnDConfig) -> int:
    J = get_layout(config.layout).num_joints
    n_h = model.topo.hinge_qadr.size
    per = 3 + 6 + n_h + 3 * J  # root position, orientation (6D), joint angles, root-relative joints
    # and their per-frame changes, gravity's direction in the first camera, the estimator's contacts
    return 2 * per + 3 + NUM_CONTACTS


def init_params(key: Array, model: Model, config: DnDConfig = DnDConfig()) -> dict:  # noqa: B008
    """Fresh parameters: TPNet and D&D's two networks (``params["dnd"]``)."""
    k1, k2, k3 = jax.random.split(key, 3)
    F = num_features(model, config)
    x = jnp.zeros((8, F), jnp.float32)
    dyn = ClipConvNet(dynet_outputs(), config.channels, config.depth).init(k2, x)["params"]
    pd = ClipConvNet(pd_outputs(model, config), config.channels, config.depth).init(k3, x)["params"]
    return {**init_tpnet_params(k1, model, config), "dnd": {"dynet": dyn, "pd": pd}}


def load_dnd_params(path) -> dict:
    """D&D's network variables from a msgpack file (float16 or float32) as float32 arrays."""
    return load_float32_params(path)


@functools.cache
def default_dnd_params() -> dict:
    """The shipped D&D networks (``jmocap/assets/dnd_nets.msgpack``, made by
    ``experiments/train_dnd.py --ship``)."""
    if not ASSET.exists():
        raise FileNotFoundError(f"no shipped D&D weights at {ASSET}; train them with experiments/train_dnd.py --ship")
    return load_dnd_params(ASSET)


def dnd_params(params) -> dict:
    """``params["dnd"]`` where a run's parameters carry D&D's networks, else the shipped ones."""
    if isinstance(params, dict) and "dnd" in params:
        return params["dnd"]
    return default_dnd_params()


# ---------------------------------------------------------------------------------------
# the initial motion in the camera frame, and the networks' outputs
# ---------------------------------------------------------------------------------------


@struct.dataclass
class Initial:
    """The kinematics backbone's output (TPNet), in the camera frame of each frame."""

    q_cam: Array  # (T, nq) root position and orientation relative to the camera, joint angles
    p_rr: Array  # (T, J, 3) root-relative joints, camera axes
    contact_logits: Array  # (T, 4) TPNet's (not used by D&D)
    q_world: Array  # (T, nq) TPNet's world pose through the first frame's camera (the Motion's q_hat)
    contacts: Array  # (T, 4) the contact estimator's probabilities (jmocap.methods.contact_estimation)


def initial_motion(params: dict, model: Model, inputs: ClipInputs, config: DnDConfig) -> Initial:
    """TPNet's pose in each frame's camera, and the contact estimator's probabilities (Rempe et
    al.'s MLP, shipped; its windows are seen from the cameras ``inputs`` give: D&D passes the
    first frame's camera for all, the track being unknown)."""
    from jmocap.methods import contact_estimation as CE

    tp = S.target_pose(params, model, inputs, config)
    q_cam = tp.q_hat.at[:, 0:3].set(tp.trans_cam).at[:, 3:7].set(mat_to_quat(tp.rot_cam))
    contacts = CE.estimate_contacts(CE.contact_params(params), inputs, config.layout, depth=tp.trans_cam[:, 2])
    return Initial(q_cam, tp.p_rr, tp.contact_logits, tp.q_hat, contacts)


def seen_inputs(inputs: ClipInputs, config: DnDConfig) -> ClipInputs:
    """What D&D reads of the clip's cameras: the first frame's camera only, unless the variant
    uses a known track (``camera_motion="track"``)."""
    if config.camera_motion == "track":
        return inputs
    return inputs.with_static_camera(jnp.asarray(inputs.world_to_camera())[..., 0, :, :])


def last_real(mask: Array) -> Array:
    """(T,) index of the frame each frame reads: itself, or the last real frame for padding."""
    T = mask.shape[0]
    n = jnp.maximum(jnp.sum(mask.astype(jnp.int32)), 1)
    return jnp.minimum(jnp.arange(T), n - 1)


def features(model: Model, init: Initial, gravity_cam0: Array, mask: Array) -> Array:
    """(T, F) the networks' input: the initial motion's root position (x/z, y/z, log z),
    orientation (6D), joint angles, root-relative joints, their per-frame changes, gravity's
    direction in the first frame's camera and the contact estimator's logits. Padding frames
    repeat the last real frame."""
    idx = last_real(mask)
    q = init.q_cam[idx]
    p_rr = init.p_rr[idx]
    T = q.shape[0]
    z = jnp.maximum(q[:, 2], 0.3)
    pos = jnp.stack([q[:, 0] / z, q[:, 1] / z, jnp.log(z)], -1)
    rot = quat_to_mat(q[:, 3:7])[..., :2].reshape(T, 6)
    per = jnp.concatenate([pos, rot, q[:, model.topo.hinge_qadr], p_rr.reshape(T, -1)], -1)
    delta = jnp.concatenate([jnp.zeros_like(per[:1]), per[1:] - per[:-1]]) * 10.0
    g = jnp.broadcast_to(gravity_cam0 / GRAVITY, (T, 3))
    return jnp.concatenate([per, delta, g, estimator_logits(init.contacts[idx])], -1)


def estimator_logits(p: Array) -> Array:
    """The contact estimator's probabilities as logits, bounded (+-4)."""
    p = jnp.clip(p, 0.018, 0.982)
    return jnp.log(p) - jnp.log1p(-p)


@struct.dataclass
class Physical:
    """DyNet's physical properties per frame (camera axes)."""

    omega: Array  # (T, 3) camera angular velocity (rad/s)
    accel: Array  # (T, 3) camera linear acceleration (m/s^2)
    grf: Array  # (T, 4, 3) ground reaction forces lambda (N)
    contact_logits: Array  # (T, 4)
    eta: Array  # (T, 3) direct root actuation (N)


@struct.dataclass
class Control:
    """The PD controller's parameters per frame."""

    kp: Array  # (T, nv) 1/s^2
    kd: Array  # (T, nv) 1/s
    alpha: Array  # (T, nv) acceleration offsets (acceleration units, as jmocap's PD: docs/method.md)
    target: Array  # (T, nq) the attentive target state q~ (eq. 7); q_hat itself for meta-PD
    weights: Array  # (T, 2W + 1) attention weights over frames t-W..t+W (ones at W for meta-PD)


def physical_properties(net: dict, model: Model, x: Array, config: DnDConfig) -> Physical:
    """DyNet over the clip. Its contact logits refine the estimator's (the last input
    features): a fresh DyNet's contacts are the estimator's."""
    out = ClipConvNet(dynet_outputs(), config.channels, config.depth).apply({"params": net["dynet"]}, x)
    T = x.shape[0]
    weight = S.body_weight(model, x.dtype)
    o = jnp.split(out, np.cumsum([3, 3, 3 * NUM_CONTACTS, NUM_CONTACTS]), -1)
    # bounded heads (slopes at zero: 1 rad/s, 3 m/s^2, a quarter and a tenth of the body weight
    # per unit): up to 3 rad/s, 10 m/s^2, 1.5 body weights per contact point, half of one for eta
    omega, accel = 3.0 * jnp.tanh(o[0] / 3.0), 10.0 * jnp.tanh(0.3 * o[1])
    if config.camera_motion == "none":
        omega, accel = jnp.zeros_like(omega), jnp.zeros_like(accel)
    grf = weight * 1.5 * jnp.tanh(o[2].reshape(T, NUM_CONTACTS, 3) / 6.0)
    eta = weight * 0.5 * jnp.tanh(o[4] / 5.0)
    return Physical(omega, accel, grf, x[:, -NUM_CONTACTS:] + o[3], eta)


def attention_average(q: Array, weights: Array, W: int) -> Array:
    """Eq. 7: ``q~_t = sum_j w_tj q_j`` over ``j = t-W..t+W`` (edges replicated): positions and
    joint angles averaged, the root quaternion by the normalised weighted sum of quaternions on
    the hemisphere of frame t's."""
    T = q.shape[0]
    idx = jnp.clip(jnp.arange(T)[:, None] + jnp.arange(-W, W + 1)[None], 0, T - 1)  # (T, 2W+1)
    win = q[idx]  # (T, 2W+1, nq)
    lin = jnp.einsum("tk,tkn->tn", weights, win)
    quat = win[..., 3:7]
    sign = jnp.sign(jnp.sum(quat * q[:, None, 3:7], -1, keepdims=True) + 1e-12)
    qq = quat_normalize(jnp.einsum("tk,tkn->tn", weights, quat * sign))
    return lin.at[:, 3:7].set(qq)


def pd_control(net: dict, model: Model, x: Array, q_cam: Array, config: DnDConfig) -> Control:
    out = ClipConvNet(pd_outputs(model, config), config.channels, config.depth).apply({"params": net["pd"]}, x)
    nv = model.nv
    dtype = x.dtype
    kp0 = S.kp_initial(model, config.kp_root_pos, config.kp_root_rot, config.kp_joint, dtype)
    kp = kp0 * jnp.exp(2.0 * jnp.tanh(out[:, :nv]))
    kd = 2.0 * jnp.sqrt(kp) * jnp.exp(jnp.tanh(out[:, nv : 2 * nv]))
    alpha = 50.0 * jnp.tanh(0.2 * out[:, 2 * nv : 3 * nv])  # up to 50 rad/s^2 (m/s^2)
    W = config.attention
    if config.pd == "attentive":
        offsets = jnp.arange(-W, W + 1, dtype=dtype)
        prior = -0.5 * (offsets / 1.5) ** 2  # a fresh controller attends to its own frame and the next
        weights = jax.nn.softmax(out[:, 3 * nv :] + prior, -1)
        target = attention_average(q_cam, weights, W)
    else:
        weights = jnp.zeros((q_cam.shape[0], 2 * W + 1), dtype).at[:, W].set(1.0)
        target = q_cam
    return Control(kp, kd, alpha, target, weights)


def contact_sample(logits: Array, key: Array | None, config: DnDConfig, train: bool) -> Array:
    """The contact state ``b`` (T, 4) that weighs the forces: PCT's Gumbel-softmax sample (eq. 6,
    40) in training (``contacts="pct"``), else ``p > threshold`` (no gradient to the logits)."""
    p = jax.nn.sigmoid(logits)
    hard = jax.lax.stop_gradient((p > config.contact_threshold).astype(p.dtype))
    if not train or config.contacts == "discrete" or key is None:
        return hard
    g = jax.random.gumbel(key, (*logits.shape, 2), logits.dtype)
    # b = p e^g1 / (p e^g1 + (1 - p) e^g0), with a temperature: a two-class softmax
    z = (jax.nn.log_sigmoid(logits) + g[..., 1] - jax.nn.log_sigmoid(-logits) - g[..., 0]) / config.gumbel_temperature
    return jax.nn.sigmoid(z)


# ---------------------------------------------------------------------------------------
# the camera's motion from a known track
# ---------------------------------------------------------------------------------------


def track_motion(track: Array, fps) -> tuple[Array, Array, Array]:
    """``(omega, alpha, accel)`` (T, 3) each, in the camera's axes, of a world -> camera track
    (T, 4, 4): ``omega_t`` the constant angular velocity that turns camera t into camera t+1 over
    one frame (so integrating it reproduces the track's orientations exactly), ``alpha`` its
    central difference, ``accel`` the camera centre's central second difference turned into
    camera t's axes. The last frame repeats the one before."""
    dt = 1.0 / jnp.asarray(fps, track.dtype)
    R = track[:, :3, :3]
    c = -jnp.einsum("tji,tj->ti", R, track[:, :3, 3])  # centres: -R^T t
    qcw = mat_to_quat(jnp.swapaxes(R, -1, -2))  # camera -> world
    omega = jax.vmap(quat_error)(qcw[1:], qcw[:-1]) / dt  # body (camera) frame rotation t -> t+1
    omega = jnp.concatenate([omega, omega[-1:]])
    alpha = jnp.gradient(omega, axis=0) / dt if omega.shape[0] > 1 else jnp.zeros_like(omega)
    acc_w = jnp.gradient(jnp.gradient(c, axis=0), axis=0) / dt**2 if c.shape[0] > 2 else jnp.zeros_like(c)
    accel = jnp.einsum("tij,tj->ti", R, acc_w)
    return omega, alpha, accel


def rotate_camera(R: Array, omega: Array, dt) -> Array:
    """World -> camera rotation after the camera turned by ``omega`` (its own axes) for ``dt``:
    the camera's axes in the world ``R^T`` become ``R^T exp(omega dt)``."""
    return quat_to_mat(quat_exp(omega * dt)).T @ R


# ---------------------------------------------------------------------------------------
# the forward dynamics and the constrained update
# ---------------------------------------------------------------------------------------


@struct.dataclass
class State:
    q: Array  # (nq,) relative to the camera
    qd: Array  # (nv,) relative to the camera
    R: Array  # (3, 3) world -> camera rotation
    pos: Array  # (3,) root position in the world
    vel: Array  # (3,) root velocity in the world


@struct.dataclass
class FrameInput:
    target: Array  # (nq,) q~ of the frame stepped to
    kp: Array
    kd: Array
    alpha: Array
    omega: Array
    alpha_cam: Array  # d omega / dt
    accel: Array
    grf: Array  # (4, 3)
    b: Array  # (4,)
    eta: Array  # (3,)
    real: Array  # () bool


@struct.dataclass
class StepReport:
    impulse: Array  # (3,) the world root velocity change the constrained update made (m/s)


def constrained_update(model: Model, kin, metric: Array, q: Array, qd: Array, vel: Array, R: Array,
                       omega: Array, b: Array, weight, target: Array | None = None) -> tuple[Array, Array]:
    """Eq. 15 (soft form): ``[qd*, vel*]`` minimising ``|qd* - qd|^2_M + m |vel* - vel|^2 +
    weight sum_j b_j |v_j - target_j|^2`` where ``v_j = vel* + R^T (A_j qd* + omega x (x_j -
    root))`` is the world velocity of contact point ``j`` (``A_j``: its camera-frame Jacobian
    relative to the root) and ``target`` (4, 3) its wanted world velocity (None: at rest). One
    (nv + 3) Cholesky solve; ``b = 0`` leaves the velocities unchanged."""
    nv = model.nv
    dtype = qd.dtype
    Jc = P.contact_jacobian(model, q, kin=kin).reshape(NUM_CONTACTS, 3, nv)
    A = Jc.at[:, :, 0:3].add(-jnp.eye(3, dtype=dtype))  # relative to the root's velocity
    x = P.site_positions(model, q, model.topo.contact_sites, kin=kin) - q[0:3]
    d = jnp.einsum("ji,cj->ci", R, jnp.cross(omega, x))  # R^T (omega x r): (4, 3)
    if target is not None:
        d = d - target
    C = jnp.concatenate([jnp.einsum("ji,cjv->civ", R, A), jnp.broadcast_to(jnp.eye(3, dtype=dtype), (NUM_CONTACTS, 3, 3))], -1)
    wb = weight * b  # (4,)
    H = metric + jnp.einsum("c,civ,ciw->vw", wb, C, C)
    rhs = metric @ jnp.concatenate([qd, vel]) - jnp.einsum("c,civ,ci->v", wb, C, d)
    sol = P.cho_solve(P.cholesky(H), rhs)
    return sol[:nv], sol[nv:]


def step(model: Model, state: State, f: FrameInput, dt, config: DnDConfig) -> tuple[State, StepReport]:
    """One sub-step of the dynamics (module docstring, 1-5)."""
    q, qd, R = state.q, state.qd, state.R
    dtype = q.dtype
    kin = P.forward_kinematics(model, q)
    M = P.mass_matrix(model, q, kin=kin)
    L = P.cholesky(M)
    g_cam = R @ jnp.asarray(model.gravity, dtype)
    zero = jnp.zeros(model.nv, dtype)
    h_g = P.rnea(model, q, zero, zero, kin=kin, gravity=g_cam)  # the force that holds the pose against gravity
    frame = P.FrameMotion(f.omega, f.alpha_cam, f.accel)
    inertial = P.inertial_force(model, q, qd, frame, g_cam, kin=kin)
    Jc = P.contact_jacobian(model, q, kin=kin)
    force = f.b[:, None] * f.grf  # (4, 3)
    external = Jc.T @ force.reshape(-1) - h_g + inertial
    # the PD (eq. 8) in acceleration units with the Coriolis compensation h_c (which cancels),
    # its stiff part implicit (stable PD): a large gain does not make the step unstable
    e = S.pd_error(model, f.target, q)
    acc_pd = (f.kp * (e - dt * qd) - f.kd * qd) / (1.0 + dt * f.kd + dt * dt * f.kp)
    qdd = acc_pd + f.alpha + P.cho_solve(L, external)
    qd_free = jnp.clip(qd + dt * qdd, -config.max_velocity, config.max_velocity)
    # eq. 10: the world trajectory, moved by the estimated external forces and gravity
    m = S.body_mass(model, dtype)
    acc_w = R.T @ (f.eta + force.sum(0)) / m + jnp.asarray(model.gravity, dtype)
    vel_free = state.vel + dt * acc_w
    # eq. 15, in the kinetic-energy metric (M for the pose, m for the root's world velocity)
    metric = jnp.zeros((model.nv + 3, model.nv + 3), dtype).at[: model.nv, : model.nv].set(config.pose_stiffness * M)
    metric = metric.at[model.nv :, model.nv :].set(m * jnp.eye(3, dtype=dtype))
    # jmocap's addition: the floor is known (the world of the first frame's camera), so contact
    # points in contact are also drawn to it, a share ``floor_recovery`` of their height per step
    height = state.pos[2] + (P.site_positions(model, q, model.topo.contact_sites, kin=kin) - q[0:3]) @ R[:, 2]
    target = jnp.zeros((NUM_CONTACTS, 3), dtype).at[:, 2].set(-config.floor_recovery * height / dt)
    qd_new, vel_new = constrained_update(model, kin, metric, q, qd_free, vel_free, R, f.omega, f.b,
                                         config.constraint_weight * m, target)
    qd_new = jnp.clip(qd_new, -config.max_velocity, config.max_velocity)
    vel_new = jnp.clip(vel_new, -config.max_velocity, config.max_velocity)
    q_new = P.integrate_positions(model, q, qd_new, dt)
    new = State(q_new, qd_new, rotate_camera(R, f.omega, dt), state.pos + dt * vel_new, vel_new)
    new = jax.tree.map(lambda a, b: jnp.where(f.real, a, b), new, state)
    return new, StepReport(jnp.where(f.real, vel_new - vel_free, 0.0))


def simulate(model: Model, init: State, frames: FrameInput, fps, config: DnDConfig) -> tuple[State, State, StepReport]:
    """The dynamics over a clip: frame t+1's state from frame t's, stepping towards frame t+1's
    target with frame t's forces and camera motion. Returns the last state, every frame's state
    (T, ...; frame 0 is ``init``) and every sub-step's report (T - 1, k, ...)."""
    k = config.iterations
    dt = (1.0 / jnp.asarray(fps, init.q.dtype)) / k

    def frame(state, f):
        def sub(s, _):
            return step(model, s, f, dt, config)

        new, rep = jax.lax.scan(sub, state, None, length=k)
        return new, (new, rep)

    last, (states, reports) = jax.lax.scan(frame, init, frames)
    states = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), init, states)
    return last, states, reports


# ---------------------------------------------------------------------------------------
# a clip
# ---------------------------------------------------------------------------------------


@struct.dataclass
class Rollout:
    """Everything D&D computes for a clip (training reads the intermediate quantities)."""

    states: State  # (T, ...) per frame
    reports: StepReport  # (T - 1, k, ...)
    physical: Physical
    control: Control
    b: Array  # (T, 4) the contact states used
    init: Initial


def frame_inputs(model: Model, inputs: ClipInputs, init: Initial, phys: Physical, ctrl: Control, b: Array,
                 config: DnDConfig) -> FrameInput:
    """Frame t's step: frame t's forces and camera motion towards frame t+1's target (T - 1)."""
    dtype = init.q_cam.dtype
    if config.camera_motion == "track":
        omega, alpha, accel = track_motion(jnp.asarray(inputs.world_to_camera(), dtype), inputs.fps)
    else:
        omega, accel = phys.omega, phys.accel
        fps = jnp.asarray(inputs.fps, dtype)
        alpha = jnp.gradient(omega, axis=0) * fps if omega.shape[0] > 1 else jnp.zeros_like(omega)
    mask = jnp.asarray(inputs.mask)
    return FrameInput(
        target=ctrl.target[1:], kp=ctrl.kp[1:], kd=ctrl.kd[1:], alpha=ctrl.alpha[1:],
        omega=omega[:-1], alpha_cam=alpha[:-1], accel=accel[:-1], grf=phys.grf[:-1], b=b[:-1], eta=phys.eta[:-1],
        real=mask[1:],
    )


def initial_state(model: Model, inputs: ClipInputs, q_cam: Array, fps) -> State:
    """At frame 0: the initial motion's first pose and its velocity (a forward difference), the
    first frame's camera, the root's world position through it, the camera taken as still."""
    dtype = q_cam.dtype
    E = jnp.asarray(inputs.world_to_camera(), dtype)[0]
    R, t = E[:3, :3], E[:3, 3]
    qd0 = P.finite_difference_velocity(model, q_cam[:2], fps)[1] if q_cam.shape[0] > 1 else jnp.zeros(model.nv, dtype)
    qd0 = jnp.clip(qd0, -5.0, 5.0)
    return State(q_cam[0], qd0, R, R.T @ (q_cam[0, 0:3] - t), R.T @ qd0[0:3])


def rollout(params: dict, model: Model, inputs: ClipInputs, config: DnDConfig, *, key: Array | None = None,
            train: bool = False, init_state: State | None = None, initial: Initial | None = None) -> Rollout:
    """D&D over one clip. ``train`` samples PCT's contacts with ``key``; ``init_state`` replaces
    the state at frame 0 (training starts from the ground truth); ``initial`` the backbone's
    output (training precomputes it: the backbone is frozen)."""
    _check(config)
    net = dnd_params(params)
    inputs = seen_inputs(inputs, config)
    init = initial_motion(params, model, inputs, config) if initial is None else initial
    dtype = init.q_cam.dtype
    mask = jnp.asarray(inputs.mask)
    E0 = jnp.asarray(inputs.world_to_camera(), dtype)[0]
    x = features(model, init, E0[:3, :3] @ jnp.asarray(model.gravity, dtype), mask)
    phys = physical_properties(net, model, x, config)
    ctrl = pd_control(net, model, x, init.q_cam[last_real(mask)], config)
    b = contact_sample(phys.contact_logits, key, config, train)
    frames = frame_inputs(model, inputs, init, phys, ctrl, b, config)
    state0 = initial_state(model, inputs, init.q_cam, inputs.fps) if init_state is None else init_state
    _, states, reports = simulate(model, state0, frames, inputs.fps, config)
    return Rollout(states, reports, phys, ctrl, b, init)


def world_pose(states: State) -> Array:
    """(T, nq) the world motion: the root's world position, its camera-frame orientation turned
    into the world by ``R^T``, the joint angles."""
    rot_w = jnp.einsum("tji,tjk->tik", states.R, quat_to_mat(states.q[:, 3:7]))
    return states.q.at[:, 0:3].set(states.pos).at[:, 3:7].set(mat_to_quat(rot_w))


def estimated_track(states: State) -> Array:
    """(T, 4, 4) the world -> camera track the motion implies: the integrated orientation, and
    the camera placed so that the root appears where the camera-frame pose has it."""
    T = states.R.shape[0]
    t = states.q[:, 0:3] - jnp.einsum("tij,tj->ti", states.R, states.pos)
    E = jnp.zeros((T, 4, 4), states.R.dtype).at[:, :3, :3].set(states.R).at[:, :3, 3].set(t)
    return E.at[:, 3, 3].set(1.0)


def estimate_track(params: dict, model: Model, inputs: ClipInputs, config: DnDConfig = DnDConfig()) -> Array:  # noqa: B008
    """(T, 4, 4) the camera track D&D estimates for a clip (:func:`estimated_track` of its
    rollout), without the world motion's outputs (forces, inverse dynamics)."""
    return estimated_track(rollout(params, model, inputs, config).states)


def world_forces(states: State, grf: Array, b: Array) -> Array:
    """(T, 4, 3) the contact forces ``b lambda`` in the world's axes."""
    return jnp.einsum("tji,tcj->tci", states.R, b[..., None] * grf)


def _outputs(model: Model, q: Array, grf: Array, mask: Array, fps) -> tuple[Array, Array]:
    """``(qd, tau)``: the world motion's finite-difference velocities and its inverse dynamics
    less the contact forces (``tau[:6]``: the residual root wrench it needs)."""
    from jmocap.methods.trajopt import frame_velocities

    length = jnp.sum(mask.astype(jnp.int32))
    qd, qdd = frame_velocities(q, jnp.asarray(fps, q.dtype), length)

    def one(qt, v, a, f):
        kin = P.forward_kinematics(model, qt)
        return P.rnea(model, qt, v, a, kin=kin) - P.contact_jacobian(model, qt, kin=kin).T @ f.reshape(-1)

    tau = jax.vmap(one)(q, qd, qdd, grf)
    m = mask.astype(q.dtype)[:, None]
    return qd * m, tau * m


def reconstruct(params: dict, model: Model, inputs: ClipInputs, config: DnDConfig = DnDConfig()) -> Motion:  # noqa: B008
    """2D keypoints of one clip (and its first frame's camera) -> a world :class:`Motion`."""
    r = rollout(params, model, inputs, config)
    mask = jnp.asarray(inputs.mask)
    q = world_pose(r.states)
    grf = world_forces(r.states, r.physical.grf, r.b) * mask[:, None, None]
    qd, tau = _outputs(model, q, grf, mask, inputs.fps)
    prob = jax.nn.sigmoid(r.physical.contact_logits) * mask[:, None]
    impulse = jnp.linalg.norm(r.reports.impulse, axis=-1).sum(-1)  # (T - 1,)
    diagnostics = dict(
        projection_impulse_mean_m_s=jnp.sum(impulse * mask[1:]) / jnp.maximum(jnp.sum(mask[1:]), 1),
        camera_turn_deg=jnp.degrees(jnp.arccos(jnp.clip(
            (jnp.trace(r.states.R[0] @ r.states.R[jnp.sum(mask) - 1].T) - 1.0) / 2.0, -1.0, 1.0))),
    )
    return Motion(q, qd, tau, grf, prob, r.init.q_world, mask, diagnostics=diagnostics,
                  camera_track=estimated_track(r.states))


METHOD = register(
    Method(
        name="dnd",
        summary="D&D: inertial force control for an unknown moving camera, probabilistic contact "
        "torque, attentive PD, trajectory dynamics and a contact-constrained update (whole clips)",
        paper="003 (D&D, Li et al. 2022), Sec. 3.2-3.5, on 000's (Neural PhysCap) kinematic target",
        config_type=DnDConfig,
        reconstruct=reconstruct,
        init_params=init_params,
        **whole_clip(reconstruct),
        from_weights=LEARNED_STAGE_FIELDS,
        shipped_networks=("dnd",),
    )
)

for _name, _change, _summary in (
    ("dnd_residual_force", {"camera_motion": "none"},
     "D&D without inertial force control: the camera held still, a residual force instead (Tab. 3)"),
    ("dnd_discrete_contacts", {"contacts": "discrete"}, "D&D trained with thresholded contacts, no PCT (Tab. 3)"),
    ("dnd_meta_pd", {"pd": "meta"}, "D&D with per-frame PD gains and no attention (meta-PD, Tab. 3)"),
    ("dnd_known_track", {"camera_motion": "track"}, "D&D's dynamics with the clip's known camera track's motion"),
):
    register_variant(Variant(_name, "dnd", _change, _summary))

__all__ = [
    "CAMERA_MOTIONS",
    "METHOD",
    "ClipConvNet",
    "Control",
    "DnDConfig",
    "Initial",
    "Physical",
    "Rollout",
    "State",
    "attention_average",
    "constrained_update",
    "contact_sample",
    "default_dnd_params",
    "dnd_params",
    "estimate_track",
    "estimated_track",
    "init_params",
    "initial_motion",
    "reconstruct",
    "rollout",
    "rotate_camera",
    "simulate",
    "track_motion",
    "world_pose",
]
