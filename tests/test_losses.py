"""Tests of jmocap.losses against hand-worked values and numpy re-derivations of the paper's
equations (Neural PhysCap, Shimada et al. 2021, eqs. 8-12 and 17-25; /work/shared/papers/000).

jmocap's documented departures from the paper (module docstring): every loss is a mean over
frames (and over joints / points where the docstring says so) with an optional frame mask,
instead of a plain sum, and forces / torques are divided by the body weight.  The numpy
references below implement the paper's equation per frame and then apply exactly those
documented normalisations, so a change of either is caught.

Tolerance: REF_TOL 1e-12 relative (float64; the same sums in a different order).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jmocap import losses

REF_TOL = 1e-12

pytestmark = pytest.mark.usefixtures("enable_x64")


def f(x):
    return float(np.asarray(x))


# ----------------------------------------------------------------------------- masked_mean


def test_masked_mean_hand_values():
    x = np.array([[1.0, 3.0], [10.0, 20.0], [100.0, 300.0]])
    assert f(losses.masked_mean(x)) == pytest.approx(434.0 / 6, rel=REF_TOL)
    # frames 0 and 2: (1 + 3 + 100 + 300) / 4
    assert f(losses.masked_mean(x, np.array([True, False, True]))) == pytest.approx(101.0, rel=REF_TOL)
    # the mask broadcasts over trailing axes; a float mask weighs frames
    x3 = np.arange(12.0).reshape(3, 2, 2)
    assert f(losses.masked_mean(x3, np.array([0.0, 1.0, 0.0]))) == pytest.approx(5.5, rel=REF_TOL)
    # no valid frame: 0, not NaN
    assert f(losses.masked_mean(x, np.zeros(3, bool))) == 0.0


# ----------------------------------------------------------------------------- TPNet (17-24)


def test_loss_3d_eq18():
    # two frames, two joints; offsets (3, 4, 0) -> 25 and (0, 0, 1) -> 1
    gt = np.zeros((2, 2, 3))
    pred = np.array([[[3.0, 4, 0], [0, 0, 1]], [[0, 0, 2], [1, 2, 2]]])
    # per frame sum over joints: 26, 4 + 9 = 13; jmocap's mean over frames and joints: 39 / 4
    assert f(losses.loss_3d(pred, gt)) == pytest.approx(39.0 / 4, rel=REF_TOL)
    assert f(losses.loss_3d(pred, gt, mask=np.array([True, False]))) == pytest.approx(13.0, rel=REF_TOL)
    # weight switches joint 0 off (missing ground truth); the mean still counts it
    w = np.array([0.0, 1.0])
    assert f(losses.loss_3d(pred, gt, weight=w)) == pytest.approx((1 + 9) / 4, rel=REF_TOL)


def test_loss_2d_eq19():
    size = np.array([1000.0, 500.0])
    gt = np.zeros((1, 3, 2))
    pred = np.array([[[100.0, 50.0], [0.0, 0.0], [5000.0, -250.0]]])
    # normalised errors (0.1, 0.1) -> 0.02; 0; (5 clipped to 2, -0.5) -> 4.25
    assert f(losses.loss_2d(pred, gt, size)) == pytest.approx((0.02 + 0 + 4.25) / 3, rel=REF_TOL)
    conf = np.array([[0.5, 1.0, 0.0]])  # confidence weighs joints; 0 = missing
    assert f(losses.loss_2d(pred, gt, size, conf)) == pytest.approx(0.01 / 3, rel=REF_TOL)
    # numpy re-derivation on random data inside the clip range
    rng = np.random.default_rng(0)
    p, g = rng.uniform(0, 1000, (2, 4, 5, 2))
    c = rng.uniform(size=(4, 5))
    m = np.array([True, True, False, True])
    ref = (((p - g) / size) ** 2).sum(-1) * c
    assert f(losses.loss_2d(p, g, size, c, m)) == pytest.approx(ref[m].mean(), rel=REF_TOL)


def test_loss_ori_eq20_is_the_rotation_angle():
    """||R1 - R2||_F^2 = 2 tr(I - R1^T R2) = 8 sin^2(theta / 2) for the relative angle theta."""
    from scipy.spatial.transform import Rotation

    r1 = Rotation.random(5, random_state=1)
    theta = np.array([0.0, 0.3, 1.0, 2.0, np.pi])
    axes = np.random.default_rng(2).normal(size=(5, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    r2 = r1 * Rotation.from_rotvec(axes * theta[:, None])
    got = f(losses.loss_ori(r2.as_matrix(), r1.as_matrix()))
    assert got == pytest.approx(np.mean(8 * np.sin(theta / 2) ** 2), rel=REF_TOL)


def test_loss_irr_eqs21_22():
    lower = np.array([-1.0, 0.0, -0.5])
    upper = np.array([1.0, 2.0, 0.5])
    q = np.array([[1.5, -0.2, 0.0],   # (0.5)^2 + (0.2)^2 = 0.29
                  [0.0, 1.0, 0.25],  # inside: 0
                  [-3.0, 2.5, 0.6]])  # 4 + 0.25 + 0.01 = 4.26
    # summed over joints (as eq. 21), averaged over frames
    assert f(losses.loss_irr(q, lower, upper)) == pytest.approx((0.29 + 0 + 4.26) / 3, rel=REF_TOL)
    assert f(losses.loss_irr(q, lower, upper, np.array([False, True, False]))) == 0.0


def test_loss_contact_eq23_binary_cross_entropy():
    rng = np.random.default_rng(3)
    logits = rng.normal(scale=3.0, size=(6, 4))
    labels = (rng.uniform(size=(6, 4)) < 0.5).astype(float)
    p = 1 / (1 + np.exp(-logits))
    per_frame = -(labels * np.log(p) + (1 - labels) * np.log(1 - p)).sum(-1)  # eq. 23
    assert f(losses.loss_contact(logits, labels)) == pytest.approx(per_frame.mean(), rel=REF_TOL)
    # hand value: logit 0 is p = 1/2, log 2 per point
    assert f(losses.loss_contact(np.zeros((1, 4)), np.ones((1, 4)))) == pytest.approx(4 * np.log(2), rel=REF_TOL)
    # stable where log(sigmoid) would overflow: a confident wrong answer costs |logit|
    big = np.array([[60.0, -60.0, 60.0, -60.0]])
    lab = np.array([[0.0, 1.0, 1.0, 0.0]])
    assert f(losses.loss_contact(big, lab)) == pytest.approx(120.0, rel=REF_TOL)
    # its gradient is sigmoid(logit) - label (divided by the number of frames)
    g = np.asarray(jax.grad(losses.loss_contact)(logits, labels))
    np.testing.assert_allclose(g, (p - labels) / len(logits), rtol=1e-12, atol=1e-15)


def test_loss_translation_eq24_and_dyn_eq25():
    t = np.array([[0.0, 0.0, 3.0], [1.0, 1.0, 1.0]])
    assert f(losses.loss_translation(t, np.zeros((2, 3)))) == pytest.approx((9 + 3) / 2, rel=REF_TOL)
    e = np.array([[0.1, -0.2], [0.0, 0.3]])
    tau = np.array([[100.0, 0.0], [30.0, 40.0]])
    # ||e||^2 + phi ||tau||^2 with the paper's phi = 1e-6: (0.05 + 0.01) and (0.09 + 0.0025)
    assert f(losses.loss_dyn(e, tau)) == pytest.approx((0.06 + 0.0925) / 2, rel=REF_TOL)
    assert f(losses.loss_dyn(e, tau, phi=0.0)) == pytest.approx((0.05 + 0.09) / 2, rel=REF_TOL)


# ----------------------------------------------------------------------------- GRFNet (8-12)


def cone_ref(force, normal, mu):
    """Eq. 10 in numpy: theta^2 where theta > theta_max = arctan(mu), theta the angle
    between the contact normal and the force."""
    n = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    cos = np.sum(force * n, -1) / np.linalg.norm(force, axis=-1)
    theta = np.arccos(np.clip(cos, -1.0, 1.0))
    return np.where(theta > np.arctan(mu), theta**2, 0.0)


def test_loss_force_eq8_cone_eq10_smooth_eq11_and_grf_eq12():
    weight = 73.0 * 9.81
    rng = np.random.default_rng(4)
    T, C = 5, 4
    tau_root = rng.normal(scale=200.0, size=(T, 6))
    grf = rng.normal(scale=300.0, size=(T, C, 3))
    grf_raw = rng.normal(scale=300.0, size=(T, C, 3))
    prev = rng.normal(scale=300.0, size=(T, C, 3))
    up = np.array([0.0, 0.0, 1.0])
    mu = 0.8
    # eq. 8: ||tau*_root||^2 per body weight
    l_force = np.mean(np.sum((tau_root / weight) ** 2, -1))
    assert f(losses.loss_force(tau_root, weight)) == pytest.approx(l_force, rel=REF_TOL)
    # eq. 11: ||lambda - lambda_prev||^2 over all points, per body weight
    l_smooth = np.mean(np.sum(((grf - prev) / weight) ** 2, (-2, -1)))
    assert f(losses.loss_smooth(grf, prev, weight)) == pytest.approx(l_smooth, rel=REF_TOL)
    # eq. 10, summed over the contact points, hand values first: 45 degrees > arctan(0.8)
    # = 38.7 degrees costs (pi/4)^2; 26.6 degrees costs nothing; straight down is theta = pi
    hand = np.array([[[1.0, 0, 1], [0.5, 0, 1], [0, 0, -2], [0, 0, 5]]])
    assert f(losses.loss_cone(hand, up, mu)) == pytest.approx((np.pi / 4) ** 2 + np.pi**2, rel=REF_TOL)
    assert f(losses.loss_cone(hand, up, mu=1.5)) == pytest.approx(np.pi**2, rel=REF_TOL)
    l_cone = np.mean(np.sum(cone_ref(grf_raw / weight, up, mu), -1))
    assert f(losses.loss_cone(grf_raw / weight, up, mu)) == pytest.approx(l_cone, rel=REF_TOL)
    # eq. 12: their sum (the cone on GRFNet's raw output)
    got = f(losses.loss_grf(tau_root, grf, grf_raw, prev, weight, up, mu))
    assert got == pytest.approx(l_force + l_smooth + l_cone, rel=REF_TOL)
    # masked frames drop out of every term
    m = np.array([True, False, True, True, False])
    want = (np.mean(np.sum((tau_root[m] / weight) ** 2, -1))
            + np.mean(np.sum(((grf[m] - prev[m]) / weight) ** 2, (-2, -1)))
            + np.mean(np.sum(cone_ref(grf_raw[m] / weight, up, mu), -1)))
    assert f(losses.loss_grf(tau_root, grf, grf_raw, prev, weight, up, mu, m)) == pytest.approx(want, rel=REF_TOL)
