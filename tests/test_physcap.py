"""The ``physcap`` method (jmocap.methods.physcap) and the stages it composes: gradient flow
through the dynamic cycle, causality, padding, the hard constraint, what each ablation switch
changes, the traced config (no recompilation, gradients against finite differences) and the
closed-form translation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import x64
from jmocap import methods
from jmocap import physics as P
from jmocap.camera import Camera, canonicalise, default_extrinsics, project
from jmocap.inputs import ClipInputs
from jmocap.methods.physcap import CycleState, PhysCapConfig, init_params, reconstruct, simulate
from jmocap.methods.stages import causal_windows, least_squares_translation, soft_limit_wrench
from jmocap.model import load_model
from jmocap.nets import NetConfig

SMALL = PhysCapConfig(nets=NetConfig(tp_width=16, dyn_width=32, grf_width=32, tp_blocks=2))


@pytest.fixture(scope="module")
def model():
    return load_model(with_mjx=False)


def perturbed_params(model, config, scale=0.05, seed=0):
    """Fresh parameters with noise on every leaf, so that zero-initialised output layers do not
    hide gradients of the layers before them."""
    params = init_params(jax.random.PRNGKey(seed), model, config)
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.PRNGKey(seed + 1), len(leaves))
    leaves = [x + scale * jax.random.normal(k, x.shape, x.dtype) for x, k in zip(leaves, keys, strict=True)]
    return jax.tree.unflatten(tree, leaves)


def standing_targets(model, T, sink=0.0):
    q = np.tile(model.keyframe("stand"), (T, 1))
    q[:, 2] -= sink
    hq = model.topo.hinge_qadr
    q[:, hq] += 0.05 * np.sin(np.arange(T))[:, None]
    return q


def synthetic_inputs(model, T=12, seed=0):
    """Keypoints of a standing subject seen by the default camera (no noise)."""
    rng = np.random.default_rng(seed)
    q = standing_targets(model, T)
    q[:, 0] += rng.normal(scale=0.1)
    kp3 = np.asarray(jax.vmap(lambda x: P.keypoints(model, x, "body25"))(q))
    cam = Camera.from_intrinsics(1000.0, 1000.0, 640.0, 360.0, 1280, 720, default_extrinsics())
    uv = np.asarray(project(cam, kp3))
    kp = np.concatenate([uv, np.ones((*uv.shape[:2], 1))], -1).astype(np.float32)
    return ClipInputs(kp, np.array([1000, 1000, 640, 360], np.float32), np.array([1280, 720], np.float32),
                      default_extrinsics().astype(np.float32), np.float32(30.0), np.ones(T, bool))


def test_gradient_flows_through_cycles_projection_and_scan(model):
    """A loss on the final q has finite, non-zero gradients w.r.t. DyNet and GRFNet through the
    k = 6 iterations per frame, the hard-constraint projection and the scan over frames.

    With a limited root residual (the option where contact forces move the body); in the default
    literal eqs. 7 + 13 the contact forces cancel and GRFNet gets no gradient from the pose
    (checked at the end), only from L_force."""
    cfg = SMALL.replace(root_residual_limit=0.5)
    params = perturbed_params(model, cfg, scale=0.01)
    T = 3
    q_hat = jnp.asarray(standing_targets(model, T), jnp.float32)
    init = CycleState(q_hat[0].at[2].add(-0.01), jnp.zeros(model.nv), jnp.zeros((4, 3)))  # 1 cm deep
    prob = jnp.ones((T, 4))

    def loss(params):
        _, out = simulate(params, model, q_hat, prob, jnp.ones(T, bool), 30.0, cfg, init=init)
        return jnp.sum((out.q[-1] - q_hat[-1]) ** 2)

    grads = jax.jit(jax.grad(loss))(params)
    for net in ("dynet", "grfnet"):
        leaves = jax.tree.leaves(grads[net])
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves), net
        assert sum(float(jnp.sum(g * g)) for g in leaves) > 0, net
        # every layer receives gradient, not only the output layer
        assert all(float(jnp.max(jnp.abs(g))) > 0 for g in leaves), net
    cfg = SMALL  # root_residual_limit=None: tau* + J^T lambda - h = tau - h
    literal = jax.jit(jax.grad(loss))(params)
    assert all(float(jnp.max(jnp.abs(g))) == 0 for g in jax.tree.leaves(literal["grfnet"]))
    assert any(float(jnp.max(jnp.abs(g))) > 0 for g in jax.tree.leaves(literal["dynet"]))


@pytest.mark.slow
def test_cycle_gradient_matches_finite_differences(model):
    """Directional derivative of the final pose w.r.t. DyNet and GRFNet parameters (x64), with a
    limited root residual so that GRFNet moves the body."""
    with x64():
        cfg = SMALL.replace(root_residual_limit=0.5)
        params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), perturbed_params(model, cfg, scale=0.01))
        T = 2
        q_hat = jnp.asarray(standing_targets(model, T, sink=0.0))
        init = CycleState(q_hat[0].at[2].add(-0.005), jnp.zeros(model.nv), jnp.zeros((4, 3)))
        prob = jnp.ones((T, 4))

        def loss(params):
            _, out = simulate(params, model, q_hat, prob, jnp.ones(T, bool), 30.0, cfg, init=init)
            return jnp.sum(jnp.sin(3.0 * out.q[-1]))

        f = jax.jit(loss)
        g = jax.jit(jax.grad(loss))(params)
        for net in ("dynet", "grfnet"):
            direction = jax.tree.map(lambda x: jnp.zeros_like(x), params)
            keys = jax.random.split(jax.random.PRNGKey(3), len(jax.tree.leaves(params[net])))
            sub = jax.tree.unflatten(
                jax.tree.structure(params[net]),
                [jax.random.normal(k, x.shape, x.dtype) for k, x in zip(keys, jax.tree.leaves(params[net]), strict=True)],
            )
            direction = {**direction, net: sub}
            eps = 1e-6
            plus = jax.tree.map(lambda p, d: p + eps * d, params, direction)  # noqa: B023 (called within the iteration)
            minus = jax.tree.map(lambda p, d: p - eps * d, params, direction)  # noqa: B023 (called within the iteration)
            fd = (f(plus) - f(minus)) / (2 * eps)
            ad = sum(jnp.sum(a * b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(direction), strict=True))
            assert abs(float(fd)) > 1e-8, net
            np.testing.assert_allclose(float(ad), float(fd), rtol=1e-4, err_msg=net)


def test_reconstruct_is_causal_and_ignores_padding(model):
    cfg = SMALL
    params = perturbed_params(model, cfg, scale=0.01)
    T = 10
    inp = synthetic_inputs(model, T)
    rec = jax.jit(reconstruct)
    full = rec(params, model, inp, cfg)
    # changing the last frame's keypoints changes nothing before it
    kp = np.array(inp.keypoints)
    kp[-1, :, :2] += 30.0
    changed = rec(params, model, inp.replace(keypoints=kp), cfg)
    np.testing.assert_array_equal(full.q[:-1], changed.q[:-1])
    assert not np.allclose(full.target_q[-1], changed.target_q[-1])
    # padding: a clip padded with junk frames gives the same real frames
    pad = 6
    padded = ClipInputs(
        np.concatenate([inp.keypoints, np.full((pad, 25, 3), 7.0, np.float32)]),
        inp.intrinsics, inp.image_size, inp.extrinsics, inp.fps,
        np.concatenate([inp.mask, np.zeros(pad, bool)]),
    )
    out = rec(params, model, padded, cfg)
    np.testing.assert_allclose(out.q[:T], full.q, atol=1e-5)
    np.testing.assert_array_equal(out.mask, padded.mask)
    # padded frames hold the last real state
    np.testing.assert_array_equal(out.q[T:], np.broadcast_to(out.q[T - 1], out.q[T:].shape))


@pytest.mark.slow  # two float64 compiles of the whole pipeline (~50 s); jmocap.batch's tests vmap it too
def test_vmap_over_clips_matches_single_clips(model):
    """In float64: in float32 batched and single kernels round differently and 48 cycle steps
    amplify the difference to ~1e-3."""
    cfg = SMALL
    clips = [synthetic_inputs(model, 8, seed=s) for s in range(3)]  # numpy, made before x64
    with x64():
        model = load_model(with_mjx=False)  # its arrays made under x64 (no int32/int64 mix)
        params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), perturbed_params(model, cfg, scale=0.01))
        batch = jax.tree.map(lambda *x: np.stack(x).astype(np.float64) if np.stack(x).dtype == np.float32 else np.stack(x), *clips)
        out = jax.jit(jax.vmap(reconstruct, in_axes=(None, None, 0, None)))(params, model, batch, cfg)
        rec = jax.jit(reconstruct)
        for i in range(len(clips)):
            single = rec(params, model, jax.tree.map(lambda x, i=i: x[i], batch), cfg)
            np.testing.assert_allclose(out.q[i], single.q, atol=1e-8)


def test_hard_constraint_prevents_penetration(model):
    """Targets 5 cm below the floor: with the projection the contact points stay above the
    floor (to the recovery tolerance); without it they sink."""
    params = perturbed_params(model, SMALL, scale=0.0)
    T = 8
    q_hat = jnp.asarray(standing_targets(model, T, sink=0.05), jnp.float32)
    prob = jnp.ones((T, 4))
    init = CycleState(jnp.asarray(standing_targets(model, 1)[0], jnp.float32), jnp.zeros(model.nv), jnp.zeros((4, 3)))

    def min_height(cfg):
        _, out = jax.jit(simulate)(params, model, q_hat, prob, jnp.ones(T, bool), 30.0, cfg, init=init)
        assert not np.any(np.asarray(out.grf)) and not np.any(np.asarray(out.steps.grf_raw))  # use_grfnet=False
        h = jax.vmap(lambda q: P.contact_points(model, q)[1])(out.q)
        return float(jnp.min(h))

    with_c = min_height(SMALL.replace(use_dynet=False, use_grfnet=False))
    without = min_height(SMALL.replace(use_dynet=False, use_grfnet=False, hard_constraint=False))
    assert with_c > -1e-3
    assert without < -0.01


def test_each_switch_changes_what_it_names(model):
    """Each ablation (and the kinematic method) changes exactly the part of the result it names
    (use_grfnet / hard_constraint are in test_hard_constraint_prevents_penetration, the root
    residual limit in the gradient test)."""
    params = perturbed_params(model, SMALL, scale=0.01)
    inp = synthetic_inputs(model, 6)
    rec = jax.jit(reconstruct)
    full = rec(params, model, inp, SMALL)
    # the kinematic method: TPNet's pose is the result, no forces
    kin_m = methods.get_method("kinematic")
    kin = jax.jit(kin_m.reconstruct)(params, model, inp, kin_m.make_config(methods.config_dict(SMALL)))
    np.testing.assert_array_equal(kin.q, kin.target_q)
    np.testing.assert_array_equal(kin.target_q, full.target_q)  # the same learned stage
    assert not np.any(np.asarray(kin.tau)) and not np.any(np.asarray(kin.grf))
    # fixed gains: the same target, a different motion (DyNet's gains are not k_p_ini)
    fixed = rec(params, model, inp, SMALL.replace(use_dynet=False))
    np.testing.assert_array_equal(fixed.target_q, full.target_q)
    assert np.abs(np.asarray(fixed.q[1:]) - np.asarray(full.q[1:])).max() > 1e-5
    # no canonicalisation: C_T reads K_rr, so the root translation of the target changes, the
    # root-relative pose (C_P) does not
    nocano = rec(params, model, inp, SMALL.replace(canonicalise=False))
    np.testing.assert_array_equal(nocano.target_q[:, 7:], full.target_q[:, 7:])
    assert np.abs(np.asarray(nocano.target_q[:, :3]) - np.asarray(full.target_q[:, :3])).max() > 1e-3
    # the identity metric of the projection: finite, the same target
    ident = rec(params, model, inp, SMALL.replace(metric="identity"))
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(ident))
    np.testing.assert_array_equal(ident.target_q, full.target_q)


def test_traced_parameters_do_not_recompile_static_ones_do(model):
    """Gains, friction and recovery factors are traced leaves of the config: changing them reuses
    the compiled program; a static field (iterations) compiles a new one."""
    cfg = SMALL.replace(use_dynet=False)
    params = perturbed_params(model, cfg, scale=0.01)
    T = 3
    q_hat = jnp.asarray(standing_targets(model, T), jnp.float32)
    prob = jnp.ones((T, 4))
    f = jax.jit(lambda c: simulate(params, model, q_hat, prob, jnp.ones(T, bool), 30.0, c)[1].q)
    a = f(cfg)
    b = f(cfg.replace(kp_joint=900.0, mu=0.5, beta=0.1, damping_ratio=0.7))
    assert f._cache_size() == 1
    assert np.abs(np.asarray(a) - np.asarray(b)).max() > 1e-6  # and they do take effect
    f(cfg.replace(iterations=2))
    assert f._cache_size() == 2
    assert set(methods.traced_fields(PhysCapConfig)) >= {"kp_joint", "kp_root_pos", "mu", "beta", "damping_ratio"}
    assert "iterations" in methods.static_fields(PhysCapConfig)


def test_gradient_with_respect_to_gains_matches_finite_differences(model):
    """d(loss)/d(k_p, damping) through the cycle (x64) against central differences: the traced
    config is differentiable (system identification, docs/architecture.md)."""
    with x64():
        m64 = load_model()
        cfg = SMALL.replace(use_dynet=False, use_grfnet=False, iterations=2)
        params = {}
        T = 3
        q_hat = jnp.asarray(standing_targets(m64, T))
        init = CycleState(q_hat[0].at[7:].add(0.05), jnp.zeros(m64.nv), jnp.zeros((4, 3)))

        def loss(kp, zeta):
            c = cfg.replace(kp_joint=kp, damping_ratio=zeta)
            _, out = simulate(params, m64, q_hat, jnp.ones((T, 4)), jnp.ones(T, bool), 30.0, c, init=init)
            return jnp.sum(jnp.sin(3.0 * out.q[-1]))

        g = jax.jit(jax.grad(loss, argnums=(0, 1)))(1600.0, 1.0)
        f = jax.jit(loss)
        for i, eps in enumerate((1e-2, 1e-6)):
            args_p = [1600.0, 1.0]
            args_m = [1600.0, 1.0]
            args_p[i] += eps
            args_m[i] -= eps
            fd = (float(f(*args_p)) - float(f(*args_m))) / (2 * eps)
            assert abs(fd) > 1e-9
            np.testing.assert_allclose(float(g[i]), fd, rtol=1e-5)


def test_least_squares_translation_is_exact_without_noise(model):
    rng = np.random.default_rng(5)
    for _ in range(5):
        q = np.array(model.keyframe("stand"))
        q[:3] = 0.0
        quat = rng.normal(size=4)
        q[3:7] = quat / np.linalg.norm(quat)
        p_rr = np.asarray(P.keypoints(model, q, "body25"))
        t = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(3, 8)])
        X = p_rr + t
        uv = X[:, :2] / X[:, 2:3] * 1000.0 + 500.0
        kc = canonicalise(np.concatenate([uv, np.ones((25, 1))], -1), np.array([1000.0, 1000.0, 500.0, 500.0]))
        # exact without the weak depth prior; with it, biased by at most a few mm at 3-8 m
        np.testing.assert_allclose(least_squares_translation(jnp.asarray(p_rr), kc, prior_weight=0.0), t, atol=2e-5)
        np.testing.assert_allclose(least_squares_translation(jnp.asarray(p_rr), kc), t, atol=5e-3)


def test_soft_limit_wrench_by_hand():
    w = jnp.array([3.0, 4.0, 0.0, 0.0, 0.0, 0.0])
    # |f| = 5, limit 5 -> scale 1/sqrt(2)
    np.testing.assert_allclose(soft_limit_wrench(w, 5.0)[:3], np.array([3.0, 4.0, 0.0]) / np.sqrt(2), rtol=1e-6)
    np.testing.assert_allclose(soft_limit_wrench(w, 5.0)[3:], 0.0)
    small = jnp.array([1e-3, 0, 0, 0, 2e-3, 0])
    np.testing.assert_allclose(soft_limit_wrench(small, 1000.0), small, rtol=1e-6)


def test_causal_windows():
    x = jnp.arange(5)
    np.testing.assert_array_equal(causal_windows(x, 3), [[0, 0, 0], [0, 0, 1], [0, 1, 2], [1, 2, 3], [2, 3, 4]])


def test_from_clip_pads_and_rejects_short_length():
    from jmocap.data.clip import Clip

    kp = np.ones((4, 25, 3), np.float32)
    clip = Clip(name="c", layout="body25", fps=30.0, keypoints=kp,
                intrinsics=np.array([1000.0, 1000.0, 500.0, 500.0]), image_size=np.array([1000, 1000]))
    inp = ClipInputs.from_clip(clip, length=6)
    assert inp.keypoints.shape == (6, 25, 3)
    np.testing.assert_array_equal(inp.mask, [1, 1, 1, 1, 0, 0])
    with pytest.raises(ValueError, match="more than the padded length"):
        ClipInputs.from_clip(clip, length=3)
