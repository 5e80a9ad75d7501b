"""The tracking QP of the ``pip`` method (PIP's motion optimiser, jmocap.physics.tracking).

References: finite differences for the bias acceleration and the gradients, Clarabel (interior
point, float64) for the QP solutions on >= 1,000 instances taken from real cycle states, and
hand-worked cases for the contact rule and unconditional non-penetration.
"""

from __future__ import annotations

import functools
from importlib.resources import files

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jmocap import physics as P
from jmocap.data.clip import load_clip
from jmocap.inputs import ClipInputs
from jmocap.methods import pip
from jmocap.methods import stages as S
from jmocap.model import load_model
from jmocap.physics.qp import solve_projection_info
from jmocap.physics.tracking import (
    TrackingWeights,
    contact_state,
    point_bias_acceleration,
    solve_qp,
)
from jmocap.pipeline import subject_model
from jmocap.weights import load_run_params
from qp_reference import clarabel_projection, kkt_optimal, polished_projection

DEMO = files("jmocap") / "assets/demo/ground_truth"


def _random_state(model, rng, dtype=np.float64):
    q = np.asarray(model.qpos0, dtype).copy()
    q[2] = 1.0
    axis = rng.normal(size=3)
    angle = rng.uniform(0, 0.5)
    q[3:7] = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / np.linalg.norm(axis)])
    hq = model.topo.hinge_qadr
    q[hq] = rng.uniform(-0.4, 0.4, size=hq.size)
    qd = rng.normal(size=model.nv).astype(dtype)
    return jnp.asarray(q), jnp.asarray(qd)


def _bias_check(model, q, qd, offset):
    bodies = np.arange(1, model.topo.nbody)

    def points(q):
        kin = P.forward_kinematics(model, q)
        return kin, kin.xpos[bodies] + jnp.einsum("bij,bj->bi", kin.xmat[bodies], offset)

    def velocity(s):
        kin, p = points(P.integrate_positions(model, q, qd, s))
        J, _ = P.point_jacobian(model, kin, p, bodies)
        return J @ qd

    h = 1e-5
    fd = (velocity(h) - velocity(-h)) / (2 * h)
    kin, p = points(q)
    got = point_bias_acceleration(model, kin, qd, p, bodies)
    np.testing.assert_allclose(got, fd, rtol=1e-6, atol=1e-6 * float(jnp.max(jnp.abs(fd))))


def test_point_bias_acceleration_matches_finite_differences(enable_x64):
    """Jdot qd of body origins and offset points = d/ds [J(q(s)) qd] along q(s) = q (+) s qd."""
    model = load_model()
    rng = np.random.default_rng(0)
    for _ in range(3):
        q, qd = _random_state(model, rng)
        _bias_check(model, q, qd, jnp.asarray(rng.normal(scale=0.1, size=(model.topo.nbody - 1, 3))))


def test_contact_state_is_pips_rule():
    height = jnp.array([0.004, 0.004, 0.02, 0.02, 0.04, 0.04, -0.01, -0.01])
    prob = jnp.array([0.1, 0.9, 0.1, 0.9, 0.1, 0.9, 0.1, 0.9])
    got = contact_state(height, prob)
    # touching: always; near (< 3 cm): when the estimator says so; above 3 cm: never
    np.testing.assert_array_equal(got, [True, True, False, True, False, False, True, True])


def _demo_cycle(names=("demo_walk", "demo_run", "demo_jump"), frames=120):
    """Cycle states of the pip method on the demo clips: (model, config, states, refs, dt)."""
    x64 = bool(jax.config.jax_enable_x64)
    runs = [_demo_run(name, frames, x64) for name in names]
    return runs[0][0], [r[1] for r in runs]


@functools.lru_cache(maxsize=8)
def _demo_run(name: str, frames: int, x64: bool):
    """One demo clip's pip cycle in the precision of ``x64``, computed once per test module (the
    tests that read the same clip share it: it is a minute of compilation and simulation)."""
    params, config = load_run_params(None, method="pip")
    dtype = jnp.float64 if x64 else jnp.float32
    params = jax.tree.map(lambda a: jnp.asarray(a, dtype), params)
    clip = load_clip(DEMO / f"{name}.npz").slice(0, frames)
    model = subject_model(clip)
    inputs = ClipInputs.from_clip(clip)
    inputs = inputs.replace(keypoints=jnp.asarray(inputs.keypoints, dtype))

    @jax.jit
    def run(params, inputs, model=model):
        ref = pip.clip_reference(params, model, inputs, config)
        _, fo = pip.simulate(model, ref, jnp.asarray(inputs.mask), inputs.fps, config)
        return ref, fo

    ref, fo = run(params, inputs)
    return config, (model, ref, fo, 1.0 / clip.fps / config.iterations)


