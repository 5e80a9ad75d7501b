"""jmocap.metrics against values computed by hand on small cases (the arithmetic is in the
comments), plus two references: the synthetic data's own contact-labelling rule and the
centre of mass from forward kinematics (for the zero-moment point).

Tolerances: float32 arithmetic on values of order 1 (metres, pixels, percentages): 1e-3 of the
unit reported (mm, px, %) unless a comment says otherwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tests.conftest import mujoco_com

from jmocap import metrics as M
from jmocap.camera import Camera, default_extrinsics

TOL = 1e-3


def close(value, expected, tol=TOL):
    assert np.asarray(value) == pytest.approx(expected, abs=tol), (float(np.asarray(value)), expected)


# ---------------------------------------------------------------------------------------
# pose
# ---------------------------------------------------------------------------------------


def mpjpe_case():
    """2 frames, 2 joints (root = joint 0)."""
    gt = np.array([[[0, 0, 0], [1, 0, 0]]] * 2, np.float32)
    pred = np.array(
        [
            [[0.1, 0, 0], [1.1, 0.3, 0.4]],  # frame 0
            [[0, 0, 2.0], [1, 0, 2.0]],  # frame 1: gt moved up by 2 m
        ],
        np.float32,
    )
    return pred, gt


def test_mpjpe_root_aligned_absolute_and_masked():
    pred, gt = mpjpe_case()
    first = np.array([True, False])
    # frame 0, root-aligned: joint 1 relative (1.0, 0.3, 0.4) vs (1, 0, 0): 0.5 m; root 0 -> 250 mm
    close(M.mpjpe(pred, gt, first), 250.0)
    # frame 0, absolute: root 0.1 m, joint |(0.1, 0.3, 0.4)| = sqrt(0.26) = 0.509902 m
    # -> (100 + 509.902) / 2 = 304.951 mm
    close(M.mpjpe(pred, gt, first, align="none"), 304.951)
    # both frames: root-aligned frame 1 is exact -> (250 + 0) / 2; absolute (304.951 + 2000) / 2
    close(M.mpjpe(pred, gt), 125.0)
    close(M.mpjpe(pred, gt, align="none"), 1152.4755)
    # global root translation error: 100 mm (frame 0), 2000 mm (frame 1)
    close(M.root_translation_error(pred, gt, first), 100.0)
    close(M.root_translation_error(pred, gt), 1050.0)
    # a masked-out frame may hold anything
    pred2 = pred.copy()
    pred2[1] = 1e6
    close(M.mpjpe(pred2, gt, first), 250.0)


def test_pck_and_auc_count_thresholds():
    gt = np.zeros((1, 4, 3), np.float32)
    pred = np.zeros((1, 4, 3), np.float32)
    pred[0, :, 0] = [0.0, 0.052, 0.102, 0.2]  # errors 0, 52, 102, 200 mm (joint 0 = root: no shift)
    # PCK@150: 0, 52, 102 < 150 -> 3 / 4
    close(M.pck(pred, gt), 75.0)
    close(M.pck(pred, gt, threshold_mm=100.0), 50.0)  # 0, 52
    # AUC over 0, 5, ..., 150 (31 thresholds, error < threshold):
    # 0 mm passes 5..150 (30), 52 passes 55..150 (20), 102 passes 105..150 (10), 200 none
    # -> (30 + 20 + 10 + 0) / (31 * 4) = 60 / 124 = 48.387 %
    close(M.auc(pred, gt), 48.3871)
    close(M.auc(pred, gt, align="none"), 48.3871)


def reflection_case():
    """Six points on the axes, +-a, +-b, +-c with a < b < c (centred, principal axes = axes)."""
    a, b, c = 0.1, 0.2, 0.3
    gt = np.array([[a, 0, 0], [-a, 0, 0], [0, b, 0], [0, -b, 0], [0, 0, c], [0, 0, -c]], np.float32)
    return gt


def test_procrustes_undoes_a_similarity_transform():
    gt = reflection_case() + np.array([0.3, -0.1, 0.05], np.float32)
    gt = np.stack([gt, gt[::-1] * 1.5])  # 2 frames
    ang = 0.7
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]], np.float32)
    R = R @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float32)  # a proper rotation
    pred = 0.5 * gt @ R.T + np.array([2.0, 1.0, -1.0], np.float32)
    close(M.pa_mpjpe(pred, gt), 0.0, 1e-3)
    assert float(M.mpjpe(pred, gt)) > 50.0


def test_procrustes_reflected_pose_is_not_a_rotation():
    gt = reflection_case()[None]
    pred = gt * np.array([-1.0, 1.0, 1.0], np.float32)  # mirror image x -> -x, labels kept
    # Umeyama: X^T Y = diag(-2a^2, 2b^2, 2c^2) = U S V^T with U = diag(-1, 1, 1), V = I; the
    # unconstrained R = V U^T is the mirror itself (error 0). det(V U^T) = -1 flips the smallest
    # singular direction (x, a < b < c): R = V diag(-1, 1, 1) U^T = I, and the scale is
    # s = (-2a^2 + 2b^2 + 2c^2) / (2a^2 + 2b^2 + 2c^2) = 0.24 / 0.28 = 6/7.
    # Aligned pred = 6/7 pred. Errors: (+-a, 0, 0): a + 6a/7 = 13a/7; (0, +-b, 0): b/7; (0, 0, +-c): c/7
    # mean = (13a + b + c) / 21 = 1.8 / 21 m = 85.714 mm
    close(M.pa_mpjpe(pred, gt), 85.7143)
    # the same after any similarity transform of the prediction
    close(M.pa_mpjpe(3.0 * pred + 1.0, gt), 85.7143)
    aligned = np.asarray(M.procrustes_align(pred, gt))
    np.testing.assert_allclose(aligned, 6.0 / 7.0 * pred, atol=1e-6)


# ---------------------------------------------------------------------------------------
# sparse-IMU metrics (PIP [002] Sec. 4, Fig. 3): orientations, root frame, travelled distance
# ---------------------------------------------------------------------------------------


def rot(axis: str, deg: float) -> np.ndarray:
    """The rotation by ``deg`` degrees about the world axis ``axis`` ("x", "y" or "z")."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R.astype(np.float32)


