"""jmocap.export: BVH round trip against MuJoCo C, result files, bad input.

Reference: MuJoCo C ``mj_kinematics`` body positions (``xpos``). The BVH is read back with
``read_bvh`` / ``bvh_joint_positions``, a generic BVH parser and forward kinematics that know
nothing of jmocap's model (they follow the published format: offsets, channel products in
listed order), and mapped back to jmocap's world with the *documented* conventions only
(``docs/formats.md``: y-up ``(X, Y, Z) = (y, z, x)``, centimetres). Tolerance 1 mm (the
brief's); the file stores 6 decimals (1e-8 m in cm, 1e-6 degree), so the actual error is
about 1e-7 m: anything near 1 mm would be a convention error, not rounding.
"""

from __future__ import annotations

import os

import mujoco
import numpy as np
import pytest

import jmocap
from conftest import random_configurations
from jmocap.data import FormatError
from jmocap.export import bvh_joint_positions, read_bvh, write_bvh

# documented conventions: BVH (X, Y, Z) = (y, z, x) of the jmocap world (y-up), or unchanged
TO_BVH = {"y": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), "z": np.eye(3)}
UNIT = {"cm": 100.0, "m": 1.0}
TOL_M = 1e-3


@pytest.fixture(scope="module")
def models():
    return {
        "default": jmocap.load_model(with_mjx=False),
        "1.55m": jmocap.load_model(height_m=1.55, with_mjx=False),
    }


def mujoco_xpos(model, q):
    d = mujoco.MjData(model.mj)
    out = []
    for qt in q:
        d.qpos[:] = qt
        mujoco.mj_kinematics(model.mj, d)
        out.append(d.xpos.copy())
    return np.stack(out)  # (T, nbody, 3)


def bvh_world_positions(bvh, up="y", units="cm"):
    """BVH joint positions mapped back to jmocap's world (metres), by the documented rule."""
    return bvh_joint_positions(bvh) @ TO_BVH[up] / UNIT[units]  # row vectors: C^T p


@pytest.mark.parametrize("which", ["default", "1.55m"])
@pytest.mark.parametrize("up,units", [("y", "cm"), ("z", "m")])
def test_bvh_round_trip_matches_mujoco(models, which, up, units, tmp_path):
    model = models[which]
    q, _ = random_configurations(model.mj, 40, seed=3)  # random root pose, hinges within limits
    path = write_bvh(tmp_path / "motion.bvh", model, q, fps=25.0, up=up, units=units)
    bvh = read_bvh(path)

    names = model.topo.body_names
    assert set(bvh.names) == set(names[1:])  # one BVH joint per body (world excluded)
    assert bvh.frames.shape[0] == len(q)
    assert bvh.frame_time == pytest.approx(1 / 25.0, rel=1e-6)

    ids = [names.index(n) for n in bvh.names]
    ref = mujoco_xpos(model, q)[:, ids]
    got = bvh_world_positions(bvh, up, units)
    err = np.abs(got - ref).max()
    assert err < TOL_M, f"max body position error {err * 1e3:.4f} mm"

    # parents and offsets: the model's tree and body_pos (scaled model: its own lengths)
    for j, b in enumerate(ids):
        p = bvh.parents[j]
        assert (names[ids[p]] if p >= 0 else "world") == names[model.mj.body_parentid[b]]
        if p >= 0:
            np.testing.assert_allclose(
                bvh.offsets[j] @ TO_BVH[up] / UNIT[units], model.mj.body_pos[b], atol=1e-7
            )


