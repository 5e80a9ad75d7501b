"""Cameras and 2D keypoints of the synthetic clips (``jmocap.data.synthetic.cameras`` and
``jmocap.data.synthetic.keypoints``).

References: a homogeneous ``K [R t]`` numpy pinhole, a numpy look-at and a hand-worked
camera, the configured probabilities and noise levels of :class:`Corruption` (statistical
bounds).

Tolerances: projections 1e-3 px for stored clips (float32 storage of 3D points ~1e-7 m at
<= 8 m gives ~1e-4 px), 1e-9 px for float64 inputs; look-at 1e-14 (float64 rounding: the
package camera is called in float64 whatever the JAX setting); corruption statistics are
fixed-seed checks of 400 frames x 25 joints with generous bounds.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jmocap.data import synthetic as S
from jmocap.layouts import get_layout


def _pinhole(K, E, X):
    Km = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1.0]])
    P = Km @ E[:3, :]
    Xh = np.concatenate([X, np.ones(X.shape[:-1] + (1,))], axis=-1)
    x = Xh @ P.T
    return x[..., :2] / x[..., 2:3]


def test_clean_keypoints_are_projections():
    clip = S.generate_clip(4, 0, S.SynthConfig(frames=30, kinds=("stand",), layout="coco17",
                                               corruption=S.Corruption.none()))
    uv = _pinhole(clip.intrinsics, clip.extrinsics, clip.gt_keypoints3d.astype(np.float64))
    np.testing.assert_allclose(clip.keypoints[..., :2], uv, atol=1e-3, rtol=1e-6)
    assert np.all(clip.keypoints[..., 2] == 1.0)
    np.testing.assert_allclose(S.clean_keypoints2d(clip), uv, atol=1e-6)
    # camera: OpenCV axes, in front, upright, within the configured ranges
    E = clip.extrinsics
    cam = -E[:3, :3].T @ E[:3, 3]
    assert 0.3 <= cam[2] <= 2.0
    fx = clip.intrinsics[0]
    assert fx <= 2000.0
    assert tuple(clip.image_size) in S.CameraConfig().image_sizes
    Xc = clip.gt_keypoints3d.astype(np.float64) @ E[:3, :3].T + E[:3, 3]
    assert Xc[..., 2].min() > 1.0
    head, feet = clip.keypoints[:, 0, 1], clip.keypoints[:, 15:17, 1].mean(axis=1)
    assert np.all(head < feet)  # image y grows downwards: head above the ankles


def _look_at_reference(eye, target, up=(0.0, 0.0, 1.0)):
    """Rows of R: image right = forward x up, image down = forward x right, forward."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, -R @ eye
    return E


def test_look_at_hand_worked():
    # at (0, -4, 1) looking along world +y: image right = world +x, image down = world -z
    E = S.look_at_extrinsics([0.0, -4.0, 1.0], [0.0, 0.0, 1.0])
    ref = np.array([[1.0, 0, 0, 0], [0, 0, -1, 1], [0, 1, 0, 4], [0, 0, 0, 1]])
    np.testing.assert_allclose(E, ref, atol=1e-15)


