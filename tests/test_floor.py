"""The floor of an uncalibrated static camera (jmocap.methods.floor) and the world change that
scores its estimates (jmocap.evaluate, ``camera``).

References: planes and cameras built by hand and by :meth:`jmocap.camera.Camera.look_at`; the
ground truth's own poses seen through the clip's true camera; forward kinematics for the moved
motion; and, for the evaluation harness, the kinematic method, whose camera-frame output does
not depend on the extrinsics (so its scores must not either, once moved into the true world).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jmocap import physics as P
from jmocap.camera import Camera, default_extrinsics
from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.methods import floor as F
from jmocap.methods import stages as S
from jmocap.model import character
from jmocap.motion import Motion
from jmocap.physics.rotations import quat_to_mat


def _camera(pitch_deg: float, roll_deg: float, height: float) -> np.ndarray:
    """World -> camera of a camera ``height`` above the floor, pitched down and rolled."""
    up = np.asarray(F.camera_angles_inverse(pitch_deg, roll_deg))
    return np.asarray(F.extrinsics_from_floor(jnp.asarray(up), jnp.asarray(height), jnp.array([0.3, 0.2, 5.0])))


def _up_error_deg(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_camera_angles_of_known_cameras():
    # the default camera is level: it sees the world's up as the image's up, (0, -1, 0)
    E = default_extrinsics()
    p, r = F.camera_angles(jnp.asarray(E[:3, 2]))
    assert float(p) == pytest.approx(0.0, abs=1e-9) and float(r) == pytest.approx(0.0, abs=1e-9)
    # a camera 2 m up looking at a point on the floor 2 m in front of it: 45 degrees down
    cam = Camera.look_at((0.0, -2.0, 2.0), (0.0, 0.0, 0.0), dtype=np.float64)
    p, r = F.camera_angles(jnp.asarray(np.asarray(cam.extrinsics)[:3, 2]))
    assert float(p) == pytest.approx(45.0, abs=1e-6) and float(r) == pytest.approx(0.0, abs=1e-6)
    # and back: the angles give the up direction they were read from
    for pitch, roll in ((12.0, -3.0), (-20.0, 7.5), (60.0, 0.0)):
        up = F.camera_angles_inverse(pitch, roll)
        p, r = F.camera_angles(up)
        assert (float(p), float(r)) == pytest.approx((pitch, roll), abs=1e-4)


@pytest.mark.parametrize("pitch,roll,height", [(0.0, 0.0, 1.0), (15.0, -4.0, 1.6), (-8.0, 6.0, 0.4), (35.0, 2.0, 3.0)])
def test_extrinsics_from_floor_put_the_camera_at_its_height(pitch, roll, height):
    up = F.camera_angles_inverse(pitch, roll)
    centre = jnp.array([0.4, 0.3, 4.0])  # a camera-frame point: the person
    E = np.asarray(F.extrinsics_from_floor(up, jnp.asarray(height), centre), np.float64)
    R, t = E[:3, :3], E[:3, 3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(R[:, 2], np.asarray(up), atol=1e-6)  # world z is the fitted up
    eye = -R.T @ t
    assert eye[2] == pytest.approx(height, abs=1e-5)  # the camera at its height above the floor
    # the person's point lies above the world origin, at its own height above the floor
    c_w = R.T @ (np.asarray(centre) - t)
    np.testing.assert_allclose(c_w[:2], 0.0, atol=1e-5)
    assert c_w[2] == pytest.approx(height + float(np.asarray(centre) @ np.asarray(up)), abs=1e-5)
    # the optical axis points along world +y (no sideways component)
    axis_w = R.T @ np.array([0.0, 0.0, 1.0])
    assert abs(axis_w[0]) < 1e-6 and axis_w[1] > 0


def _soles_on_floor(E: np.ndarray, spots: np.ndarray, rng) -> np.ndarray:
    """Per frame, 8 camera-frame sole points of a foot at each floor spot (world x, y): the lowest
    on the floor, the others 1-10 cm above it."""
    T = len(spots)
    pts = np.zeros((T, 8, 3))
    pts[:, :, :2] = spots[:, None, :] + rng.normal(0, 0.05, (T, 8, 2))
    pts[:, 1:, 2] = rng.uniform(0.01, 0.10, (T, 7))
    return pts @ E[:3, :3].T + E[:3, 3]


def test_fit_floor_finds_the_plane_the_feet_span():
    """Feet over 4 x 4 m of floor: the plane is found (to 0.2 degrees, 1 cm) although the body's
    up axes lean 8 degrees and a fifth of the frames are flights 30 cm up."""
    rng = np.random.default_rng(0)
    E = _camera(12.0, -3.0, 1.4)
    T = 120
    spots = np.stack([rng.uniform(-2, 2, T), rng.uniform(3, 7, T)], -1)
    pts = _soles_on_floor(E, spots, rng)
    flight = rng.random(T) < 0.2
    pts[flight] += 0.3 * E[:3, 2]
    up_true = E[:3, 2]
    lean = np.asarray(F.camera_angles_inverse(12.0 + 8.0, -3.0))  # the bodies lean 8 degrees
    up, height, support = F.fit_floor(jnp.asarray(pts), jnp.broadcast_to(jnp.asarray(lean), (T, 3)),
                                      jnp.ones(T, bool))
    assert _up_error_deg(up, up_true) < 0.2
    assert float(height) == pytest.approx(1.4, abs=0.01)
    assert float(support) == pytest.approx(1 - flight.mean(), abs=0.02)


def test_fit_floor_on_one_spot_keeps_the_body_up():
    """A person who stays on one spot gives one floor point: the tilt is the body's up (the
    prior), and the height is the floor's through that point."""
    rng = np.random.default_rng(1)
    E = _camera(5.0, 0.0, 1.2)
    T = 60
    pts = _soles_on_floor(E, np.tile([[0.0, 4.0]], (T, 1)), rng)
    pts[:, :, :] = pts[:1]  # exactly the same point every frame
    body_up = jnp.asarray(np.tile(E[:3, 2], (T, 1)))
    up, height, _ = F.fit_floor(jnp.asarray(pts), body_up, jnp.ones(T, bool))
    assert _up_error_deg(up, E[:3, 2]) < 0.05
    assert float(height) == pytest.approx(1.2, abs=0.005)