def test_bvh_channel_layout(models, tmp_path):
    model = models["default"]
    q = np.tile(model.keyframe("stand"), (3, 1))
    knee = model.mj.jnt_qposadr[model.mj.joint("left_knee_y").id]
    q[:, knee] = [0.0, 0.5, 1.0]
    bvh = read_bvh(write_bvh(tmp_path / "m.bvh", model, q, fps=30.0))

    assert bvh.names[0] == "pelvis" and bvh.parents[0] == -1
    assert bvh.channels[0] == ("Xposition", "Yposition", "Zposition", "Yrotation", "Xrotation", "Zrotation")
    np.testing.assert_array_equal(bvh.offsets[0], 0.0)
    for name, chans in zip(bvh.names[1:], bvh.channels[1:], strict=True):
        assert len(chans) == 3 and sorted(c[0] for c in chans) == ["X", "Y", "Z"], name
        assert all(c.endswith("rotation") for c in chans), name
    # hinge order y, x, z (hip) -> BVH X, Z, Y (y-up); the knee's hinge y -> X, then zeros
    assert bvh.channels[bvh.names.index("left_hip")] == ("Xrotation", "Zrotation", "Yrotation")
    assert bvh.channels[bvh.names.index("left_shoulder")] == ("Zrotation", "Yrotation", "Xrotation")
    k = bvh.frames[:, bvh.channel_slice("left_knee")]
    np.testing.assert_allclose(k, np.degrees([[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]]), atol=1e-6)
    np.testing.assert_array_equal(bvh.frames[:, bvh.channel_slice("head")], 0.0)  # rigid
    # standing: root at (0, 1 m, 0) in y-up centimetres, no rotation
    np.testing.assert_allclose(bvh.frames[:, :6], [[0, 100, 0, 0, 0, 0]] * 3, atol=1e-6)
    # leaves end in End Sites (toes, head, hands)
    leaves = {bvh.names[j] for j, _ in bvh.end_sites}
    assert leaves == {"left_foot", "right_foot", "head", "left_hand", "right_hand"}
    head_top = dict((bvh.names[j], o) for j, o in bvh.end_sites)["head"]
    np.testing.assert_allclose(head_top, [0, 15.0, 0], atol=1e-6)  # kp_head_top, 15 cm up


def test_bvh_root_angles_are_continuous(models, tmp_path):
    """A root spinning twice about the vertical: unwrapped Euler angles, same positions."""
    model = models["default"]
    T = 120
    yaw = np.linspace(0, 4 * np.pi, T)
    q = np.tile(model.keyframe("stand"), (T, 1))
    q[:, 3:7] = np.stack([np.cos(yaw / 2), 0 * yaw, 0.1 * np.sin(yaw / 2), np.sin(yaw / 2)], 1)
    q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    bvh = read_bvh(write_bvh(tmp_path / "spin.bvh", model, q, fps=30.0))
    jumps = np.abs(np.diff(bvh.frames[:, 3:6], axis=0)).max()
    assert jumps < 20.0, f"root Euler angle jumps by {jumps} degrees between frames"
    ids = [model.topo.body_names.index(n) for n in bvh.names]
    err = np.abs(bvh_world_positions(bvh) - mujoco_xpos(model, q)[:, ids]).max()
    assert err < TOL_M


def test_bvh_is_written_atomically(models, tmp_path):
    model = models["default"]
    q = model.keyframe("stand")[None]
    path = tmp_path / "out" / "a.bvh"
    path.parent.mkdir()
    path.write_text("old")
    write_bvh(path, model, q, fps=30)
    assert path.read_text().startswith("HIERARCHY")
    assert os.listdir(path.parent) == ["a.bvh"]  # no temp file left behind


@pytest.mark.parametrize(
    "bad,match",
    [
        ("nan", r"frame 2: coordinate 10 \(left_knee_y\) is nan"),
        ("nq", r"expected shape \(T, nq=48\), got \(4, 47\)"),
        ("1d", r"expected shape \(T, nq=48\)"),
        ("quat", r"frame 1: root quaternion"),
        ("fps", r"fps must be positive"),
    ],
)
def test_write_bvh_rejects_bad_input(models, tmp_path, bad, match):
    model = models["default"]
    q = np.tile(model.keyframe("stand"), (4, 1))
    fps = 30.0
    if bad == "nan":
        q[2, 10] = np.nan
    elif bad == "nq":
        q = q[:, :-1]
    elif bad == "1d":
        q = q[0]
    elif bad == "quat":
        q[1, 3:7] = 0.0
    elif bad == "fps":
        fps = 0.0
    path = tmp_path / "bad.bvh"
    with pytest.raises(ValueError, match=match) as e:
        write_bvh(path, model, q, fps)
    assert "bad.bvh" in str(e.value)
    assert not path.exists() and os.listdir(tmp_path) == []


def test_read_bvh_rejects_malformed_files(models, tmp_path):
    model = models["default"]
    good = write_bvh(tmp_path / "g.bvh", model, np.tile(model.keyframe("stand"), (2, 1)), 30).read_text()
    cases = {
        "truncated.bvh": (good[: good.rindex("\n", 0, -2)], r"MOTION has \d+ values, expected 2 frames"),
        "channel.bvh": (good.replace("Xrotation", "Wrotation", 1), r"line \d+: joint .* unknown channel 'Wrotation'"),
        "number.bvh": (good.replace("OFFSET 0.000000", "OFFSET zero", 1), r"line 4: OFFSET of 'pelvis': expected a number"),
        "nohier.bvh": ("MOTION\n", r"line 1: expected 'HIERARCHY'"),
    }
    for name, (text, match) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(FormatError, match=match):
            read_bvh(tmp_path / name)
