"""The result format (jmocap.results): the writer's every field read back by the reader, the
reader's tolerance of older files and its errors, the character a result names, and the
atomic writer (jmocap.io) underneath."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jmocap.data import FormatError
from jmocap.data.clip import Clip
from jmocap.io import atomic_write, atomic_writer, npz_bytes
from jmocap.model import character
from jmocap.results import (
    MOTION_FIELDS,
    RESULT_FORMAT,
    assumed_fields,
    load_result,
    result_arrays,
    result_model,
    write_result,
)


def _clip(T=6, **kw):
    rng = np.random.default_rng(0)
    kp = np.concatenate([rng.uniform(0, 500, (T, 25, 2)), np.ones((T, 25, 1))], -1).astype(np.float32)
    return Clip(name="walk/take1", layout="body25", fps=25.0, keypoints=kp,
                intrinsics=np.array([900.0, 910.0, 320.0, 240.0]), image_size=np.array([640, 480]), **kw)


def test_every_written_field_reads_back(tmp_path):
    track = np.repeat(np.eye(4)[None], 6, 0)
    track[:, :3, 3] = [[0.02 * t, 0.0, 4.0] for t in range(6)]  # a camera sliding sideways (optional field)
    step = {"boxes": [{"center": [1.0, 0.0, 0.1], "half_size": [0.3, 0.4, 0.1], "yaw_deg": 20.0}]}
    clip = _clip(height_m=1.62, mass_kg=55.0, camera_track=track, scene=step)  # terrain (optional)
    model = character(1.62, 55.0)
    T, rng = clip.num_frames, np.random.default_rng(1)
    shapes = {"q": (model.nq,), "qd": (model.nv,), "tau": (model.nv,), "grf": (4, 3), "contact_prob": (4,),
              "target_q": (model.nq,), "keypoints3d": (25, 3)}
    res = {k: rng.normal(size=(T, *shapes[k])).astype(np.float32) for k in MOTION_FIELDS}
    res["certified"] = rng.random(T) > 0.1  # the optional per-frame QP certificates
    res["diagnostics"] = {"objective_final": 1.25, "iterations": 200.0}  # an optimiser's report
    res["camera_track_estimated"] = track + 0.01  # a method's own estimate of the track (dnd)
    identity = {"config": json.dumps({"mu": 0.8}), "params_sha256": "ab" * 32, "model_sha256": "cd" * 32,
                "version": "9.9"}
    arrays = result_arrays(clip, res, method="physcap", height_m=1.62, mass_kg=model.total_mass,
                           forces_estimated=True, identity=identity, source="in/walk.npz",
                           assumed=assumed_fields(clip))
    data = write_result(tmp_path / "r.npz", arrays)
    assert data == npz_bytes(arrays)  # deterministic bytes: equal results give equal files
    r = load_result(tmp_path / "r.npz")
    assert set(r) == set(arrays)  # the reader knows every field the writer writes, nothing else
    for k in (*MOTION_FIELDS, "certified"):
        np.testing.assert_array_equal(r[k], res[k])
    np.testing.assert_array_equal(r["keypoints2d"], clip.keypoints)
    np.testing.assert_array_equal(r["camera_track"], track)
    np.testing.assert_array_equal(r["camera_track_estimated"], track + 0.01)
    np.testing.assert_array_equal(r["extrinsics"], track[0])
    assert r["diagnostics"] == res["diagnostics"]
    np.testing.assert_allclose(r["scene"].centers, clip.scene.centers)
    np.testing.assert_allclose(r["scene"].rotations, clip.scene.rotations, atol=1e-15)
    assert r["format"] == RESULT_FORMAT and r["name"] == "walk/take1" and r["source"] == "in/walk.npz"
    assert r["method"] == "physcap" and r["forces_estimated"] is True and r["layout"] == "body25"
    assert (r["fps"], r["height_m"]) == (25.0, 1.62) and r["mass_kg"] == pytest.approx(55.0)
    np.testing.assert_array_equal(r["intrinsics"], clip.intrinsics)
    np.testing.assert_array_equal(r["image_size"], [640, 480])
    assert r["extrinsics"].shape == (4, 4) and r["assumed"] == []  # the track gives the camera
    assert {k: r[k] for k in identity} == identity
    assert result_model(r) is character(1.62, 55.0)  # the cached character of that subject


def test_defaults_are_named_and_give_the_nominal_character(tmp_path):
    clip = _clip()
    assert assumed_fields(clip) == ["extrinsics", "height_m", "mass_kg"]
    res = {k: np.zeros((clip.num_frames, 4, 3) if k == "grf" else (clip.num_frames, 4), np.float32)
           for k in MOTION_FIELDS}
    res.update(q=np.zeros((6, 48), np.float32), target_q=np.zeros((6, 48), np.float32),
               qd=np.zeros((6, 47), np.float32), tau=np.zeros((6, 47), np.float32),
               keypoints3d=np.zeros((6, 25, 3), np.float32))
    arrays = result_arrays(clip, res, method="kinematic", height_m=1.75, mass_kg=character().total_mass,
                           forces_estimated=False, identity={}, source="x", assumed=assumed_fields(clip))
    write_result(tmp_path / "k.npz", arrays)
    r = load_result(tmp_path / "k.npz")
    assert r["forces_estimated"] is False and result_model(r) is character()


def test_forces_not_estimated_are_absent_not_zero(tmp_path):
    """A method that estimates no forces leaves tau and grf out of the file; an older file that
    holds zeros there with forces_estimated False reads as absent too."""
    clip = _clip()
    T = clip.num_frames
    res = {k: np.zeros((T, 4, 3) if k == "grf" else (T, 4), np.float32) for k in MOTION_FIELDS}
    res.update(q=np.zeros((T, 48), np.float32), target_q=np.zeros((T, 48), np.float32),
               qd=np.zeros((T, 47), np.float32), tau=np.zeros((T, 47), np.float32),
               keypoints3d=np.zeros((T, 25, 3), np.float32))
    arrays = result_arrays(clip, res, method="kinematic", height_m=1.75, mass_kg=character().total_mass,
                           forces_estimated=False, identity={}, source="x")
    assert "tau" not in arrays and "grf" not in arrays and "q" in arrays
    write_result(tmp_path / "k.npz", arrays)
    with np.load(tmp_path / "k.npz") as z:
        assert "tau" not in z.files and "grf" not in z.files
    r = load_result(tmp_path / "k.npz")
    assert r["tau"] is None and r["grf"] is None and r["q"].shape == (T, 48)
    old = dict(arrays, tau=np.zeros((T, 47), np.float32), grf=np.zeros((T, 4, 3), np.float32))
    write_result(tmp_path / "old.npz", old)
    r = load_result(tmp_path / "old.npz")
    assert r["tau"] is None and r["grf"] is None
    # with estimates, the same zeros are data
    write_result(tmp_path / "est.npz", dict(old, forces_estimated=np.array(True)))
    r = load_result(tmp_path / "est.npz")
    assert r["grf"].shape == (T, 4, 3) and r["tau"].shape == (T, 47)


# ---- result files ----------------------------------------------------------------------


def test_load_result_tolerates_missing_optional_keys(tmp_path):
    q = np.zeros((5, 48), np.float32)
    np.savez(tmp_path / "r.npz", q=q, fps=np.array(30.0), layout=np.array("body25"), extra=np.arange(3))
    r = load_result(tmp_path / "r.npz")
    assert r["q"].shape == (5, 48) and r["fps"] == 30.0 and r["layout"] == "body25"
    for key in ("qd", "tau", "grf", "contact_prob", "keypoints2d", "intrinsics", "height_m", "config"):
        assert r[key] is None
    np.testing.assert_array_equal(r["extra"], np.arange(3))


def test_load_result_rejects_bad_files(tmp_path):
    q = np.zeros((5, 48))
    cases = {
        "noq.npz": ({"fps": np.array(30.0)}, r"missing field 'q'"),
        "frames.npz": ({"q": q, "fps": np.array(30.0), "grf": np.zeros((4, 4, 3))}, r"'grf' has 4 frames, 'q' has 5"),
        "shape.npz": ({"q": q, "fps": np.array(30.0), "grf": np.zeros((5, 3))}, r"'grf' has shape \(5, 3\)"),
        "fps.npz": ({"q": q, "fps": np.array(-1.0)}, r"'fps' must be positive"),
        "diag.npz": ({"q": q, "fps": np.array(30.0), "diagnostics": np.array('["x"]')},
                     r"'diagnostics' is not a JSON object of numbers"),
    }
    for name, (arrays, match) in cases.items():
        np.savez(tmp_path / name, **arrays)
        with pytest.raises(FormatError, match=match) as e:
            load_result(tmp_path / name)
        assert name in str(e.value)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="not a readable .npz"):
        load_result(tmp_path / "junk.npz")


def test_atomic_writer_leaves_the_old_file_on_failure(tmp_path):
    path = tmp_path / "a.txt"
    atomic_write(path, "old")
    with pytest.raises(RuntimeError), atomic_writer(path) as f:
        f.write(b"half")
        raise RuntimeError("crash while writing")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    atomic_write(path, b"new")
    assert path.read_bytes() == b"new"
