"""Synthetic IMUs with ground truth: six virtual sensors rigidly attached to the character.

:func:`imu_signals` is the sensor model on any motion ``q`` of a MuJoCo model: a sensor on body
``b`` (:data:`~jmocap.data.imu.SENSOR_BODIES`) at ``offset`` in the body's frame and mounted
with rotation ``R_BS`` has

* orientation ``R_WS = R_WB R_BS`` (``R_WB`` MuJoCo C's ``xmat`` of the body, ``mj_kinematics``);
* acceleration: the second central difference of its world position
  ``p = xpos + R_WB offset``: ``a[t] = (p[t+1] - 2 p[t] + p[t-1]) fps^2``; the first and last
  frames, which have no neighbour on one side, take the value of the frame next to them
  (``a[0] = a[1]``, ``a[T-1] = a[T-2]``: the second difference of their three nearest frames);
* both expressed in the sensors' world ``I``, ``R_IS = R_WI^T R_WS`` and ``a_I = R_WI^T a``: a
  free acceleration (gravity removed, as DIP-IMU / TotalCapture / TransPose's synthetic data
  and Xsens' "free acceleration" are) in the global frame, as PIP / TransPose take it.

:func:`generate_imu_clip` runs it on a synthetic clip's ground-truth motion (``gt_q``: the
simulated one with ``physics=True``) with a random mounting (:class:`SensorPlacement`) and
realistic corruption (:class:`IMUCorruption`), and keeps the clip's ground truth. Its random
stream is ``numpy.random.default_rng([seed, index, IMU_STREAM])``, separate from the motion's
(``[seed, index, attempt]``), so the IMU clip of ``(seed, index)`` moves exactly as the video
clip of ``(seed, index)`` made with the same :class:`~jmocap.data.synthetic.clips.SynthConfig`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import mujoco
import numpy as np

from jmocap.constants import GRAVITY
from jmocap.data.imu import (
    DEFAULT_MAX_GAP,
    NUM_SENSORS,
    SENSOR_BODIES,
    SENSORS,
    IMUClip,
    readings_with_gaps,
)
from jmocap.data.synthetic.clips import (
    SynthConfig,
    _jsonable,
    clip_name,
    generate_clip_and_character,
)
from jmocap.data.synthetic.errors import GenerationError
from jmocap.data.synthetic.rotations import _exp_rot, _rz

IMU_GENERATOR = "jmocap.data.synthetic.imu/1"
#: third entry of the IMU random stream's seed sequence ("IMU" in ASCII)
IMU_STREAM = 0x494D55


@dataclass(frozen=True)
class SensorPlacement:
    """Where the virtual sensors sit (all drawn per clip and recorded in the clip).

    Nominal spot in the body's frame: forearm and lower leg halfway to the next joint (wrist,
    ankle), head halfway up to the top of the head, pelvis at the pelvis origin; plus a uniform
    offset in ``[-offset_m, offset_m]`` per axis. Mounting ``R_BS``: axis uniform on the sphere,
    angle uniform in ``[0, mount_max_deg]``. Sensor world ``I``: jmocap's world turned about the
    vertical by a yaw uniform in ``[-inertial_yaw_deg, inertial_yaw_deg]`` (an IMU's heading
    reference is magnetic north or its start-up heading, not the scene's), ``R_WI = Rz(yaw)``."""

    offset_m: float = 0.03
    mount_max_deg: float = 180.0
    inertial_yaw_deg: float = 180.0


@dataclass(frozen=True)
class IMUCorruption:
    """Sensor errors added to the exact signals (:meth:`none` turns every one off).

    ============================  =======  =================================================
    parameter                     default  effect
    ============================  =======  =================================================
    ``acc_noise``                 0.1      white noise on each acceleration axis, std (m/s^2)
    ``acc_bias``                  0.1      constant per-sensor bias, each axis ~ N(0, std^2), in I
    ``ori_noise_deg``             0.5      white rotation noise, rotation vector per axis ~
                                           N(0, std^2) in the sensor frame (degrees)
    ``drift_yaw_deg_per_min``     3.0      heading drift about the vertical, rate uniform in
                                           +-this per sensor (degrees per minute)
    ``drift_tilt_deg_per_min``    0.3      tilt drift about a random horizontal axis, rate uniform
                                           in [0, this] (degrees per minute)
    ``drop_prob``                 0.002    share of sensor frames dropped (bursts)
    ``drop_burst``                4.0      mean dropout length (frames; geometric, at most
                                           ``max_gap``), filled by the gap rule
    ``max_gap``                   8        longest dropout (:data:`~jmocap.data.imu.DEFAULT_MAX_GAP`)
    ============================  =======  =================================================

    The drift ``D(t)`` rotates the sensor's idea of its world: orientation ``D R_IS``, and the
    free acceleration it computes from the specific force with that orientation,
    ``D a_I + g (D z - z)`` (a tilt leaks gravity, a heading drift does not). Then
    ``R = D R_IS exp(n)``, ``a = D a_I + g (D z - z) + bias + w``."""

    acc_noise: float = 0.1
    acc_bias: float = 0.1
    ori_noise_deg: float = 0.5
    drift_yaw_deg_per_min: float = 3.0
    drift_tilt_deg_per_min: float = 0.3
    drop_prob: float = 0.002
    drop_burst: float = 4.0
    max_gap: int = DEFAULT_MAX_GAP

    @staticmethod
    def none() -> IMUCorruption:
        return IMUCorruption(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0, DEFAULT_MAX_GAP)


@dataclass(frozen=True)
class IMUSynthConfig:
    """What :func:`generate_imu_clip` makes: the motion (``synth``, whose camera and keypoint
    corruption are not used), the sensor placement and the corruption."""

    synth: SynthConfig = field(default_factory=SynthConfig)
    placement: SensorPlacement = field(default_factory=SensorPlacement)
    corruption: IMUCorruption = field(default_factory=IMUCorruption)

    def to_json(self) -> dict:
        return {"synth": self.synth.to_json(), "placement": _jsonable(dataclasses.asdict(self.placement)),
                "corruption": _jsonable(dataclasses.asdict(self.corruption))}


def nominal_offsets(mj: mujoco.MjModel) -> np.ndarray:
    """The nominal sensor spots (6, 3) in their bodies' frames (see :class:`SensorPlacement`)."""
    child = {"left_elbow": "left_wrist", "right_elbow": "right_wrist", "left_knee": "left_ankle",
             "right_knee": "right_ankle"}
    out = np.zeros((NUM_SENSORS, 3))
    for i, b in enumerate(SENSOR_BODIES):
        if b in child:
            out[i] = 0.5 * mj.body_pos[mj.body(child[b]).id]
        elif b == "head":
            out[i] = 0.5 * mj.site_pos[mj.site("kp_head_top").id]
    return out


def imu_signals(mj: mujoco.MjModel, q: np.ndarray, fps: float, offsets: np.ndarray | None = None,
                bone_from_sensor: np.ndarray | None = None, world_from_inertial: np.ndarray | None = None,
                bodies=SENSOR_BODIES) -> tuple[np.ndarray, np.ndarray]:
    """Exact sensor readings ``(R_IS (T, n, 3, 3), a_I (T, n, 3))`` of a motion ``q`` (T, nq),
    T >= 3, for sensors on ``bodies`` at ``offsets`` (n, 3) in the bodies' frames, mounted with
    ``bone_from_sensor`` (n, 3, 3), in the sensor world ``world_from_inertial`` (defaults: zero
    offsets, identity mountings, ``I = W``). See the module docstring for the model."""
    q = np.asarray(q, np.float64)
    T = len(q)
    if T < 3:
        raise ValueError(f"imu_signals needs at least 3 frames for a second difference, got {T}")
    ids = [mj.body(b).id for b in bodies]
    n = len(ids)
    offsets = np.zeros((n, 3)) if offsets is None else np.asarray(offsets, np.float64)
    R_BS = np.tile(np.eye(3), (n, 1, 1)) if bone_from_sensor is None else np.asarray(bone_from_sensor)
    R_WI = np.eye(3) if world_from_inertial is None else np.asarray(world_from_inertial, np.float64)
    d = mujoco.MjData(mj)
    R_WB = np.empty((T, n, 3, 3))
    x = np.empty((T, n, 3))
    for t in range(T):
        d.qpos[:] = q[t]
        mujoco.mj_kinematics(mj, d)
        R_WB[t] = d.xmat[ids].reshape(n, 3, 3)
        x[t] = d.xpos[ids]
    p = x + np.einsum("tnij,nj->tni", R_WB, offsets)
    a = np.empty_like(p)
    a[1:-1] = (p[2:] - 2.0 * p[1:-1] + p[:-2]) * fps * fps
    a[0], a[-1] = a[1], a[-2]
    return R_WI.T @ R_WB @ R_BS, a @ R_WI


def _random_rotation(rng, max_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return _exp_rot(axis * np.radians(rng.uniform(0.0, max_deg)))


def _dropouts(rng, T: int, prob: float, burst: float, max_gap: int) -> np.ndarray:
    """(T, 6) mask of dropped sensor frames: bursts start with probability ``prob / burst`` per
    frame and last a geometric number of frames of mean ``burst`` (at most ``max_gap``); the
    first and last frames are never dropped (so every gap is interior), nothing when T < 3."""
    m = np.zeros((T, NUM_SENSORS), bool)
    if prob <= 0 or T < 3:
        return m
    starts = rng.random((T, NUM_SENSORS)) < prob / max(burst, 1.0)
    lengths = np.minimum(rng.geometric(1.0 / max(burst, 1.0), size=(T, NUM_SENSORS)), max_gap)
    for t, s in zip(*np.nonzero(starts), strict=True):
        m[t:t + lengths[t, s], s] = True
    m[0] = m[-1] = False
    return m


def corrupt_imu(rng, ori: np.ndarray, acc: np.ndarray, fps: float, c: IMUCorruption):
    """Apply :class:`IMUCorruption` to exact readings ``(R_IS, a_I)``; returns ``(ori, acc, drop
    mask, info)`` with the dropped frames NaN (for the gap rule) and the drawn parameters."""
    T = len(ori)
    n = ori.shape[1]
    tmin = np.arange(T) / fps / 60.0  # minutes
    yaw_rate = rng.uniform(-1, 1, n) * c.drift_yaw_deg_per_min
    tilt_rate = rng.uniform(0, 1, n) * c.drift_tilt_deg_per_min
    tilt_dir = rng.uniform(0, 2 * np.pi, n)
    tilt_axis = np.stack([np.cos(tilt_dir), np.sin(tilt_dir), np.zeros(n)], 1)
    D = _rz(np.radians(yaw_rate[None] * tmin[:, None])) @ _exp_rot(
        tilt_axis[None] * np.radians(tilt_rate[None] * tmin[:, None])[..., None])  # (T, n, 3, 3)
    noise = _exp_rot(rng.normal(scale=np.radians(c.ori_noise_deg), size=(T, n, 3)))
    ori = D @ ori @ noise
    z = np.array([0.0, 0.0, 1.0])
    bias = rng.normal(scale=c.acc_bias, size=(n, 3))
    acc = (np.einsum("tnij,tnj->tni", D, acc) + GRAVITY * (D[..., :, 2] - z) + bias
           + rng.normal(scale=c.acc_noise, size=(T, n, 3)))
    drop = _dropouts(rng, T, c.drop_prob, c.drop_burst, c.max_gap)
    ori[drop] = np.nan
    acc[drop] = np.nan
    info = {"acc_bias_inertial": bias.tolist(), "drift_yaw_deg_per_min": yaw_rate.tolist(),
            "drift_tilt_deg_per_min": tilt_rate.tolist(), "drift_tilt_axis": tilt_axis.tolist(),
            "dropped_sensor_frames": int(drop.sum())}
    return ori, acc, drop, info


def generate_imu_clip(seed: int, index: int = 0, config: IMUSynthConfig = IMUSynthConfig(),
                      name: str | None = None) -> IMUClip:
    """One synthetic IMU clip, deterministic in ``(seed, index, config)``: the motion of
    :func:`~jmocap.data.synthetic.generate_clip` (same seed, index and ``config.synth``), six
    sensors on it (:func:`imu_signals`) with a drawn placement, corrupted, and the clip's
    ground truth (``gt_q`` ... and, with ``physics``, the forces). The calibration fields hold
    the true world alignment and mountings (what a perfect T-pose calibration gives; the true
    accelerometer bias is in ``meta["imu"]``, not subtracted)."""
    clip, ch = generate_clip_and_character(seed, index, config.synth, name)
    if clip.num_frames < 3:
        raise GenerationError(f"clip {index}: an IMU clip needs at least 3 frames, got {clip.num_frames}")
    rng = np.random.default_rng([int(seed), int(index), IMU_STREAM])
    pl = config.placement
    offsets = nominal_offsets(ch.mj) + rng.uniform(-pl.offset_m, pl.offset_m, size=(NUM_SENSORS, 3))
    R_BS = np.stack([_random_rotation(rng, pl.mount_max_deg) for _ in range(NUM_SENSORS)])
    yaw = float(np.radians(rng.uniform(-pl.inertial_yaw_deg, pl.inertial_yaw_deg)))
    R_WI = _rz(yaw)
    ori, acc = imu_signals(ch.mj, clip.gt_q.astype(np.float64), clip.fps, offsets, R_BS, R_WI)
    ori, acc, _drop, info = corrupt_imu(rng, ori, acc, clip.fps, config.corruption)
    ori, acc, filled, gap_meta = readings_with_gaps(ori, acc, f"clip {clip.name!r}", "fill",
                                                    config.corruption.max_gap)
    meta = dict(clip.meta)
    for k in ("camera", "corruption", "corruption_stats", "clean_keypoints2d"):
        meta.pop(k, None)
    meta.update(imu_generator=IMU_GENERATOR, imu={
        "sensors": list(SENSORS), "bodies": list(SENSOR_BODIES), "inertial_yaw_rad": yaw,
        "placement": _jsonable(dataclasses.asdict(pl)),
        "corruption": _jsonable(dataclasses.asdict(config.corruption)), **info,
        "acc_bias_world": (np.asarray(info["acc_bias_inertial"]) @ R_WI.T).tolist(),
        "acceleration": "second central difference of the sensor position, ends copy their neighbour",
    }, **gap_meta)
    return IMUClip(
        name=clip.name, fps=clip.fps, ori=ori, acc=acc, world_from_inertial=R_WI, bone_from_sensor=R_BS,
        sensor_offset=offsets, filled=filled, layout=clip.layout, gt_q=clip.gt_q, gt_qd=clip.gt_qd,
        gt_keypoints3d=clip.gt_keypoints3d, gt_contacts=clip.gt_contacts, gt_tau=clip.gt_tau, gt_grf=clip.gt_grf,
        gt_residual=clip.gt_residual, gt_foot_force=clip.gt_foot_force, gt_cop=clip.gt_cop,
        gt_free_moment=clip.gt_free_moment, height_m=clip.height_m, mass_kg=clip.mass_kg, meta=meta,
    )


__all__ = [
    "IMU_GENERATOR",
    "IMU_STREAM",
    "IMUCorruption",
    "IMUSynthConfig",
    "SensorPlacement",
    "clip_name",
    "corrupt_imu",
    "generate_imu_clip",
    "imu_signals",
    "nominal_offsets",
]