def test_sip_and_angular_error_by_hand():
    T = 3
    gt = np.tile(np.eye(3, dtype=np.float32), (T, 4, 1, 1))  # (T, 4, 3, 3)
    # every body turned 90 deg about z in every frame -> 90
    close(M.sip_error(np.tile(rot("z", 90), (T, 4, 1, 1)), gt), 90.0)
    # four bodies at 30 (x), 60 (y), 90 (z), 0 deg -> (30 + 60 + 90 + 0) / 4 = 45
    mix = np.stack([rot("x", 30), rot("y", 60), rot("z", 90), np.eye(3, dtype=np.float32)])
    close(M.sip_error(np.tile(mix, (T, 1, 1, 1)), gt), 45.0)
    # the angle is that of gt^T pred, whatever the truth: the same offsets on a rotated truth
    base = rot("x", 25) @ rot("z", -70)
    close(M.sip_error(np.tile(base @ mix, (T, 1, 1, 1)), np.tile(base, (T, 4, 1, 1))), 45.0)
    # 179 deg: no loss near pi; 0.01 deg: none near 0 (arccos would give ~0.02 in float32)
    close(M.sip_error(np.tile(rot("y", 179), (T, 4, 1, 1)), gt), 179.0)
    close(M.sip_error(np.tile(rot("y", 0.01), (T, 4, 1, 1)), gt), 0.01, 1e-4)
    # a prediction equal to the truth -> 0 (random rotations)
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(T, 4, 3, 3)))
    Q = (Q * np.sign(np.linalg.det(Q))[..., None, None]).astype(np.float32)
    close(M.sip_error(Q, Q), 0.0)
    # angular error: the same over any number of bodies; 6 bodies at 0, 0, 30, 60, 90, 0 -> 30
    six = np.concatenate([np.tile(np.eye(3, dtype=np.float32), (2, 1, 1)), mix], 0)
    close(M.angular_error(np.tile(six, (T, 1, 1, 1)), np.tile(np.eye(3, dtype=np.float32), (T, 6, 1, 1))), 30.0)
    np.testing.assert_allclose(np.asarray(M.orientation_errors(mix[None], gt[:1]))[0], [30, 60, 90, 0], atol=1e-3)


def test_sip_error_root_alignment_and_masks():
    T = 4
    gt_root = np.tile(rot("x", 10), (T, 1, 1))
    gt = np.tile(np.stack([rot("x", 10) @ rot("y", a) for a in (0, 20, 40, 60)]), (T, 1, 1, 1))
    # a global heading error of 40 deg about z turns the root and every body: global SIP = 40,
    # root-aligned 0 (the offset cancels in R_root^T R_b)
    off = rot("z", 40)
    pred, pred_root = off @ gt, off @ gt_root
    close(M.sip_error(pred, gt), 40.0)
    close(M.sip_error(pred, gt, pred_root=pred_root, gt_root=gt_root), 0.0)
    # ... and with a local error on top: body 2 bent 20 deg more about its root's z: in the root
    # frame only that body errs, 20 / 4 = 5 deg
    local = pred.copy()
    local[:, 2] = pred_root @ rot("z", 20) @ np.swapaxes(pred_root, -1, -2) @ pred[:, 2]
    close(M.sip_error(local, gt, pred_root=pred_root, gt_root=gt_root), 5.0)
    # masks: frames 2, 3 missing (garbage there) -> frames 0, 1 only; per-body mask
    bad = np.tile(rot("z", 90), (T, 4, 1, 1))
    bad[2:] = np.nan
    frames = np.array([True, True, False, False])
    close(M.sip_error(bad, np.tile(np.eye(3, dtype=np.float32), (T, 4, 1, 1)), frames), 90.0)
    bodies = np.ones((T, 4), bool)
    bodies[:, 2] = False  # body 2 missing: (0 + 0 + 0) / 3 in the root frame
    close(M.sip_error(local, gt, bodies, pred_root=pred_root, gt_root=gt_root), 0.0)
    assert np.isnan(M.sip_error(local, gt, np.zeros(T, bool)))
    # wrong shapes and arguments
    with pytest.raises(ValueError, match=r"pred_rot must hold the 4 SIP_BODIES"):
        M.sip_error(gt[:, :3], gt[:, :3])
    with pytest.raises(ValueError, match=r"pred_rot must have shape \(\.\.\., T, B, 3, 3\), got \(4, 4, 3\)"):
        M.angular_error(gt[..., 0], gt[..., 0])
    with pytest.raises(ValueError, match="pred_rot and gt_rot must have the same shape"):
        M.angular_error(gt[:, :2], gt)
    with pytest.raises(ValueError, match="must be given together"):
        M.sip_error(pred, gt, pred_root=pred_root)
    with pytest.raises(ValueError, match=r"gt_root must have shape \(\.\.\., T, 3, 3\) = \(4, 3, 3\)"):
        M.sip_error(pred, gt, pred_root=pred_root, gt_root=gt_root[:2])
    with pytest.raises(ValueError, match="mask must have shape"):
        M.sip_error(pred, gt, np.ones(3, bool))


