"""Synthetic IMUs (jmocap.data.synthetic.imu) against references: hand-worked constant and
uniform circular motions, MuJoCo C's xmat and its own body accelerations (mj_rnePostConstraint /
mj_objectAcceleration) on smooth and on simulated motion, noise statistics, determinism, and
`jmocap data synth --imu` end to end."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from jmocap.cli import main
from jmocap.constants import GRAVITY
from jmocap.data.archive import Archive, read_manifest
from jmocap.data.imu import SENSOR_BODIES, IMUClip, load_imu_clip, readings_with_gaps, save_imu_clip
from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.data.synthetic.imu import (
    IMUCorruption,
    IMUSynthConfig,
    corrupt_imu,
    generate_imu_clip,
    imu_signals,
)
from jmocap.model import load_model


@pytest.fixture(scope="module")
def mj():
    return load_model().mj


def yaw_quat(psi):
    return np.stack([np.cos(psi / 2), 0 * psi, 0 * psi, np.sin(psi / 2)], -1)


def rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def random_rotations(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    out = np.zeros((n, 9))
    for i in range(n):
        mujoco.mju_quat2Mat(out[i], q[i])
    return out.reshape(n, 3, 3)


def test_constant_acceleration_is_exact(mj):
    """Root translating with constant acceleration a = (1.5, -0.5, 2) m/s^2, fixed orientation: the
    second difference is exact, every sensor (any offset, any mounting) reads R_WI^T a."""
    fps, T = 60.0, 12
    t = np.arange(T) / fps
    acc_w = np.array([1.5, -0.5, 2.0])
    q = np.zeros((T, mj.nq))
    q[:, :3] = np.array([0.2, 0.1, 1.0]) + 0.5 * t[:, None] ** 2 * acc_w
    q[:, 3:7] = yaw_quat(np.full(T, 0.3))
    rng = np.random.default_rng(0)
    R_BS, R_WI = random_rotations(rng, 6), rz(0.4)
    ori, acc = imu_signals(mj, q, fps, rng.uniform(-0.1, 0.1, (6, 3)), R_BS, R_WI)
    np.testing.assert_allclose(acc, np.broadcast_to(R_WI.T @ acc_w, (T, 6, 3)), atol=1e-9)
    # orientation: MuJoCo C's xmat of each body times the mounting, in I
    d = mujoco.MjData(mj)
    d.qpos[:] = q[5]
    mujoco.mj_kinematics(mj, d)
    for i, b in enumerate(SENSOR_BODIES):
        np.testing.assert_allclose(ori[5, i], R_WI.T @ d.xmat[mj.body(b).id].reshape(3, 3) @ R_BS[i], atol=1e-12)


def test_uniform_circular_motion(mj):
    """The pelvis turning at omega = 2 rad/s about the vertical through its origin: a sensor
    r = 0.1 m in front of it moves on a circle, centripetal acceleration omega^2 r = 0.4 m/s^2
    towards the axis (the central difference gives (2 - 2 cos(omega dt)) / dt^2 r, 0.4 * (1 -
    1e-4) at 60 fps); its orientation is Rz(omega t) R_BS."""
    fps, T, w, r = 60.0, 30, 2.0, 0.1
    psi = w * np.arange(T) / fps
    q = np.zeros((T, mj.nq))
    q[:, 2] = 1.0
    q[:, 3:7] = yaw_quat(psi)
    off = np.zeros((6, 3))
    off[5] = (r, 0.0, 0.0)  # the pelvis sensor
    R_BS = random_rotations(np.random.default_rng(1), 6)
    ori, acc = imu_signals(mj, q, fps, off, R_BS)
    dt = 1 / fps
    expect = -(2 - 2 * np.cos(w * dt)) / dt**2 * r * np.stack([np.cos(psi), np.sin(psi), 0 * psi], 1)
    np.testing.assert_allclose(acc[1:-1, 5], expect[1:-1], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(acc[1:-1, 5], axis=1), 0.4, rtol=2e-4)
    np.testing.assert_allclose(acc[0, 5], acc[1, 5])  # the ends copy their neighbour
    np.testing.assert_allclose(acc[-1, 5], acc[-2, 5])
    for t in (0, 7, 29):
        np.testing.assert_allclose(ori[t, 5], rz(psi[t]) @ R_BS[5], atol=1e-12)


def _mujoco_point_acc(mj, d, body, offset_w):
    """Classical acceleration (world, gravity removed) of a point fixed on ``body`` at world
    offset ``offset_w`` from its origin, from MuJoCo C (mj_rnePostConstraint has run)."""
    a6, v6 = np.zeros(6), np.zeros(6)
    mujoco.mj_objectAcceleration(mj, d, mujoco.mjtObj.mjOBJ_XBODY, body, a6, 0)
    mujoco.mj_objectVelocity(mj, d, mujoco.mjtObj.mjOBJ_XBODY, body, v6, 0)
    alpha, a0, om = a6[:3], a6[3:], v6[:3]
    return a0 + np.cross(alpha, offset_w) + np.cross(om, np.cross(om, offset_w)) - np.array([0, 0, GRAVITY])


def _set_state(mj, d, q, qd, qdd):
    d.qpos[:], d.qvel[:], d.qacc[:] = q, qd, qdd
    mujoco.mj_fwdPosition(mj, d)
    mujoco.mj_fwdVelocity(mj, d)
    d.qacc[:] = qdd
    mujoco.mj_rnePostConstraint(mj, d)


def test_smooth_motion_against_mujoco_body_acceleration(mj):
    """Every dof moving smoothly (analytic q, qd, qdd): the finite-difference accelerations of
    the six sensors (with offsets) match MuJoCo C's own (cacc, mj_objectAcceleration, plus the
    rigid-body terms for the offset) within the central difference's O(dt^2) error."""
    fps, T = 240.0, 61
    t = np.arange(T) / fps
    rng = np.random.default_rng(2)
    nh = mj.nq - 7
    amp, fr, ph = rng.uniform(0.1, 0.3, nh), rng.uniform(1.0, 3.0, nh), rng.uniform(0, 6, nh)
    q = np.zeros((T, mj.nq))
    qd = np.zeros((T, mj.nv))
    qdd = np.zeros((T, mj.nv))
    q[:, 0], qd[:, 0], qdd[:, 0] = 0.3 * np.sin(t), 0.3 * np.cos(t), -0.3 * np.sin(t)
    q[:, 1], qd[:, 1] = 0.8 * t, 0.8
    q[:, 2], qd[:, 2], qdd[:, 2] = 1 + 0.05 * np.sin(4 * t), 0.2 * np.cos(4 * t), -0.8 * np.sin(4 * t)
    psi = 0.6 * np.sin(2 * t)
    q[:, 3:7] = yaw_quat(psi)
    qd[:, 5], qdd[:, 5] = 1.2 * np.cos(2 * t), -2.4 * np.sin(2 * t)  # body-frame = world z rate (yaw only)
    arg = fr[None] * t[:, None] + ph[None]
    q[:, 7:] = amp * np.sin(arg)
    qd[:, 6:] = amp * fr * np.cos(arg)
    qdd[:, 6:] = -amp * fr**2 * np.sin(arg)
    off = rng.uniform(-0.05, 0.05, (6, 3))
    _, acc = imu_signals(mj, q, fps, off)
    d = mujoco.MjData(mj)
    errs = []
    for k in range(1, T - 1):
        _set_state(mj, d, q[k], qd[k], qdd[k])
        for i, b in enumerate(SENSOR_BODIES):
            bid = mj.body(b).id
            ref = _mujoco_point_acc(mj, d, bid, d.xmat[bid].reshape(3, 3) @ off[i])
            errs.append(np.linalg.norm(acc[k, i] - ref))
    # the central difference errs by dt^2/12 |p''''|: |p''''| is a few hundred m/s^4 here
    # (joint frequencies up to 3 rad/s, chains of ~1 m), i.e. ~1e-3 m/s^2 at 240 fps
    assert max(errs) < 5e-3, max(errs)


