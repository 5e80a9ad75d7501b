"""PIP's kinematics module (Yi et al. 2022, Sec. 3.1): recurrent networks from six IMUs to the
root-relative joint positions, the pose, the joint velocities and the foot contacts, with PIP's
learned RNN state initialisation.

Input (PIP / TransPose's ``normalize_and_concat``): per frame the calibrated bone orientations
``R_WB`` (6, 3, 3) and free accelerations ``a_W`` (6, 3) of :meth:`jmocap.data.imu.IMUClip.calibrated`
(:data:`~jmocap.data.imu.SENSORS` order, pelvis last) become one 72-vector
``x = [acc (18), ori (54)]``: the five non-root sensors' accelerations relative to the pelvis
sensor's, ``R_root^T (a_s - a_root)``, and the pelvis sensor's own, ``R_root^T a_root``, all
divided by ``acc_scale`` (30 m/s^2); the five orientations relative to the pelvis,
``R_root^T R_s``, and the pelvis orientation ``R_root`` itself (row-major 3x3 each).

Networks (:class:`IMUKinematics`; each one PIP's ``RNN``: input dropout, Dense + ReLU, a
``layers``-layer unidirectional LSTM, a linear head):

* ``P_L`` (``leaf``): x -> the five leaf joints (wrists, ankles, head) in the root frame (15);
* ``P_A`` (``joints``): [leaf, x] -> the 23 non-root joints (body origins) in the root frame (69);
* ``R_A`` (``pose``): [joints, x] -> jmocap's 41 hinge angles (``pi tanh``, as TPNet); the root
  orientation is the pelvis sensor's (PIP: "directly measured by the IMU on the pelvis");
* ``V_A`` (``vel``): [joints, x] -> the world-frame velocities of all 24 joints expressed in the
  root frame, divided by ``vel_scale`` (3 m/s) (72; joint 0 is the root's velocity);
* ``C_F`` (``contact``): [joints, x] -> logits of jmocap's four contact sites (L heel, L toe,
  R heel, R toe), width ``contact_width``.

PIP's learned initialisation: two fully connected networks (``I_PL``, ``I_VA``: Dense + ReLU,
Dense + ReLU, Dense to every layer's ``(h, c)``) map the first frame's leaf joint positions and
joint velocities to ``P_L``'s and ``V_A``'s initial LSTM states; the other three start at zero.
``learned_init=False`` (the paper's ablation) starts every network at zero.

Everything is causal and online: :func:`step` advances one frame with the state carried, and
:func:`run` is ``lax.scan`` of it, so a clip run in chunks (the state handed on) equals the
whole-clip run. :func:`targets` turns a clip's ground truth into the training targets.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap import physics as P
from jmocap.model import Model
from jmocap.physics.rotations import mat_to_quat

Array = jax.Array

#: PIP / TransPose's leaf joints, as bodies of jmocap's character (the body frame's origin is the
#: joint): wrists, ankles and head (the head body's origin is the top of the neck)
LEAF_BODIES = ("left_wrist", "right_wrist", "left_ankle", "right_ankle", "head")
ROOT_BODY = "pelvis"
NUM_INPUT = 72


@dataclass(frozen=True)
class IMUNetConfig:
    """Widths and normalisation of :class:`IMUKinematics` (PIP: width 256, contact 64, 2 layers)."""

    width: int = 256  # LSTM width of P_L, P_A, R_A, V_A
    contact_width: int = 64  # of C_F
    layers: int = 2  # LSTM layers per network
    dropout: float = 0.2  # on each network's input (training only)
    learned_init: bool = True  # PIP's learned RNN initialisation of P_L and V_A (else zero)
    acc_scale: float = 30.0  # m/s^2
    vel_scale: float = 3.0  # m/s
    contact_pos_weight: float = 1.0  # weight of the "in contact" class in the contacts' BCE (training only)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@struct.dataclass
class Outputs:
    """Per-frame outputs (leading axes ``(..., T)``); positions and velocities in the root frame."""

    leaf: Array  # (..., 5, 3) m
    joints: Array  # (..., 23, 3) m, the non-root bodies
    hinges: Array  # (..., n_hinges) rad
    vel: Array  # (..., 24, 3) m/s, every body (root first)
    contact_logits: Array  # (..., 4)


# --- layout of jmocap's character ----------------------------------------------------------


def body_indices(model: Model) -> dict[str, np.ndarray]:
    """Body ids: ``root`` (the pelvis), ``joints`` (every other body, in model order),
    ``bodies`` (root then joints) and ``leaf``."""
    root = model.body_id(ROOT_BODY)
    nb = model.topo.nbody
    joints = np.array([b for b in range(1, nb) if b != root])
    return {
        "root": np.array(root),
        "joints": joints,
        "bodies": np.concatenate([[root], joints]),
        "leaf": np.array([model.body_id(n) for n in LEAF_BODIES]),
    }


# --- inputs ----------------------------------------------------------------------------------


def imu_features(ori: Array, acc: Array, acc_scale: float = 30.0) -> Array:
    """PIP's network input (..., 72) from calibrated bone orientations (..., 6, 3, 3) and free
    accelerations (..., 6, 3) in jmocap's world (pelvis sensor last)."""
    R_root = ori[..., 5, :, :]
    rel = jnp.concatenate([acc[..., :5, :] - acc[..., 5:, :], acc[..., 5:, :]], -2)
    a = jnp.einsum("...ij,...si->...sj", R_root, rel) / acc_scale  # R_root^T a
    o = jnp.concatenate([jnp.einsum("...ji,...sjk->...sik", R_root, ori[..., :5, :, :]), ori[..., 5:, :, :]], -3)
    return jnp.concatenate([a.reshape(*a.shape[:-2], 18), o.reshape(*o.shape[:-3], 54)], -1)