@pytest.mark.parametrize("x64", [False, True])
def test_look_at_is_float64_whatever_the_jax_setting(x64):
    """The package camera runs in float64 for the generator even with x64 off (float32 would
    be ~1e-7 off)."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", x64)
    try:
        eye, target = np.array([4.0, -2.0, 1.3]), np.array([0.2, 0.5, 0.9])
        E = S.look_at_extrinsics(eye, target)
    finally:
        jax.config.update("jax_enable_x64", old)
    assert isinstance(E, np.ndarray) and E.dtype == np.float64 and E.flags.writeable
    np.testing.assert_allclose(E, _look_at_reference(eye, target), rtol=0, atol=1e-14)
    np.testing.assert_allclose(-E[:3, :3].T @ E[:3, 3], eye, atol=1e-14)  # camera centre
    uv, z = S.project_points([1000.0, 1000.0, 640.0, 360.0], E, target)
    np.testing.assert_allclose(uv, [640.0, 360.0], atol=1e-9)  # the target is on the axis
    assert z > 0


def test_project_points_is_the_pinhole():
    rng = np.random.default_rng(0)
    E = S.look_at_extrinsics([3.0, -4.0, 1.5], [0.2, 0.1, 0.9])
    K = np.array([1200.0, 1180.0, 950.0, 530.0])
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (7, 25, 3))
    uv, z = S.project_points(K, E, X)
    assert uv.shape == (7, 25, 2) and z.shape == (7, 25)
    np.testing.assert_allclose(uv, _pinhole(K, E, X), atol=1e-9)
    np.testing.assert_allclose(z, X @ E[2, :3] + E[2, 3], atol=1e-12)


def test_sample_camera_keeps_the_subject_in_view():
    rng = np.random.default_rng(3)
    cfg = S.CameraConfig()
    T, J = 60, 25
    pts = np.zeros((T, J, 3))
    pts[..., 0] = np.linspace(0, 3, T)[:, None] + rng.uniform(-0.2, 0.2, (T, J))  # walks 3 m
    pts[..., 1] = rng.uniform(-0.2, 0.2, (T, J))
    pts[..., 2] = rng.uniform(0.0, 1.8, (T, J))
    for _ in range(5):
        K, size, E, info = S.sample_camera(rng, pts, cfg)
        uv, z = _pinhole(K, E, pts), (pts @ E[:3, :3].T + E[:3, 3])[..., 2]
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < size[0]) & (uv[..., 1] >= 0) & (uv[..., 1] < size[1])
        assert inside.mean() >= cfg.min_visible
        assert z.min() >= cfg.min_depth_m
        assert tuple(size) in cfg.image_sizes
        cam = -E[:3, :3].T @ E[:3, 3]
        assert cfg.height_m[0] <= cam[2] <= cfg.height_m[1]
        np.testing.assert_allclose(E[:3, :3] @ E[:3, :3].T, np.eye(3), atol=1e-12)
        assert E[1, 2] < 0  # camera y (image down) points to world -z: upright image


def _corrupted(corruption, T=400, seed=0):
    rng = np.random.default_rng(seed)
    lay = get_layout("body25")
    uv = np.stack([rng.uniform(400, 600, (T, lay.num_joints)),
                   np.linspace(100, 900, lay.num_joints)[None].repeat(T, 0)], axis=-1)
    kp, stats = S.corrupt_keypoints(rng, uv, lay, (1000, 1000), corruption)
    return uv, kp, stats


def test_corruption_drop_fraction():
    for p in (0.05, 0.2):
        c = S.Corruption(noise_px=0, noise_rel=0, outlier_prob=0, swap_prob=0, drop_prob=p,
                         drop_outside=False)
        uv, kp, stats = _corrupted(c)
        frac = float(np.mean(kp[..., 2] == 0))
        assert abs(frac - p) < 0.35 * p + 0.01, (p, frac)
        ok = kp[..., 2] > 0
        np.testing.assert_allclose(kp[..., :2][ok], uv[ok], atol=1e-3)  # no noise
        assert np.all(kp[..., :2][~ok] == 0)


def test_corruption_noise_outliers_swaps_confidence():
    c = S.Corruption(noise_px=3.0, noise_rel=0.0, joint_scale=1.0, noise_corr=0.0, outlier_prob=0,
                     drop_prob=0, swap_prob=0, drop_outside=False)
    uv, kp, _ = _corrupted(c)
    err = kp[..., :2] - uv
    assert abs(err.std() - 3.0) < 0.3
    assert np.all((kp[..., 2] > 0.4) & (kp[..., 2] <= 1.0))
    # outliers: large jumps, lower confidence
    c = S.Corruption(noise_px=0, noise_rel=0, outlier_prob=0.05, drop_prob=0, swap_prob=0,
                     drop_outside=False)
    uv, kp, stats = _corrupted(c)
    moved = np.linalg.norm(kp[..., :2] - uv, axis=-1) > 1.0
    assert abs(moved.mean() - 0.05) < 0.02
    assert kp[..., 2][moved].max() <= 0.5 < kp[..., 2][~moved].min()
    # swaps exchange left/right joints
    c = S.Corruption(noise_px=0, noise_rel=0, outlier_prob=0, drop_prob=0, swap_prob=0.05,
                     drop_outside=False)
    uv, kp, stats = _corrupted(c)
    assert stats["swap_events"] > 0
    lay = get_layout("body25")
    swapped = 0
    for a, b in lay.flip_pairs:
        s = np.all(np.abs(kp[:, a, :2] - uv[:, b]) < 1e-3, axis=-1) & np.any(np.abs(uv[:, a] - uv[:, b]) > 1, axis=-1)
        swapped += int(s.sum())
    assert swapped > 0
    # none: exact
    uv, kp, _ = _corrupted(S.Corruption.none())
    np.testing.assert_allclose(kp[..., :2], uv, atol=1e-3)
    assert np.all(kp[..., 2] == 1)


def test_extended_cameras_focal_roll_and_pitch():
    """CameraConfig.extended(): the focal length in 35 mm-equivalent millimetres of the image's
    long side, the roll about the optical axis read back from the extrinsics (the image of the
    world's up direction), cameras within 2-10 m and 0.3-3 m high, the subject in view."""
    rng = np.random.default_rng(4)
    cfg = S.CameraConfig.extended()
    T, J = 60, 25
    pts = np.zeros((T, J, 3))
    pts[..., 0] = np.linspace(0, 2, T)[:, None] + rng.uniform(-0.2, 0.2, (T, J))
    pts[..., 1] = rng.uniform(-0.2, 0.2, (T, J))
    pts[..., 2] = rng.uniform(0.0, 1.8, (T, J))
    rolls, pitches = [], []
    for _ in range(12):
        K, size, E, info = S.sample_camera(rng, pts, cfg)
        uv = _pinhole(K, E, pts)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < size[0]) & (uv[..., 1] >= 0) & (uv[..., 1] < size[1])
        assert inside.mean() >= cfg.min_visible
        if not info.get("focal_shrunk"):
            f_mm = K[0] * 36.0 / max(size)
            assert 13.0 - 1e-9 <= f_mm <= 120.0 + 1e-9
        cam = -E[:3, :3].T @ E[:3, 3]
        assert 0.3 <= cam[2] <= 3.0
        up = E[:3, :3] @ np.array([0.0, 0.0, 1.0])  # world up in camera axes (image y is down)
        roll = np.degrees(np.arctan2(up[0], -up[1]))
        assert abs(roll) <= 5.0 + 1e-9
        np.testing.assert_allclose(roll, info["roll_deg"], atol=1e-9)
        rolls.append(abs(roll))
        pitches.append(np.degrees(np.arcsin(np.clip(-(E[2, :3] @ np.array([0, 0, 1.0])), -1, 1))))
    assert max(rolls) > 1.0  # rolled at all
    assert max(np.abs(pitches)) > 10.0  # some cameras look up or down at the subject