def test_body_rotations_of_the_character():
    """Forward kinematics on the character: every body frame is the world's at the rest pose."""
    import jmocap

    model = jmocap.load_model(with_mjx=False)
    q0 = np.asarray(model.qpos0, np.float32)
    yaw = q0.copy()
    yaw[3:7] = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]  # root turned 90 deg about z
    arm = q0.copy()
    arm[model.mj.jnt_qposadr[model.mj.joint("left_shoulder_x").id]] = 0.5  # 0.5 rad at the shoulder
    q = np.stack([q0, yaw, arm])  # (T = 3, nq)
    R = np.asarray(M.body_rotations(model, q, M.SIP_BODIES))
    assert R.shape == (3, 4, 3, 3)
    np.testing.assert_allclose(R[0], np.tile(np.eye(3), (4, 1, 1)), atol=1e-6)
    np.testing.assert_allclose(R[1], np.tile(rot("z", 90), (4, 1, 1)), atol=1e-6)
    np.testing.assert_allclose(R[2, 2], rot("x", np.degrees(0.5)), atol=1e-6)  # left_shoulder
    rest = np.asarray(M.body_rotations(model, np.stack([q0] * 3), M.SIP_BODIES))
    # per frame: 0; 90 on all four; 0.5 rad = 28.6479 deg on one of four -> (0 + 90 + 7.16197) / 3
    close(M.sip_error(R, rest), (90.0 + np.degrees(0.5) / 4) / 3)
    root = np.asarray(M.body_rotations(model, q, ("pelvis",)))[:, 0]
    root0 = np.asarray(M.body_rotations(model, np.stack([q0] * 3), ("pelvis",)))[:, 0]
    close(M.sip_error(R, rest, pred_root=root, gt_root=root0), np.degrees(0.5) / 4 / 3)
    every = M.body_rotations(model, q[None])  # leading batch dims, every body but the world
    assert every.shape == (1, 3, model.topo.nbody - 1, 3, 3)
    with pytest.raises(ValueError, match=rf"q must have shape \(\.\.\., T, {model.nq}\)"):
        M.body_rotations(model, q[:, :-1])


def test_mpjpe_root_frame_aligns_root_position_and_orientation():
    # gt: root (joint 0) at the origin, joint 1 at (1, 0, 0), root orientation I
    gt = np.array([[[0, 0, 0], [1, 0, 0]]], np.float32)
    eye = np.eye(3, dtype=np.float32)[None]
    # the estimate turned 90 deg about z with its root, and moved: the offset cancels
    pred = np.array([[[5, 5, 0], [5, 6, 0]]], np.float32)
    close(M.mpjpe_root_frame(pred, gt, rot("z", 90)[None], eye), 0.0)
    # root position aligned only (TransPose's "positional error" as its paper words it: mpjpe):
    # joint 1 (0, 1, 0) vs (1, 0, 0): sqrt(2) m, root 0 -> 707.107 mm
    close(M.mpjpe(pred, gt), 707.1068)
    # the same with a root orientation that does not explain the turn
    close(M.mpjpe_root_frame(pred, gt, eye, eye), 707.1068)
    # a real error in the root frame: joint 1 at 1.2 m along its root's y -> 0.2 m / 2 joints
    pred2 = np.array([[[5, 5, 0], [5, 6.2, 0]]], np.float32)
    close(M.mpjpe_root_frame(pred2, gt, rot("z", 90)[None], eye), 100.0)
    # masks: a second frame with garbage, masked out
    two = np.concatenate([pred2, np.full_like(pred2, 1e6)])
    roots = np.concatenate([rot("z", 90)[None], eye])
    close(M.mpjpe_root_frame(two, np.concatenate([gt, gt]), roots, np.concatenate([eye, eye]),
                             np.array([True, False])), 100.0)
    with pytest.raises(ValueError, match=r"pred_root must have shape \(\.\.\., T, 3, 3\) = \(1, 3, 3\)"):
        M.mpjpe_root_frame(pred, gt, eye[0], eye)


def walk(T: int, step: float, drift: float, still: int = 0):
    """A straight walk along x, ``step`` m per frame after ``still`` standing frames; the estimate
    drifts sideways by ``drift`` m every frame (also while standing)."""
    t = np.arange(T)
    gt = np.zeros((T, 3), np.float32)
    gt[:, 0] = step * np.maximum(t - still, 0)
    pred = gt.copy()
    pred[:, 1] = drift * t
    return pred, gt


def test_cumulative_translation_error_on_a_straight_walk():
    # 0.25 m per frame, sideways drift 0.025 m per frame: after d metres (4 d frames) the error is
    # 0.1 d: 0.1, 0.2, 0.3 m at 1, 2, 3 m. The walk is 16 steps = 4 m: 5 m is never reached.
    pred, gt = walk(17, 0.25, 0.025)
    curve = np.asarray(M.cumulative_translation_error(pred, gt, distances=(1.0, 2.0, 3.0, 5.0)))
    np.testing.assert_allclose(curve[:3], [0.1, 0.2, 0.3], atol=1e-5)
    assert np.isnan(curve[3])
    close(M.mean_translation_error(pred, gt, distances=(1.0, 2.0, 3.0, 5.0)), 0.2, 1e-5)  # (0.1+0.2+0.3)/3
    # a global offset of the estimate cancels (each window's start is aligned)
    close(M.cumulative_translation_error(pred + 7.0, gt, distances=(2.0,))[0], 0.2, 1e-5)
    # 0.3 m steps overshoot 1 m (4 steps = 1.2 m, drift 0.12 m): rescaled to 1 m, 0.12 / 1.2 = 0.1
    pred3, gt3 = walk(20, 0.3, 0.03)
    np.testing.assert_allclose(np.asarray(M.cumulative_translation_error(pred3, gt3, distances=(1.0, 3.0))),
                               [0.1, 0.3], atol=1e-5)
    # a prediction equal to the truth -> 0
    close(M.cumulative_translation_error(gt, gt, distances=(1.0,))[0], 0.0)


