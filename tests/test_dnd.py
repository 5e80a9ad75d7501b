"""D&D (issue 20, items 3-6): the camera's motion from a track, the constrained update, PCT's
gradient, the attentive PD controller, and the method through the batch engine.

References: the track's own orientations (integration of its angular velocity), a constant
acceleration's exact second difference, the world velocity of a contact point by forward-mode
differentiation of its world position in time (independent of the update's algebra), and
finite behaviour of a registered method run through ``jmocap.batch``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import x64
from jmocap import physics as P
from jmocap.methods import dnd as D
from jmocap.model import load_model
from jmocap.physics.rotations import axis_angle_to_mat

SMALL = D.DnDConfig(channels=16, depth=2, attention=4, iterations=1)


@pytest.fixture(scope="module")
def model():
    return load_model(with_mjx=False)


def _track(T=40, fps=30.0):
    """A camera turning about a tilted axis at a varying rate while its centre accelerates
    uniformly: world -> camera (T, 4, 4) in float64."""
    t = np.arange(T) / fps
    axis = np.array([0.3, -1.0, 0.4]) / np.linalg.norm([0.3, -1.0, 0.4])
    angle = 0.8 * t + 0.3 * np.sin(2.0 * t)
    Rcw = np.asarray(axis_angle_to_mat(jnp.broadcast_to(jnp.asarray(axis), (T, 3)), jnp.asarray(angle)))
    a_w = np.array([0.7, -0.2, 0.1])
    c = np.array([1.0, -3.0, 1.5]) + np.outer(t, [0.5, 0.2, 0.0]) + 0.5 * np.outer(t**2, a_w)
    E = np.zeros((T, 4, 4))
    E[:, :3, :3] = np.swapaxes(Rcw, -1, -2)
    E[:, :3, 3] = -np.einsum("tij,tj->ti", E[:, :3, :3], c)
    E[:, 3, 3] = 1.0
    return E, a_w


def test_track_motion_integrates_back_to_the_track_and_sees_the_acceleration():
    with x64():
        E, a_w = _track()
        fps = 30.0
        omega, alpha, accel = D.track_motion(jnp.asarray(E), fps)
        R = jnp.asarray(E[0, :3, :3])
        k = 3
        for t in range(len(E) - 1):
            for _ in range(k):  # sub-steps of one frame, the way the dynamics integrate it
                R = D.rotate_camera(R, omega[t], 1.0 / (fps * k))
            np.testing.assert_allclose(np.asarray(R), E[t + 1, :3, :3], atol=1e-10)
        # a uniformly accelerating centre: the second difference is exact inside the clip
        want = np.einsum("tij,j->ti", E[:, :3, :3], a_w)
        np.testing.assert_allclose(np.asarray(accel)[2:-2], want[2:-2], atol=1e-8)
        assert np.all(np.isfinite(np.asarray(alpha)))


def test_constrained_update_pins_contacts_in_the_world(model):
    """With the contacts of one foot in contact and a large weight, their world velocity --
    the time derivative of ``pos + R^T (x_j(q) - root)`` as the step integrates it -- vanishes;
    without contacts the velocities are unchanged."""
    with x64():
        rng = np.random.default_rng(0)
        q = jnp.asarray(model.qpos0, jnp.float64).at[0:3].set(jnp.array([0.2, 0.5, 4.0]))
        qd = jnp.asarray(rng.normal(0, 0.5, model.nv))
        vel = jnp.asarray(rng.normal(0, 0.5, 3))
        R = jnp.asarray(np.asarray(axis_angle_to_mat(jnp.array([1.0, 0.0, 0.0]), jnp.array(2.0))))
        omega = jnp.array([0.1, -0.3, 0.2])
        kin = P.forward_kinematics(model, q)
        M = P.mass_matrix(model, q, kin=kin)
        m = float(np.sum(model.body_mass))
        metric = jnp.zeros((model.nv + 3,) * 2).at[: model.nv, : model.nv].set(M).at[model.nv :, model.nv :].set(m * jnp.eye(3))

        def world_velocity(qd_, vel_):
            def x_w(s):
                qs = P.integrate_positions(model, q, qd_, s)
                Rs = D.rotate_camera(R, omega, s)
                sites = P.site_positions(model, qs, model.topo.contact_sites)
                return vel_ * s + (sites - qs[0:3]) @ Rs  # R^T x as row vectors

            return jax.jvp(x_w, (0.0,), (1.0,))[1]

        b = jnp.array([1.0, 1.0, 0.0, 0.0])
        qd1, vel1 = D.constrained_update(model, kin, metric, q, qd, vel, R, omega, b, 1e7 * m)
        v = world_velocity(qd1, vel1)
        assert float(jnp.max(jnp.abs(v[:2]))) < 1e-4
        assert float(jnp.max(jnp.abs(world_velocity(qd, vel)[:2]))) > 0.1  # it had to move them
        qd0, vel0 = D.constrained_update(model, kin, metric, q, qd, vel, R, omega, jnp.zeros(4), 1e7 * m)
        np.testing.assert_allclose(np.asarray(qd0), np.asarray(qd), atol=1e-12)
        np.testing.assert_allclose(np.asarray(vel0), np.asarray(vel), atol=1e-12)


def _initial(model, T=20, jitter=0.0, seed=0):
    """A smooth camera-frame motion (a step forward, knees swinging), optionally with jitter."""
    rng = np.random.default_rng(seed)
    q0 = np.asarray(model.qpos0, np.float32)
    t = np.arange(T) / 30.0
    q = np.repeat(q0[None], T, 0)
    q[:, 0] = 0.3 * t
    q[:, 2] = 4.0
    q[:, 7:] += 0.2 * np.sin(2.0 * t)[:, None]
    q += jitter * rng.normal(size=q.shape).astype(np.float32) * (np.arange(model.nq) != 3)
    q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=-1, keepdims=True)
    J = 25
    return D.Initial(jnp.asarray(q), jnp.zeros((T, J, 3)), jnp.zeros((T, 4)), jnp.asarray(q), jnp.full((T, 4), 0.5))


def test_attention_weights_sum_to_one_and_a_jittery_target_gives_a_smooth_motion(model):
    """Item 5: the attention weights of every frame are a distribution (any parameters), and the
    controller turns a jittery initial motion into a motion far smoother than it."""
    cfg = SMALL
    net = D.init_params(jax.random.PRNGKey(0), model, cfg)["dnd"]
    # a controller whose head is not zero, so that the weights are not only the prior's
    noisy = jax.tree.map(lambda a: a + 0.3 * jax.random.normal(jax.random.PRNGKey(1), a.shape), net)
    init = _initial(model, jitter=0.03)
    x = D.features(model, init, jnp.array([0.0, 9.81, 0.0]), jnp.ones(20, bool))
    for params in (net, noisy):
        ctrl = D.pd_control(params, model, x, init.q_cam, cfg)
        w = np.asarray(ctrl.weights)
        assert w.shape == (20, 2 * cfg.attention + 1) and np.all(w >= 0)
        np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-6)
    ctrl = D.pd_control(net, model, x, init.q_cam, cfg)
    phys = D.physical_properties(net, model, x, cfg)
    T = 20
    inputs = _inputs(T)
    b = jnp.zeros((T, 4))
    frames = D.frame_inputs(model, inputs, init, phys, ctrl, b, cfg)
    state = D.initial_state(model, inputs, init.q_cam, 30.0)
    # gravity and the inertial force off the table: a body floating in a still camera
    state = state.replace(R=jnp.eye(3))
    frames = frames.replace(grf=frames.grf * 0)
    _, states, _ = D.simulate(model.replace(gravity=np.zeros(3)), state, frames, 30.0, cfg)

    def roughness(q):
        return float(jnp.mean(jnp.abs(q[2:, 7:] - 2 * q[1:-1, 7:] + q[:-2, 7:])))

    assert roughness(states.q) < 0.25 * roughness(init.q_cam)
    assert roughness(ctrl.target) < 0.5 * roughness(init.q_cam)


def _inputs(T, track=None):
    from jmocap.inputs import ClipInputs

    E = np.eye(4, dtype=np.float32) if track is None else track[0]
    tr = np.broadcast_to(E, (T, 4, 4)) if track is None else track
    return ClipInputs(jnp.zeros((T, 25, 3)), jnp.array([1000.0, 1000.0, 640.0, 360.0]), jnp.array([1280.0, 720.0]),
                      jnp.asarray(E), jnp.float32(30.0), jnp.ones(T, bool), jnp.asarray(tr, jnp.float32))


@pytest.mark.parametrize("contacts", ["pct", "discrete"])
def test_pct_gradient_reaches_the_contact_head_without_contact_labels(model, contacts):
    """Item 4: a loss on the motion alone (no contact label) reaches DyNet's contact logits
    through PCT's Gumbel-softmax sample; with thresholded contacts it cannot."""
    cfg = SMALL.replace(contacts=contacts)
    T = 12
    init = _initial(model, T)
    net = D.init_params(jax.random.PRNGKey(0), model, cfg)["dnd"]
    logits = slice(6 + 3 * 4, 6 + 3 * 4 + 4)
    head = net["dynet"]["Dense_1"]
    head["bias"] = head["bias"].at[logits].set(jnp.array([2.0, 2.0, -2.0, -2.0]))  # the left foot down
    inputs = _inputs(T)

    def loss(net):
        params = {"dnd": net}
        r = D.rollout(params, model, inputs, cfg, key=jax.random.PRNGKey(3), train=True, initial=init)
        return jnp.sum(r.states.pos**2) + jnp.sum(r.states.q[:, 7:] ** 2)

    g = jax.grad(loss)(net)
    head = g["dynet"]["Dense_1"]
    contact_grad = float(jnp.sum(jnp.abs(head["kernel"][:, logits])) + jnp.sum(jnp.abs(head["bias"][logits])))
    force_grad = float(jnp.sum(jnp.abs(head["kernel"][:, 6:18])))
    assert np.isfinite(contact_grad) and force_grad > 0
    if contacts == "pct":
        assert contact_grad > 1e-6
    else:
        assert contact_grad == 0.0