def _objective(qp, x):
    H, g = np.asarray(qp.H, np.float64), np.asarray(qp.g, np.float64)
    return 0.5 * x @ H @ x - g @ x


def _solve_x(qp):
    info = solve_projection_info(None, qp.G, qp.v, qp.lower, chol=qp.L)
    return info.x, info.converged


@pytest.mark.parametrize("stride", [10, pytest.param(1, marks=pytest.mark.slow)])
def test_tracking_qp_matches_clarabel_on_cycle_states(enable_x64, stride):
    """QPs from the cycle's own states on the demo clips (each frame's state with PIP's contact
    state, and with every point, none, the heels only and the toes only in contact): jmocap's
    exact solver certifies every one; on every ``stride``-th frame it reaches Clarabel's optimum
    (stride 1, ``make test-slow``: >= 1,000 QPs; stride 10 in the default suite: >= 100)."""
    config, runs = _demo_cycle(("demo_walk", "demo_run"))
    n = n_kkt = 0
    patterns = jnp.array([[1] * 8, [0] * 8, [1, 1, 0, 0, 1, 1, 0, 0], [0, 0, 1, 1, 0, 0, 1, 1]], bool)
    for model, ref, fo, dt in runs:
        T = fo.q.shape[0]
        states = pip.CycleState(fo.q, fo.qd, jnp.zeros((T, 4, 3)))
        rule = jax.jit(jax.vmap(lambda s, r, model=model, dt=dt: pip.step_qp(model, s, r, dt, config)[0]))
        given = jax.jit(jax.vmap(lambda s, r, o, model=model, dt=dt: pip.step_qp(model, s, r, dt, config, o)[0],
                                 in_axes=(0, 0, None)))
        for qps in [rule(states, ref)] + [given(states, ref, o) for o in patterns]:
            xs, ok = jax.jit(jax.vmap(_solve_x))(qps)
            assert bool(jnp.all(ok)), "a float64 tracking QP was not certified"
            for t in range(0, T, stride):
                qp = jax.tree.map(lambda a, t=t: np.asarray(a[t]), qps)
                x_ref, status = polished_projection(qp.H, qp.G, qp.v, qp.lower)
                x = np.asarray(xs[t], np.float64)
                if status not in ("polished", "Solved", "AlmostSolved"):
                    # Clarabel stalls (MaxIterations, at any tolerance) on a few instances whose
                    # slacks span 1e-14 to 4e3: there the reference is the KKT conditions
                    # checked in numpy (sufficient for this strictly convex QP)
                    assert kkt_optimal(qp.H, qp.G, qp.v, qp.lower, x), (t, status)
                    n_kkt += 1
                    n += 1
                    continue
                # feasible, and the same optimal value (the optimum is unique; x itself is
                # as accurate as H's conditioning allows)
                finite = np.isfinite(qp.lower)
                slack = qp.G[finite] @ x - qp.lower[finite]
                assert slack.min() >= -1e-7 * (1 + np.abs(qp.lower[finite]).max())
                f, f_ref = _objective(qp, x), _objective(qp, x_ref)
                assert f <= f_ref + 1e-8 * (1 + abs(f_ref)), (t, f, f_ref)
                n += 1
    assert n >= 1000 // stride, n
    assert n_kkt <= 0.02 * n, (n_kkt, n)  # Clarabel is the reference on all but a few


def _pyramid_faces(mu):
    return np.array([[s1, s2, mu] for s1 in (1.0, -1.0) for s2 in (1.0, -1.0)])