def test_cumulative_translation_error_standstill_masks_and_shapes():
    # standing for frames 0..2, then 0.25 m per frame to frame 10 (2 m); drift 0.025 m per frame.
    # d = 1 m: starts 0, 1, 2 all end at frame 6 (s = 1.0), errors 0.025 * (6 - i) = 0.15, 0.125,
    # 0.1; starts 3..6 end at 7..10, 0.1 each. PIP's rule keeps the first start of each end:
    # (0.15 + 4 * 0.1) / 5 = 0.11; every start: (0.15 + 0.125 + 0.1 + 0.4) / 7 = 0.110714
    pred, gt = walk(11, 0.25, 0.025, still=2)
    close(M.cumulative_translation_error(pred, gt, distances=(1.0,))[0], 0.11, 1e-5)
    close(M.cumulative_translation_error(pred, gt, distances=(1.0,), distinct_ends=False)[0], 0.110714, 1e-5)
    # mask: frame 8 of the 4 m walk missing (garbage there): 1 m windows (4 frames) avoid it
    # (starts 0..3 and 9..12, still 0.1); every 2 m and 3 m window (8, 12 frames) contains it -> NaN
    pred, gt = walk(17, 0.25, 0.025)
    pred[8] = 1e6
    mask = np.arange(17) != 8
    curve = np.asarray(M.cumulative_translation_error(pred, gt, mask, distances=(1.0, 2.0, 3.0)))
    close(curve[0], 0.1, 1e-5)
    assert np.isnan(curve[1:]).all()
    close(M.mean_translation_error(pred, gt, mask, distances=(1.0, 2.0, 3.0)), 0.1, 1e-5)
    # leading batch dims: two clips, the second drifting twice as fast
    p2, g2 = walk(17, 0.25, 0.05)
    both = np.asarray(M.cumulative_translation_error(np.stack([walk(17, 0.25, 0.025)[0], p2]), np.stack([gt, g2]),
                                                     distances=(1.0, 2.0)))
    np.testing.assert_allclose(both, [[0.1, 0.2], [0.2, 0.4]], atol=1e-5)
    with pytest.raises(ValueError, match=r"pred must have shape \(\.\.\., T, 3\), got \(17, 2\)"):
        M.cumulative_translation_error(pred[:, :2], gt[:, :2])
    with pytest.raises(ValueError, match="pred and gt must have the same shape"):
        M.cumulative_translation_error(pred[:5], gt)
    with pytest.raises(ValueError, match=r"mask must have shape \(\.\.\., T\) = \(17,\)"):
        M.cumulative_translation_error(pred, gt, mask[:5])


# ---------------------------------------------------------------------------------------
# smoothness
# ---------------------------------------------------------------------------------------


def test_e_smooth_and_sigma_smooth():
    gt = np.zeros((5, 1, 3), np.float32)
    pred = np.zeros((5, 1, 3), np.float32)
    gt[:, 0, 0] = [0.0, 0.01, 0.02, 0.03, 0.04]  # Jit_GT = 10, 10, 10, 10 mm
    pred[:, 0, 0] = [0.0, 0.01, 0.03, 0.03, 9.0]  # Jit_X = 10, 20, 0, (huge) mm
    mask = np.array([True, True, True, True, False])
    # |Jit_GT - Jit_X| over the 3 real pairs: 0, 10, 10 -> e = 20/3 = 6.6667 mm
    # sigma = sqrt(((0 - 6.667)^2 + 2 (10 - 6.667)^2) / 3) = sqrt(22.222) = 4.7140 mm
    e, s = M.smoothness_error(pred, gt, mask)
    close(e, 6.6667)
    close(s, 4.7140)
    # masking frame 2 leaves only the pair (0, 1): 0
    e, s = M.smoothness_error(pred, gt, np.array([True, True, False, True, False]))
    close(e, 0.0)
    close(s, 0.0)


def test_jitter_and_acceleration_of_known_polynomials():
    fps = 10.0
    t = np.arange(6) / fps
    c = 500.0
    gt = np.zeros((6, 2, 3), np.float32)
    gt[:, 0, 0] = c * t**3 + t**2  # jerk 6c = 3000 m/s^3; the quadratic adds none
    # third differences of a cubic are exact: 6 c (1/fps)^3 * fps^3 = 3000 m/s^3 = 3 km/s^3 on
    # joint 0, 0 on the static joint 1 -> mean 1.5 km/s^3
    close(M.jitter(gt, fps), 1.5)
    # masking the last frame drops the pair window 2..5 but not the value
    close(M.jitter(gt, fps, np.arange(6) < 5), 1.5)
    # no complete window of 4 real frames -> undefined
    assert np.isnan(M.jitter(gt, fps, np.arange(6) < 3))
    # acceleration: pred = gt + 1/2 alpha t^2 on both joints, alpha = 2 m/s^2:
    # second differences alpha (1/fps)^2 * fps^2 = 2 m/s^2 exactly
    pred = gt.copy()
    pred[..., 1] += (0.5 * 2.0 * t**2)[:, None]
    close(M.acceleration_error(pred, gt, fps), 2.0)


# ---------------------------------------------------------------------------------------
# 2D reprojection
# ---------------------------------------------------------------------------------------


def test_reprojection_in_input_and_virtual_side_view():
    # default camera: at (0, -4, 1) looking along +y; f = 1000 px, principal point (640, 360)
    cam = Camera.from_intrinsics(1000.0, 1000.0, 640.0, 360.0, 1280, 720, default_extrinsics(1.0, 4.0),
                                 dtype=jnp.float32)
    gt = np.array([[[0, 0, 1.0], [0.5, 0, 1.5]]], np.float32)
    pred = gt.copy()
    pred[0, 0, 1] = 0.4  # joint 0 moved 0.4 m along the optical axis: same pixel in the input view
    e, s = M.reprojection_error(pred, gt, cam)
    close(e, 0.0)
    close(s, 0.0)
    # side view: rotated +90 deg about the vertical through the mean gt root (0, 0): the camera
    # centre (0, -4) goes to (4, 0) (counter-clockwise), looking along -x; world +y is now image
    # right at depth 4 m: 1000 px * 0.4 m / 4 m = 100 px on joint 0, 0 on joint 1
    side = M.side_view_camera(cam, gt[0, 0])
    np.testing.assert_allclose(np.asarray(side.position), [4.0, 0.0, 1.0], atol=1e-5)
    e, s = M.reprojection_error(pred, gt, side)
    close(e, 50.0)  # (100 + 0) / 2
    close(s, 50.0)


