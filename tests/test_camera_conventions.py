"""Camera files in the common conventions (jmocap.data.formats.camera_file): every form of the
extrinsics, K, lens distortion and y-up worlds, against OpenCV's own ``projectPoints`` /
``undistortPoints`` (skipped without opencv) and a hand-worked pinhole projection; and the
errors: nothing in a camera file is silently ignored."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jmocap.data.clip import FormatError
from jmocap.data.formats.camera_file import (
    Y_UP_TO_Z_UP,
    distort_normalized,
    read_camera_json,
    rodrigues,
    undistort_points,
)

K = np.array([[1150.0, 0.0, 962.5], [0.0, 1140.0, 541.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.012])  # a wide-angle lens, OpenCV order
RVEC = np.array([1.9, -0.35, 0.42])
TVEC = np.array([0.3, 0.9, 4.2])


def _pinhole(E, intr, X):
    """Hand-worked pinhole projection: x_cam = E [X; 1], u = fx x / z + cx, v = fy y / z + cy."""
    xc = X @ E[:3, :3].T + E[:3, 3]
    fx, fy, cx, cy = intr
    return np.stack([fx * xc[:, 0] / xc[:, 2] + cx, fy * xc[:, 1] / xc[:, 2] + cy], -1)


def _points(E, n=40, seed=0):
    """World points in front of the camera E (2-6 m deep, inside the image)."""
    rng = np.random.default_rng(seed)
    cam = np.stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-0.8, 0.8, n), rng.uniform(2.0, 6.0, n)], -1)
    R, t = E[:3, :3], E[:3, 3]
    return (cam - t) @ R  # R^T (x_cam - t)


def _write(tmp_path, data, name="cam.json"):
    p = tmp_path / name
    p.write_text(json.dumps(data))
    return p


def _E(R, t):
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, t
    return E


BASE = {"width": 1920, "height": 1080}


def _forms():
    R = rodrigues(RVEC)
    E = _E(R, TVEC)
    pose = np.linalg.inv(E)
    return E, {
        "extrinsics": {"extrinsics": E.tolist()},
        "R/t": {"R": R.tolist(), "t": TVEC.tolist()},
        "rvec/tvec": {"rvec": RVEC.tolist(), "tvec": TVEC.tolist()},
        "R_world_to_cam": {"R_world_to_cam": R.tolist(), "t_world_to_cam": TVEC.tolist()},
        "cam_to_world": {"cam_to_world": pose.tolist()},
        "camera pose": {"camera_position": pose[:3, 3].tolist(), "camera_rotation": pose[:3, :3].tolist()},
    }


@pytest.mark.parametrize("form", ["extrinsics", "R/t", "rvec/tvec", "R_world_to_cam", "cam_to_world", "camera pose"])
def test_every_extrinsics_form_is_the_same_camera(tmp_path, form):
    E, forms = _forms()
    side = read_camera_json(_write(tmp_path, {**BASE, "K": K.tolist(), **forms[form]}))
    np.testing.assert_allclose(side["intrinsics"], [1150.0, 1140.0, 962.5, 541.0])
    np.testing.assert_allclose(side["extrinsics"], E, atol=1e-12)
    X = _points(E)
    np.testing.assert_allclose(_pinhole(side["extrinsics"], side["intrinsics"], X), _pinhole(E, side["intrinsics"], X),
                               atol=1e-9)


def test_rodrigues_and_projection_match_opencv():
    cv2 = pytest.importorskip("cv2")
    R_cv, _ = cv2.Rodrigues(RVEC)
    np.testing.assert_allclose(rodrigues(RVEC), R_cv, atol=1e-12)
    E = _E(R_cv, TVEC)
    X = _points(E)
    ref, _ = cv2.projectPoints(X, RVEC, TVEC, K, np.zeros(5))
    intr = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    np.testing.assert_allclose(_pinhole(E, intr, X), ref[:, 0], atol=1e-8)
    import jax.numpy as jnp

    from jmocap.camera import Camera, project

    cam = Camera(jnp.asarray(intr, jnp.float32), jnp.zeros(2, jnp.float32), jnp.asarray(E, jnp.float32))
    np.testing.assert_allclose(np.asarray(project(cam, jnp.asarray(X, jnp.float32))), ref[:, 0], atol=0.05)


@pytest.mark.parametrize("dist", [DIST[:4], DIST, np.r_[DIST, 0.02, -0.01, 0.003]])
def test_lens_distortion_is_opencvs_and_undistortion_inverts_it(dist):
    cv2 = pytest.importorskip("cv2")
    E = _E(rodrigues(RVEC), TVEC)
    X = _points(E, n=200, seed=1)
    seen, _ = cv2.projectPoints(X, RVEC, TVEC, K, dist)  # through the lens
    ideal, _ = cv2.projectPoints(X, RVEC, TVEC, K, np.zeros(5))
    intr = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    # the forward model is OpenCV's
    xn = (ideal[:, 0] - K[[0, 1], [2, 2]]) / K[[0, 1], [0, 1]]
    fwd = distort_normalized(xn, dist) * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]
    np.testing.assert_allclose(fwd, seen[:, 0], atol=1e-8)
    # undistortion gives back the ideal pinhole's pixels, as OpenCV's undistortPoints does
    np.testing.assert_allclose(undistort_points(seen[:, 0], intr, dist), ideal[:, 0], atol=1e-4)
    ref = cv2.undistortPoints(seen, K, dist, P=K,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    np.testing.assert_allclose(undistort_points(seen[:, 0], intr, dist), ref[:, 0], atol=1e-4)


def test_distortion_hand_worked():
    # k1 only: x_d = x (1 + k1 r^2); at x = (0.2, 0.1), r^2 = 0.05, k1 = -0.3: factor 0.985
    np.testing.assert_allclose(distort_normalized(np.array([0.2, 0.1]), np.array([-0.3, 0, 0, 0])),
                               [0.197, 0.0985], atol=1e-15)
    # tangential p1 only: dx = 2 p1 x y, dy = p1 (r^2 + 2 y^2)
    np.testing.assert_allclose(distort_normalized(np.array([0.2, 0.1]), np.array([0, 0, 0.01, 0])),
                               [0.2 + 2 * 0.01 * 0.02, 0.1 + 0.01 * (0.05 + 0.02)], atol=1e-15)


def test_y_up_world_with_a_floor(tmp_path):
    """A y-up world (x, y up, z) with the floor at y = 0.8: jmocap's world is (x, -z, y - 0.8)."""
    E, forms = _forms()
    side = read_camera_json(_write(tmp_path, {**BASE, "K": K.tolist(), **forms["rvec/tvec"], "world_up": "y",
                                              "floor_height": 0.8}))
    X_file = _points(E)
    X_jmocap = X_file @ Y_UP_TO_Z_UP.T - [0.0, 0.0, 0.8]
    intr = side["intrinsics"]
    np.testing.assert_allclose(_pinhole(side["extrinsics"], intr, X_jmocap), _pinhole(E, intr, X_file), atol=1e-9)
    np.testing.assert_allclose(Y_UP_TO_Z_UP @ [0.0, 1.0, 0.0], [0, 0, 1])  # up is up
    assert np.isclose(np.linalg.det(Y_UP_TO_Z_UP), 1.0)
    assert "y-up" in side["convention"]


