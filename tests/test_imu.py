"""IMU clips (jmocap.data.imu) and the IMU dataset readers (jmocap.data.formats.imu_datasets):
schema, round trips, calibration against known offsets, the gap rule, every error, and
pickles that must not run."""

from __future__ import annotations

import json
import os
import pickle
import struct

import mujoco
import numpy as np
import pytest

from jmocap.data.clip import ClipFormatError, FormatError
from jmocap.data.formats import load_pickle_file, read_dip_imu, read_imu, read_totalcapture_dip
from jmocap.data.formats.imu_datasets import DIP_IMU_MASK, TOTALCAPTURE_DIP_MASK
from jmocap.data.imu import (
    DEFAULT_MAX_GAP,
    FORMAT,
    ORTHO_TOL,
    SENSORS,
    SMPL_TO_JMOCAP,
    IMUClip,
    IMUClipFormatError,
    calibrate_tpose,
    fill_gaps,
    imu_clip_to_arrays,
    load_imu_clip,
    matrix_to_quat,
    quat_to_matrix,
    read_imu_json,
    readings_with_gaps,
    rotation_z,
    save_imu_clip,
    tpose_bone_orientations,
    write_imu_json,
)
from jmocap.io import atomic_write_npz


def random_rotations(rng, shape):
    q = rng.normal(size=shape + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_to_matrix(q)


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def make_clip(T=20, seed=0, **kw):
    rng = np.random.default_rng(seed)
    return IMUClip(name="c", fps=60.0, ori=random_rotations(rng, (T, 6)), acc=rng.normal(size=(T, 6, 3)), **kw)


# --- rotations ---------------------------------------------------------------------------------


def test_quaternion_conversions_match_mujoco():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for qi in q:
        ref = np.zeros(9)
        mujoco.mju_quat2Mat(ref, qi)
        np.testing.assert_allclose(quat_to_matrix(qi), ref.reshape(3, 3), atol=1e-12)
        back = matrix_to_quat(ref.reshape(3, 3))
        ref_q = np.zeros(4)
        mujoco.mju_mat2Quat(ref_q, ref)
        ref_q *= np.sign(ref_q[0])
        np.testing.assert_allclose(back, ref_q, atol=1e-9)


def test_quaternion_input_equals_matrices():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(5, 6, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    a = IMUClip(name="q", fps=60, ori=q, acc=np.zeros((5, 6, 3)))
    np.testing.assert_allclose(a.ori, quat_to_matrix(q), atol=1e-6)
    with pytest.raises(IMUClipFormatError, match=r"sensor 'left_lower_leg' has a quaternion of norm 1.1 at frame 3"):
        q2 = q.copy()
        q2[3, 2] *= 1.1
        IMUClip(name="q", fps=60, ori=q2, acc=np.zeros((5, 6, 3)))


# --- the clip ---------------------------------------------------------------------------------


def test_calibrated_hand_worked():
    """R_WI = Rz(90 deg), R_IS = I, R_BS = Rx(90 deg): the bone is Rz(90) Rx(-90); an
    acceleration (1, 0, 0) in I is (0, 1, 0) in W, less the bias."""
    T = 3
    bias = np.zeros((6, 3))
    bias[4] = (0.0, 0.5, 0.0)
    clip = IMUClip(name="h", fps=100.0, ori=np.tile(np.eye(3), (T, 6, 1, 1)),
                   acc=np.tile([1.0, 0.0, 0.0], (T, 6, 1)), world_from_inertial=rotation_z(np.pi / 2),
                   bone_from_sensor=np.tile(rot_x(np.pi / 2), (6, 1, 1)), acc_bias=bias)
    R, a = clip.calibrated()
    expect = np.array([[0.0, 0, -1], [1, 0, 0], [0, -1, 0]])  # Rz(90) Rx(-90), worked by hand
    np.testing.assert_allclose(R[1, 3], expect, atol=1e-6)
    np.testing.assert_allclose(a[0, 0], [0.0, 1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(a[2, 4], [0.0, 0.5, 0.0], atol=1e-6)
    assert R.shape == (T, 6, 3, 3) and a.shape == (T, 6, 3)
    np.testing.assert_allclose(clip.sensor_orientations()[0, 0], rotation_z(np.pi / 2), atol=1e-6)


def test_npz_round_trip_and_determinism(tmp_path):
    rng = np.random.default_rng(3)
    T = 12
    clip = make_clip(T, layout="body25", gt_q=rng.normal(size=(T, 48)), gt_qd=rng.normal(size=(T, 47)),
                     gt_keypoints3d=rng.normal(size=(T, 25, 3)), gt_contacts=np.ones((T, 4)),
                     gt_grf=rng.normal(size=(T, 4, 3)), sensor_offset=rng.normal(size=(6, 3)) * 0.01,
                     filled=np.zeros((T, 6), bool), world_from_inertial=rotation_z(0.3),
                     bone_from_sensor=random_rotations(rng, (6,)), acc_bias=rng.normal(size=(6, 3)),
                     gt_smpl_pose=rng.normal(size=(T, 72)), height_m=1.7, mass_kg=64.0, meta={"k": [1, 2]})
    p1, p2 = save_imu_clip(tmp_path / "a.npz", clip), save_imu_clip(tmp_path / "b.npz", clip)
    assert p1.read_bytes() == p2.read_bytes()
    back = load_imu_clip(p1)
    for k in ("ori", "acc", "world_from_inertial", "bone_from_sensor", "acc_bias", "sensor_offset", "filled",
              "gt_q", "gt_qd", "gt_keypoints3d", "gt_contacts", "gt_grf", "gt_smpl_pose"):
        np.testing.assert_array_equal(getattr(back, k), getattr(clip, k), err_msg=k)
    assert back.fps == 60.0 and back.layout == "body25" and back.meta == {"k": [1, 2]} and back.height_m == 1.7
    assert back.gt_smpl_pose.shape == (T, 24, 3)
    with np.load(p1) as z:
        assert str(z["format"]) == FORMAT and z["sensors"].tolist() == list(SENSORS)
    sl = back.slice(2, 5)
    assert len(sl) == 3 and sl.gt_q.shape == (3, 48) and sl.filled.shape == (3, 6)


def test_npz_sensor_order_is_read_from_the_file(tmp_path):
    clip = make_clip(4)
    arr = imu_clip_to_arrays(clip)
    perm = [5, 4, 3, 2, 1, 0]
    arr["sensors"] = np.array([SENSORS[i] for i in perm])
    arr["ori"], arr["acc"] = clip.ori[:, perm], clip.acc[:, perm]
    arr["bone_from_sensor"] = clip.bone_from_sensor[perm]
    atomic_write_npz(tmp_path / "p.npz", arr)
    back = load_imu_clip(tmp_path / "p.npz")
    np.testing.assert_array_equal(back.ori, clip.ori)
    arr["sensors"] = np.array(["left_forearm", "right_forearm", "left_lower_leg", "right_lower_leg", "neck", "pelvis"])
    atomic_write_npz(tmp_path / "m.npz", arr)
    with pytest.raises(IMUClipFormatError, match=r"m.npz: field 'sensors': missing sensor\(s\) \['head'\]; "
                                                 r"unknown sensor\(s\) \['neck'\]"):
        load_imu_clip(tmp_path / "m.npz")
    arr["sensors"] = np.array(SENSORS[:5])
    atomic_write_npz(tmp_path / "f.npz", arr)
    with pytest.raises(IMUClipFormatError, match=r"missing sensor\(s\) \['pelvis'\]"):
        load_imu_clip(tmp_path / "f.npz")


def test_construction_errors():
    T = 6
    rng = np.random.default_rng(4)
    ori = random_rotations(rng, (T, 6))
    acc = np.zeros((T, 6, 3))

    def bad(match, **kw):
        args = dict(name="e", fps=60.0, ori=ori, acc=acc) | kw
        with pytest.raises(IMUClipFormatError, match=match) as e:
            IMUClip(**args)
        assert isinstance(e.value, ClipFormatError) and isinstance(e.value, FormatError)

    o = ori.copy()
    o[4, 1] *= 1.01  # scaled: |R R^T - I| = 0.02 > ORTHO_TOL
    bad(rf"IMU clip 'e': field 'ori': sensor 'right_forearm' is not a rotation matrix at frame 4 .*tolerance {ORTHO_TOL}",
        ori=o)
    o = ori.copy()
    o[2, 5] = -o[2, 5]  # a reflection
    bad(r"sensor 'pelvis' is not a rotation matrix at frame 2 .*det = -1", ori=o)
    o = ori.copy()
    o[3, 0, 0, 0] = np.nan
    bad(r"field 'ori': sensor 'left_forearm' has non-finite values, first at frame 3", ori=o)
    a = acc.copy()
    a[5, 4, 2] = np.inf
    bad(r"field 'acc': sensor 'head' has non-finite values, first at frame 5", acc=a)
    bad(r"field 'ori' must have shape \(T, 6, 3, 3\)", ori=ori[:, :5])
    bad(r"field 'acc' must have shape \(T, 6, 3\) with T = 6", acc=acc[:4])
    bad(r"field 'ori' has T = 0", ori=ori[:0], acc=acc[:0])
    bad(r"field 'fps' must be finite and > 0", fps=0.0)
    bad(r"field 'fps' must be a number", fps="60")
    bad(r"field 'ori' cannot be read as float64: it holds strings", ori=np.full((T, 6, 3, 3), "x"))
    bad(r"field 'world_from_inertial' must be a \(3, 3\) rotation", world_from_inertial=np.eye(3) * 2)
    bad(r"field 'bone_from_sensor': sensor 'left_lower_leg' is not a rotation",
        bone_from_sensor=np.stack([np.eye(3)] * 2 + [np.eye(3) * 1.1] + [np.eye(3)] * 3))
    bad(r"field 'acc_bias' must have shape \(6, 3\)", acc_bias=np.zeros((5, 3)))
    bad(r"field 'filled' must be \(T, 6\) booleans", filled=np.zeros((T, 5), bool))
    # the ground truth is the video clip's, checked by the same code
    bad(r"field 'gt_q' has 5 frames but 'ori' has 6", gt_q=np.zeros((5, 48)))
    bad(r"field 'gt_contacts' must be 0 or 1, first bad value at frame 0", gt_contacts=np.full((T, 4), 0.5))
    bad(r"field 'gt_keypoints3d' needs a keypoint layout", gt_keypoints3d=np.zeros((T, 25, 3)))
    bad(r"field 'gt_grf' has non-finite values, first at frame 1",
        gt_grf=np.where(np.arange(T)[:, None, None] == 1, np.nan, np.zeros((T, 4, 3))))
    bad(r"field 'gt_smpl_pose' must have shape \(T, 24, 3\)", gt_smpl_pose=np.zeros((T, 23, 3)))
    bad(r"field 'layout' is 'nope'", layout="nope")


def test_load_errors(tmp_path):
    clip = make_clip(4)
    arr = imu_clip_to_arrays(clip)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(IMUClipFormatError, match=r"junk.npz: not a readable .npz file"):
        load_imu_clip(tmp_path / "junk.npz")
    atomic_write_npz(tmp_path / "v.npz", arr | {"format": np.array("jmocap-clip-1")})
    with pytest.raises(IMUClipFormatError, match=r"v.npz: field 'format' is 'jmocap-clip-1', expected 'jmocap-imu-clip-1'"):
        load_imu_clip(tmp_path / "v.npz")
    atomic_write_npz(tmp_path / "n.npz", {k: v for k, v in arr.items() if k != "acc"})
    with pytest.raises(IMUClipFormatError, match=r"n.npz: missing field 'acc'"):
        load_imu_clip(tmp_path / "n.npz")
    o = arr["ori"].copy()
    o[2, 3] = np.diag([1.0, 1.0, 1.2])
    atomic_write_npz(tmp_path / "r.npz", arr | {"ori": o})
    with pytest.raises(IMUClipFormatError, match=r"r.npz: field 'ori': sensor 'right_lower_leg' is not a rotation matrix "
                                                 r"at frame 2"):
        load_imu_clip(tmp_path / "r.npz")
    with pytest.raises(IMUClipFormatError, match=r"r.npz: field 'ori'"):
        read_imu(tmp_path / "r.npz")


# --- calibration ------------------------------------------------------------------------------


def test_calibrate_tpose_recovers_known_offsets():
    """Synthetic T-pose with a known world alignment, known mountings and a known accelerometer
    offset: calibrate_tpose recovers them, and the calibrated clip gives the true bones."""
    rng = np.random.default_rng(5)
    R_WI = random_rotations(rng, ())  # any world alignment
    R_BS = random_rotations(rng, (6,))
    bias_W = rng.normal(scale=0.2, size=(6, 3))
    heading = 0.7
    R_WB_t = tpose_bone_orientations(heading)
    np.testing.assert_allclose(R_WB_t[0], rotation_z(heading))
    # readings: R_IS = R_WI^T R_WB R_BS; a still T-pose reads only the offset
    N = 40
    noise = np.stack([quat_to_matrix(np.r_[1.0, rng.normal(scale=2e-3, size=3)] /
                                     np.linalg.norm(np.r_[1.0, rng.normal(scale=2e-3, size=3)])) for _ in range(N * 7)])
    tpose = R_WI.T @ R_WB_t @ R_BS @ noise[: N * 6].reshape(N, 6, 3, 3)
    reference = R_WI.T @ noise[N * 6:]  # a sensor held on jmocap's world axes
    acc = (bias_W @ R_WI)[None] + rng.normal(scale=0.05, size=(N, 6, 3))  # R_WI^T b, row-vector form
    cal = calibrate_tpose(tpose, R_WB_t, reference_ori=reference, tpose_acc=acc)

    def angle(A, B):
        return np.degrees(np.arccos(np.clip((np.trace(np.swapaxes(A, -1, -2) @ B, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))

    assert angle(cal.world_from_inertial, R_WI) < 0.2
    assert np.all(angle(cal.bone_from_sensor, R_BS) < 0.3)
    np.testing.assert_allclose(cal.acc_bias, bias_W, atol=0.03)
    # exact without noise; quaternion input; world_from_inertial given directly
    exact = calibrate_tpose(matrix_to_quat(R_WI.T @ R_WB_t @ R_BS), R_WB_t, world_from_inertial=R_WI)
    np.testing.assert_allclose(exact.bone_from_sensor, R_BS, atol=1e-9)
    np.testing.assert_allclose(exact.acc_bias, 0.0)
    # a motion read through the calibration gives the true bones and world accelerations
    T = 8
    R_WB = random_rotations(rng, (T, 6))
    a_W = rng.normal(size=(T, 6, 3))
    clip = IMUClip(name="m", fps=60, ori=R_WI.T @ R_WB @ R_BS, acc=(a_W + bias_W) @ R_WI)
    R, a = clip.with_calibration(exact.__class__(R_WI, exact.bone_from_sensor, bias_W)).calibrated()
    np.testing.assert_allclose(R, R_WB, atol=1e-5)
    np.testing.assert_allclose(a, a_W, atol=1e-5)
    with pytest.raises(ValueError, match="exactly one of reference_ori"):
        calibrate_tpose(tpose)
    with pytest.raises(ValueError, match="tpose_ori: not rotation matrices"):
        calibrate_tpose(tpose * 1.1, world_from_inertial=np.eye(3))
    with pytest.raises(ValueError, match=r"tpose_ori: expected shape \(6, 3, 3\)"):
        calibrate_tpose(tpose[:, :5], world_from_inertial=np.eye(3))


# --- gaps -------------------------------------------------------------------------------------


def test_gap_rule():
    T = 10
    ori = np.tile(np.eye(3), (T, 6, 1, 1))
    ori[:, 2] = rotation_z(0.0)
    ori[6:, 2] = rotation_z(np.pi / 2)
    acc = np.zeros((T, 6, 3))
    acc[:, 2, 0] = np.arange(T)
    missing = np.zeros((T, 6), bool)
    missing[3:6, 2] = True  # interior: frames 2 (0 deg) and 6 (90 deg) around it
    missing[:2, 4] = True  # at the start
    missing[8:, 5] = True  # at the end
    acc[3:6, 2] = 99.0
    ori[:2, 4] = rotation_z(1.0)
    o, a, runs = fill_gaps(ori, acc, missing, "f")
    for k, t in enumerate((3, 4, 5)):
        np.testing.assert_allclose(o[t, 2], rotation_z(np.pi / 2 * (k + 1) / 4), atol=1e-12)
    np.testing.assert_allclose(a[3:6, 2, 0], [3.0, 4.0, 5.0])  # the line between frames 2 and 6
    np.testing.assert_allclose(o[:2, 4], np.tile(np.eye(3), (2, 1, 1)))  # held from frame 2
    np.testing.assert_allclose(o[8:, 5], ori[7, 5][None].repeat(2, 0))
    assert runs == {"left_lower_leg": [[3, 6]], "head": [[0, 2]], "pelvis": [[8, 10]]}
    long = np.zeros((T, 6), bool)
    long[1:1 + DEFAULT_MAX_GAP + 1, 0] = True
    with pytest.raises(IMUClipFormatError, match=rf"f: sensor 'left_forearm': 9 missing frames in a row \(frames 1-9\), "
                                                 rf"more than max_gap = {DEFAULT_MAX_GAP}"):
        fill_gaps(ori, acc, long, "f")
    fill_gaps(ori, acc, long, "f", max_gap=9)
    allm = np.zeros((T, 6), bool)
    allm[:, 3] = True
    with pytest.raises(IMUClipFormatError, match=r"sensor 'right_lower_leg' has no valid frame"):
        fill_gaps(ori, acc, allm, "f")
    # NaN readings: filled and reported, or refused
    raw_o, raw_a = ori.copy(), acc.copy()
    raw_o[4, 1] = np.nan
    raw_a[7, 0, 1] = np.nan
    o, a, filled, meta = readings_with_gaps(raw_o, raw_a, "w")
    assert filled[4, 1] and filled[7, 0] and filled.sum() == 2 and meta["gaps"] == {"left_forearm": [[7, 8]],
                                                                                  "right_forearm": [[4, 5]]}
    assert np.isfinite(o).all() and np.isfinite(a).all()
    with pytest.raises(IMUClipFormatError, match=r"w: field 'ori': sensor 'right_forearm' has NaN \(a dropout\), "
                                                 r"first at frame 4 \(2 sensor frames in all\)"):
        readings_with_gaps(raw_o, raw_a, "w", gaps="error")
    raw_a[1, 1, 1] = np.inf
    with pytest.raises(IMUClipFormatError, match=r"w: field 'acc': sensor 'right_forearm' has an infinite value at frame 1"):
        readings_with_gaps(raw_o, raw_a, "w")


# --- JSON -------------------------------------------------------------------------------------


def test_json_round_trip_quaternions_and_nulls(tmp_path):
    clip = make_clip(6, world_from_inertial=rotation_z(0.2), sensor_offset=np.full((6, 3), 0.01))
    write_imu_json(tmp_path / "c.json", clip)
    back = read_imu_json(tmp_path / "c.json")
    np.testing.assert_allclose(back.ori, clip.ori)
    np.testing.assert_allclose(back.acc, clip.acc)
    np.testing.assert_allclose(back.world_from_inertial, clip.world_from_inertial)
    np.testing.assert_allclose(back.sensor_offset, clip.sensor_offset)
    assert back.name == "c" and back.fps == 60.0
    doc = json.loads((tmp_path / "c.json").read_text())
    del doc["calibration"]
    doc["sensors"]["head"] = {"quat": matrix_to_quat(clip.ori[:, 4]).tolist(), "acc": clip.acc[:, 4].tolist()}
    doc["sensors"]["head"]["quat"][2] = None  # a dropout
    (tmp_path / "q.json").write_text(json.dumps(doc))
    q = read_imu(tmp_path / "q.json")
    assert q.filled[2, 4] and q.filled.sum() == 1 and q.meta["gaps"] == {"head": [[2, 3]]}
    np.testing.assert_allclose(q.ori[3, 4], clip.ori[3, 4], atol=1e-6)

    def bad(mut, match):
        d = json.loads(json.dumps(doc))
        mut(d)
        (tmp_path / "b.json").write_text(json.dumps(d))
        with pytest.raises(IMUClipFormatError, match=match):
            read_imu_json(tmp_path / "b.json")

    bad(lambda d: d["sensors"].pop("pelvis"), r"b.json: field 'sensors': missing sensor\(s\) \['pelvis'\]")
    bad(lambda d: d.update(extra=1), r"b.json: unknown key\(s\) \['extra'\]")
    bad(lambda d: d["sensors"]["left_forearm"]["acc"][1].__setitem__(0, True),
        r"field 'sensors.left_forearm.acc\[1\]'\[0\]: expected a number, got true")
    bad(lambda d: d["sensors"]["left_forearm"]["acc"].pop(), r"the sensors have different frame counts")
    bad(lambda d: d.update(fps="60"), r"field 'fps' must be a number")
    bad(lambda d: d["sensors"]["head"]["quat"].__setitem__(1, [2.0, 0, 0, 0]),
        r"field 'sensors.head.quat': frame 1 has norm 2")
    bad(lambda d: d["sensors"]["right_forearm"]["ori"][0][0].__setitem__(0, 3.0),
        r"field 'ori': sensor 'right_forearm' is not a rotation matrix at frame 0")


# --- DIP-IMU / TotalCapture pickles -----------------------------------------------------------


class _Py2Pickler(pickle._Pickler):
    """Writes ``bytes`` as Python 2 ``str`` (BINSTRING opcodes), as DIP-IMU's Python 2 pickles
    hold their keys and numpy's array data."""

    dispatch = pickle._Pickler.dispatch.copy()

    def save_py2_str(self, obj):
        n = len(obj)
        if n < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([n]) + obj)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", n) + obj)
        self.memoize(obj)

    dispatch[bytes] = save_py2_str


def py2_pickle(path, obj):
    with open(path, "wb") as f:
        _Py2Pickler(f, protocol=2).dump(obj)


def _dip_arrays(T, n, seed=6):
    rng = np.random.default_rng(seed)
    ori = random_rotations(rng, (T, n))
    acc = np.zeros((T, n, 3))
    acc[..., 0] = np.arange(n)  # each sensor identifiable by its source index
    acc[..., 1] = np.arange(T)[:, None]
    return ori, acc, rng.normal(size=(T, 72))


def test_dip_imu_reader(tmp_path):
    T = 30
    ori, acc, gt = _dip_arrays(T, 17)
    ori[10:13, 8] = np.nan  # a dropout of the right lower arm (3 frames)
    acc[10:13, 8] = np.nan
    path = tmp_path / "s_09" / "01.pkl"
    path.parent.mkdir()
    py2_pickle(path, {b"imu_ori": ori, b"imu_acc": acc, b"gt": gt, b"sop": np.zeros((T, 3))})
    assert pickle.load(open(path, "rb"), encoding="latin1")["imu_acc"].shape == (T, 17, 3)  # a true py2 pickle
    clip = read_dip_imu(path)
    assert clip.name == "01" and clip.fps == 60.0 and len(clip) == T
    np.testing.assert_array_equal(clip.acc[0, :, 0], DIP_IMU_MASK)  # sources 7, 8, 11, 12, 0, 2
    np.testing.assert_allclose(clip.ori[:, 4], ori[:, 0], atol=1e-6)  # head = DIP sensor 0
    assert clip.filled[10:13, 1].all() and clip.filled.sum() == 3
    np.testing.assert_allclose(clip.acc[10:13, 1, 1], [10, 11, 12])  # linear between frames 9 and 13
    assert clip.meta["gaps"] == {"right_forearm": [[10, 13]]}
    assert clip.meta["source_sensor_indices"] == [7, 8, 11, 12, 0, 2]
    np.testing.assert_allclose(clip.gt_smpl_pose.reshape(T, 72), gt, atol=1e-6)
    # calibrated: SMPL's bones in jmocap's world and body frames, R_WB = M R M^T; a_W = M a
    R, a = clip.calibrated()
    M = SMPL_TO_JMOCAP
    np.testing.assert_allclose(R[5, 0], M @ ori[5, 7] @ M.T, atol=1e-5)
    np.testing.assert_allclose(a[5, 0], M @ acc[5, 7], atol=1e-5)
    # a subject standing upright in SMPL's rest pose (bones = I in SMPL's world) is jmocap's T-pose
    np.testing.assert_allclose(M @ np.eye(3) @ M.T, tpose_bone_orientations()[0])
    np.testing.assert_allclose(M @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0])  # SMPL's up is jmocap's z
    assert read_imu(path).meta["dataset"] == "DIP-IMU"
    with pytest.raises(IMUClipFormatError, match=r"01.pkl: field 'imu_ori': sensor 'right_forearm' has NaN"):
        read_dip_imu(path, gaps="error")
    with pytest.raises(IMUClipFormatError, match=r"01.pkl: sensor 'right_forearm': 3 missing frames in a row"):
        read_dip_imu(path, max_gap=2)
    assert read_dip_imu(path, ground_truth=False).gt_smpl_pose is None


def test_dip_imu_reader_errors(tmp_path):
    T = 8
    ori, acc, gt = _dip_arrays(T, 17)

    def bad(doc, match, **kw):
        p = tmp_path / "bad.pkl"
        py2_pickle(p, doc)
        with pytest.raises(IMUClipFormatError, match=match):
            read_dip_imu(p, **kw)

    bad({b"imu_acc": acc, b"gt": gt}, r"bad.pkl: missing field 'imu_ori'")
    bad({b"imu_ori": ori[:, :16], b"imu_acc": acc, b"gt": gt}, r"field 'imu_ori' must have shape \(T, 17, 3, 3\)")
    bad({b"imu_ori": ori, b"imu_acc": acc[:5], b"gt": gt}, r"field 'imu_acc' must have shape \(8, 17, 3\)")
    g = gt.copy()
    g[3, 5] = np.nan
    bad({b"imu_ori": ori, b"imu_acc": acc, b"gt": g}, r"field 'gt' has non-finite values, first at frame 3 "
                                                     r"\(ground_truth=False")
    o = ori.copy()
    o[6, 11] *= 1.5
    bad({b"imu_ori": o, b"imu_acc": acc, b"gt": gt}, r"field 'imu_ori': sensor 'left_lower_leg' is not a rotation matrix "
                                                    r"at frame 6")
    bad({b"imu_ori": ori, b"imu_acc": np.full(acc.shape, "x"), b"gt": gt}, r"field 'imu_acc' must be a numeric array")
    bad([1, 2], r"expected a pickled dict")


def test_totalcapture_dip_reader(tmp_path):
    T = 20
    ori, acc, gt = _dip_arrays(T, 6, seed=7)
    p = tmp_path / "s1_acting1.pkl"
    with open(p, "wb") as f:
        pickle.dump({"ori": ori, "acc": acc, "gt": gt[:15]}, f, protocol=4)  # gt shorter: cut to 15
    clip = read_totalcapture_dip(p)
    assert len(clip) == 15 and clip.meta["truncated"] == {"imu_frames": 20, "gt_frames": 15, "kept": 15}
    np.testing.assert_array_equal(clip.acc[0, :, 0], TOTALCAPTURE_DIP_MASK)  # stored legs first, arms second
    assert read_imu(p).meta["dataset"] == "TotalCapture"
    with pytest.raises(IMUClipFormatError, match=r"field 'ori' must have shape \(T, 6, 3, 3\)"):
        with open(p, "wb") as f:
            pickle.dump({"ori": ori[:, :5], "acc": acc[:, :5]}, f)
        read_totalcapture_dip(p)


class _Evil:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


def test_malicious_pickles_do_not_run(tmp_path):
    flag = tmp_path / "pwned"
    ori, acc, gt = _dip_arrays(4, 17)
    for i, doc in enumerate([_Evil(flag), {"imu_ori": ori, "imu_acc": acc, "gt": _Evil(flag)}]):
        p = tmp_path / f"evil{i}.pkl"
        with open(p, "wb") as f:
            pickle.dump(doc, f, protocol=2)
        for reader in (read_dip_imu, read_imu):
            with pytest.raises(FormatError, match=rf"evil{i}.pkl: field 'pickle': refuses to unpickle '(posix|os)\.system'"):
                reader(p)
    # builtins.eval, a subclass of ndarray, a truncated file
    p = tmp_path / "eval.pkl"
    p.write_bytes(b"\x80\x02cbuiltins\neval\nq\x00X\x0b\x00\x00\x00print('hi')q\x01\x85q\x02Rq\x03.")
    with pytest.raises(FormatError, match=r"refuses to unpickle 'builtins.eval'"):
        load_pickle_file(p)
    p.write_bytes(pickle.dumps({"imu_ori": ori}, protocol=2)[:40])
    with pytest.raises(FormatError, match=r"not a readable pickle file"):
        read_dip_imu(p)
    assert not flag.exists()