# --- networks -----------------------------------------------------------------------------------


class RNN(nn.Module):
    """PIP's ``RNN``: dropout on the input, Dense + ReLU, ``layers`` LSTM layers, linear head;
    one frame: ``(carry, x) -> (carry, y)``, carry a tuple of per-layer ``(c, h)``."""

    out: int
    width: int
    layers: int = 2
    dropout: float = 0.0

    @nn.compact
    def __call__(self, carry, x, *, train: bool = False):
        h = nn.Dropout(self.dropout, deterministic=not train)(x)
        h = nn.relu(nn.Dense(self.width)(h))
        new = []
        for i in range(self.layers):
            c_i, h = nn.OptimizedLSTMCell(self.width, name=f"lstm{i}")(carry[i], h)
            new.append(c_i)
        return tuple(new), nn.Dense(self.out)(h)


class InitNet(nn.Module):
    """PIP's initial-state network: input -> every LSTM layer's ``(c, h)`` (Dense + ReLU, Dense +
    ReLU, Dense; widths ``width``, ``width * layers``, ``2 * layers * width``)."""

    width: int
    layers: int = 2

    @nn.compact
    def __call__(self, x):
        h = nn.relu(nn.Dense(self.width)(x))
        h = nn.relu(nn.Dense(self.width * self.layers)(h))
        h = nn.Dense(2 * self.layers * self.width)(h).reshape(*x.shape[:-1], self.layers, 2, self.width)
        return tuple((h[..., i, 1, :], h[..., i, 0, :]) for i in range(self.layers))  # PIP: (h, c)