@pytest.mark.parametrize("data, field, words", [
    ({"fx": 1, "fy": 1, "cx": 0, "cy": 0, "R_cam": np.eye(3).tolist()}, "R_cam", "unknown key"),
    ({"K": K.tolist(), "R": np.eye(3).tolist()}, "R", "needs 't'"),
    ({"K": K.tolist(), "t_world_to_cam": [0, 0, 1]}, "t_world_to_cam", "needs 'R_world_to_cam'"),
    ({"K": K.tolist(), "extrinsics": np.eye(4).tolist(), "rvec": [0, 0, 0], "t": [0, 0, 1]}, None, "more than one way"),
    ({"K": K.tolist(), "fx": 1000}, "fx", "given twice"),
    ({"K": [[1000, 5, 960], [0, 1000, 540], [0, 0, 1]]}, "K", "no skew"),
    ({"K": K.tolist(), "dist": [0.1, 0.2, 0.3]}, "dist", "4, 5 or 8"),
    ({"K": K.tolist(), "world_up": "y"}, "world_up", "without extrinsics"),
    ({"K": K.tolist(), "world_up": "x", "extrinsics": np.eye(4).tolist()}, "world_up", "must be"),
    ({"K": K.tolist(), "R": (2 * np.eye(3)).tolist(), "t": [0, 0, 1]}, "R", "rotation"),
    ({"K": K.tolist(), "camera_position": [0, 0, 1], "camera_rotation": np.diag([1.0, 1.0, -1.0]).tolist()},
     "camera_rotation", "rotation"),
    ({"fy": 1000, "cx": 960, "cy": 540}, "fx", "missing"),
])
def test_bad_camera_files_name_the_key(tmp_path, data, field, words):
    p = _write(tmp_path, {**BASE, **data})
    with pytest.raises(FormatError) as e:
        read_camera_json(p)
    msg = str(e.value)
    assert str(p) in msg and words in msg, msg
    if field is not None:
        assert repr(field) in msg, msg


def test_a_clip_read_through_a_lens_is_undistorted(tmp_path):
    """An OpenPose folder with a sidecar that has K and dist: the clip's keypoints are the ideal
    pinhole camera's pixels (as OpenCV undistorts them), missing joints stay missing."""
    from jmocap.data.formats import read_clip
    from jmocap.layouts import get_layout

    J = get_layout("body25").num_joints
    rng = np.random.default_rng(3)
    uv = np.stack([rng.uniform(200, 1700, (4, J)), rng.uniform(100, 1000, (4, J))], -1)
    conf = np.full((4, J), 0.9)
    conf[1, 3] = 0.0  # a missing joint
    folder = tmp_path / "take"
    folder.mkdir()
    for t in range(4):
        flat = np.concatenate([uv[t], conf[t][:, None]], -1).ravel().tolist()
        (folder / f"take_{t:012d}_keypoints.json").write_text(json.dumps(
            {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat}]}))
    _write(tmp_path, {**BASE, "K": K.tolist(), "dist": DIST.tolist(), **_forms()[1]["rvec/tvec"]},
           name="take.camera.json")
    clip = read_clip(folder)
    intr = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    want = undistort_points(uv, intr, DIST)
    ok = conf > 0
    np.testing.assert_allclose(clip.keypoints[..., :2][ok], want[ok], atol=1e-3)
    assert clip.keypoints[1, 3, 2] == 0.0
    assert clip.meta["undistorted"] == pytest.approx(DIST.tolist())
    np.testing.assert_allclose(clip.extrinsics, _forms()[0], atol=1e-9)