@pytest.fixture(scope="module")
def physics_clip():
    cfg = IMUSynthConfig(synth=SynthConfig(frames=60, fps=120.0, physics=True, kinds=("walk",)),
                         corruption=IMUCorruption.none())
    return generate_imu_clip(3, 0, cfg)


def test_simulated_clip_against_mujoco(mj, physics_clip):
    """On the physics variant, the sensors follow the *simulated* gt_q: orientation = MuJoCo C's
    xmat times the mounting, and acceleration = MuJoCo C's body acceleration at the simulated
    state (qacc from the simulation's velocities, central difference) within the finite
    difference's error."""
    clip = physics_clip
    assert clip.meta["physics_variant"] and clip.gt_grf is not None and clip.gt_tau is not None
    from jmocap.data.synthetic.character import character

    ch = character(clip.height_m)
    m = ch.mj
    d = mujoco.MjData(m)
    R, a = clip.calibrated()  # bones and accelerations in jmocap's world (acc_bias 0)
    R_S = clip.sensor_orientations()
    q, qd = clip.gt_q.astype(np.float64), clip.gt_qd.astype(np.float64)
    T = len(clip)
    ref = np.zeros((T, 6, 3))
    for k in range(1, T - 1):
        qdd = (qd[k + 1] - qd[k - 1]) * clip.fps / 2  # the simulation's qacc, averaged over 2 frames
        _set_state(m, d, q[k], qd[k], qdd)
        for i, b in enumerate(SENSOR_BODIES):
            bid = m.body(b).id
            xmat = d.xmat[bid].reshape(3, 3)
            np.testing.assert_allclose(R_S[k, i], xmat @ clip.bone_from_sensor[i], atol=2e-5)
            np.testing.assert_allclose(R[k, i], xmat, atol=2e-5)
            ref[k, i] = _mujoco_point_acc(m, d, bid, xmat @ clip.sensor_offset[i])
    # The second difference is a weighted average of the acceleration over [t - dt, t + dt], so
    # its error is bounded by how much the acceleration changes from frame to frame; with foot
    # impacts the lower legs reach ~50 m/s^2 and change by 5-30 m/s^2 per frame at 120 fps.
    # Measured: error median 0.4 m/s^2, max 5; frame-to-frame change median 3.4 m/s^2.
    err = np.linalg.norm(a - ref, axis=-1)[2:-2]
    var = np.maximum(np.linalg.norm(ref[3:-1] - ref[2:-2], axis=-1), np.linalg.norm(ref[1:-3] - ref[2:-2], axis=-1))
    assert np.linalg.norm(ref, axis=-1).max() > 20.0  # the clip moves (walking, impacts)
    assert np.all(err <= var + 0.05), (err - var).max()
    assert err.mean() < 0.25 * var.mean(), (err.mean(), var.mean())  # a frame shift or a lost lever arm fails


