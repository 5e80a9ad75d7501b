"""Tests of jmocap.camera against independent numpy math and hand-computed values.

Tolerances: float32 JAX vs float64 numpy references; pixel values are O(1e3), so relative
1e-5 (about 1e-2 px) covers float32 rounding; canonical coordinates are O(1), so 1e-5 absolute.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jmocap.camera import (
    Camera,
    camera_to_world,
    canonicalise,
    default_intrinsics,
    project,
    root_relative,
    unproject,
    world_to_camera,
)
from jmocap.layouts import get_layout


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _random_extrinsics(rng) -> np.ndarray:
    E = np.eye(4)
    E[:3, :3] = _random_rotation(rng)
    E[:3, 3] = rng.normal(size=3)
    return E


def _points_in_front(rng, E, n) -> np.ndarray:
    """World points whose camera-frame depth is in [2, 8] m."""
    Xc = np.concatenate([rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 8, (n, 1))], axis=1)
    R, t = E[:3, :3], E[:3, 3]
    return (Xc - t) @ R  # R^T (Xc - t), row-wise


def _numpy_project(intr, E, X):
    """Independent reference: homogeneous K [R t] X with numpy float64."""
    fx, fy, cx, cy = intr
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    P = K @ E[:3, :]
    Xh = np.concatenate([X, np.ones((len(X), 1))], axis=1)
    x = Xh @ P.T
    return x[:, :2] / x[:, 2:3], x[:, 2]


def test_project_hand_computed():
    # identity extrinsics: world = camera frame
    cam = Camera.from_intrinsics(1000.0, 900.0, 640.0, 360.0, 1280, 720)
    uv, z = project(cam, jnp.array([[0.5, -0.25, 2.0], [0.0, 0.0, 4.0]]), return_depth=True)
    # u = 1000 * 0.5/2 + 640 = 890, v = 900 * -0.25/2 + 360 = 247.5
    np.testing.assert_allclose(np.asarray(uv), [[890.0, 247.5], [640.0, 360.0]], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(z), [2.0, 4.0])


def test_look_at_hand_computed():
    # camera 5 m behind the origin along -y, at height 1 m, looking along +y (horizontal)
    cam = Camera.look_at([0.0, -5.0, 1.0], [0.0, 0.0, 1.0], fx=1000.0, width=1920, height=1080)
    uv, z = project(cam, jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 2.0]]), return_depth=True)
    # the target is at the image centre; +x world is image right, +z world (up) is image up
    np.testing.assert_allclose(
        np.asarray(uv), [[960.0, 540.0], [960 + 200.0, 540 - 200.0]], rtol=1e-6
    )
    np.testing.assert_allclose(np.asarray(z), [5.0, 5.0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(cam.position), [0.0, -5.0, 1.0], atol=1e-6)


def test_project_matches_numpy_reference():
    rng = np.random.default_rng(0)
    for _ in range(5):
        intr = np.array(
            [
                rng.uniform(300, 2000),
                rng.uniform(300, 2000),
                rng.uniform(200, 1000),
                rng.uniform(200, 800),
            ]
        )
        E = _random_extrinsics(rng)
        X = _points_in_front(rng, E, 50)
        cam = Camera.from_intrinsics(*intr, 1920, 1080, extrinsics=E)
        uv, z = project(cam, jnp.asarray(X, jnp.float32), return_depth=True)
        uv_ref, z_ref = _numpy_project(intr, E, X)
        np.testing.assert_allclose(np.asarray(uv), uv_ref, rtol=1e-5, atol=1e-2)
        np.testing.assert_allclose(np.asarray(z), z_ref, rtol=1e-5, atol=1e-5)


def test_project_unproject_round_trip():
    rng = np.random.default_rng(1)
    E = _random_extrinsics(rng)
    X = _points_in_front(rng, E, 100).reshape(10, 10, 3)
    cam = Camera.from_intrinsics(1100.0, 1050.0, 950.0, 530.0, 1920, 1080, extrinsics=E)
    uv, z = project(cam, X, return_depth=True)
    X2 = unproject(cam, uv, z)
    np.testing.assert_allclose(np.asarray(X2), X, atol=2e-5 * 10)
    Xc = world_to_camera(cam, X)
    np.testing.assert_allclose(np.asarray(camera_to_world(cam, Xc)), X, atol=1e-5)


def test_canonicalise_equals_camera_ratio():
    """K_c = [X/Z, Y/Z] of the camera-frame points (eq. 6), for random intrinsics."""
    rng = np.random.default_rng(2)
    for _ in range(5):
        intr = np.array(
            [
                rng.uniform(300, 2000),
                rng.uniform(300, 2000),
                rng.uniform(200, 1000),
                rng.uniform(200, 800),
            ]
        )
        E = _random_extrinsics(rng)
        X = _points_in_front(rng, E, 17)
        uv_ref, _ = _numpy_project(intr, E, X)
        Xc = X @ E[:3, :3].T + E[:3, 3]
        kc = canonicalise(jnp.asarray(uv_ref, jnp.float32), jnp.asarray(intr, jnp.float32))
        np.testing.assert_allclose(np.asarray(kc), Xc[:, :2] / Xc[:, 2:3], atol=1e-5)


def test_canonicalise_invariant_to_intrinsics():
    """The same 3D motion seen with different focal lengths / principal points gives one K_c."""
    rng = np.random.default_rng(3)
    E = _random_extrinsics(rng)
    X = _points_in_front(rng, E, 20 * 25).reshape(20, 25, 3)  # T=20 frames, 25 joints
    results = []
    for intr in (
        [500.0, 500.0, 320.0, 240.0],
        [1500.0, 1400.0, 960.0, 540.0],
        [1000.0, 1000.0, 0.0, 0.0],
    ):
        cam = Camera.from_intrinsics(*intr, 1920, 1080, extrinsics=E)
        uv = project(cam, X)
        kp = jnp.concatenate([uv, jnp.ones(uv.shape[:-1] + (1,))], axis=-1)  # with confidence
        results.append(np.asarray(canonicalise(kp, jnp.asarray(intr))))
    for r in results[1:]:
        np.testing.assert_allclose(r, results[0], atol=1e-5)
    assert results[0].shape == (20, 25, 3)
    np.testing.assert_array_equal(results[0][..., 2], 1.0)


def test_canonicalise_keeps_confidence_and_zeros_missing():
    kp = jnp.array([[[1100.0, 640.0, 0.8], [0.0, 0.0, 0.0]]])
    out = np.asarray(canonicalise(kp, jnp.array([1000.0, 1000.0, 960.0, 540.0])))
    np.testing.assert_allclose(out[0, 0], [0.14, 0.1, 0.8], atol=1e-6)
    np.testing.assert_array_equal(out[0, 1], [0.0, 0.0, 0.0])


def test_canonicalise_batched_intrinsics_prefix():
    """Intrinsics (B, 4) apply to keypoints (B, T, J, 3), matching a per-clip loop."""
    rng = np.random.default_rng(4)
    kp = rng.uniform(0, 1000, (3, 7, 17, 3)).astype(np.float32)
    kp[..., 2] = rng.uniform(0.1, 1, (3, 7, 17))
    intr = rng.uniform(300, 1500, (3, 4)).astype(np.float32)
    out = np.asarray(canonicalise(kp, intr))
    for b in range(3):
        np.testing.assert_allclose(out[b], np.asarray(canonicalise(kp[b], intr[b])), rtol=1e-6)


def test_root_relative_hand_computed():
    layout = get_layout("h36m17")
    kp = np.zeros((2, 17, 3), np.float32)
    kp[..., 2] = 1.0
    kp[:, 0, :2] = [960.0, 540.0]  # Hip = root
    kp[:, 3, :2] = [1152.0, 756.0]  # RFoot
    out = np.asarray(root_relative(kp, jnp.array([1920.0, 1080.0]), layout))
    np.testing.assert_allclose(out[0, 0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(out[0, 3], [0.1, 0.2, 1.0], atol=1e-6)
    # without confidence channel: same coordinates
    out2 = np.asarray(root_relative(kp[..., :2], (1920, 1080), "h36m17"))
    np.testing.assert_allclose(out2, out[..., :2], atol=1e-7)


def test_root_relative_missing_root():
    """COCO root = mean of visible hips; a frame with no visible root joint is all-missing."""
    layout = get_layout("coco17")
    lh, rh = layout.index("left_hip"), layout.index("right_hip")
    nose = layout.index("nose")
    kp = np.zeros((3, 17, 3), np.float32)
    kp[:, nose] = [500.0, 100.0, 0.9]
    kp[:, lh] = [600.0, 500.0, 1.0]
    kp[:, rh] = [400.0, 500.0, 1.0]
    kp[1, rh] = 0.0  # frame 1: right hip missing -> root = left hip
    kp[2, lh] = 0.0  # frame 2: both hips missing -> frame missing
    kp[2, rh] = 0.0
    out = np.asarray(root_relative(kp, (1000.0, 1000.0), layout))
    np.testing.assert_allclose(out[0, nose], [0.0, -0.4, 0.9], atol=1e-6)
    np.testing.assert_allclose(out[1, nose], [-0.1, -0.4, 0.9], atol=1e-6)
    np.testing.assert_array_equal(out[1, rh], [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(out[2], 0.0)
    # other missing joints have zero coordinates
    np.testing.assert_array_equal(out[0, 1], [0.0, 0.0, 0.0])


@pytest.mark.parametrize("layout_name,root,hips", [("body25", "MidHip", ("RHip", "LHip")),
                                                    ("h36m17", "Hip", ("RHip", "LHip"))])
def test_root_relative_falls_back_to_the_hips(layout_name, root, hips):
    """A frame whose root joint is missing but both hips are seen takes the hips' midpoint as
    its root (the character's mid-hip site is their 3D midpoint exactly); with a hip missing too,
    the frame is missing as before. Hand-worked values."""
    layout = get_layout(layout_name)
    r, (rh, lh) = layout.index(root), (layout.index(h) for h in hips)
    other = next(i for i in range(layout.num_joints) if i not in (r, rh, lh))
    kp = np.zeros((3, layout.num_joints, 3), np.float32)
    kp[:, rh] = [400.0, 500.0, 0.8]
    kp[:, lh] = [600.0, 520.0, 0.9]
    kp[:, r] = [500.0, 510.0, 1.0]  # the hips' midpoint
    kp[:, other] = [550.0, 110.0, 0.7]
    kp[1, r, 2] = 0.0  # frame 1: root missing, hips seen
    kp[2, r, 2] = 0.0  # frame 2: root and the left hip missing
    kp[2, lh, 2] = 0.0
    out = np.asarray(root_relative(kp, (1000.0, 1000.0), layout))
    np.testing.assert_allclose(out[0, other], [0.05, -0.4, 0.7], atol=1e-6)
    np.testing.assert_allclose(out[1, other], out[0, other], atol=1e-6)
    np.testing.assert_allclose(out[1, rh], [-0.1, -0.01, 0.8], atol=1e-6)
    np.testing.assert_array_equal(out[1, r], [0.0, 0.0, 0.0])  # the root joint itself stays missing
    np.testing.assert_array_equal(out[2], 0.0)
    assert get_layout("coco17").root_fallback == ()  # COCO's root is the hips already


def test_jit_and_vmap_over_cameras():
    rng = np.random.default_rng(5)
    B = 4
    Es = np.stack([_random_extrinsics(rng) for _ in range(B)])
    X = np.stack([_points_in_front(rng, Es[b], 30) for b in range(B)])  # (B, 30, 3)
    intr = rng.uniform(500, 1500, (B, 4))
    cams = Camera.from_intrinsics(
        intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3], 1920, 1080, extrinsics=Es
    )
    assert cams.batch_shape == (B,)
    f = jax.jit(jax.vmap(project))
    uv = np.asarray(f(cams, jnp.asarray(X, jnp.float32)))
    uv_bcast = np.asarray(
        jax.jit(project)(cams, jnp.asarray(X, jnp.float32))
    )  # prefix broadcasting
    for b in range(B):
        ref, _ = _numpy_project(intr[b], Es[b], X[b])
        np.testing.assert_allclose(uv[b], ref, rtol=1e-5, atol=1e-2)
        np.testing.assert_allclose(uv_bcast[b], ref, rtol=1e-5, atol=1e-2)
    # one camera, many point sets
    many = jax.jit(jax.vmap(project, in_axes=(None, 0)))(
        Camera.from_intrinsics(*intr[0], 1920, 1080, extrinsics=Es[0]), jnp.asarray(X, jnp.float32)
    )
    assert many.shape == (B, 30, 2)
    # canonicalise / root_relative jit + vmap
    kp = jnp.concatenate([jnp.asarray(uv), jnp.ones((B, 30, 1))], -1)[:, :25]
    kc = jax.jit(jax.vmap(canonicalise))(kp, jnp.asarray(intr, jnp.float32))
    assert kc.shape == (B, 25, 3)
    krr = jax.jit(jax.vmap(lambda k, s: root_relative(k, s, "body25")))(
        kp, jnp.full((B, 2), 1000.0)
    )
    assert krr.shape == (B, 25, 3)


def test_gradients_finite():
    rng = np.random.default_rng(6)
    E = _random_extrinsics(rng)
    X = jnp.asarray(_points_in_front(rng, E, 25), jnp.float32)
    cam = Camera.from_intrinsics(1000.0, 1000.0, 960.0, 540.0, 1920, 1080, extrinsics=E)

    def loss(cam, X):
        return jnp.sum(project(cam, X) ** 2) * 1e-6

    g_cam, g_X = jax.grad(loss, argnums=(0, 1))(cam, X)
    for leaf in jax.tree_util.tree_leaves((g_cam, g_X)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    # finite-difference check of d loss / d X for one coordinate (float64 reference)
    Xn = np.asarray(X, np.float64)

    def loss_np(Xn):
        uv, _ = _numpy_project(np.array([1000.0, 1000.0, 960.0, 540.0]), E, Xn)
        return np.sum(uv**2) * 1e-6

    eps = 1e-5
    Xp, Xm = Xn.copy(), Xn.copy()
    Xp[3, 1] += eps
    Xm[3, 1] -= eps
    fd = (loss_np(Xp) - loss_np(Xm)) / (2 * eps)
    np.testing.assert_allclose(float(g_X[3, 1]), fd, rtol=1e-3)
    # degenerate inputs: point at depth 0, missing root, missing joints
    g0 = jax.grad(lambda X: jnp.sum(project(Camera.from_intrinsics(1.0, 1.0, 0.0, 0.0, 2, 2), X)))(
        jnp.zeros((1, 3))
    )
    assert np.all(np.isfinite(np.asarray(g0)))
    kp = jnp.zeros((4, 17, 3))
    g1 = jax.grad(
        lambda k: (
            jnp.sum(root_relative(k, (100.0, 100.0), "coco17"))
            + jnp.sum(canonicalise(k, jnp.ones(4)))
        )
    )(kp)
    assert np.all(np.isfinite(np.asarray(g1)))


def test_x64():
    with jax.enable_x64(True):
        cam = Camera.from_intrinsics(1000.0, 1000.0, 960.0, 540.0, 1920, 1080)
        assert cam.intrinsics.dtype == jnp.float64
        uv = project(cam, jnp.array([[0.1, 0.2, 3.0]]))
        assert uv.dtype == jnp.float64


def test_default_intrinsics():
    np.testing.assert_array_equal(default_intrinsics(1920, 1080), [1000.0, 1000.0, 960.0, 540.0])
    cam = Camera.default(640, 480)
    np.testing.assert_allclose(np.asarray(cam.intrinsics), [1000.0, 1000.0, 320.0, 240.0])
    np.testing.assert_allclose(np.asarray(cam.extrinsics), np.eye(4))
    with pytest.raises(ValueError):
        default_intrinsics(0, 480)