@pytest.mark.slow
def test_training_window_loss_is_finite_and_its_gradient_matches_finite_differences(model):
    """The training loss (jmocap.train_dnd.window_loss) on a made-up window: finite, and its
    gradient along a random direction of DyNet's parameters agrees with a central difference."""
    from jmocap.train_dnd import LOSS_WEIGHTS, window_loss

    with x64():
        cfg = SMALL.replace(contacts="discrete")  # deterministic: no Gumbel noise
        T = 10
        init = _initial(model, T)
        E, _ = _track(T)
        q = np.asarray(init.q_cam, np.float64)
        d = dict(q_cam=q, p_rr=np.zeros((T, 25, 3)), logits=np.zeros((T, 4)), q_world=q, contacts=np.full((T, 4), 0.3), track=E,
                 gt_q=q, gt_q_cam=q, gt_kp_cam=np.zeros((T, 25, 3)) + [0, 0, 4.0], gt_2d=np.zeros((T, 25, 2)) + 600,
                 gt_contacts=np.zeros((T, 4)), gt_omega=np.zeros((T, 3)), gt_accel=np.zeros((T, 3)),
                 intrinsics=np.array([1000.0, 1000.0, 640.0, 360.0]), image_size=np.array([1280.0, 720.0]),
                 fps=np.float64(30.0))
        d = jax.tree.map(jnp.asarray, d)
        net = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64),
                           D.init_params(jax.random.PRNGKey(0), model, cfg)["dnd"])
        net = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.PRNGKey(2), a.shape, a.dtype), net)

        def f(n):
            return window_loss(n, model, d, None, cfg, 3, LOSS_WEIGHTS)[0]

        g = jax.grad(f)(net)
        direction = jax.tree.map(lambda a: jax.random.normal(jax.random.PRNGKey(5), a.shape, a.dtype), net)
        eps = 1e-5
        plus = f(jax.tree.map(lambda a, v: a + eps * v, net, direction))
        minus = f(jax.tree.map(lambda a, v: a - eps * v, net, direction))
        fd = (plus - minus) / (2 * eps)
        an = sum(jnp.sum(a * v) for a, v in zip(jax.tree.leaves(g), jax.tree.leaves(direction), strict=True))
        assert np.isfinite(float(f(net)))
        assert float(an) == pytest.approx(float(fd), rel=1e-4, abs=1e-7)