def test_side_view_scores_only_joints_in_front_of_the_side_camera():
    """``evaluate_arrays``' side view leaves out ground-truth joints nearer than SIDE_VIEW_NEAR_M to
    the side camera (a subject who walks past it): worked by hand on 2 frames of 2 joints."""
    cam = Camera.from_intrinsics(1000.0, 1000.0, 640.0, 360.0, 1280, 720, default_extrinsics(1.0, 4.0),
                                 dtype=jnp.float32)
    # the mean root (joint 0) is (2, 0, 1): the input camera's centre (0, -4), 4.5 m from it, turns
    # +90 deg about it to (6, -2): the side camera looks along -x, a point's depth is 6 - x.
    # Frame 1's joint 1 is at x = 5.8, 0.2 m in front of it: left out. Joint 0 of both frames is
    # 4 m deep; the prediction moves it 0.4 m along y: 100 px. Frame 0's joint 1 (x = 4, 2 m
    # deep) is moved 0.1 m along y: 50 px. The mean is (100 + 50 + 100) / 3.
    gt = np.array([[[2.0, 0, 1.0], [4.0, 0, 1.0]], [[2.0, 0, 1.0], [5.8, 0, 1.0]]], np.float32)
    pred = gt.copy()
    pred[:, 0, 1] += 0.4
    pred[0, 1, 1] += 0.1
    pred[1, 1, 1] += 0.1
    side = M.side_view_camera(cam, gt[0, 0])
    np.testing.assert_allclose(np.asarray(side.position), [6.0, -2.0, 1.0], atol=1e-5)
    out = M.evaluate_arrays({"keypoints3d": pred}, {"keypoints3d": gt}, fps=30.0, camera=cam, root=(0,))
    close(out["reproj_side_px"], 250.0 / 3)


# ---------------------------------------------------------------------------------------
# foot-floor contact
# ---------------------------------------------------------------------------------------


def floor_case():
    """3 frames, 2 foot points: x and z in metres (y = 0)."""
    x = np.array([[0.0, 0.0], [0.03, 0.005], [0.03, 0.005]])
    z = np.array([[0.0, 0.04], [-0.002, 0.035], [-0.05, 0.10]])
    pts = np.stack([x, np.zeros_like(x), z], -1).astype(np.float32)
    contacts = np.array([[1, 1], [1, 1], [0, 0]], np.float32)
    return pts, contacts


def test_floor_metrics_by_hand():
    pts, c = floor_case()
    # MPE: |z| over in-contact pairs: 0, 40, 2, 35 mm -> 77 / 4 = 19.25 mm
    close(M.mean_penetration_error(pts, c), 19.25)
    # PNP (1 mm tolerance): frame 0 ok; frame 1 has -2 mm; frame 2 has -50 mm -> 1/3
    close(M.non_penetration(pts), 33.3333)
    close(M.non_penetration(pts, tolerance=0.005), 66.6667)  # -2 mm tolerated
    # floating: in-contact and z > 3 cm: 0.04, 0.035 of 4 -> 50 %
    close(M.foot_floating(pts, c), 50.0)
    # penetration: z < -3 cm at any time: -0.05 of 6 -> 16.667 %
    close(M.foot_penetration(pts), 16.6667)
    # skate: in contact at t = 1 (both points): point 0 moved |(0.03, 0, -0.002)| = 30.07 mm > 20;
    # point 1 |(0.005, 0, -0.005)| = 7.07 mm -> 1 / 2
    close(M.foot_skate(pts, c), 50.0)
    # mask frame 1 out: MPE (0 + 40) / 2; PNP frames 0, 2 -> 1/2; floating 1/2; penetration 1/4;
    # skate has no pair of real frames in contact -> undefined
    m = np.array([True, False, True])
    close(M.mean_penetration_error(pts, c, m), 20.0)
    close(M.non_penetration(pts, m), 50.0)
    close(M.foot_floating(pts, c, m), 50.0)
    close(M.foot_penetration(pts, m), 25.0)
    assert np.isnan(M.foot_skate(pts, c, m))


def test_contact_labels_match_the_synthetic_rule():
    from jmocap.data.synthetic import contact_labels

    rng = np.random.default_rng(0)
    pts = np.cumsum(rng.normal(scale=0.012, size=(40, 4, 3)), 0)
    pts[..., 2] = np.abs(pts[..., 2]) * 0.5
    ref = contact_labels(pts.astype(np.float64))
    ours = np.asarray(M.contact_labels(pts.astype(np.float32)))
    assert 0 < ref.sum() < ref.size  # both labels occur
    np.testing.assert_array_equal(ours, ref.astype(bool))


# ---------------------------------------------------------------------------------------
# dynamics
# ---------------------------------------------------------------------------------------


def test_grf_mean_max_and_ballistic_with_a_flight_phase():
    w = 98.1  # 10 kg
    grf = np.zeros((5, 2, 3), np.float32)
    grf[0, :, 2] = 49.05  # net 98.1 N = 100 %
    grf[1, 0, 2] = 196.2  # 200 %
    # frame 2: flight, no force (0 %)
    grf[3, 1] = [29.43, 0.0, 39.24]  # |(0.3, 0, 0.4)| w = 0.5 w = 50 %, in flight
    grf[4, 0, 2] = 98.1  # 100 %, in flight
    flight = np.array([False, False, True, True, True])
    close(M.grf_mean(grf, w), 90.0)  # (100 + 200 + 0 + 50 + 100) / 5
    close(M.grf_max(grf, w), 200.0)
    close(M.grf_ballistic(grf, w, flight), 50.0)  # median(0, 50, 100)
    m = np.array([True, True, True, True, False])
    close(M.grf_mean(grf, w, m), 87.5)  # 350 / 4
    close(M.grf_ballistic(grf, w, flight, m), 25.0)  # median(0, 50)
    close(M.grf_max(grf, w, np.array([True, False, True, True, True])), 100.0)
    assert np.isnan(M.grf_ballistic(grf, w, np.zeros(5, bool)))  # no flight: undefined


