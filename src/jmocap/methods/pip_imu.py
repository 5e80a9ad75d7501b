"""``pip`` on six IMUs: Physical Inertial Poser (Yi et al. 2022), its kinematics module driving
the physics of the video ``pip`` method.

1. **Kinematics module** (PIP Sec. 3.1, :mod:`jmocap.nets_imu`): the cascade of recurrent
   networks reads the calibrated sensors frame by frame and gives the hinge angles, the root
   frame's body positions, every body's velocity and the four contact probabilities; the root
   orientation is the pelvis sensor's. Its initial state is the learned one of the clip's known
   first pose (PIP: the calibration pose; :attr:`IMUInputs.has_first`), else zero.
2. **Kinematic estimate**: the pose with the root translated by the integral of the estimated
   root velocity from the first pose's root (PIP's kinematics-only variant).
3. **Physics** (PIP Sec. 3.2): that estimate and the contact probabilities are the reference of
   the video method's dual PD controller and motion-tracking QP
   (:func:`jmocap.methods.pip.reference`, :func:`jmocap.methods.pip.simulate`, the same
   functions and :class:`~jmocap.methods.pip.PIPConfig`): the body moves by gravity, the
   contact forces in their friction pyramids and a penalised residual root wrench, and gives
   joint torques and ground reaction forces. The root's horizontal anchor and velocity targets
   come from the integrated estimate (PIP tracks the estimated root velocity); its height from
   gravity and the contacts.

Online with a fixed latency: frame t depends on frames <= t + ``pip.smoothing_radius`` (6
frames, 0.2 s at 30 fps, by default: :func:`lookahead`): the reference poses are smoothed by the
video method's centred Gaussian (:func:`jmocap.methods.pip.smooth_poses`, sigma 3 frames)
before they are tracked, which on the validation archive took the net GRF error from 48 to 28
% BW and the residual from 7.3 to 5.2 % BW at 0.7 mm less joint error (docs/method.md);
``smoothing_radius=0`` is PIP's causal setting (latency 0: the networks, the reference's
backward differences and the root-velocity filter are causal, and the physics steps forward in
time). Pure functions of arrays with static shapes: ``jax.jit`` and ``jax.vmap`` over clips
apply. The paper's ablations: :func:`single_pd` (no position PD: rotations only, plus the root's
anchor) and :func:`zero_init` (every network from the zero state).
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap import nets_imu as N
from jmocap import physics as P
from jmocap.methods import pip as PIP
from jmocap.methods.base import static
from jmocap.model import Model
from jmocap.motion import Motion

Array = jnp.ndarray

#: the shipped kinematics-module weights and their network config
ASSET = Path(__file__).resolve().parents[1] / "assets" / "imu_kinematics.msgpack"
ASSET_CONFIG = ASSET.with_suffix(".json")


@struct.dataclass
class IMUInputs:
    """One IMU clip as the method reads it (leading axis T: frames, padded to a fixed length)."""

    ori: Array  # (T, 6, 3, 3) calibrated bone orientations in jmocap's world, pelvis last
    acc: Array  # (T, 6, 3) free accelerations in jmocap's world (m/s^2)
    mask: Array  # (T,) bool: real frames (padding repeats the last real frame)
    fps: Array  # ()
    first_q: Array  # (nq,) the known first pose (PIP: the calibration pose); any value when not has_first
    has_first: Array  # () bool: first_q is known (learned initial state), else the zero state

    @classmethod
    def from_clip(cls, clip, model: Model, length: int | None = None, *, first_pose: bool = True) -> IMUInputs:
        """From an :class:`jmocap.data.imu.IMUClip` (calibrated with its own calibration) for
        the character ``model``, edge-padded to ``length`` frames. ``first_pose``: take the
        clip's first ground-truth pose as the known first pose (PIP's evaluation does; a clip
        without ``gt_q`` then starts from the zero state)."""
        ori, acc = clip.calibrated()
        T = clip.num_frames
        n = T if length is None else int(length)
        if n < T:
            raise ValueError(f"{clip.name}: {T} frames do not fit in length {n}")
        idx = np.concatenate([np.arange(T), np.full(n - T, T - 1)])
        has = bool(first_pose and clip.gt_q is not None)
        if has and clip.gt_q.shape[1] != model.nq:
            raise ValueError(f"{clip.name}: gt_q has {clip.gt_q.shape[1]} coordinates, the character {model.nq}")
        # unknown: the rest pose (identity root quaternion), unused but a valid configuration
        first = np.asarray(clip.gt_q[0], np.float32) if has else np.eye(1, model.nq, 3, dtype=np.float32)[0]
        return cls(jnp.asarray(ori[idx], jnp.float32), jnp.asarray(acc[idx], jnp.float32),
                   jnp.asarray(np.arange(n) < T), jnp.asarray(clip.fps, jnp.float32), jnp.asarray(first),
                   jnp.asarray(has))


@struct.dataclass
class PIPIMUConfig:
    """The kinematics module's network (static) and the physics (:class:`PIPConfig`'s traced
    gains and weights; its video-only fields are unused). ``physics=False``: the kinematic
    estimate only (PIP's kinematics-only rows)."""

    net: N.IMUNetConfig = static(N.IMUNetConfig())
    pip: PIP.PIPConfig = PIP.PIPConfig(smoothing_radius=6, smoothing_sigma=3.0, reference_source="tpnet",
                                       contact_source="tpnet", contact_threshold=0.5, w_slip=2.0)
    physics: bool = static(True)


def lookahead(config: PIPIMUConfig) -> int:
    """Frames after a frame that its output depends on (the method's latency)."""
    return int(config.pip.smoothing_radius) if config.physics else 0


def single_pd(config: PIPIMUConfig) -> PIPIMUConfig:
    """The paper's ablation: a single PD controller on the rotations (no body-position PD)."""
    return config.replace(pip=config.pip.replace(kp_pos=0.0, kd_pos=0.0))


def zero_init(inputs: IMUInputs) -> IMUInputs:
    """The paper's ablation of the learned initialisation: every network from the zero state."""
    return inputs.replace(has_first=jnp.zeros_like(inputs.has_first))


@struct.dataclass
class Kinematics:
    q: Array  # (T, nq) the kinematic estimate (root translated by the integrated velocity)
    prob: Array  # (T, 4) contact probabilities (L heel, L toe, R heel, R toe)
    out: N.Outputs  # the networks' raw outputs


def kinematics(params, model: Model, inputs: IMUInputs, config: PIPIMUConfig = PIPIMUConfig()) -> Kinematics:  # noqa: B008
    """The kinematics module over the clip and the kinematic estimate (steps 1-2 of the module doc)."""
    x = N.imu_features(inputs.ori, inputs.acc, config.net.acc_scale)
    kin0 = P.forward_kinematics(model, inputs.first_q)
    ids = N.body_indices(model)
    R0, root0 = kin0.xmat[ids["root"]], kin0.xpos[ids["root"]]
    leaf0 = (kin0.xpos[ids["leaf"]] - root0) @ R0  # R0^T (x - root), row-wise
    learned = N.initial_state(params, model, config.net, leaf0)
    zero = N.zero_state(config.net, (), x.dtype)
    carry = jax.tree.map(lambda a, b: jnp.where(inputs.has_first, a, b), learned, zero)
    _, out = N.run(params, model, config.net, carry, x)
    R_root = inputs.ori[:, 5]
    start = jnp.where(inputs.has_first, inputs.first_q[:3], jnp.zeros(3, x.dtype))
    q = N.pose(model, out, R_root, N.integrate_root(out, R_root, inputs.fps, start))
    # padded frames repeat the last real frame's estimate
    last = jnp.max(jnp.where(inputs.mask, jnp.arange(q.shape[0]), 0))
    keep = inputs.mask[:, None]
    q = jnp.where(keep, q, q[last])
    prob = jnp.where(keep, N.contact_probability(out), 0.0)
    return Kinematics(q, prob, out)


def reconstruct(params, model: Model, inputs: IMUInputs, config: PIPIMUConfig = PIPIMUConfig()) -> Motion:  # noqa: B008
    """Six IMUs of one clip -> :class:`Motion` (the module doc). With ``config.physics`` False
    the motion is the kinematic estimate (no forces: ``tau`` and ``grf`` zero)."""
    k = kinematics(params, model, inputs, config)
    mask = jnp.asarray(inputs.mask)
    if not config.physics:
        qd = P.finite_difference_velocity(model, k.q, inputs.fps)
        T = k.q.shape[0]
        return Motion(k.q, qd, jnp.zeros((T, model.nv), k.q.dtype), jnp.zeros((T, 4, 3), k.q.dtype), k.prob, k.q,
                      mask)
    q_ref = PIP.smooth_poses(k.q, mask, config.pip.smoothing_radius, config.pip.smoothing_sigma)
    ref = PIP.reference(model, q_ref, k.prob, inputs.fps, config.pip.velocity_smoothing_s)
    _, out = PIP.simulate(model, ref, mask, inputs.fps, config.pip)
    return PIP.to_motion(out, ref, mask)


def load_params(path=ASSET, config_path=None) -> tuple[dict, N.IMUNetConfig]:
    """Kinematics-module weights and their network config (``path`` with ``.json`` beside it:
    the shipped ones by default; a training run's ``params.msgpack`` and ``config.json``)."""
    import json

    from flax import serialization

    path = Path(path)
    cfg_path = Path(config_path) if config_path else (path.with_suffix(".json") if path == ASSET
                                                       else path.with_name("config.json"))
    if not path.exists():
        raise FileNotFoundError(f"no IMU kinematics weights at {path}")
    meta = json.loads(cfg_path.read_text())
    net = meta.get("net", meta)
    fields = {k: v for k, v in net.items() if k in N.IMUNetConfig.__dataclass_fields__}
    raw = serialization.msgpack_restore(path.read_bytes())  # float16 or float32 on disk
    return jax.tree.map(lambda x: np.asarray(x, np.float32), raw), N.IMUNetConfig(**fields)


__all__ = ["IMUInputs", "Kinematics", "PIPIMUConfig", "kinematics", "load_params", "lookahead", "reconstruct",
           "single_pd", "zero_init"]