def test_moving_a_motion_moves_its_estimated_track_with_it():
    """``floor.move_motion`` (eval's change of world for a withheld camera) keeps what every
    estimated camera sees: ``E' (R X + t) = E X`` for the root of every frame."""
    from jmocap.methods.floor import move_motion
    from jmocap.motion import Motion

    with x64():
        T = 6
        E, _ = _track(T)
        rng = np.random.default_rng(1)
        q = np.zeros((T, 48))
        q[:, 0:3] = rng.normal(size=(T, 3))
        q[:, 3] = 1.0
        m = Motion(jnp.asarray(q), jnp.zeros((T, 47)), jnp.zeros((T, 47)), jnp.zeros((T, 4, 3)), jnp.zeros((T, 4)),
                   jnp.asarray(q), jnp.ones(T, bool), camera_track=jnp.asarray(E))
        R = np.asarray(axis_angle_to_mat(jnp.array([0.2, 0.9, -0.4]) / np.linalg.norm([0.2, 0.9, -0.4]), jnp.array(0.7)))
        t = np.array([0.3, -1.2, 0.05])
        moved = move_motion(m, jnp.asarray(R), jnp.asarray(t))
        before = np.einsum("tij,tj->ti", E[:, :3, :3], q[:, 0:3]) + E[:, :3, 3]
        Em = np.asarray(moved.camera_track)
        after = np.einsum("tij,tj->ti", Em[:, :3, :3], np.asarray(moved.q[:, 0:3])) + Em[:, :3, 3]
        np.testing.assert_allclose(after, before, atol=1e-12)
        np.testing.assert_allclose(np.asarray(moved.q[:, 0:3]), q[:, 0:3] @ R.T + t, atol=1e-12)