def test_net_force_cone_keeps_contacts_plus_residual_in_the_pyramid(enable_x64):
    """A target that asks the body for 2 g forward (the floor gives at most mu g) with a cheap
    residual (weight 1 instead of 300): without the net-force rows the residual supplies the
    rest, beyond friction; with them the net external
    force (contacts + residual = the root's translational rows of the equation of motion) stays
    in the pyramid, and the solution is Clarabel's optimum of the QP with the rows."""
    from jmocap.physics.tracking import tracking_qp

    clip = load_clip(DEMO / "demo_walk.npz")
    model = subject_model(clip)
    q = jnp.asarray(clip.gt_q[10], jnp.float64)
    qd = jnp.asarray(clip.gt_qd[10], jnp.float64)
    bodies = pip.tracked_bodies(model)
    mass = float(np.sum(model.body_mass))
    faces = _pyramid_faces(pip.PIPConfig().mu)

    @functools.partial(jax.jit, static_argnums=0)
    def solve(rows, q, qd):
        body = S.rigid_body_terms(model, q, qd)
        pts, bodies_c, height = S.sole_points(model, body.kin)
        acc_pos = jnp.tile(jnp.array([2 * 9.81, 0.0, 0.0]), (len(bodies), 1))
        qp = tracking_qp(model, body.kin, body.M, body.h, qd, jnp.zeros(model.nv - 3), bodies, acc_pos, pts,
                         bodies_c, height, height < 0.03, 1 / 60, weights=TrackingWeights(residual=1.0),
                         net_force_cone=rows)
        return qp, solve_qp(qp), _solve_x(qp)[0]

    net = {}
    for rows in (False, True):
        qp, sol, x = solve(rows, q, qd)
        assert bool(qp.in_contact.any())
        assert qp.G.shape[0] == 8 * 4 + 8 + (4 if rows else 0)
        assert bool(sol.certified)
        net[rows] = np.asarray(sol.grf.sum(0) + sol.tau[:3]) / mass
        if rows:
            Q = jax.tree.map(lambda a: np.asarray(a), qp)
            x_ref, _ = polished_projection(Q.H, Q.G, Q.v, Q.lower)
            x = np.asarray(x, np.float64)
            assert _objective(Q, x) <= _objective(Q, x_ref) + 1e-8 * (1 + abs(_objective(Q, x_ref)))
    assert np.min(faces @ net[False]) < -1.0  # the residual pushed beyond friction (m/s^2)
    assert np.min(faces @ net[True]) >= -1e-6
    assert net[True][0] > 0.5 * 0.8 * 9.81  # it still pushes forward, as far as friction allows


def test_float32_cycle_is_certified_and_finite():
    """The shipped precision: every QP of the demo clips' cycle certified, forces in the pyramid."""
    _, runs = _demo_cycle(("demo_walk", "demo_run"))
    for _model, _ref, fo, _ in runs:
        assert fo.q.dtype == jnp.float32 and fo.grf.dtype == jnp.float32
        assert bool(jnp.all(jnp.isfinite(fo.q))) and bool(jnp.all(jnp.isfinite(fo.grf)))
        assert float(jnp.mean(~fo.certified)) <= 0.001
        f = np.asarray(fo.grf)
        fz = f[..., 2]
        assert fz.min() >= -1e-3 * fz.max()
        assert np.all(np.abs(f[..., 0]) + np.abs(f[..., 1]) <= 0.8 * fz + 1e-3 * fz.max() + 1e-3)


def test_walking_left_and_right_forces_are_not_the_same_curve():
    """Regression: the shipped physcap config gave L and R vertical GRF correlated at 0.999."""
    _, runs = _demo_cycle(("demo_walk",))
    _, _, fo, _ = runs[0]
    g = np.asarray(fo.grf)
    left, right = g[:, 0, 2] + g[:, 1, 2], g[:, 2, 2] + g[:, 3, 2]
    assert np.std(left) > 0 and np.std(right) > 0
    assert np.corrcoef(left, right)[0, 1] < 0.5
    assert np.max(np.abs(left - right)) > 0.2 * np.max(left + right)