def test_root_residual_grf_error_and_torque_error():
    tau = np.zeros((2, 8), np.float32)
    tau[0, :3] = [3, 4, 0]  # 5 N over 10 N = 50 %
    tau[1, :3] = [0, 0, 1]  # 10 %
    close(M.root_residual(tau, 10.0), 30.0)
    # net GRF over each model's weight: (0, 0, 100) / 100 = (0, 0, 1.0) vs (10, 0, 60) / 50 =
    # (0.2, 0, 1.2): |(-0.2, 0, -0.2)| = 0.28284 -> 28.284 %
    grf = np.array([[[0, 0, 50], [0, 0, 50]]], np.float32)
    gt_grf = np.array([[[10, 0, 60], [0, 0, 0]]], np.float32)
    close(M.grf_error(grf, gt_grf, 100.0, 50.0), 28.2843)
    # torques per kg on the hinge dofs (6:): (2, -4) / 2 = (1, -2) vs (3, 0) / 3 = (1, 0) -> mean(0, 2)
    t = np.zeros((1, 8), np.float32)
    t[0, 6:] = [2, -4]
    t_gt = np.zeros((1, 8), np.float32)
    t_gt[0, :6] = 99.0  # the root entries do not count
    t_gt[0, 6:] = [3, 0]
    close(M.torque_error(t, t_gt, 2.0, 3.0), 1.0)


def test_foot_grf_correlation_by_hand():
    # left foot (points 0, 1) and right (2, 3); only the vertical components count
    gt = np.zeros((4, 4, 3), np.float32)
    gt[:, 0, 2] = [0, 1, 2, 3]  # left heel: the true left foot rises 0, 1, 2, 3
    gt[:, 3, 2] = [3, 2, 1, 0]  # right toe: falls
    gt[:, :, 0] = 50.0  # horizontal forces are ignored
    est = np.zeros_like(gt)
    est[:, 1, 2] = [0, 2, 4, 6]  # the left foot on its toe, twice as strong: r = +1
    est[:, 2, 2] = [0, 1, 2, 3]  # the right foot backwards: r = -1
    close(M.foot_grf_correlation(est, gt), 0.0)  # mean(+1, -1)
    est[:, 2, 2] = [3, 1, 1, 0]  # x = (1.75, -0.25, -0.25, -1.25), y = (1.5, .5, -.5, -1.5): r = 4.5 / sqrt(4.75 * 5)
    close(M.foot_grf_correlation(est, gt), 0.5 * (1.0 + 4.5 / np.sqrt(4.75 * 5.0)))
    # a constant foot has no correlation: the mean is over the other foot
    est[:, 2, 2] = 7.0
    close(M.foot_grf_correlation(est, gt), 1.0)
    # both constant (L = R = a constant): undefined
    assert np.isnan(M.foot_grf_correlation(np.ones_like(gt), gt))
    # the mask drops frames: on frames 0-2 the right estimate (3, 1, 1) vs truth (3, 2, 1):
    # x = (4/3, -2/3, -2/3), y = (1, 0, -1): r = 2 / sqrt(8/3 * 2)
    est[:, 2, 2] = [3, 1, 1, 99]
    close(M.foot_grf_correlation(est, gt, np.array([True, True, True, False])), 0.5 * (1.0 + 2.0 / np.sqrt(16 / 3)))


def test_support_polygon_distance_inside_outside():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    on = np.ones(4, bool)

    def d(p, active=on, v=sq):
        return float(M.support_polygon_distance(np.asarray(p, np.float32), v, active))

    close(d([0.5, 0.5]), 0.0)  # inside
    close(d([1.0, 0.5]), 0.0)  # on an edge
    close(d([0.5, 1.5]), 0.5)  # above the top edge
    close(d([2.0, 2.0]), np.sqrt(2.0))  # nearest is the corner (1, 1)
    close(d([0.5, 0.5], v=sq[[0, 2, 1, 3]]), 0.0)  # vertex order does not matter
    one_foot = np.array([True, True, False, False])  # the segment (0, 0)-(1, 0)
    close(d([0.5, 0.5], one_foot), 0.5)
    close(d([-1.0, 0.0], one_foot), 1.0)
    close(d([0.5, 0.5], np.array([False, False, True, False])), np.sqrt(0.5))  # the point (1, 1)
    assert np.isnan(d([0.5, 0.5], np.zeros(4, bool)))
    # 3D vertices: z is ignored; batched over frames
    v3 = np.concatenate([sq, np.full((4, 1), 0.02, np.float32)], -1)
    out = M.support_polygon_distance(np.array([[0.5, 0.5], [0.5, 1.5]], np.float32), np.stack([v3, v3]),
                                     np.ones((2, 4), bool))
    np.testing.assert_allclose(np.asarray(out), [0.0, 0.5], atol=1e-6)


def test_zmp_distance_frame_selection():
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    support = np.broadcast_to(sq, (4, 4, 3))
    zmp = np.array([[9, 9], [0.5, 1.5], [2, 2], [9, 9]], np.float32)  # edge frames: not central
    fz = np.full(4, 100.0, np.float32)
    c = np.ones((4, 4), bool)
    # frames 1 and 2 count: (0.5 + sqrt 2) / 2 = 0.95711 m
    close(M.zmp_distance(zmp, fz, 100.0, support, c), 0.957107)
    fz2 = fz.copy()
    fz2[2] = 5.0  # 5 % of the body weight: the ZMP is undefined there
    close(M.zmp_distance(zmp, fz2, 100.0, support, c), 0.5)
    c2 = c.copy()
    c2[1] = False  # no support: not counted
    close(M.zmp_distance(zmp, fz, 100.0, support, c2), np.sqrt(2.0))