def test_padded_and_behind_camera_frames_are_ignored():
    rng = np.random.default_rng(2)
    E = _camera(10.0, 2.0, 1.7)
    T = 80
    spots = np.stack([rng.uniform(-2, 2, T), rng.uniform(3, 7, T)], -1)
    pts = _soles_on_floor(E, spots, rng)
    mask = np.arange(T) < 60
    pts[60:] = rng.normal(0, 10, (20, 8, 3))  # padding holds garbage
    pts[5] = np.nan  # and a non-finite frame
    up, height, _ = F.fit_floor(jnp.asarray(pts), jnp.asarray(np.tile(E[:3, 2], (T, 1))), jnp.asarray(mask))
    assert np.isfinite(np.asarray(up)).all()
    assert _up_error_deg(up, E[:3, 2]) < 0.2 and float(height) == pytest.approx(1.7, abs=0.01)


@pytest.mark.parametrize("index", [0, 3])
def test_floor_from_the_true_pose_is_the_true_camera(index):
    """The ground truth's own poses seen from the clip's camera (TPNet replaced by the truth):
    the camera's tilt to within 1.5 degrees and its height to within 5 cm."""
    clip = generate_clip(5, index, SynthConfig(frames=90))
    model = character(clip.height_m, clip.mass_kg)
    E = np.asarray(clip.extrinsics, np.float32)
    R, t = E[:3, :3], E[:3, 3]
    q = jnp.asarray(clip.gt_q, jnp.float32)
    rot_cam = jnp.einsum("ij,tjk->tik", R, jax.vmap(quat_to_mat)(q[:, 3:7]))
    T = q.shape[0]
    tp = S.TargetPose(q, jnp.zeros((T, 4)), rot_cam, q[:, :3] @ R.T + t, q[:, :3] @ R.T + t, jnp.zeros((T, 25, 3)))
    est = F.floor_from_target(model, tp, jnp.ones(T, bool))
    assert bool(est.usable)
    assert _up_error_deg(est.up, R[:, 2]) < 1.5
    assert float(est.height_m) == pytest.approx(float((-R.T @ t)[2]), abs=0.05)
    # the estimated camera sees the person where the true one does: same camera-frame points
    X_w = np.asarray(clip.gt_keypoints3d[:, 8], np.float64)  # MidHip, true world
    X_c = X_w @ R.T + t
    E_est = np.asarray(est.extrinsics, np.float64)
    X_w_est = (X_c - E_est[:3, 3]) @ E_est[:3, :3]
    # ... and above the estimated floor at about the height they have above the true one
    np.testing.assert_allclose(X_w_est[:, 2], X_w[:, 2], atol=0.1)