def test_noise_statistics():
    rng = np.random.default_rng(4)
    T, fps = 6000, 60.0
    ori = np.tile(np.eye(3), (T, 6, 1, 1)) @ random_rotations(rng, 6)
    acc = np.zeros((T, 6, 3))
    off = IMUCorruption.none()

    # white acceleration noise
    o, a, drop, _ = corrupt_imu(np.random.default_rng(0), ori, acc, fps, IMUCorruption(**{**off.__dict__, "acc_noise": 0.2}))
    assert not drop.any() and np.allclose(o, ori)
    assert abs(a.std() - 0.2) < 0.005 and abs(a.mean()) < 0.005
    # white orientation noise: rotation-vector components with std 0.5 deg
    o, a, _, _ = corrupt_imu(np.random.default_rng(0), ori, acc, fps, IMUCorruption(**{**off.__dict__, "ori_noise_deg": 0.5}))
    rel = np.swapaxes(ori, -1, -2) @ o
    w = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1) / 2
    assert abs(np.degrees(w.std()) - 0.5) < 0.02 and np.allclose(a, 0)
    # constant bias
    o, a, _, info = corrupt_imu(np.random.default_rng(0), ori, acc, fps, IMUCorruption(**{**off.__dict__, "acc_bias": 0.1}))
    np.testing.assert_allclose(a, np.broadcast_to(info["acc_bias_inertial"], a.shape))
    # heading drift: R_meas R^T = Rz(rate t), |rate| <= 3 deg/min; vertical acceleration untouched
    acc_z = np.zeros((T, 6, 3))
    acc_z[..., 2] = 1.0
    acc_z[..., 0] = 0.5
    o, a, _, info = corrupt_imu(np.random.default_rng(0), ori, acc_z, fps,
                                IMUCorruption(**{**off.__dict__, "drift_yaw_deg_per_min": 3.0}))
    rate = np.array(info["drift_yaw_deg_per_min"])
    assert np.all(np.abs(rate) <= 3.0) and np.all(np.abs(rate) > 0)
    tl = (T - 1) / fps / 60
    for s in range(6):
        np.testing.assert_allclose(o[-1, s] @ ori[-1, s].T, rz(np.radians(rate[s] * tl)), atol=1e-9)
    np.testing.assert_allclose(a[..., 2], 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(a[..., :2], axis=-1), 0.5, atol=1e-12)
    # tilt drift leaks gravity: |a| grows like g * angle
    o, a, _, info = corrupt_imu(np.random.default_rng(0), ori, acc, fps,
                                IMUCorruption(**{**off.__dict__, "drift_tilt_deg_per_min": 0.3}))
    ang = np.radians(np.array(info["drift_tilt_deg_per_min"]) * tl)
    np.testing.assert_allclose(np.linalg.norm(a[-1], axis=-1), GRAVITY * np.sqrt(2 - 2 * np.cos(ang)), rtol=1e-6)
    # dropouts: the share asked for, filled by the gap rule, never longer than max_gap
    o, a, drop, info = corrupt_imu(np.random.default_rng(0), ori, acc, fps,
                                   IMUCorruption(**{**off.__dict__, "drop_prob": 0.02, "drop_burst": 4.0}))
    assert 0.012 < drop.mean() < 0.028 and info["dropped_sensor_frames"] == drop.sum()
    o2, a2, filled, meta = readings_with_gaps(o, a, "t", "fill", 8)
    np.testing.assert_array_equal(filled, drop)
    assert max(b - s for runs in meta["gaps"].values() for s, b in runs) <= 8