def test_zmp_from_wrench_static_and_cart_table():
    # static: f = (0, 0, 100) through the COM c = (1.1, 1.8, 0.9); moment about o = (1, 2, 1):
    # n = (c - o) x f = (0.1, -0.2, -0.1) x (0, 0, 100) = (-20, -10, 0)
    # p_x = 1 - (-10 + 1 * 0) / 100 = 1.1, p_y = 2 + (-20 - 1 * 0) / 100 = 1.8 (the COM)
    p = M.zmp_from_wrench(jnp.array([0, 0, 100.0]), jnp.array([-20.0, -10.0, 0.0]), jnp.array([1.0, 2.0, 1.0]))
    np.testing.assert_allclose(np.asarray(p), [1.1, 1.8], atol=1e-6)
    # cart-table: m = 10, a = 2 m/s^2 forward, g = 10: f = (20, 0, 100) through c = o = (0, 0, 1):
    # p_x = 0 - (0 + 1 * 20) / 100 = -0.2 = c_x - c_z a / g
    p = M.zmp_from_wrench(jnp.array([20.0, 0, 100.0]), jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(np.asarray(p), [-0.2, 0.0], atol=1e-6)


def test_zero_moment_point_of_the_humanoid_against_its_centre_of_mass():
    """Reference: the centre of mass c from MuJoCo C (``subtree_com`` of the world). Standing
    still, the ZMP is c's floor projection; accelerating forward rigidly by a, it is
    c_x - c_z a / g (cart-table)."""
    import jmocap

    model = jmocap.load_model(with_mjx=False)
    fps, a = 30.0, 2.0
    t = np.arange(5) / fps
    q = np.tile(model.keyframe("stand"), (5, 1))
    q[:, 0] += 0.5 * a * t**2
    c = mujoco_com(model.mj, q)
    mass = model.total_mass
    zmp, force = jax.jit(M.zero_moment_point)(model, q.astype(np.float32), fps)
    # interior frames (central differences are exact for the quadratic): 1e-3 m, float32 differences
    np.testing.assert_allclose(np.asarray(zmp)[1:4, 0], c[1:4, 0] - c[1:4, 2] * a / 9.81, atol=1e-3)
    np.testing.assert_allclose(np.asarray(zmp)[1:4, 1], c[1:4, 1], atol=1e-3)
    np.testing.assert_allclose(np.asarray(force)[2], [mass * a, 0.0, mass * 9.81], rtol=1e-3, atol=1e-2)
    # standing still: the ZMP is under the centre of mass
    zmp0, _ = jax.jit(M.zero_moment_point)(model, np.tile(q[:1], (5, 1)).astype(np.float32), fps)
    np.testing.assert_allclose(np.asarray(zmp0)[2], c[0, :2], atol=1e-3)


# ---------------------------------------------------------------------------------------
# contact classification
# ---------------------------------------------------------------------------------------


def test_contact_classification_counts():
    prob = np.array([[0.9, 0.2, 0.6, 0.4], [0.1, 0.8, 0.7, 0.9]], np.float32)
    gt = np.array([[1, 0, 0, 1], [0, 1, 1, 0]], np.float32)
    # frame 0: pred 1 0 1 0 vs 1 0 0 1 -> TP 1, TN 1, FP 1, FN 1
    # frame 1: pred 0 1 1 1 vs 0 1 1 0 -> TP 2, TN 1, FP 1
    # TP 3, TN 2, FP 2, FN 1: acc 5/8, precision 3/5, recall 3/4, F1 6 / (6 + 2 + 1)
    r = M.contact_classification(prob, gt)
    close(r["accuracy"], 62.5)
    close(r["precision"], 60.0)
    close(r["recall"], 75.0)
    close(r["f1"], 66.6667)
    close(r["balanced_accuracy"], 62.5)  # (recall 3/4 + specificity 2/4) / 2
    # frame 1 alone: acc 3/4, precision 2/3, recall 2/2, F1 4/5
    r = M.contact_classification(prob, gt, np.array([False, True]))
    close(r["accuracy"], 75.0)
    close(r["precision"], 66.6667)
    close(r["recall"], 100.0)
    close(r["f1"], 80.0)
    close(r["balanced_accuracy"], 75.0)  # (2/2 + 1/2) / 2
    # nothing predicted in contact: precision undefined
    assert np.isnan(M.contact_classification(np.zeros((1, 4)), gt[:1])["precision"])


# ---------------------------------------------------------------------------------------
# conventions: errors, jit, vmap, the flat evaluation
# ---------------------------------------------------------------------------------------


def test_bad_input_names_the_argument_and_shape():
    pred, gt = mpjpe_case()
    with pytest.raises(ValueError, match=r"pred must have shape \(\.\.\., T, J, 3\), got \(2, 2, 2\)"):
        M.mpjpe(pred[..., :2], gt)
    with pytest.raises(ValueError, match="pred and gt must have the same shape"):
        M.mpjpe(pred[:, :1], gt)
    with pytest.raises(ValueError, match=r"mask must have shape \(\.\.\., T\) = \(2,\), got \(3,\)"):
        M.mpjpe(pred, gt, np.ones(3, bool))
    with pytest.raises(ValueError, match="align must be one of"):
        M.mpjpe(pred, gt, align="bogus")
    with pytest.raises(ValueError, match="contacts must have shape"):
        M.foot_floating(*floor_case()[:1], np.ones((3, 3)))


def test_metrics_jit_and_vmap_over_clips():
    pred, gt = mpjpe_case()
    masks = np.array([[True, False], [True, True]])
    batched = jax.jit(jax.vmap(lambda m: M.mpjpe(pred, gt, m)))(masks)
    np.testing.assert_allclose(np.asarray(batched), [250.0, 125.0], atol=TOL)
    # leading batch dims directly, with per-clip fps
    g = np.zeros((6, 1, 3), np.float32)
    g[:, 0, 0] = 500.0 * (np.arange(6) / 10.0) ** 3
    both = np.stack([g, 2 * g])
    out = jax.jit(M.jitter)(both, jnp.array([10.0, 10.0]))
    np.testing.assert_allclose(np.asarray(out), [3.0, 6.0], rtol=1e-4)
    # the sparse-IMU metrics: vmapped over clips inside jit
    R = np.stack([np.tile(rot("z", 90), (2, 4, 1, 1)), np.tile(rot("z", 30), (2, 4, 1, 1))])
    eye = np.tile(np.eye(3, dtype=np.float32), (2, 2, 4, 1, 1))
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(M.sip_error))(R, eye)), [90.0, 30.0], atol=TOL)
    walks = [walk(17, 0.25, c) for c in (0.025, 0.05)]
    curves = jax.jit(jax.vmap(lambda p, g: M.cumulative_translation_error(p, g, distances=(1.0, 2.0))))(
        np.stack([w[0] for w in walks]), np.stack([w[1] for w in walks]))
    np.testing.assert_allclose(np.asarray(curves), [[0.1, 0.2], [0.2, 0.4]], atol=1e-5)