def test_demo_cycle_is_held_up_by_its_contacts():
    """Regression (the shipped default on the demo walk and run, 4 s each): the body is held up
    by the contact forces, not by the virtual root force. Over a clip that starts and ends at
    about the same vertical speed, Newton gives a mean net vertical force of one body weight
    (m dv_z / T is small); here the contacts must carry it (measured: 0.99 and 0.95 body weights)
    and the residual root force stays a fraction of a body weight on average (measured 9.5 and
    12.2 %; the physcap configuration this guards against needed 2-3 body weights)."""
    _, runs = _demo_cycle(("demo_walk", "demo_run"))
    for model, _ref, fo, _ in runs:
        weight = float(np.sum(model.body_mass)) * 9.81
        residual = np.linalg.norm(np.asarray(fo.tau)[:, :3], axis=-1) / weight
        contact_z = np.asarray(fo.grf)[..., 2].sum(-1) / weight
        assert residual.mean() <= 0.25
        assert 0.85 <= contact_z.mean() <= 1.15


def _standing(model, shift=0.0):
    """The standing pose moved up by ``shift`` (float64), the tracked bodies and their origins."""
    q = jnp.asarray(model.mj.key_qpos[0] if model.mj.nkey else model.qpos0, jnp.float64).at[2].add(shift)
    bodies = pip.tracked_bodies(model)
    return q, bodies, P.forward_kinematics(model, q).xpos[bodies]


@pytest.mark.parametrize("shift", [0.02, 0.0, -0.02])
@pytest.mark.parametrize("contact", [True, False])
def test_non_penetration_is_unconditional(enable_x64, shift, contact):
    """Above, touching, below the floor; in contact or not: every sole point ends the step on or
    above the floor; a point above may move down to it; the solution is Clarabel's."""
    model = load_model()
    config = pip.PIPConfig()
    q, bodies, pos = _standing(model, shift)
    qd = jnp.zeros(model.nv).at[2].set(-3.0)  # moving down fast: free, it would pass the floor
    ref = pip.Reference(q, jnp.zeros(model.nv), pos - jnp.array([0, 0, 0.3]), jnp.zeros((bodies.size, 3)),
                        jnp.array([0.0, 0.0, -2.0]), jnp.ones(4))
    dt = 1.0 / 60
    state = pip.CycleState(q, qd, jnp.zeros((4, 3)))
    qp, _ = pip.step_qp(model, state, ref, dt, config, jnp.full(8, contact))
    sol = solve_qp(qp)
    assert bool(sol.certified)
    kin = P.forward_kinematics(model, q)
    pts, b, height = pip.sole_points(model, kin)
    J, _ = P.point_jacobian(model, kin, pts, b)
    z_next = np.asarray(height + dt * (J[:, 2] @ (qd + dt * sol.qdd)))
    assert z_next.min() >= -1e-9
    # the lowest point lands on the floor, not above it (a point above may always move down)
    assert z_next.min() < 1e-9
    x_ref, _, _ = clarabel_projection(qp.H, qp.G, qp.v, qp.lower)
    x = np.asarray(_solve_x(qp)[0], np.float64)
    assert _objective(qp, x) <= _objective(qp, x_ref) + 1e-9 * (1 + abs(_objective(qp, x_ref)))
    if not contact:
        np.testing.assert_array_equal(np.asarray(sol.grf), 0.0)