def test_move_motion_moves_the_body_rigidly():
    """The moved configuration's keypoints are the rigidly moved keypoints (forward kinematics
    as the reference); forces and the root's world-frame velocity turn with the world, the
    root's own-frame angular velocity and the hinges do not change."""
    model = character()
    rng = np.random.default_rng(3)
    T = 5
    q = np.tile(np.asarray(model.qpos0, np.float64), (T, 1))
    q[:, :3] = rng.normal(0, 1, (T, 3))
    quat = rng.normal(0, 1, (T, 4))
    q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    q[:, 7:] += rng.normal(0, 0.3, (T, model.nq - 7))
    q = jnp.asarray(q, jnp.float32)
    motion = Motion(q=q, qd=jnp.asarray(rng.normal(0, 1, (T, model.nv)), jnp.float32),
                    tau=jnp.asarray(rng.normal(0, 1, (T, model.nv)), jnp.float32),
                    grf=jnp.asarray(rng.normal(0, 100, (T, 4, 3)), jnp.float32),
                    contact_prob=jnp.zeros((T, 4)), target_q=q, mask=jnp.ones(T, bool))
    E_from = _camera(10.0, 3.0, 1.5)
    E_to = np.asarray(Camera.look_at((1.0, -4.0, 1.2), (0.0, 0.0, 0.9), dtype=np.float64).extrinsics)
    R, t = F.change_world(jnp.asarray(E_from, jnp.float32), jnp.asarray(E_to, jnp.float32))
    moved = F.move_motion(motion, R, t)
    kp = jax.vmap(lambda x: P.keypoints(model, x, "body25"))
    want = np.asarray(kp(q)) @ np.asarray(R).T + np.asarray(t)
    np.testing.assert_allclose(np.asarray(kp(moved.q)), want, atol=2e-5)
    # the same points in the camera: E_to X_to == E_from X_from
    X_from = np.asarray(kp(q)).reshape(-1, 3)
    X_to = np.asarray(kp(moved.q)).reshape(-1, 3)
    np.testing.assert_allclose(X_to @ E_to[:3, :3].T + E_to[:3, 3], X_from @ E_from[:3, :3].T + E_from[:3, 3],
                               atol=5e-5)
    np.testing.assert_allclose(moved.grf, np.asarray(motion.grf) @ np.asarray(R).T, atol=1e-4)
    np.testing.assert_allclose(moved.qd[:, :3], np.asarray(motion.qd[:, :3]) @ np.asarray(R).T, atol=1e-5)
    np.testing.assert_allclose(moved.tau[:, :3], np.asarray(motion.tau[:, :3]) @ np.asarray(R).T, atol=1e-5)
    np.testing.assert_array_equal(moved.qd[:, 3:], motion.qd[:, 3:])
    np.testing.assert_array_equal(moved.q[:, 7:], motion.q[:, 7:])


# ---------------------------------------------------------------------------------------
# the shipped TPNet, the batch engine and the evaluation harness
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def shipped():
    from jmocap.weights import default_params

    return default_params("kinematic")


def _demo(name: str, frames: int = 120):
    from jmocap.data.clip import load_clip
    from jmocap.demo import demo_assets

    return load_clip(demo_assets() / "ground_truth" / f"demo_{name}.npz").slice(0, frames)


@pytest.mark.parametrize("name", ["walk", "run", "jump"])
def test_shipped_estimate_on_the_demo_clips(shipped, name):
    """The demo clips' cameras from their keypoints alone: measured 1.9 / 0.6 / 2.8 degrees and
    9 / 5 / 10 cm on 2026-12-05 (the first 120 frames); the thresholds are about twice that."""
    from jmocap.pipeline import FloorEstimator

    clip = _demo(name)
    est = FloorEstimator(*shipped).estimate(clip)
    R, t = clip.extrinsics[:3, :3], clip.extrinsics[:3, 3]
    assert bool(est.usable)
    assert _up_error_deg(est.up, R[:, 2]) < 5.0
    assert float(est.height_m) == pytest.approx(float((-R.T @ t)[2]), abs=0.3)