def test_shipped_dnd_runs_in_the_batch_engine_and_reads_only_the_first_camera(tmp_path):
    """``jmocap reconstruct --method dnd``'s engine on a hand-held clip: a finite world motion and
    an estimated camera track that starts at the clip's first camera; the clip's own track after
    its first frame is never read (the same result with the track replaced by its first frame)."""
    from jmocap.batch import BatchOptions, reconstruct_archive
    from jmocap.data.clip import save_clip
    from jmocap.data.synthetic import SynthConfig, generate_clip
    from jmocap.results import load_result
    from jmocap.weights import check_params, load_run_params

    clip = generate_clip(31, 0, SynthConfig(frames=48, moving_camera=("handheld",)))
    still = clip.replace(camera_track=None, meta={**clip.meta})
    params, config = load_run_params(None, method="dnd")
    check_params(params, config, "dnd")  # the shipped networks come from their own file
    out = {}
    for name, c in (("moving", clip), ("still", still)):
        src = tmp_path / f"in_{name}"
        src.mkdir()
        save_clip(src / f"{c.name}.npz", c)
        reconstruct_archive(src, tmp_path / name, params, config, BatchOptions(batch=1, bucket=16), method="dnd")
        out[name] = load_result(tmp_path / name / f"{c.name}.npz")
    q = out["moving"]["q"]
    assert np.isfinite(q).all() and np.isfinite(out["moving"]["grf"]).all()
    # the result keeps the input track and the estimated one, which starts at the first camera
    est = out["still"]["camera_track_estimated"]
    assert out["still"]["camera_track"] is None and est.shape == (48, 4, 4)
    np.testing.assert_allclose(est[0], clip.camera_track[0], atol=1e-4)
    np.testing.assert_allclose(out["moving"]["camera_track"], clip.camera_track, atol=1e-12)
    np.testing.assert_allclose(q, out["still"]["q"], atol=1e-5)
    # the root starts where TPNet puts it in the first camera, at a standing height
    assert 0.5 < q[0, 2] < 1.5


@pytest.mark.slow
def test_training_resumes_where_it_stopped(tmp_path, monkeypatch):
    """An interrupted training run, re-run, ends with the networks of an uninterrupted one (the
    checkpoint holds the parameters, optimiser state, step, key and the window sampler)."""
    from jmocap.data.clip import save_clip
    from jmocap.data.synthetic import SynthConfig, generate_clip
    from jmocap.train_dnd import DnDData, DnDTrainConfig, train
    from jmocap.weights import load_run_params

    data = tmp_path / "data"
    data.mkdir()
    for i in range(2):
        c = generate_clip(5, i, SynthConfig(frames=40, moving_camera=("pan", "dolly")))
        save_clip(data / f"{c.name}.npz", c)
    params, kin = load_run_params(None, method="kinematic")
    base = SMALL.replace(layout=kin.layout, nets=kin.nets)

    def cfg(out):
        return DnDTrainConfig(data=str(data), out=str(out), steps=4, batch=2, context=32, warmup=8,
                              checkpoint_every=2, log_every=1)

    whole = train(cfg(tmp_path / "whole"), params, base, progress=False)
    calls = {"n": 0}
    sample = DnDData.sample

    def interrupted(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return sample(self, *a, **k)

    monkeypatch.setattr(DnDData, "sample", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(cfg(tmp_path / "cut"), params, base, progress=False)
    monkeypatch.setattr(DnDData, "sample", sample)
    resumed = train(cfg(tmp_path / "cut"), params, base, progress=False)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