class IMUKinematics(nn.Module):
    """The five RNNs and the two initial-state networks (module docstring)."""

    n_hinges: int
    n_joints: int = 23  # non-root bodies
    config: IMUNetConfig = IMUNetConfig()

    def setup(self):
        c = self.config
        kw = dict(width=c.width, layers=c.layers, dropout=c.dropout)
        self.leaf = RNN(out=15, **kw)
        self.joints = RNN(out=3 * self.n_joints, **kw)
        self.pose = RNN(out=self.n_hinges, **kw)
        self.vel = RNN(out=3 * (self.n_joints + 1), **kw)
        self.contact = RNN(out=4, width=c.contact_width, layers=c.layers, dropout=c.dropout)
        self.init_leaf = InitNet(c.width, c.layers)
        self.init_vel = InitNet(c.width, c.layers)

    def initial_state(self, leaf0, vel0):
        """The carry from the first frame's leaf positions (..., 5, 3) and joint velocities
        (..., 24, 3) (root frame, m and m/s): learned for P_L and V_A (``learned_init``),
        zero elsewhere."""
        c = self.config
        batch = leaf0.shape[:-2]
        zero = zero_state(c, batch, leaf0.dtype)
        if not c.learned_init:
            return zero
        li = self.init_leaf(leaf0.reshape(*batch, -1))
        vi = self.init_vel(vel0.reshape(*batch, -1) / c.vel_scale)
        return {**zero, "leaf": li, "vel": vi}

    def step(self, carry, x, *, train: bool = False):
        """One frame: ``(carry, x (..., 72)) -> (carry, raw outputs)``."""
        s_leaf, leaf = self.leaf(carry["leaf"], x, train=train)
        s_joints, joints = self.joints(carry["joints"], jnp.concatenate([leaf, x], -1), train=train)
        u = jnp.concatenate([joints, x], -1)
        s_pose, hinge_raw = self.pose(carry["pose"], u, train=train)
        s_vel, vel = self.vel(carry["vel"], u, train=train)
        s_con, logits = self.contact(carry["contact"], u, train=train)
        new = {"leaf": s_leaf, "joints": s_joints, "pose": s_pose, "vel": s_vel, "contact": s_con}
        b = x.shape[:-1]
        out = Outputs(leaf.reshape(*b, 5, 3), joints.reshape(*b, self.n_joints, 3), jnp.pi * jnp.tanh(hinge_raw),
                      vel.reshape(*b, self.n_joints + 1, 3) * self.config.vel_scale, logits)
        return new, out

    def __call__(self, x, leaf0, vel0):  # for init: touches every submodule
        return self.step(self.initial_state(leaf0, vel0), x)


def zero_state(config: IMUNetConfig, batch: tuple[int, ...] = (), dtype=jnp.float32) -> dict:
    """Every network's LSTM state at zero (the ablation's start; also the carry's shapes)."""

    def z(w):
        return tuple((jnp.zeros(batch + (w,), dtype), jnp.zeros(batch + (w,), dtype)) for _ in range(config.layers))

    w = config.width
    return {"leaf": z(w), "joints": z(w), "pose": z(w), "vel": z(w), "contact": z(config.contact_width)}


# --- pure functions ---------------------------------------------------------------------------


def make_net(model: Model, config: IMUNetConfig = IMUNetConfig()) -> IMUKinematics:
    return IMUKinematics(n_hinges=int(model.topo.hinge_qadr.size), n_joints=int(model.topo.nbody) - 2, config=config)


def init_params(key, model: Model, config: IMUNetConfig = IMUNetConfig()) -> dict:
    """Fresh parameters ``{"params": ...}`` of :class:`IMUKinematics` for ``model``'s character."""
    net = make_net(model, config)
    nj = int(model.topo.nbody) - 2
    return net.init(key, jnp.zeros((NUM_INPUT,)), jnp.zeros((5, 3)), jnp.zeros((nj + 1, 3)))


def initial_state(params, model: Model, config: IMUNetConfig, leaf0: Array, vel0: Array | None = None) -> dict:
    """The carry before a clip's first frame (learned from ``leaf0`` (..., 5, 3) and ``vel0``
    (..., 24, 3), zero velocity when None; zero with ``learned_init=False``)."""
    if vel0 is None:
        vel0 = jnp.zeros(leaf0.shape[:-2] + (int(model.topo.nbody) - 1, 3), leaf0.dtype)
    return make_net(model, config).apply(params, leaf0, vel0, method=IMUKinematics.initial_state)


def step(params, model: Model, config: IMUNetConfig, carry: dict, x: Array, *, train: bool = False,
         rng=None) -> tuple[dict, Outputs]:
    """One frame online: input (..., 72) (:func:`imu_features`) and the carry -> (carry, outputs)."""
    rngs = {"dropout": rng} if rng is not None else {}
    return make_net(model, config).apply(params, carry, x, train=train, rngs=rngs, method=IMUKinematics.step)