def test_occlusion_bursts_hide_one_limb_or_side():
    lay = get_layout("body25")
    groups = S.keypoints._limb_groups(lay)
    assert [lay.joints[i] for i in groups[("left", "arm")]] == ["LShoulder", "LElbow", "LWrist"]
    assert [lay.joints[i] for i in groups[("right", "leg")]] == ["RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel"]
    c = S.Corruption(noise_px=0, noise_rel=0, outlier_prob=0, drop_prob=0, swap_prob=0, drop_outside=False,
                     occlusion_prob=0.02, occlusion_burst=10.0, occlusion_drop=0.5)
    uv, kp, stats = _corrupted(c, T=2000)
    assert stats["occlusion_events"] > 10
    hidden = (kp[..., 2] < 0.45)  # dropped (0) or guessed (conf_occluded <= 0.4); clean >= 0.75
    limb = sorted(i for g in groups.values() for i in g)
    others = [j for j in range(lay.num_joints) if j not in limb]
    assert not hidden[:, others].any()  # the face, neck and hips are never occluded
    assert abs(hidden.mean() - stats["occluded"]) < 1e-12
    dropped = kp[..., 2] == 0
    assert 0.4 < dropped.sum() / hidden.sum() < 0.6  # occlusion_drop
    guessed = hidden & ~dropped
    moved = np.linalg.norm(kp[..., :2] - uv, axis=-1)
    assert np.all(moved[~hidden] < 1e-3) and np.median(moved[guessed]) > 1.0
    # every hidden frame hides whole groups: a limb's joints are hidden together
    for g in groups.values():
        h = hidden[:, g]
        assert np.all(h.all(axis=1) | ~h.any(axis=1))
    # off by default, and the default corruption's draws are unchanged by the option
    _, kp0, st0 = _corrupted(S.Corruption())
    assert "occlusion_events" not in st0