def test_gradients_match_finite_differences(enable_x64):
    """d(qdd, grf)/d(target) through the exact QP (active constraints included)."""
    model = load_model()
    config = pip.PIPConfig()
    q, bodies, pos = _standing(model, 0.002)
    qd = jnp.zeros(model.nv).at[0].set(0.3)
    dt = 1.0 / 60
    state = pip.CycleState(q, qd, jnp.zeros((4, 3)))
    w = jnp.asarray(np.random.default_rng(1).normal(size=model.nv + 24))

    def f(root_vel):
        ref = pip.Reference(q, jnp.zeros(model.nv), pos, jnp.zeros((bodies.size, 3)), root_vel, jnp.ones(4))
        sol = solve_qp(pip.step_qp(model, state, ref, dt, config)[0])
        return jnp.concatenate([sol.qdd, sol.grf.reshape(-1) / 100.0]) @ w, sol.certified

    # compiled once each (eagerly, the solver's loops dispatch op by op: 2.2x the time)
    grad = jax.jit(jax.grad(f, has_aux=True))
    value = jax.jit(jax.vmap(f))
    x0 = jnp.array([0.5, -0.2, 0.1])
    g, certified = grad(x0)
    h = 1e-6
    steps = h * jnp.concatenate([jnp.eye(3), -jnp.eye(3)])
    vals, ok = value(x0 + steps)
    assert bool(certified) and bool(jnp.all(ok))
    fd = np.asarray(vals[:3] - vals[3:]) / (2 * h)
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_an_uncertified_solve_is_made_safe(enable_x64):
    """An infeasible QP (two contradictory rows added) is not certified: its forces are still
    finite, in the friction pyramid, and its torques follow from the equation of motion."""
    model = load_model()
    config = pip.PIPConfig()
    q, bodies, pos = _standing(model)
    ref = pip.Reference(q, jnp.zeros(model.nv), pos, jnp.zeros((bodies.size, 3)), jnp.zeros(3), jnp.ones(4))
    state = pip.CycleState(q, jnp.zeros(model.nv), jnp.zeros((4, 3)))
    qp, _ = pip.step_qp(model, state, ref, 1.0 / 60, config, jnp.ones(8, bool))
    n = qp.G.shape[1]
    row = jnp.zeros(n).at[model.nv].set(1.0)
    bad = qp.replace(G=jnp.concatenate([qp.G, row[None], -row[None]]),
                     lower=jnp.concatenate([qp.lower, jnp.array([1.0, 0.0])]))
    sol = solve_qp(bad)
    assert not bool(sol.certified)
    f = np.asarray(sol.grf)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(np.asarray(sol.tau)))
    assert np.all(np.abs(f[:, 0]) + np.abs(f[:, 1]) <= config.mu * f[:, 2] + 1e-9)
    # the torques are the equation of motion's with these forces
    body = S.rigid_body_terms(model, q, jnp.zeros(model.nv))
    pts, b, _ = pip.sole_points(model, body.kin)
    J, _ = P.point_jacobian(model, body.kin, pts, b)
    want = body.M @ sol.qdd + body.h - jnp.einsum("pdv,pd->v", J, sol.grf)
    np.testing.assert_allclose(np.asarray(sol.tau), np.asarray(want), atol=1e-6 * float(jnp.abs(want).max()))


@pytest.mark.slow  # ~1 min warm each: it compiles three chunk shapes; `make test-slow`
@pytest.mark.parametrize("name,changes", [("pip_tpnet", {}), ("pip", {"reference_source": "tpnet"})])
def test_chunked_equals_whole_clip(name, changes):
    """The pipeline's chunks (state and velocity filter carried; history before and, with the
    contact MLP and the smoothing, 6 frames of lookahead after each chunk) agree with
    ``reconstruct`` on the whole clip to float32 rounding, relative to each field's magnitude.

    Not with the default fitted reference: the per-frame Levenberg-Marquardt fit is not a
    continuous function of its input in float32 (its accept/reject steps and weakly observed
    joints: a 1e-7 change of TPNet's start moves a fitted wrist by 0.8 rad on the demo walk), so
    two compiled programs (chunk and whole clip) may round into different fits (measured on this
    clip: 0.1 mm mean, 0.6 mm max keypoint difference; docs/method.md). The fit's inputs (TPNet's pose, the
    contact estimate, the causal image scale) are chunk-exact, which this test checks for the
    contact estimate and the lookahead through the ``reference_source="tpnet"`` case."""
    from jmocap.pipeline import Reconstructor

    params, config = load_run_params(None, method=name)
    config = config.replace(**changes)
    clip = load_clip(DEMO / "demo_walk.npz").slice(0, 30)
    chunked = Reconstructor(params, config, method="pip", chunk=12, bucket=4, batch=1).run([clip])[0]
    model = subject_model(clip)
    whole = jax.jit(pip.reconstruct)(params, model, ClipInputs.from_clip(clip), config)
    # with the lookahead, the reference, the contacts and the poses agree; the velocities and
    # forces of a few frames can differ by a contact decision that rounding flips (measured: 32
    # of 1,410 velocity entries, 0.01 m/s), so they are compared only in the causal case
    fields = ("q", "qd", "tau", "grf", "target_q", "contact_prob") if not changes else ("q", "target_q", "contact_prob")
    for k in fields:
        w = np.asarray(getattr(whole, k))
        np.testing.assert_allclose(chunked[k], w, rtol=0, atol=2e-3 * (float(np.abs(w).max()) + 1e-3), err_msg=k)
    if not changes:
        np.testing.assert_array_equal(chunked["certified"], np.asarray(whole.certified))