def run(params, model: Model, config: IMUNetConfig, carry: dict, x: Array, *, train: bool = False,
        rng=None) -> tuple[dict, Outputs]:
    """Frames ``x`` (T, 72) from ``carry``: ``lax.scan`` of :func:`step` (one dropout key per frame
    when training). Returns the carry after the last frame and the outputs (leading axis T)."""
    T = x.shape[0]
    keys = jax.random.split(rng, T) if (train and rng is not None) else None

    def body(c, xs):
        xt, k = xs
        return step(params, model, config, c, xt, train=train, rng=k)

    return jax.lax.scan(body, carry, (x, keys))


def pose(model: Model, out: Outputs, R_root: Array, root_pos: Array | None = None) -> Array:
    """Configurations (T, nq) from the outputs: the root orientation of the pelvis sensor
    ``R_root`` (T, 3, 3), the estimated hinge angles, the root at ``root_pos`` (T, 3; zero when
    None: the kinematics module does not estimate the translation)."""
    T = out.hinges.shape[0]
    q = jnp.zeros((T, model.nq), out.hinges.dtype)
    if root_pos is not None:
        q = q.at[:, 0:3].set(root_pos)
    return q.at[:, 3:7].set(mat_to_quat(R_root)).at[:, model.topo.hinge_qadr].set(out.hinges)


def integrate_root(out: Outputs, R_root: Array, fps, start: Array) -> Array:
    """Root positions (T, 3) from the estimated root velocity (V_A's joint 0, rotated to the world
    by the pelvis sensor) integrated from ``start`` (3,) (PIP's kinematics-only translation)."""
    v = jnp.einsum("tij,tj->ti", R_root, out.vel[:, 0])
    disp = jnp.concatenate([jnp.zeros((1, 3), v.dtype), jnp.cumsum(v[1:], 0) / fps])
    return start + disp


# --- targets from ground truth -----------------------------------------------------------------


def targets(model: Model, gt_q: Array, fps, gt_contacts: Array | None = None) -> dict[str, Array]:
    """Training targets of one clip from its ground-truth motion ``gt_q`` (T, nq) on the subject's
    character ``model`` (forward kinematics with :mod:`jmocap.physics`), in the root frame as PIP:

    * ``leaf`` (T, 5, 3), ``joints`` (T, 23, 3): ``R_root^T (x_b - x_root)`` of the leaf / non-root
      bodies' origins;
    * ``hinges`` (T, n_hinges): the hinge angles of ``gt_q``;
    * ``vel`` (T, 24, 3): ``R_root^T v_b``, ``v_b`` the world velocity of every body's origin (root
      first) by backward differences (frame 0: the forward difference);
    * ``contacts`` (T, 4) float (zeros when ``gt_contacts`` is None);
    * ``R_root`` (T, 3, 3), ``xpos`` (T, nbody, 3), ``xmat`` (T, nbody, 3, 3): world frame.
    """
    ids = body_indices(model)
    gt_q = jnp.asarray(gt_q)
    kin = jax.vmap(lambda q: P.forward_kinematics(model, q))(gt_q)
    xpos, xmat = kin.xpos, kin.xmat
    R = xmat[:, ids["root"]]
    root = xpos[:, ids["root"]]

    def local(p):  # (T, n, 3) world -> root frame
        return jnp.einsum("tij,tni->tnj", R, p)

    bodies = xpos[:, ids["bodies"]]
    fps = jnp.asarray(fps, bodies.dtype)
    d = (bodies[1:] - bodies[:-1]) * fps
    v = jnp.concatenate([d[:1], d]) if bodies.shape[0] > 1 else jnp.zeros_like(bodies)
    T = gt_q.shape[0]
    con = jnp.zeros((T, 4), bodies.dtype) if gt_contacts is None else jnp.asarray(gt_contacts, bodies.dtype)
    return {
        "leaf": local(xpos[:, ids["leaf"]] - root[:, None]),
        "joints": local(xpos[:, ids["joints"]] - root[:, None]),
        "hinges": gt_q[:, model.topo.hinge_qadr],
        "vel": local(v),
        "contacts": con,
        "R_root": R,
        "xpos": xpos,
        "xmat": xmat,
    }


