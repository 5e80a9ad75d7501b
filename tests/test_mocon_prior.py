"""``mocon``'s learned distribution prior (Neural MoCon Sec. 3.3; issue 21, item 4).

References: MuJoCo's own quaternion functions for the feature geometry, hand-worked values and a
Monte-Carlo estimate for the KL divergence, the controller's committed simulation (MuJoCo C) for
the training recipe's physical branch, and JAX's gradients for which network each loss term
trains.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import rollout

from jmocap.data import synthetic as S
from jmocap.inputs import ClipInputs
from jmocap.methods import mocon as MC
from jmocap.methods import mocon_prior as MP
from jmocap.pipeline import subject_model
from test_mocon import FAST, _reference

NU = 41


def _unit(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_quaternion_helpers_match_mujoco():
    rng = np.random.default_rng(0)
    a, b = _unit(rng, 20), _unit(rng, 20)
    v = rng.normal(size=(20, 3))
    got_mul, got_log, got_rot = MP._quat_mul(a, b), MP._quat_log(a), MP._quat_rotate_inv(a, v)
    for i in range(20):
        want = np.zeros(4)
        mujoco.mju_mulQuat(want, a[i], b[i])
        np.testing.assert_allclose(got_mul[i], want, atol=1e-12)
        vel = np.zeros(3)
        # MuJoCo's quat2Vel is the rotation vector / dt, through the shorter way round
        mujoco.mju_quat2Vel(vel, a[i] if a[i, 0] >= 0 else -a[i], 1.0)
        np.testing.assert_allclose(got_log[i], vel, atol=1e-10)
        neg, r = np.zeros(4), np.zeros(3)
        mujoco.mju_negQuat(neg, a[i])
        mujoco.mju_rotVecQuat(r, v[i], neg)
        np.testing.assert_allclose(got_rot[i], r, atol=1e-12)


def test_kl_of_diagonal_gaussians():
    # hand-worked: KL(N(0, 1) || N(1, 2^2)) = ln 2 + (1 + 1) / 8 - 1/2
    kl = float(MP.kl_diag(jnp.zeros(1), jnp.ones(1), jnp.ones(1), 2 * jnp.ones(1)))
    assert kl == pytest.approx(np.log(2) + 0.25 - 0.5, abs=1e-6)
    assert float(MP.kl_diag(jnp.ones(3), jnp.ones(3) * 0.3, jnp.ones(3), jnp.ones(3) * 0.3)) == pytest.approx(0, abs=1e-6)
    # Monte Carlo: E_q[log q - log p] over 3 dimensions
    rng = np.random.default_rng(1)
    mq, sq, mp, sp = rng.normal(size=3), rng.uniform(0.3, 2, 3), rng.normal(size=3), rng.uniform(0.3, 2, 3)
    x = mq + sq * rng.normal(size=(400_000, 3))

    def logpdf(x, m, s):
        return -0.5 * ((x - m) / s) ** 2 - np.log(s) - 0.5 * np.log(2 * np.pi)

    r = np.sum(logpdf(x, mq, sq) - logpdf(x, mp, sp), -1)
    kl = float(MP.kl_diag(jnp.asarray(mq), jnp.asarray(sq), jnp.asarray(mp), jnp.asarray(sp)))
    assert abs(kl - r.mean()) < 4 * r.std() / np.sqrt(len(r)) + 1e-5 * kl


def test_an_untrained_encoder_is_the_fixed_gaussian_and_sigma_is_bounded():
    params = MP.init_prior_params(jax.random.PRNGKey(0), NU)
    f = jax.random.normal(jax.random.PRNGKey(1), (5, MP.num_features(NU)))
    mu, sigma = MP.encode(params, f)
    np.testing.assert_array_equal(np.asarray(mu), 0.0)
    np.testing.assert_allclose(np.asarray(sigma), 1.0, rtol=1e-6)
    big = jax.tree.map(lambda x: x, params)
    big["encoder"]["mlp"]["out"]["bias"] = jnp.full(2 * NU, 1e3).at[NU:].set(jnp.r_[jnp.full(NU // 2, 1e3),
                                                                                      jnp.full(NU - NU // 2, -1e3)])
    _, s = MP.encode(big, f)
    assert np.all((np.asarray(s) >= MP.SIGMA_MIN * (1 - 1e-5)) & (np.asarray(s) <= MP.SIGMA_MAX * (1 + 1e-5)))
    assert MP.nu_of(params) == NU


def _yaw(rng):
    a = rng.uniform(-np.pi, np.pi)
    return np.array([np.cos(a / 2), 0, 0, np.sin(a / 2)]), rng.normal(size=3) * [2, 2, 0]


def _move(q, qd, yaw, shift):
    """The same state turned about the vertical by ``yaw`` and shifted horizontally."""
    q, qd = q.copy(), qd.copy()
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, yaw)
    R = R.reshape(3, 3)
    q[..., :3] = q[..., :3] @ R.T + shift
    q[..., 3:7] = MP._quat_mul(np.broadcast_to(yaw, q[..., 3:7].shape), q[..., 3:7])
    qd[..., :3] = qd[..., :3] @ R.T  # the free joint's linear velocity is in the world frame
    return q, qd


def test_features_and_deviations_are_relative_to_the_reference():
    """The character on its reference gives zero errors; turning and moving the whole scene about
    the vertical (state and reference together) changes nothing."""
    rng = np.random.default_rng(2)
    nq, nv = 7 + NU, 6 + NU
    ref = rng.normal(size=(3, nq)) * 0.3
    ref[:, 3:7] = _unit(rng, 3)
    ref[:, 2] = 1.0
    ref_qd = rng.normal(size=nv)
    q = ref[0] + rng.normal(size=nq) * 0.05
    q[3:7] = MP._quat_mul(ref[0, 3:7], np.r_[1.0, rng.normal(size=3) * 0.05])
    q[3:7] /= np.linalg.norm(q[3:7])
    qd = ref_qd + rng.normal(size=nv) * 0.2
    contact, prev = np.array([1.0, 0, 1, 0]), rng.normal(size=NU)
    f = MP.window_features(q, qd, ref, ref_qd, contact, prev)
    assert f.shape == (MP.num_features(NU),)
    on = MP.window_features(ref[0], ref_qd, ref, ref_qd, contact, prev)
    np.testing.assert_allclose(on[:2 * NU + 12], 0.0, atol=1e-6)
    yaw, shift = _yaw(rng)
    q2, qd2 = _move(q, qd, yaw, shift)
    ref2, ref_qd2 = _move(ref, ref_qd, yaw, shift)
    np.testing.assert_allclose(MP.window_features(q2, qd2, ref2, ref_qd2, contact, prev), f, atol=2e-5)
    dev = MP.deviation(q, ref[1], ref[0])
    assert dev.shape == (NU + 6,)
    np.testing.assert_allclose(MP.deviation(ref[1], ref[1], ref[0]), 0.0, atol=1e-6)
    np.testing.assert_allclose(MP.deviation(q2, ref2[1], ref2[0]), dev, atol=2e-5)


def test_each_loss_term_trains_its_network(enable_x64):
    """L_sim (Eq. 6) trains the decoder at the simulated corrections; L_rec (Eq. 7) trains the
    encoder only, through the decoder (checked against a finite difference, float64); the KL term
    (Eq. 5) trains the encoder."""
    params = MP.init_prior_params(jax.random.PRNGKey(0), NU)
    # a non-zero encoder output layer, so the encoder's gradients are not trivially zero
    params["encoder"]["mlp"]["out"]["kernel"] = 0.01 * jax.random.normal(jax.random.PRNGKey(3), (256, 2 * NU))
    params["decoder"]["mlp"]["out"]["kernel"] = 0.01 * jax.random.normal(jax.random.PRNGKey(4), (256, MP.num_decoded(NU)))
    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), params)
    k = jax.random.split(jax.random.PRNGKey(5), 5)
    B = 8
    f = jax.random.normal(k[0], (B, MP.num_features(NU)), jnp.float64)
    eps = jax.random.normal(k[1], (B, NU), jnp.float64)
    sim = jax.random.normal(k[2], (B, MP.num_decoded(NU)), jnp.float64)
    mu_ce, sig_ce = jax.random.normal(k[3], (B, NU), jnp.float64) * 0.3, jnp.full((B, NU), 0.5)
    w = jnp.ones(B)

    def total(p, kl_weight):
        return MP.two_branch_loss(p, f, eps, sim, mu_ce, sig_ce, w, kl_weight=kl_weight, reg_weight=0.0)[0]

    def sim_only(p):
        mu, sigma = MP.encode(p, f)
        pred = MP.decode(p, f, jax.lax.stop_gradient(mu + sigma * eps))
        return jnp.mean((pred - sim) ** 2)

    def rec_only(p):
        mu, sigma = MP.encode(p, f)
        return jnp.mean(MP.decode(p, f, mu + sigma * eps) ** 2)

    grad = jax.jit(jax.grad(total), static_argnums=1)
    g = grad(params, 0.2)
    g_sim = jax.jit(jax.grad(sim_only))(params)
    for a, b in zip(jax.tree.leaves(g["decoder"]), jax.tree.leaves(g_sim["decoder"]), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7)
    assert all(float(jnp.abs(x).max()) == 0 for x in jax.tree.leaves(g_sim["encoder"]))
    g0 = grad(params, 0.0)  # L_rec alone reaches the encoder
    assert max(float(jnp.abs(x).max()) for x in jax.tree.leaves(g0["encoder"])) > 0
    # and it is L_rec's: a finite difference of L_rec along the encoder's output bias
    d = jnp.zeros(2 * NU).at[3].set(1.0)
    h = 1e-5

    def along(t):
        p = jax.tree.map(lambda x: x, params)
        p["encoder"]["mlp"]["out"]["bias"] = params["encoder"]["mlp"]["out"]["bias"] + t * d
        return rec_only(p)

    fd = (along(h) - along(-h)) / (2 * h)
    assert float(g0["encoder"]["mlp"]["out"]["bias"][3]) == pytest.approx(float(fd), rel=1e-5, abs=1e-9)


@pytest.fixture(scope="module")
def walk():
    return S.generate_clip(1, 0, S.SynthConfig(frames=45, kinds=("walk",), physics=True))


def test_the_recorded_windows_replay_in_mujoco(walk):
    """The training recipe's physical branch: each committed window's recorded start state and
    best correction, rolled out by ``mujoco.rollout`` through :func:`mocon.window_controls`,
    reproduce the controller's committed simulation."""
    model = subject_model(walk)
    config = MC.MoconConfig(**FAST)
    rec: dict = {}
    motion = MC.track(model, ClipInputs.from_clip(walk), _reference(walk), config, record=rec)
    c, windows = rec["clip"], rec["windows"]
    assert len(windows) >= (len(walk.gt_q) - 1) // config.window_frames
    sim = MC.Simulation(model, None, walk.fps, config)
    last = {w["k0"]: w for w in windows}  # a rewound window is recorded again: the last one was committed
    datas = [mujoco.MjData(sim.mj) for _ in range(2)]
    n, errs = c["n"], []
    for k0, w in sorted(last.items()):
        if w["k1"] >= len(motion.q):  # the window into the held frame past the clip's end
            continue
        ctrl = MC.window_controls(c["q_ref"], c["ff"], c["hinge_q"], n, w["prev"] * c["spread"],
                                  (w["best"] * c["spread"])[None], k0, w["k1"], w["k2"], config.lookahead_gain)
        states, _ = rollout.rollout(sim.mj, datas, w["state"][None], ctrl,
                                    control_spec=mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED)
        q = states[0, (w["k1"] - k0) * n - 1, 1:1 + sim.mj.nq]
        errs.append(np.abs(q - motion.q[w["k1"]]).max())
        # the features are the recorded state's
        f = MP.window_features(w["state"][1:1 + sim.mj.nq], w["state"][1 + sim.mj.nq:1 + sim.mj.nq + sim.mj.nv],
                               c["q_ref"][[k0, w["k1"], w["k2"]]], c["qd_ref"][k0], c["contact"][w["k1"]], w["prev"])
        np.testing.assert_allclose(f, w["features"], atol=1e-6)
        assert np.all(w["sigma"] >= config.min_spread * (1 - 1e-9))
    assert max(errs) < 1e-3, errs


