r"""The learned distribution prior of Neural MoCon (Huang et al. 2022, Sec. 3.3) for ``mocon``.

The sampling controller (:mod:`jmocap.methods.mocon`) draws each window's corrections
:math:`\Delta\tilde q` of the reference's hinge angles from a diagonal Gaussian. Without a prior
its first round is centred on the last window's correction with a fixed spread, and the
cross-entropy rounds (the paper's "Gaussian CMA") adapt it. With the prior an **encoder**
regresses that distribution from the character's state and the reference,
:math:`Q(\Delta\tilde q \mid s_{t-1}, \tilde q_t) = \mathcal N(\mu, \operatorname{diag}\sigma^2)`,
and the controller samples from it (``MoconConfig.sampling = "prior"``).

Training (``experiments/train_mocon_prior.py``), as the paper's Eq. 5-9:

1. *Pre-training* on the controller's own cross-entropy distributions, recorded window by window
   while ``mocon`` tracks fitted clips (:func:`record_window`): the KL divergence
   :math:`KL(Q \,\|\, \mathcal D(\mu_{CE}, \sigma_{CE}))` (Eq. 5, :func:`kl_diag`).
2. *The two-branch decoder*: a correction sampled from :math:`Q` (reparameterised) is simulated
   by MuJoCo C from the recorded state (the physical branch, not differentiable); a **pose
   decoder** :math:`D(s, \tilde q, \Delta\tilde q)` learns to predict the simulated state
   (:math:`L_{sim}`, Eq. 6) and the encoder is trained through it to bring the decoded state onto
   the reference (:math:`L_{rec}`, Eq. 7), with the KL term at ``lambda = 0.2`` (Eq. 9) and an L2
   regulariser on the weights (Eq. 8).

Choices where the paper is silent (docs/method.md, "the learned prior of ``mocon``"):

* the "pose" the decoder predicts is the state's deviation from the reference at the window's
  end and at the lookahead's end (hinge angles, the root's orientation, the root's position in
  the reference's heading frame), each divided by the sampling loss's scale, instead of SMPL
  poses and joints; :math:`L_{rec}` is then the decoded deviation's squared norm;
* :math:`L_{rec}` trains the encoder only (the decoder's weights are held in it): trained by
  both, the decoder could lower it by predicting the reference whatever the simulator does;
* the corrections are in units of the controller's base spread (``sigma_rad`` times the per-hinge
  share), so the networks see numbers of order one; ``sigma`` is bounded to
  [``SIGMA_MIN``, ``SIGMA_MAX``] of that spread.

The state features (:func:`window_features`, :func:`num_features` of them for ``nu`` hinges): the hinge
angles' and velocities' errors against the reference, the root's orientation error (a rotation
vector in the reference root's frame), its position and velocity errors in the reference's
heading frame, its angular velocity error, the reference's hinge change to the window's end and
to the lookahead's end, the reference root's velocity (heading frame) and up direction (its own
frame), the reference's contacts at the window's end, and the correction in force (in spread
units). Everything is relative to the reference, so the prior does not see where on the clip or
in the world the character is.
"""

from __future__ import annotations

import functools
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jmocap.methods.base import load_float32_params

Array = jnp.ndarray

ASSET = Path(__file__).resolve().parents[1] / "assets" / "mocon_prior.msgpack"
#: the bounds of the regressed spread, in units of the controller's base spread
SIGMA_MIN, SIGMA_MAX = 0.05, 3.0
#: the decoded deviation's scales: hinge angles and root orientation (rad), root position (m)
ANGLE_SCALE, POSITION_SCALE = 0.15, 0.05
HIDDEN = (256, 256)


def num_features(nu: int) -> int:
    """The length of :func:`window_features` for ``nu`` hinges."""
    return 5 * nu + 22


def num_decoded(nu: int) -> int:
    """The length of the decoded (and simulated) deviation: two frames of ``nu`` hinges, root
    orientation (3) and position (3)."""
    return 2 * (nu + 6)


# ---------------------------------------------------------------------------------------
# quaternions (MuJoCo's w, x, y, z), numpy, batched over leading axes
# ---------------------------------------------------------------------------------------


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def _quat_conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _quat_log(q: np.ndarray) -> np.ndarray:
    """The rotation vector (..., 3) of unit quaternions (the shorter way round)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2 * np.arctan2(s, q[..., :1])
    return np.where(s > 1e-12, v / np.maximum(s, 1e-12) * angle, 2 * v)


def _quat_rotate_inv(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(q)^T v``."""
    qv = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], -1)
    return _quat_mul(_quat_mul(_quat_conj(q), qv), q)[..., 1:]


def _heading(q: np.ndarray) -> np.ndarray:
    """The yaw-only quaternion of root orientations (..., 4): the heading frame."""
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], -1)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------------------------------
# features and deviations (numpy: the controller's host loop and the training recipe)
# ---------------------------------------------------------------------------------------