def test_smooth_poses_against_numpy():
    """The reference smoothing: a normalised Gaussian over the real frames of the window, the root
    quaternion averaged sign-aligned with the centre frame and normalised; padded frames are
    never read and repeat the nearest real frame."""
    rng = np.random.default_rng(3)
    T, nq, radius, sigma = 20, 9, 3, 1.5
    q = rng.normal(size=(T, nq))
    quat = rng.normal(size=(T, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    q[:, 3:7] = quat
    mask = np.ones(T, bool)
    mask[16:] = False  # padding
    q[16:] = 1e6  # must not leak into real frames
    got = np.asarray(pip.smooth_poses(jnp.asarray(q), jnp.asarray(mask), radius, sigma))
    want = q.copy()
    for t in range(16):
        idx = [s for s in range(t - radius, t + radius + 1) if 0 <= s < T and mask[s]]
        w = np.exp(-0.5 * ((np.array(idx) - t) / sigma) ** 2)
        w /= w.sum()
        nb = q[idx].copy()
        sign = np.where(nb[:, 3:7] @ q[t, 3:7] < 0, -1.0, 1.0)
        nb[:, 3:7] *= sign[:, None]
        avg = w @ nb
        avg[3:7] /= np.linalg.norm(avg[3:7])
        want[t] = avg
    want[16:] = want[15]  # padded frames repeat the last real frame
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    # a quaternion and its negative are the same rotation: flipping neighbours' signs changes nothing
    flipped = q.copy()
    flipped[1::2, 3:7] *= -1
    got_f = np.asarray(pip.smooth_poses(jnp.asarray(flipped), jnp.asarray(mask), radius, sigma))
    np.testing.assert_allclose(np.abs(np.sum(got_f[:16, 3:7] * got[:16, 3:7], 1)), 1.0, atol=1e-5)
    # radius 0: the poses as they are
    np.testing.assert_allclose(np.asarray(pip.smooth_poses(jnp.asarray(q), jnp.asarray(mask), 0, sigma)), q, rtol=1e-6)


def test_lookahead_and_history_follow_the_config():
    """``pip`` reads 6 frames ahead with the contact estimator (its 9-frame windows around the 5
    frames each votes for), the smoothing radius with the smoothing (12 by default), nothing for
    ``pip_tpnet``."""
    from jmocap import methods

    _, config = load_run_params(None, method="pip")
    m = methods.get_method("pip")
    assert m.lookahead(config) == 12
    assert m.lookahead(config.replace(smoothing_radius=0)) == 6
    assert m.lookahead(config.replace(smoothing_radius=9)) == 9
    assert m.lookahead(config.replace(contact_source="tpnet", smoothing_radius=0)) == 0
    # "auto": the MLP reads BODY_25's heels and toes; other layouts use TPNet's contact head
    assert config.contact_source == "auto" and pip.contact_source(config) == "mlp"
    assert pip.contact_source(config.replace(layout="coco17")) == "tpnet"
    assert m.lookahead(config.replace(layout="coco17", smoothing_radius=0)) == 0
    with pytest.raises(ValueError, match="contact_source"):
        pip.contact_source(config.replace(contact_source="oracle"))
    _, literal = load_run_params(None, method="pip_tpnet")
    assert m.lookahead(literal) == 0
    assert m.history(config) == 2 * config.nets.window - 1 + config.smoothing_radius


@pytest.mark.parametrize("per_foot", [False, True])
def test_contact_per_foot_lets_a_loaded_foot_push_on_its_heel(enable_x64, per_foot):
    """Standing flat 1 cm above the floor, the estimate loads the left toe only: by
    point (PIP's rule) only the left toe's two points may push; per foot (``contact_per_foot``)
    the left heel's too, and never the unloaded right foot's, nor a point above ``contact_near_m``."""
    model = load_model()
    config = pip.PIPConfig(contact_per_foot=per_foot)
    for shift, near in ((0.01, True), (0.05, False)):
        q, bodies, pos = _standing(model, shift)
        ref = pip.Reference(q, jnp.zeros(model.nv), pos, jnp.zeros((bodies.size, 3)), jnp.zeros(3),
                            jnp.array([0.1, 0.9, 0.2, 0.3]))
        state = pip.CycleState(q, jnp.zeros(model.nv), jnp.zeros((4, 3)))
        _, on = pip.step_qp(model, state, ref, 1.0 / 60, config)
        want = np.array([per_foot, per_foot, True, True, False, False, False, False]) & near
        np.testing.assert_array_equal(np.asarray(on), want)


@pytest.mark.parametrize("name", ["kinematic", "physcap"])
def test_reconstructor_tiles_give_the_results_of_one_vmap(name):
    """jmocap reconstruct's engine with its batch in tiles (lax.map over tiles of 2 clips, a
    remainder of 1) against one vmap over the batch: the same results, field by field, for the
    three demo clips (cut to 24 frames, chunks of 12 carrying the state between them), to float32
    rounding."""
    from jmocap.pipeline import Reconstructor

    params, config = load_run_params(None, method=name)
    clips = [load_clip(DEMO / f"demo_{k}.npz").slice(0, 24) for k in ("walk", "run", "jump")]
    out = {tile: Reconstructor(params, config, method=name, chunk=12, bucket=4, batch=3, devices=jax.devices()[:1],
                               tile=tile).run(clips) for tile in (0, 2)}
    for one, tiled in zip(out[0], out[2], strict=True):
        for k, v in one.items():
            if k == "diagnostics":
                continue
            # float32 rounding of two compiled programs, which velocities and forces (first and
            # second differences of the poses) amplify to ~1e-4 and ~1e-3 of their range; a
            # clip's results in another's row would differ by O(1)
            np.testing.assert_allclose(tiled[k], v, rtol=1e-3, atol=1e-3 * (float(np.abs(v).max()) + 1e-3), err_msg=k)


def test_a_tracking_failure_restarts_from_the_reference():
    """A frame that ends with the root more than ``reset_m`` from the reference's restarts at
    rest at the reference pose, and the clip's result counts it; the demo walk's ground truth,
    tracked as given, never fails. A reference that jumps 3 m sideways at frame 20 (as a flipped
    or lost estimate does) fails there; with the check off the body never catches up."""
    clip = load_clip(DEMO / "demo_walk.npz").slice(0, 45)
    model = subject_model(clip)
    _, config = load_run_params(None, method="pip")
    q = jnp.asarray(clip.gt_q, jnp.float32)
    prob = jnp.asarray(clip.gt_contacts, jnp.float32)
    mask = jnp.ones(q.shape[0], bool)

    @jax.jit
    def run(q, config):
        ref = pip.reference(model, q, prob, clip.fps, config.velocity_smoothing_s)
        _, out = pip.simulate(model, ref, mask, clip.fps, config)
        return ref, out, pip.to_motion(out, ref, mask).diagnostics["resets"]

    _, out, resets = run(q, config)
    assert not np.any(out.reset) and float(resets) == 0.0
    assert float(jnp.max(jnp.linalg.norm(out.q[:, :3] - q[:, :3], axis=1))) < 0.2

    jumped = q.at[20:, 1].add(3.0)
    ref, out, resets = run(jumped, config)
    failed = np.flatnonzero(np.asarray(out.reset))
    assert failed[0] == 20 and float(resets) == failed.size
    # the restarted state: the reference pose at rest, no sole point below the floor
    np.testing.assert_allclose(np.asarray(out.q[20, :2]), np.asarray(jumped[20, :2]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(out.q[20, 7:]), np.asarray(jumped[20, 7:]), atol=1e-6)
    assert float(jnp.max(jnp.abs(out.qd[20]))) == 0.0
    _, _, h = pip.sole_points(model, P.forward_kinematics(model, out.q[20]))
    assert float(jnp.min(h)) >= -1e-6
    # after it the body stays with the moved reference (the reference's filtered root velocity
    # still carries the jump's 90 m/s finite difference for a few tenths of a second: measured
    # 0.71 m at most); with the check off it is 3 m away and needs 20 frames to come within 1 m
    err = np.linalg.norm(np.asarray(out.q[20:, :3] - jumped[20:, :3]), axis=1)
    _, off, resets = run(jumped, config.replace(reset_m=0.0))
    assert not np.any(off.reset) and float(resets) == 0.0
    err_off = np.linalg.norm(np.asarray(off.q[20:, :3] - jumped[20:, :3]), axis=1)
    assert err.max() < config.reset_m and err_off[0] > 2.5
    assert err.mean() < 0.5 * err_off.mean(), (err.mean(), err_off.mean())
