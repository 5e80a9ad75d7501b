"""Tests of jmocap.nets_imu, PIP's kinematics module (Yi et al. 2022, Sec. 3.1): shapes, the
online scan (chunks with the carried state equal the whole clip), gradients (every parameter,
finite differences in float64), the learned initial state and its ablation, the targets against
MuJoCo C's forward kinematics, and a tiny model overfitting one clip."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax
import pytest

from conftest import random_configurations, x64
from jmocap import nets_imu as N
from jmocap.data.synthetic import SynthConfig
from jmocap.data.synthetic.imu import IMUCorruption, IMUSynthConfig, generate_imu_clip
from jmocap.model import character

TINY = N.IMUNetConfig(width=8, contact_width=4, layers=2, dropout=0.0)

# compiled once per shape (eager scans and einsums would compile per call)
_run = jax.jit(N.run, static_argnums=(2,), static_argnames=("train",))
_init_state = jax.jit(N.initial_state, static_argnums=(2,))
_targets = jax.jit(N.targets)
_features = jax.jit(N.imu_features)


@pytest.fixture(scope="module")
def model():
    return character()


@pytest.fixture(scope="module")
def clip():
    """A short synthetic IMU clip with exact (uncorrupted) sensors."""
    cfg = IMUSynthConfig(synth=SynthConfig(frames=40, kinds=("walk",)), corruption=IMUCorruption.none())
    return generate_imu_clip(5, 0, cfg)


def _inputs(clip):
    ori, acc = clip.calibrated()
    return _features(jnp.asarray(ori), jnp.asarray(acc))


def _tgt(clip, dtype=jnp.float32):
    m = character(clip.height_m, clip.mass_kg)
    t = _targets(m, jnp.asarray(clip.gt_q, dtype), clip.fps, jnp.asarray(clip.gt_contacts))
    return {k: t[k] for k in ("leaf", "joints", "hinges", "vel", "contacts", "R_root")}


def test_features_and_outputs_shapes(model, clip):
    x = _inputs(clip)
    assert x.shape == (clip.num_frames, 72) and x.dtype == jnp.float32
    # the pelvis sensor's own orientation is the last 9 entries; the others are relative to it
    ori, _ = clip.calibrated()
    np.testing.assert_allclose(np.asarray(x[:, -9:]).reshape(-1, 3, 3), ori[:, 5], atol=1e-6)
    params = N.init_params(jax.random.PRNGKey(0), model, TINY)
    t = _tgt(clip)
    carry = _init_state(params, model, TINY, t["leaf"][0], t["vel"][0])
    carry2, out = _run(params, model, TINY, carry, x)
    T, nh = clip.num_frames, model.topo.hinge_qadr.size
    assert out.leaf.shape == (T, 5, 3) and out.joints.shape == (T, 23, 3)
    assert out.hinges.shape == (T, nh) and out.vel.shape == (T, 24, 3) and out.contact_logits.shape == (T, 4)
    assert all(a.dtype == jnp.float32 for a in jax.tree.leaves(out))
    assert jax.tree.structure(carry2) == jax.tree.structure(N.zero_state(TINY))
    assert np.all(np.abs(np.asarray(out.hinges)) <= np.pi)
    q = N.pose(model, out, t["R_root"])
    assert q.shape == (T, model.nq)


def test_chunked_scan_equals_whole_clip(model, clip):
    x = _inputs(clip)
    params = N.init_params(jax.random.PRNGKey(1), model, TINY)
    t = _tgt(clip)
    c0 = _init_state(params, model, TINY, t["leaf"][0], t["vel"][0])
    c_all, whole = _run(params, model, TINY, c0, x)
    carry, parts = c0, []
    for a, b in ((0, 7), (7, 8), (8, 25), (25, len(x))):
        carry, o = _run(params, model, TINY, carry, x[a:b])
        parts.append(o)
    chunked = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)
    for w, c in zip(jax.tree.leaves(whole), jax.tree.leaves(chunked), strict=True):
        np.testing.assert_allclose(np.asarray(c), np.asarray(w), rtol=1e-5, atol=1e-6)
    for w, c in zip(jax.tree.leaves(c_all), jax.tree.leaves(carry), strict=True):
        np.testing.assert_allclose(np.asarray(c), np.asarray(w), rtol=1e-5, atol=1e-6)
    # the online step is the same function
    carry, o = N.step(params, model, TINY, c0, x[0])
    np.testing.assert_allclose(np.asarray(o.hinges), np.asarray(whole.hinges[0]), rtol=1e-5, atol=1e-6)


def test_gradients_reach_every_parameter(model, clip):
    x = _inputs(clip)[:12]
    t = jax.tree.map(lambda a: a[:12], _tgt(clip))
    params = N.init_params(jax.random.PRNGKey(2), model, TINY)
    g = jax.jit(jax.grad(lambda p: N.clip_loss(p, model, TINY, x, t, clip.fps)[0]))(params)
    flat = jax.tree_util.tree_flatten_with_path(g)[0]
    names = {jax.tree_util.keystr(p) for p, _ in flat}
    assert any("init_leaf" in n for n in names) and any("init_vel" in n for n in names)
    for path, leaf in flat:
        a = np.asarray(leaf)
        assert np.all(np.isfinite(a)), jax.tree_util.keystr(path)
        assert np.abs(a).max() > 0, f"no gradient reaches {jax.tree_util.keystr(path)}"


def test_gradients_match_finite_differences_float64(model, clip):
    # inputs and targets are constants of the loss: made in float32 (the cached characters hold
    # float32 / int32 arrays), then the loss and its gradient in float64
    x32 = np.asarray(_inputs(clip)[:6])
    t32 = jax.tree.map(lambda a: np.asarray(a[:6]), _tgt(clip))
    p32 = jax.tree.map(np.asarray, N.init_params(jax.random.PRNGKey(3), model, TINY))
    with x64():
        _check_finite_differences(model, clip, x32, t32, p32)


def _check_finite_differences(model, clip, x32, t32, p32):
    x = jnp.asarray(x32, jnp.float64)
    t = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), t32)
    params = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), p32)

    @jax.jit
    def f(p):
        return N.clip_loss(p, model, TINY, x, t, clip.fps)[0]

    g = jax.grad(f)(params)
    flat, tree = jax.tree.flatten(params)
    gflat = jax.tree.leaves(g)
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
    rng = np.random.default_rng(0)
    picks = [i for i, p in enumerate(paths) if any(s in p for s in ("init_leaf", "init_vel", "leaf", "pose", "contact"))]
    checked = 0
    for i in picks[:: max(1, len(picks) // 8)]:
        a = np.asarray(flat[i])
        j = np.unravel_index(int(rng.integers(a.size)), a.shape)
        eps = 1e-6
        vals = []
        for s in (1, -1):
            b = a.copy()
            b[j] += s * eps
            fl = list(flat)
            fl[i] = jnp.asarray(b)
            vals.append(float(f(jax.tree.unflatten(tree, fl))))
        fd = (vals[0] - vals[1]) / (2 * eps)
        an = float(np.asarray(gflat[i])[j])
        assert abs(fd - an) <= 1e-6 + 1e-5 * abs(an), (paths[i], j, fd, an)
        checked += 1
    assert checked >= 6


def test_learned_initial_state_and_zero_ablation(model, clip):
    x = _inputs(clip)
    t = _tgt(clip)
    params = N.init_params(jax.random.PRNGKey(4), model, TINY)
    learned = _init_state(params, model, TINY, t["leaf"][0], t["vel"][0])
    zero = N.zero_state(TINY)
    # P_L and V_A start from the learned state, the others from zero
    assert np.abs(np.asarray(learned["leaf"][0][0])).max() > 0
    assert np.abs(np.asarray(learned["vel"][1][1])).max() > 0
    for k in ("joints", "pose", "contact"):
        assert all(np.all(np.asarray(a) == 0) for a in jax.tree.leaves(learned[k]))
    _, o1 = _run(params, model, TINY, learned, x[:5])
    _, o0 = _run(params, model, TINY, zero, x[:5])
    assert np.abs(np.asarray(o1.leaf[0] - o0.leaf[0])).max() > 1e-4
    assert np.abs(np.asarray(o1.vel[0] - o0.vel[0])).max() > 1e-4
    # the ablation flag: no initial-state networks, every network starts at zero
    abl = dataclasses.replace(TINY, learned_init=False)
    pz = N.init_params(jax.random.PRNGKey(4), model, abl)
    assert "init_leaf" not in pz["params"] and "init_vel" not in pz["params"]
    cz = N.initial_state(pz, model, abl, t["leaf"][0], t["vel"][0])
    assert all(np.all(np.asarray(a) == 0) for a in jax.tree.leaves(cz))
    assert jax.tree.structure(cz) == jax.tree.structure(zero)


@pytest.mark.usefixtures("enable_x64")
def test_targets_match_mujoco_forward_kinematics():
    m = character(1.62, 58.0)
    mj = m.mj
    qs, _ = random_configurations(mj, 6, seed=11)
    fps = 30.0
    contacts = (np.arange(24).reshape(6, 4) % 3 == 0)
    t = _targets(m, jnp.asarray(qs), fps, jnp.asarray(contacts))
    d = mujoco.MjData(mj)
    xpos, xmat = [], []
    for q in qs:
        d.qpos[:] = q
        mujoco.mj_kinematics(mj, d)
        xpos.append(d.xpos.copy())
        xmat.append(d.xmat.reshape(-1, 3, 3).copy())
    xpos, xmat = np.stack(xpos), np.stack(xmat)
    root = mj.body("pelvis").id
    R = xmat[:, root]
    leaf = [mj.body(n).id for n in N.LEAF_BODIES]
    joints = [b for b in range(1, mj.nbody) if b != root]
    np.testing.assert_allclose(np.asarray(t["R_root"]), R, atol=1e-10)
    np.testing.assert_allclose(np.asarray(t["xpos"]), xpos, atol=1e-10)
    np.testing.assert_allclose(np.asarray(t["leaf"]), np.einsum("tij,tni->tnj", R, xpos[:, leaf] - xpos[:, root:root + 1]),
                               atol=1e-10)
    np.testing.assert_allclose(np.asarray(t["joints"]),
                               np.einsum("tij,tni->tnj", R, xpos[:, joints] - xpos[:, root:root + 1]), atol=1e-10)
    bodies = [root] + joints
    v = np.diff(xpos[:, bodies], axis=0) * fps
    v = np.concatenate([v[:1], v])
    np.testing.assert_allclose(np.asarray(t["vel"]), np.einsum("tij,tni->tnj", R, v), atol=1e-8)
    np.testing.assert_allclose(np.asarray(t["hinges"]), qs[:, m.topo.hinge_qadr], atol=0)
    np.testing.assert_array_equal(np.asarray(t["contacts"]), contacts.astype(float))
    # the body names are what the docstring says: the wrists and ankles are leaves of the arms/legs
    assert set(N.LEAF_BODIES) <= set(m.topo.body_names)


def test_targets_agree_with_the_clip_sensors(clip):
    """With exact sensors the pelvis sensor's calibrated orientation is the target root frame."""
    ori, _ = clip.calibrated()
    t = _tgt(clip)
    np.testing.assert_allclose(np.asarray(t["R_root"]), ori[:, 5], atol=2e-5)