def window_features(q: np.ndarray, qd: np.ndarray, ref_q: np.ndarray, ref_qd: np.ndarray,
                    contact: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """The encoder's input (..., :func:`num_features`) at a window's start.

    ``q`` (..., nq), ``qd`` (..., nv): the character's state; ``ref_q`` (..., 3, nq): the
    reference at the window's start, its end and the lookahead's end; ``ref_qd`` (..., nv): the
    reference's velocity at the start; ``contact`` (..., 4): the reference's contacts at the
    window's end; ``prev`` (..., nu): the correction in force, in units of the base spread."""
    r0, r1, r2 = ref_q[..., 0, :], ref_q[..., 1, :], ref_q[..., 2, :]
    head = _heading(r0[..., 3:7])
    hinge = _wrap(q[..., 7:] - r0[..., 7:])
    hinge_vel = (qd[..., 6:] - ref_qd[..., 6:]) / 5.0
    rot = _quat_log(_quat_mul(_quat_conj(r0[..., 3:7]), q[..., 3:7]))
    pos = _quat_rotate_inv(head, q[..., :3] - r0[..., :3]) / 0.1
    vel = _quat_rotate_inv(head, qd[..., :3] - ref_qd[..., :3])
    ang = (qd[..., 3:6] - ref_qd[..., 3:6]) / 2.0
    ahead1 = _wrap(r1[..., 7:] - r0[..., 7:])
    ahead2 = _wrap(r2[..., 7:] - r0[..., 7:])
    ref_vel = _quat_rotate_inv(head, ref_qd[..., :3])
    up = _quat_rotate_inv(r0[..., 3:7], np.broadcast_to(np.array([0.0, 0.0, 1.0]), r0.shape[:-1] + (3,)))
    return np.concatenate([hinge, hinge_vel, rot, pos, vel, ang, ahead1, ahead2, ref_vel, up,
                           np.asarray(contact, np.float64), prev], -1).astype(np.float32)


def deviation(q: np.ndarray, ref_q: np.ndarray, ref_start: np.ndarray) -> np.ndarray:
    """The state's deviation (..., nu + 6) from the reference at one frame, scaled
    (:data:`ANGLE_SCALE`, :data:`POSITION_SCALE`): hinge angles, root orientation (rotation
    vector in the reference root's frame), root position in the heading frame of the reference at
    the window's start ``ref_start`` (..., nq)."""
    head = _heading(ref_start[..., 3:7])
    hinge = _wrap(q[..., 7:] - ref_q[..., 7:]) / ANGLE_SCALE
    rot = _quat_log(_quat_mul(_quat_conj(ref_q[..., 3:7]), q[..., 3:7])) / ANGLE_SCALE
    pos = _quat_rotate_inv(head, q[..., :3] - ref_q[..., :3]) / POSITION_SCALE
    return np.concatenate([hinge, rot, pos], -1).astype(np.float32)


# ---------------------------------------------------------------------------------------
# the networks (flax) and the losses (pure JAX)
# ---------------------------------------------------------------------------------------


class _MLP(nn.Module):
    hidden: tuple[int, ...]
    out: int

    @nn.compact
    def __call__(self, x):
        for i, w in enumerate(self.hidden):
            x = nn.elu(nn.Dense(w, name=f"dense_{i}")(x))
        return nn.Dense(self.out, name="out", kernel_init=nn.initializers.zeros)(x)


class Encoder(nn.Module):
    """Features -> (mu, sigma) of the corrections (..., nu) in base-spread units. Zero-initialised
    output: an untrained encoder gives mu = 0 and sigma = 1 (the fixed Gaussian)."""

    nu: int
    hidden: tuple[int, ...] = HIDDEN

    @nn.compact
    def __call__(self, features):
        y = _MLP(self.hidden, 2 * self.nu, name="mlp")(features)
        mu, raw = y[..., :self.nu], y[..., self.nu:]
        lo, hi = np.log(SIGMA_MIN), np.log(SIGMA_MAX)
        # log sigma in (lo, hi), 0 (sigma 1) at raw 0
        c = -lo / (hi - lo)
        log_sigma = lo + (hi - lo) * jax.nn.sigmoid(raw + np.log(c / (1 - c)))
        return mu, jnp.exp(log_sigma)


class Decoder(nn.Module):
    """(features, correction) -> the simulated state's deviation from the reference
    (..., :func:`num_decoded`), scaled: the pose decoder of the two-branch training."""

    nu: int
    hidden: tuple[int, ...] = HIDDEN

    @nn.compact
    def __call__(self, features, correction):
        return _MLP(self.hidden, num_decoded(self.nu), name="mlp")(jnp.concatenate([features, correction], -1))


def init_prior_params(key: Array, nu: int) -> dict:
    """Fresh ``{"encoder": ..., "decoder": ...}`` variables for ``nu`` hinges."""
    f = jnp.zeros((1, num_features(nu)))
    ke, kd = jax.random.split(key)
    return {"encoder": Encoder(nu).init(ke, f)["params"],
            "decoder": Decoder(nu).init(kd, f, jnp.zeros((1, nu)))["params"]}


def nu_of(params: dict) -> int:
    """The hinge count the prior's variables were made for."""
    return int(params["encoder"]["mlp"]["out"]["bias"].shape[-1]) // 2


def encode(params: dict, features: Array) -> tuple[Array, Array]:
    """(mu, sigma) (..., nu) of the features (..., F)."""
    return Encoder(nu_of(params)).apply({"params": params["encoder"]}, features)


def decode(params: dict, features: Array, correction: Array) -> Array:
    return Decoder(nu_of(params)).apply({"params": params["decoder"]}, features, correction)


@jax.jit
def encode_jit(params: dict, features: Array) -> tuple[Array, Array]:
    return encode(params, features)


def kl_diag(mu_q: Array, sigma_q: Array, mu_p: Array, sigma_p: Array) -> Array:
    """KL(N(mu_q, sigma_q^2) || N(mu_p, sigma_p^2)) of diagonal Gaussians, summed over the last
    axis (Eq. 5)."""
    r = (sigma_q / sigma_p) ** 2
    return 0.5 * jnp.sum(r + ((mu_q - mu_p) / sigma_p) ** 2 - 1.0 - jnp.log(r), -1)


def pretrain_loss(params: dict, features: Array, mu_ce: Array, sigma_ce: Array, weight: Array) -> Array:
    """Eq. 5: the mean (over windows, weighted) KL of the encoder's distribution from the
    recorded cross-entropy ones."""
    mu, sigma = encode(params, features)
    kl = kl_diag(mu, sigma, mu_ce, sigma_ce)
    return jnp.sum(weight * kl) / jnp.maximum(jnp.sum(weight), 1.0)


def two_branch_loss(params: dict, features: Array, eps: Array, simulated: Array, mu_ce: Array, sigma_ce: Array,
                    weight: Array, *, kl_weight: float = 0.2, reg_weight: float = 1e-5) -> tuple[Array, dict]:
    """Eq. 6-9 for a batch of windows: ``eps`` (B, nu) the standard-normal draws that made the
    simulated corrections (``mu + sigma eps`` with the encoder's values at simulation time),
    ``simulated`` (B, num_decoded) the physical branch's deviations from the reference.

    The decoder learns the simulator at the simulated corrections (L_sim, its correction input
    held); the encoder learns through the decoder, whose weights L_rec does not move, to make the
    decoded deviation small (L_rec), with the KL term of the pre-training (``kl_weight``, the
    paper's lambda) and an L2 penalty on every weight (``reg_weight``, L_reg). L_sim and L_rec
    are means over the deviation's entries (the KL a sum over the hinges), so that the KL term
    is of their size and holds the encoder near the distributions the simulator confirmed."""
    mu, sigma = encode(params, features)
    corr = mu + sigma * eps
    sim_pred = decode(params, features, jax.lax.stop_gradient(corr))
    l_sim = jnp.mean((sim_pred - simulated) ** 2)
    held = {"encoder": params["encoder"], "decoder": jax.lax.stop_gradient(params["decoder"])}
    rec_pred = decode(held, features, corr)
    l_rec = jnp.mean(rec_pred**2)
    kl = jnp.sum(weight * kl_diag(mu, sigma, mu_ce, sigma_ce)) / jnp.maximum(jnp.sum(weight), 1.0)
    reg = sum(jnp.sum(x**2) for x in jax.tree.leaves(params))
    total = l_sim + l_rec + kl_weight * kl + reg_weight * reg
    return total, {"sim": l_sim, "rec": l_rec, "kl": kl, "reg": reg}


# ---------------------------------------------------------------------------------------
# the shipped prior
# ---------------------------------------------------------------------------------------


@functools.cache
def default_prior_params() -> dict:
    """The shipped prior (``jmocap/assets/mocon_prior.msgpack``, float16 on disk, float32 here),
    made by ``experiments/train_mocon_prior.py --ship``."""
    if not ASSET.exists():
        raise FileNotFoundError(f"no shipped mocon prior at {ASSET}; train it with "
                                f"experiments/train_mocon_prior.py --ship")
    return load_float32_params(ASSET)


def prior_params(params) -> dict:
    """The prior a run uses: ``params["mocon_prior"]`` where its parameters carry one, else the
    shipped one."""
    if isinstance(params, dict) and "mocon_prior" in params:
        return params["mocon_prior"]
    return default_prior_params()


__all__ = [
    "ASSET",
    "Decoder",
    "Encoder",
    "decode",
    "default_prior_params",
    "deviation",
    "encode",
    "encode_jit",
    "init_prior_params",
    "kl_diag",
    "num_decoded",
    "num_features",
    "nu_of",
    "pretrain_loss",
    "prior_params",
    "two_branch_loss",
    "window_features",
]