def test_determinism_and_same_motion_as_the_video_clip(tmp_path):
    cfg = IMUSynthConfig(synth=SynthConfig(frames=30))
    a, b = generate_imu_clip(0, 1, cfg), generate_imu_clip(0, 1, cfg)
    assert save_imu_clip(tmp_path / "a.npz", a).read_bytes() == save_imu_clip(tmp_path / "b.npz", b).read_bytes()
    c = generate_imu_clip(1, 1, cfg)
    assert not np.array_equal(a.acc, c.acc)
    video = generate_clip(0, 1, cfg.synth)
    np.testing.assert_array_equal(a.gt_q, video.gt_q)
    np.testing.assert_array_equal(a.gt_keypoints3d, video.gt_keypoints3d)
    assert a.layout == "body25" and a.height_m == video.height_m and a.gt_contacts is not None
    back = load_imu_clip(tmp_path / "a.npz")
    assert isinstance(back, IMUClip) and back.meta["imu"]["bodies"] == list(SENSOR_BODIES)
    # placement drawn within the documented ranges
    assert np.all(np.abs(a.sensor_offset - _nominal(a)) <= 0.03 + 1e-12)


def _nominal(clip):
    from jmocap.data.synthetic.character import character
    from jmocap.data.synthetic.imu import nominal_offsets

    return nominal_offsets(character(clip.height_m).mj)


def test_cli_synth_imu_end_to_end(tmp_path, capsys):
    out = tmp_path / "imu"
    args = ["data", "synth", "--imu", "--out", str(out), "--clips", "2", "--frames-per-clip", "30", "--quiet"]
    assert main(args) == 0
    assert "2 clips written, 0 failed, 0 already there" in capsys.readouterr().out
    man = read_manifest(out)
    assert [e["name"] for e in man] == ["synth_000000", "synth_000001"]
    assert all(e["format"] == "jmocap-imu-clip-1" and e["imu"] and e["status"] == "ok" for e in man)
    with Archive(out) as arch:
        clips = list(arch.iter_clips(verify=True))
        assert arch.settings["generator"] == "jmocap.data.synthetic.imu"
    assert all(isinstance(c, IMUClip) and c.gt_q is not None and c.gt_contacts is not None for c in clips)
    ref = generate_imu_clip(0, 1, IMUSynthConfig(synth=SynthConfig(frames=30, corruption=_no_kp_corruption())))
    np.testing.assert_array_equal(clips[1].acc, ref.acc)
    # resume: nothing to do, then one more
    assert main(args) == 0
    assert "0 clips written, 0 failed, 2 already there" in capsys.readouterr().out
    assert main(args[:6] + ["3"] + args[7:]) == 0
    assert "1 clips written, 0 failed, 2 already there" in capsys.readouterr().out
    assert len(read_manifest(out)) == 3


def _no_kp_corruption():
    from jmocap.data.synthetic import Corruption

    return Corruption.none()


def test_cli_synth_imu_physics(tmp_path, capsys):
    out = tmp_path / "imu_phys"
    assert main(["data", "synth", "--imu", "--physics", "--out", str(out), "--clips", "2", "--frames-per-clip", "20",
                 "--quiet"]) == 0
    assert "2 clips written" in capsys.readouterr().out
    assert all(e["physics"] and e["imu"] for e in read_manifest(out))
    for clip in Archive(out):
        assert clip.gt_grf is not None and clip.gt_tau is not None and clip.meta["physics_variant"]


def test_reconstruct_sources_refuse_imu_clips(tmp_path):
    """An IMU archive given to `jmocap reconstruct` fails per clip with a clear error."""
    from jmocap.data.archive import ArchiveWriter
    from jmocap.data.sources import archive_sources

    clip = IMUClip(name="a", fps=60.0, ori=np.tile(np.eye(3), (4, 6, 1, 1)), acc=np.zeros((4, 6, 3)))
    with ArchiveWriter(tmp_path / "arch") as w:
        w.add(clip)
    with Archive(tmp_path / "arch") as arch:
        (src,) = archive_sources(arch, "arch")
        with pytest.raises(ValueError, match=r"arch:a.npz: an IMU clip \(jmocap-imu-clip-1\)"):
            src.load()