@pytest.mark.slow
def test_tiny_model_overfits_one_clip(model, clip):
    T = 32
    x = _inputs(clip)[:T]
    t = jax.tree.map(lambda a: a[:T], _tgt(clip))
    cfg = N.IMUNetConfig(width=32, contact_width=16, dropout=0.0)
    params = N.init_params(jax.random.PRNGKey(5), model, cfg)
    opt = optax.adam(1e-2)
    s = opt.init(params)

    @jax.jit
    def upd(p, s):
        (l, _), g = jax.value_and_grad(lambda p: N.clip_loss(p, model, cfg, x, t, clip.fps), has_aux=True)(p)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s, l

    first = None
    for _ in range(300):
        params, s, loss = upd(params, s)
        first = float(loss) if first is None else first
    assert float(loss) < first / 10, (first, float(loss))


@pytest.mark.parametrize("w", [1.0, 3.0])
def test_contact_loss_is_the_weighted_binary_cross_entropy(w):
    """The contact term against optax's sigmoid BCE (w = 1) and its hand-weighted form."""
    rng = np.random.default_rng(0)
    logits = jnp.asarray(rng.normal(0, 3, (20, 4)), jnp.float32)
    c = jnp.asarray(rng.random((20, 4)) > 0.4, jnp.float32)
    T, nh = 20, 41
    out = N.Outputs(leaf=jnp.zeros((T, 5, 3)), joints=jnp.zeros((T, 23, 3)), hinges=jnp.zeros((T, nh)),
                    vel=jnp.zeros((T, 24, 3)), contact_logits=logits)
    tgt = {"leaf": jnp.zeros((T, 5, 3)), "joints": jnp.zeros((T, 23, 3)), "hinges": jnp.zeros((T, nh)),
           "vel": jnp.zeros((T, 24, 3)), "contacts": c, "R_root": jnp.tile(jnp.eye(3), (T, 1, 1))}
    got = float(N.losses(out, tgt, dataclasses.replace(TINY, contact_pos_weight=w), 30.0)["contact"])
    per = optax.sigmoid_binary_cross_entropy(logits, c)
    want = np.mean(np.where(np.asarray(c) > 0.5, w, 1.0) * np.asarray(per))
    np.testing.assert_allclose(got, want, rtol=1e-5)