def test_prior_sampling_needs_a_prior_of_the_characters_size(walk):
    model = subject_model(walk)
    inputs, ref = ClipInputs.from_clip(walk), _reference(walk)
    with pytest.raises(ValueError, match="prior"):
        MC.track(model, inputs, ref, MC.MoconConfig(sampling="prior", **FAST))
    small = MP.init_prior_params(jax.random.PRNGKey(0), 5)
    with pytest.raises(ValueError, match="hinges"):
        MC.track(model, inputs, ref, MC.MoconConfig(sampling="prior", **FAST), prior=small)


def test_an_untrained_prior_samples_the_fixed_gaussian(walk):
    """With an untrained (zero-output) prior, ``sampling="prior"`` draws from mean 0 and the base
    spread: the Gaussian sampler with ``carry = 0``, the same random numbers, the same result."""
    model = subject_model(walk)
    inputs, ref = ClipInputs.from_clip(walk), _reference(walk)
    cfg = dict(FAST, iterations=1, carry=0.0)
    a = MC.track(model, inputs, ref, MC.MoconConfig(sampling="prior", **cfg),
                 prior=MP.init_prior_params(jax.random.PRNGKey(0), NU))
    b = MC.track(model, inputs, ref, MC.MoconConfig(**cfg))
    np.testing.assert_allclose(np.asarray(a.q), np.asarray(b.q), atol=1e-4)


def test_the_shipped_prior_fits_the_character():
    """The shipped prior (experiments/train_mocon_prior.py --ship) is for jmocap's 41 hinges and
    gives finite distributions within its bounds; a run's own prior takes precedence."""
    params = MP.default_prior_params()
    assert MP.nu_of(params) == NU
    f = np.random.default_rng(0).normal(size=(16, MP.num_features(NU))).astype(np.float32)
    mu, sigma = (np.asarray(x) for x in MP.encode_jit(params, jnp.asarray(f)))
    assert np.isfinite(mu).all() and np.all((sigma >= MP.SIGMA_MIN * 0.999) & (sigma <= MP.SIGMA_MAX * 1.001))
    own = MP.init_prior_params(jax.random.PRNGKey(0), NU)
    assert MP.prior_params({"mocon_prior": own}) is own and MP.prior_params({}) is params