def test_batch_estimates_the_camera_of_a_clip_without_one(shipped, tmp_path):
    """``jmocap reconstruct``'s engine: a clip without extrinsics gets the estimated camera (the
    result's ``extrinsics_source``, the manifest's ``camera_estimate``), or with
    ``camera="default"`` the default camera, named as assumed; a calibrated clip keeps its own."""
    from jmocap.batch import BatchOptions, reconstruct_archive
    from jmocap.data.clip import save_clip
    from jmocap.pipeline import FloorEstimator
    from jmocap.results import load_result

    walk = _demo("walk", 60)
    src = tmp_path / "in"
    src.mkdir()
    save_clip(src / "bare.npz", walk.replace(extrinsics=None, name="bare"))
    save_clip(src / "calibrated.npz", walk.replace(name="calibrated"))
    params, config = shipped
    want = FloorEstimator(params, config).resolve(walk.replace(extrinsics=None))
    assert want.meta["extrinsics_source"] == "estimated"
    for how in ("estimate", "default"):
        out = tmp_path / how
        reconstruct_archive(src, out, params, config, BatchOptions(batch=2, camera=how), method="kinematic")
        lines = {m["name"]: m for m in map(json.loads, (out / "manifest.jsonl").read_text().splitlines())}
        bare, cal = load_result(out / "bare.npz"), load_result(out / "calibrated.npz")
        assert cal["extrinsics_source"] == lines["calibrated"]["extrinsics_source"] == "input"
        np.testing.assert_allclose(cal["extrinsics"], walk.extrinsics, atol=1e-9)
        if how == "estimate":
            assert bare["extrinsics_source"] == lines["bare"]["extrinsics_source"] == "estimated"
            np.testing.assert_allclose(bare["extrinsics"], want.extrinsics, atol=1e-6)
            assert lines["bare"]["camera_estimate"]["height_m"] == pytest.approx(float(-(want.extrinsics[:3, :3].T
                                                                                       @ want.extrinsics[:3, 3])[2]), abs=1e-3)
            assert "extrinsics" not in bare["assumed"]
        else:
            assert bare["extrinsics_source"] == "default" and "extrinsics" in bare["assumed"]
            np.testing.assert_allclose(bare["extrinsics"], default_extrinsics(), atol=1e-9)


def test_eval_with_a_withheld_camera_scores_in_the_true_world(shipped):
    """TPNet's camera-frame output does not depend on the extrinsics, so the kinematic method
    scores the same with the camera given, estimated or replaced by the default, once its
    estimates are moved into the true world; the harness reports the floor estimate's error."""
    from jmocap.evaluate import EvalConfig, evaluate

    params, config = shipped
    clips = [_demo("walk", 64), _demo("jump", 64)]
    scores = {}
    for how in ("given", "estimate", "default"):
        res = evaluate("demo", params, config, EvalConfig(("kinematic",), 2, progress=False, camera=how), clips=clips)
        scores[how] = res.summary["kinematic"]
        if how == "estimate":
            assert set(res.info["floor"]) == {c.name for c in clips}
            assert all(v["usable"] == 1.0 and v["up_error_deg"] < 5 for v in res.info["floor"].values())
    for how in ("estimate", "default"):
        for key in ("mpjpe_mm", "pa_mpjpe_mm", "root_err_mm", "reproj_input_px"):
            assert scores[how][key] == pytest.approx(scores["given"][key], rel=1e-3, abs=1e-3), (how, key)
    with pytest.raises(ValueError, match="camera must be"):
        evaluate("demo", params, config, EvalConfig(("kinematic",), 2, progress=False, camera="nope"), clips=clips)


def test_padded_length_holds_the_clip_and_pads_by_less_than_half():
    from jmocap.pipeline import padded_length

    assert [padded_length(n) for n in (1, 64, 65, 96, 97, 129, 193, 300, 1000)] == [64, 64, 96, 96, 128, 192, 256, 384, 1024]
    for n in range(1, 3000, 7):
        L = padded_length(n)
        assert L >= n and (n <= 64 or L < 1.5 * n)