# --- losses ------------------------------------------------------------------------------------

#: loss weights (PIP: L2 for P_L, P_A, R_A; BCE for C_F; TransPose's cumulative loss for V_A)
LOSS_WEIGHTS = {"leaf": 10.0, "joints": 10.0, "pose": 1.0, "vel": 1.0, "contact": 0.5}
#: window lengths of the cumulative velocity loss (TransPose: 1, 3, 9, 27)
CUMULATIVE_WINDOWS = (1, 3, 9, 27)


def cumulative_velocity_loss(v_hat: Array, v: Array, R_root: Array, vel_scale: float, fps) -> Array:
    """TransPose's accumulative loss on the velocities (T, J, 3) (root frame): the errors rotated
    to the world frame, summed over consecutive windows of n frames (n in 1, 3, 9, 27; the
    displacement error over the window in units of ``vel_scale / fps``), squared, averaged, each
    n weighted 1/n; windows longer than the clip are skipped."""
    err = jnp.einsum("tij,tnj->tni", R_root, v_hat - v) / vel_scale
    T = err.shape[0]
    total = 0.0
    for n in CUMULATIVE_WINDOWS:
        m = T // n
        if m == 0:
            continue
        s = err[: m * n].reshape(m, n, *err.shape[1:]).sum(1)
        total = total + jnp.mean(jnp.sum(s * s, -1)) / n
    return total


def losses(out: Outputs, tgt: dict[str, Array], config: IMUNetConfig, fps) -> dict[str, Array]:
    """The per-network losses of one clip window (means over frames and joints)."""

    def l2(a, b):
        return jnp.mean(jnp.sum((a - b) ** 2, -1))

    c = tgt["contacts"]
    logits = out.contact_logits
    # (weighted) binary cross-entropy: w c softplus(-l) + (1 - c) softplus(l)
    bce = jnp.mean(config.contact_pos_weight * c * jax.nn.softplus(-logits) + (1.0 - c) * jax.nn.softplus(logits))
    return {
        "leaf": l2(out.leaf, tgt["leaf"]),
        "joints": l2(out.joints, tgt["joints"]),
        "pose": jnp.mean((out.hinges - tgt["hinges"]) ** 2),
        "vel": cumulative_velocity_loss(out.vel, tgt["vel"], tgt["R_root"], config.vel_scale, fps),
        "contact": bce,
    }


def total_loss(parts: dict[str, Array], weights: dict[str, float] | None = None) -> Array:
    w = LOSS_WEIGHTS if weights is None else weights
    return sum(w[k] * parts[k] for k in parts)


def clip_loss(params, model: Model, config: IMUNetConfig, x: Array, tgt: dict[str, Array], fps, *,
              train: bool = False, rng=None, weights=None) -> tuple[Array, dict[str, Array]]:
    """Total loss and its parts over a window ``x`` (T, 72) started from the window's first-frame
    ground truth (learned init) or zero (``learned_init=False``)."""
    carry = initial_state(params, model, config, tgt["leaf"][0], tgt["vel"][0])
    _, out = run(params, model, config, carry, x, train=train, rng=rng)
    parts = losses(out, tgt, config, fps)
    return total_loss(parts, weights), parts


def contact_probability(out: Outputs) -> Array:
    return jax.nn.sigmoid(out.contact_logits)


__all__: list[Any] = [
    "CUMULATIVE_WINDOWS",
    "IMUKinematics",
    "IMUNetConfig",
    "InitNet",
    "LEAF_BODIES",
    "LOSS_WEIGHTS",
    "Outputs",
    "RNN",
    "body_indices",
    "clip_loss",
    "contact_probability",
    "cumulative_velocity_loss",
    "imu_features",
    "init_params",
    "initial_state",
    "integrate_root",
    "losses",
    "make_net",
    "pose",
    "run",
    "step",
    "targets",
    "total_loss",
    "zero_state",
]