def test_evaluate_arrays_keys_follow_the_inputs_and_are_never_nan():
    pred, gt = mpjpe_case()
    r = M.evaluate_arrays({"keypoints3d": pred}, {"keypoints3d": gt}, fps=30.0, mask=np.array([True, False]))
    assert r["mpjpe_mm"] == pytest.approx(250.0, abs=TOL)
    assert "jitter_km_s3" not in r  # fewer than 4 real frames: undefined, absent
    assert "grf_mean_pct_bw" not in r and "reproj_input_px" not in r  # no forces, no camera
    assert all(np.isfinite(v) for v in r.values())
    # forces: ballistic only with a flight frame
    grf = np.zeros((2, 4, 3), np.float32)
    grf[:, 0, 2] = 98.1
    contacts = np.array([[1, 0, 0, 0], [1, 0, 0, 0]], np.float32)
    r = M.evaluate_arrays({"grf": grf}, {"contacts": contacts}, fps=30.0, pred_mass=10.0)
    assert r == {"grf_mean_pct_bw": pytest.approx(100.0, abs=TOL), "grf_max_pct_bw": pytest.approx(100.0, abs=TOL)}
    contacts[1] = 0
    r = M.evaluate_arrays({"grf": grf}, {"contacts": contacts}, fps=30.0, pred_mass=10.0)
    assert r["grf_ballistic_pct_bw"] == pytest.approx(100.0, abs=TOL)
    # a ground-truth flight held up by the ground truth's own root residual is not ballistic:
    # gt tau[:3] of 0.5 % BW (10 kg: 0.4905 N) keeps the frame, 2 % BW removes it (then no
    # flight frame is left and the metric is undefined)
    for residual_n, kept in ((0.4905, True), (1.962, False)):
        gt_tau = np.zeros((2, 47), np.float32)
        gt_tau[1, 2] = residual_n
        r = M.evaluate_arrays({"grf": grf}, {"contacts": contacts, "tau": gt_tau}, fps=30.0,
                              pred_mass=10.0, gt_mass=10.0)
        assert ("grf_ballistic_pct_bw" in r) == kept
    # ... and the net GRF error is scored only on the frames the ground truth's contact forces
    # explain: frame 1's estimate is 100 % BW off the truth; with a 2 % BW ground-truth residual
    # there only frame 0 (error 0) counts
    gt_grf = grf.copy()
    gt_grf[1] = 0.0
    for residual_n, err in ((0.4905, 50.0), (1.962, 0.0)):
        gt_tau = np.zeros((2, 47), np.float32)
        gt_tau[1, 2] = residual_n
        r = M.evaluate_arrays({"grf": grf}, {"grf": gt_grf, "tau": gt_tau}, fps=30.0, pred_mass=10.0, gt_mass=10.0)
        assert r["grf_err_pct_bw"] == pytest.approx(err, abs=TOL)
    bad = pred.copy()
    bad[1, 1, 2] = np.nan
    with pytest.raises(ValueError, match="pred 'keypoints3d' has non-finite values, first at frame 1"):
        M.evaluate_arrays({"keypoints3d": bad}, {"keypoints3d": gt}, fps=30.0)
    # ... unless that frame is padding
    assert "mpjpe_mm" in M.evaluate_arrays({"keypoints3d": bad}, {"keypoints3d": gt}, fps=30.0,
                                           mask=np.array([True, False]))


def test_friction_cone_violation_hand_worked():
    """Interior frames only; pulling, outside mu = 0.8, and small (flight) forces by hand."""
    from jmocap.metrics import friction_cone_violation

    f = np.array([[0, 0, 700.0], [0, 0, 700], [500, 0, 700], [600, 0, 700], [0, 0, -300], [1, 1, 5],
                  [0, 0, 700], [0, 0, 700]])
    # frames 1-6 count: 500/700 = 0.71 inside; 600/700 = 0.86 outside; -300 pulls; 5 N is flight
    np.testing.assert_allclose(float(friction_cone_violation(f, 700.0)), 100 * 2 / 6, rtol=1e-6)
    mask = np.ones(8, bool)
    mask[3] = False  # frames 2-4 lose their central difference: 1, 5, 6 remain, all admissible
    np.testing.assert_allclose(float(friction_cone_violation(f, 700.0, mask)), 0.0, atol=1e-6)
