"""``trajopt`` (Rempe et al. 2020 on jmocap's full-body dynamics): its finite differences against
MuJoCo, its force subproblem against Clarabel, its equations of motion against the MuJoCo
simulation that made the ground truth, its objective's gradient against finite differences, a
clip that already satisfies the physics, and windows stitched without a seam (slow)."""

from __future__ import annotations

from importlib.resources import files

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from tests.conftest import mujoco_com, x64

from jmocap import physics as P
from jmocap.camera import project
from jmocap.constants import GRAVITY
from jmocap.data.clip import load_clip
from jmocap.inputs import ClipInputs
from jmocap.methods import get_method
from jmocap.methods import stages as S
from jmocap.methods import trajopt as TO
from jmocap.model import character
from jmocap.scene import Scene, sdf

DEMO = files("jmocap") / "assets/demo/ground_truth"


def _walk():
    clip = load_clip(DEMO / "demo_walk.npz")
    return clip, character(clip.height_m, clip.mass_kg)


def _quiet_window(clip, frames: int) -> int:
    """The start of the ``frames``-frame window where the ground truth's rescue residual is least
    (the simulation's own physics holds there without help)."""
    r = np.linalg.norm(clip.gt_residual[:, :3], axis=-1)
    worst = [r[s:s + frames].max() for s in range(clip.num_frames - frames + 1)]
    return int(np.argmin(worst))


def test_frame_velocities_against_mujoco():
    """v_t is MuJoCo's mj_differentiatePos between frames; qdd and qd its differences/means; the
    ends take their neighbour's acceleration; frames past the clip repeat its last one."""
    clip, model = _walk()
    mj = model.mj
    q = np.asarray(clip.gt_q[:12], np.float64)
    fps = float(clip.fps)
    with x64():
        qd, qdd = TO.frame_velocities(jnp.asarray(q), fps, 10)
    v = np.zeros((12, mj.nv))
    for t in range(1, 12):
        mujoco.mj_differentiatePos(mj, v[t], 1.0 / fps, q[t - 1], q[t])
    for t in range(1, 9):
        np.testing.assert_allclose(qdd[t], (v[t + 1] - v[t]) * fps, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(qd[t], 0.5 * (v[t] + v[t + 1]), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(qdd[0], qdd[1], atol=1e-9)
    np.testing.assert_allclose(qdd[9], qdd[8], atol=1e-9)
    np.testing.assert_allclose(qdd[11], qdd[8], atol=1e-9)
    np.testing.assert_allclose(qd[9], v[9], atol=1e-8)


def test_force_subproblem_against_clarabel():
    """The FISTA solve of ``min_{c >= 0} 1/2 c^T H c - g^T c`` converges to Clarabel's solution."""
    clarabel = pytest.importorskip("clarabel")
    from scipy import sparse

    rng = np.random.default_rng(0)
    for _ in range(5):
        A = rng.normal(size=(6, 32))
        H = A.T @ A + 1e-3 * np.eye(32)
        g = A.T @ rng.normal(size=6)
        with x64():
            c = np.asarray(TO.nnls(jnp.asarray(H), jnp.asarray(g), 20000))
        P_ = sparse.csc_matrix(np.triu(H))
        cones = [clarabel.NonnegativeConeT(32)]
        s = clarabel.DefaultSettings()
        s.verbose = False
        s.tol_gap_abs = s.tol_gap_rel = s.tol_feas = 1e-12
        sol = clarabel.DefaultSolver(P_, -g, sparse.csc_matrix(-np.eye(32)), np.zeros(32), cones, s).solve()
        ref = np.asarray(sol.x)
        obj = lambda x, H=H, g=g: 0.5 * x @ H @ x - g @ x  # noqa: E731
        assert obj(c) - obj(ref) < 1e-8 * max(1.0, abs(obj(ref)))
        assert np.all(c >= 0)


def test_equations_of_motion_against_the_simulation():
    """On a ground-truth clip simulated in MuJoCo, ``rnea`` at the trajectory's finite
    differences minus ``J_c^T`` of the recorded contact forces leaves the recorded rescue
    residual as the root force (to 2 % of body weight on average)."""
    clip, model = _walk()
    q = jnp.asarray(clip.gt_q)
    qd, qdd = TO.frame_velocities(q, jnp.float32(clip.fps), clip.num_frames)

    def root_force(qt, v, a, f):
        return (P.rnea(model, qt, v, a) - P.contact_jacobian(model, qt).T @ f.ravel())[:3]

    r = np.asarray(jax.vmap(root_force)(q, qd, qdd, jnp.asarray(clip.gt_grf)))
    W = model.total_mass * 9.81
    err = np.linalg.norm(r - clip.gt_residual[:, :3], axis=-1) / W
    assert err[1:-1].mean() < 0.02, err.mean()


def test_a_frame_the_labels_call_a_flight_carries_no_force():
    """A stance frame of a simulated walk, its soles on the floor. Where the estimator called a
    flight (no site labelled before the outlier test) the soles near the floor carry nothing, and
    the whole root wrench the motion needs is residual; ``touch_in_flight`` lets them push; in a
    frame with a label, also one the outlier test removed, they push, and the residual is small."""
    clip, model = _walk()
    q = jnp.asarray(clip.gt_q)
    qd, qdd = TO.frame_velocities(q, jnp.float32(clip.fps), clip.num_frames)
    support = np.flatnonzero(clip.gt_contacts.sum(-1) >= 2)
    t = int(support[len(support) // 2])
    kin = P.forward_kinematics(model, q[t])
    config = TO.TrajOptConfig()
    edges = P.friction_pyramid_edges(jnp.asarray([0.0, 0.0, 1.0]), config.mu)
    pts, _, _ = S.sole_points(model, kin)
    touching = np.asarray(pts[:, 2]) < config.touch_m
    assert touching.any()

    def solve(allowed, may_touch):
        return TO.frame_dynamics(model, kin, q[t], qd[t], qdd[t], jnp.asarray(allowed), config, edges,
                                 may_touch=may_touch)

    none = np.zeros(8, bool)
    first = int(np.flatnonzero(touching)[0])
    flight = solve(none, False)
    np.testing.assert_array_equal(np.asarray(flight.coeff), 0.0)
    np.testing.assert_allclose(np.asarray(flight.residual), -np.asarray(flight.need), atol=1e-6)
    assert np.linalg.norm(flight.need[:3]) > 0.5  # the motion needs about a body weight
    for fd in (solve(none, True), solve(np.arange(8) == first, False)):
        assert float(jnp.sum(fd.coeff)) > 0.5
        assert np.all(np.asarray(fd.coeff)[~touching & (np.arange(8) != first)] == 0.0)
        assert np.linalg.norm(fd.residual[:3]) < 0.5 * np.linalg.norm(flight.residual[:3])

    # which frames may touch: those with a label before the outlier test, or all
    T = 6
    labels = np.zeros((T, 4), np.float32)
    labels[1, 0] = labels[2, 3] = 1.0
    prob = TO.Problem(keypoints=jnp.zeros((T, 25, 3)), intrinsics=jnp.eye(3), extrinsics=jnp.tile(jnp.eye(4), (T, 1, 1)),
                      unit_px=jnp.float32(1.0), fps=jnp.float32(30.0), mask=jnp.ones(T, bool), length=jnp.int32(T),
                      base_quat=jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (T, 1)), prior_rr=jnp.zeros((T, 25, 3)),
                      contacts=jnp.asarray(labels), anchor_kp=jnp.zeros((T, 25, 3)),
                      supported=jnp.asarray(labels.any(-1)))
    removed = prob.replace(contacts=prob.contacts.at[2].set(0.0))  # the outlier test's work
    qs = jnp.tile(q[t], (T, 1))
    for pr, cfg, expect in ((prob, config, labels.any(-1)), (removed, config, labels.any(-1)),
                            (removed.replace(supported=None), config, [False, True, False, False, False, False]),
                            (removed, config.replace(touch_in_flight=True), np.ones(T, bool))):
        np.testing.assert_array_equal(np.asarray(TO.dynamics_inputs(model, qs, pr, cfg)[3]), expect)


def test_centre_of_mass_prior_against_mujoco():
    """The physics stage's prior on the net external force, ``need[:3] - (0, 0, 1)``, is the
    centre of mass's acceleration over g: against central differences of MuJoCo C's
    ``subtree_com`` of the world body along a simulated walk (to 2 % of body weight per frame on
    average, the finite differences' O(dt)), and the term is its mean square over sigma^2, or
    that through Geman-McClure."""
    clip, model = _walk()
    T = 40
    config = get_method("trajopt").make_config(com_accel_sigma=0.2)
    prob, q, _ = _problem(model, clip, 0, T, config)
    geo = TO.geometry(model, q, "body25", dynamics=TO.dynamics_inputs(model, q, prob, config))
    accel = np.asarray(geo.dynamics.need[:, :3]) - np.array([0.0, 0.0, 1.0])
    com = mujoco_com(model.mj, clip.gt_q[:T])
    ref = (com[2:] - 2 * com[1:-1] + com[:-2]) * float(clip.fps) ** 2 / GRAVITY
    err = np.linalg.norm(accel[1:-1] - ref, axis=-1)
    assert err.mean() < 0.02, err.mean()
    r2 = np.sum(accel**2, -1) / 0.2**2
    np.testing.assert_allclose(float(TO.com_accel_term(geo.dynamics, prob, config.replace(com_accel_robust=0.0))),
                               np.mean(r2), rtol=1e-4)
    c2 = 3.0**2  # Geman-McClure: c^2 r^2 / (c^2 + r^2)
    np.testing.assert_allclose(float(TO.com_accel_term(geo.dynamics, prob, config.replace(com_accel_robust=3.0))),
                               np.mean(c2 * r2 / (c2 + r2)), rtol=1e-4)
    # centred on a learned support (config.support_prior "learned"): the vertical residual is the
    # acceleration less (support - 1); centred on MuJoCo's own c''_z / g + 1 it is the O(dt) error
    support = np.ones(T)
    support[1:-1] = 1.0 + ref[:, 2]
    on = TO.com_accel_residual(geo.dynamics, prob.replace(support=jnp.asarray(support, jnp.float32)))
    np.testing.assert_allclose(np.asarray(on)[:, :2], accel[:, :2], atol=1e-6)
    np.testing.assert_allclose(np.asarray(on)[1:-1, 2], accel[1:-1, 2] - ref[:, 2], atol=1e-6)
    assert np.abs(np.asarray(on)[1:-1, 2]).mean() < 0.02 < np.abs(accel[1:-1, 2]).mean()


def _problem(model, clip, start, frames, config, dtype=jnp.float32):
    """A trajopt problem of a ground-truth window: exact keypoints (its own projection,
    confidence 1), ground-truth contacts, the ground truth as prior."""
    sl = slice(start, start + frames)
    cut = clip.slice(start, start + frames)
    inputs = ClipInputs.from_clip(cut)
    q = jnp.asarray(clip.gt_q[sl], dtype)
    kp3 = jax.vmap(lambda x: P.keypoints(model, x, "body25"))(q)
    uv = project(inputs.camera, kp3)
    inputs = inputs.replace(keypoints=np.concatenate([np.asarray(uv), np.ones((frames, 25, 1))], -1).astype(np.float32))
    prob = TO.problem(model, inputs, q, jnp.asarray(clip.gt_contacts[sl], dtype), config)
    return prob, q, inputs


def test_objective_gradient_matches_finite_differences():
    """The gradient of the physics-stage objective (reprojection, priors, contacts, floor, the
    residual after the optimal forces by Danskin's theorem) against central differences, in
    float64 with the force subproblem solved to convergence."""
    clip, model = _walk()
    config = get_method("trajopt").make_config(nnls_iterations=4000)
    with x64():
        model64 = character(clip.height_m, clip.mass_kg)
        start = _quiet_window(clip, 8)
        prob, q, _ = _problem(model64, clip, start, 8, config, jnp.float64)
        x, base = TO.from_q(model64, q)
        rng = np.random.default_rng(1)
        prob = prob.replace(base_quat=base, support=jnp.asarray(1.0 + 0.3 * rng.normal(size=8)))  # a learned support
        x = jax.tree.map(lambda a: a + 0.005 * rng.normal(size=a.shape), x)  # off the optimum
        f = jax.jit(lambda x: TO.objective(model64, x, prob, config, physics=True))
        g = jax.jit(jax.grad(lambda x: TO.objective(model64, x, prob, config, physics=True)))(x)
        for _ in range(4):
            d = jax.tree.map(lambda a: rng.normal(size=a.shape), x)
            eps = 1e-5
            step = lambda s, d=d: jax.tree.map(lambda u, v: u + s * v, x, d)  # noqa: E731
            fd = (f(step(eps)) - f(step(-eps))) / (2 * eps)
            an = sum(float(jnp.sum(a * b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(d), strict=True))
            # 1e-2: the forces come from an iterative solve, whose own small dependence on x the
            # differences see and Danskin's gradient does not (measured 4e-3 here)
            assert abs(an - float(fd)) < 1e-2 * max(1.0, abs(float(fd))), (an, float(fd))


@pytest.mark.parametrize("rotation", ["yaw", "full"])
def test_turned_prior_is_the_best_rotation_and_its_gradient_is_exact(rotation):
    """``prior_facing_fit`` turns the prior to the rotation of least squares ("yaw": about the
    vertical, against a dense search over headings, its heights untouched; "full": against
    NumPy's SVD (Kabsch, a mirrored pair too), the yaw solution and random rotations), and the
    prior energy it gives has the gradient of ``min_R |rr - R p|^2`` (central differences of
    that minimum, float64), though the rotation is held by a gradient stop; "tpnet": the prior
    as it is."""
    config = get_method("trajopt").make_config(prior_rotation=rotation)
    with x64():
        rng = np.random.default_rng(7)
        rr = jnp.asarray(rng.normal(0, 0.3, (25, 3)))
        a = 2.3  # the prior faces 2.3 rad away (and, for "full", leans), with articulation of its own
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        if rotation == "full":
            b = 0.6
            rot = rot @ np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
        prior = (rr + jnp.asarray(rng.normal(0, 0.05, (25, 3)))) @ jnp.asarray(rot).T

        def energy(r, cfg=config):
            return jnp.sum((r - TO.prior_facing_fit(r, prior, cfg)) ** 2)

        e = float(energy(rr))
        if rotation == "yaw":
            np.testing.assert_array_equal(np.asarray(TO.prior_facing_fit(rr, prior, config)[:, 2]), np.asarray(prior[:, 2]))
            phis = np.linspace(-np.pi, np.pi, 20001)
            c, s = np.cos(phis)[:, None], np.sin(phis)[:, None]
            p, r = np.asarray(prior), np.asarray(rr)
            grid = np.sum((r[None, :, 0] - (c * p[:, 0] - s * p[:, 1])) ** 2
                          + (r[None, :, 1] - (s * p[:, 0] + c * p[:, 1])) ** 2 + (r[None, :, 2] - p[:, 2]) ** 2, -1)
            assert grid.min() - 1e-6 < e <= grid.min() + 1e-12  # the grid's resolution
        else:
            # Kabsch by NumPy's SVD, on this pair and on a mirrored one (the polar factor of the
            # mirrored pair's correlation is a reflection; the rotation must stay proper)
            for pr in (np.asarray(prior), np.asarray(prior) * np.array([1.0, 1.0, -1.0])):
                u, _, vt = np.linalg.svd(np.asarray(rr).T @ pr)
                kabsch = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
                np.testing.assert_allclose(np.asarray(TO.prior_facing_fit(rr, jnp.asarray(pr), config)),
                                           pr @ kabsch.T, atol=1e-12)
            assert e < 0.05**2 * 25 * 3 * 2  # about the articulation's own difference
            assert e <= float(energy(rr, get_method("trajopt").make_config(prior_rotation="yaw")))
            for _ in range(20):
                q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
                q = q * np.sign(np.linalg.det(q))
                assert e <= float(jnp.sum((rr - prior @ jnp.asarray(q).T) ** 2))
        g = jax.grad(energy)(rr)
        for _ in range(4):
            d = jnp.asarray(rng.normal(size=rr.shape))
            eps = 1e-6
            fd = (energy(rr + eps * d) - energy(rr - eps * d)) / (2 * eps)
            np.testing.assert_allclose(float(jnp.sum(g * d)), float(fd), rtol=1e-6)
        held = get_method("trajopt").make_config(prior_rotation="tpnet")
        assert TO.prior_facing_fit(rr, prior, held) is prior



def test_ball_joint_limits_judge_either_euler_triple():
    """A ball joint written as three hinges about orthogonal axes (hips, ankles, spine, neck,
    shoulders) has two Euler triples per rotation, ``(a, b, c)`` and ``(a + pi, pi - b, c +
    pi)``: MuJoCo C's forward kinematics of the two place every body alike. ``limit_angles``
    judges the triple inside the limits (a pose written in the other is not penalised), its
    sign is the derivative (central differences); ``continuous_hinges`` gives back a smooth
    trajectory whose frames were scattered over both triples and shifted by 2 pi."""
    model = character()
    config = get_method("trajopt").make_config()
    mj = model.mj
    hq = np.asarray(model.topo.hinge_qadr)
    tri = TO.ball_triples(model)
    hinge_names = {int(mj.jnt_qposadr[j]): mj.joint(j).name for j in range(mj.njnt) if mj.jnt_type[j] == 3}
    bodies = sorted({hinge_names[int(hq[i])].rsplit("_", 1)[0] for i in tri.ravel()})
    assert bodies == ["left_ankle", "left_hip", "left_shoulder", "neck", "right_ankle", "right_hip",
                      "right_shoulder", "spine1", "spine3"]
    lo, hi = np.asarray(model.q_lower)[hq], np.asarray(model.q_upper)[hq]

    def other(h):
        h = h.copy()
        a = h[tri]
        alt = np.stack([a[:, 0] + np.pi, np.pi - a[:, 1], a[:, 2] + np.pi], -1)
        h[tri] = (alt + np.pi) % (2 * np.pi) - np.pi
        return h

    def bodies_at(q):
        d = mujoco.MjData(mj)
        d.qpos[:] = q
        mujoco.mj_kinematics(mj, d)
        return np.concatenate([d.xpos.ravel(), d.xmat.ravel()])

    rng = np.random.default_rng(3)
    with x64():
        T = 40
        t = np.linspace(0, 1, T)[:, None]
        # a smooth trajectory inside the limits, 0.1 rad from them
        phase, mid, amp = rng.uniform(0, 6, hq.size), (lo + hi) / 2, (hi - lo) / 2 - 0.1
        h = mid + amp * np.sin(2 * np.pi * t + phase)  # (T, H)
        q = np.tile(np.asarray(model.qpos0, float), (T, 1))
        q[:, hq] = h
        for k in range(0, T, 7):
            qa = q[k].copy()
            qa[hq] = other(h[k])
            np.testing.assert_allclose(bodies_at(qa), bodies_at(q[k]), atol=1e-12)
            assert np.any(qa[hq] < lo - 0.05) or np.any(qa[hq] > hi + 0.05)  # out of limits as written
            judged, sign = TO.limit_angles(model, jnp.asarray(qa[hq]), config)
            np.testing.assert_allclose(np.asarray(judged), h[k], atol=1e-12)  # judged in the limits' triple
            assert np.all(np.asarray(sign)[tri[:, 1]] == -1.0) and np.sum(np.asarray(sign) == -1.0) == len(tri)
            as_is, _ = TO.limit_angles(model, jnp.asarray(qa[hq]), config.replace(limit_branches=False))
            np.testing.assert_array_equal(np.asarray(as_is), qa[hq])
            eps = 1e-6
            for i in tri[:, 1]:
                e = np.zeros(hq.size)
                e[i] = eps
                fd = (TO.limit_angles(model, jnp.asarray(qa[hq] + e), config)[0][i]
                      - TO.limit_angles(model, jnp.asarray(qa[hq] - e), config)[0][i]) / (2 * eps)
                assert float(fd) == pytest.approx(float(sign[i]), abs=1e-6)
        # scatter: frames after the first in the other triple or shifted by 2 pi; the continuous
        # trajectory is the original
        scattered = q.copy()
        for k in range(1, T):
            if rng.random() < 0.5:
                scattered[k, hq] = other(h[k])
            scattered[k, hq[tri.ravel()]] += 2 * np.pi * rng.integers(-1, 2, tri.size)
        back = np.asarray(TO.continuous_hinges(model, jnp.asarray(scattered), config))
        np.testing.assert_allclose(back, q, atol=1e-12)


def test_arms_down_start_hangs_the_arms():
    """The per-frame fit's second start (``arm_restart``) changes only the shoulders and elbows,
    and in MuJoCo C's forward kinematics of the model's standing keyframe with it each wrist
    hangs at least 0.4 m below its shoulder and within 20 deg of the vertical through it
    (measured: 0.53 m, 14 deg, the elbows bent 11 deg)."""
    model = character()
    mj = model.mj
    q0 = np.asarray(mj.key_qpos[mj.key("stand").id], float)
    q = np.asarray(TO.arms_down(model, jnp.asarray(q0)))
    named = sorted(int(mj.jnt_qposadr[mj.joint(n).id]) for n in TO.ARMS_DOWN_DEG)
    assert set(np.flatnonzero(q != q0)) <= set(named)
    np.testing.assert_allclose(np.degrees(q[named]), [TO.ARMS_DOWN_DEG[mj.joint(int(np.flatnonzero(mj.jnt_qposadr == a)[0])).name]
                                                      for a in named], atol=1e-9)
    d = mujoco.MjData(mj)
    d.qpos[:] = q
    mujoco.mj_kinematics(mj, d)
    for side in ("left", "right"):
        sh, wr = d.xpos[mj.body(f"{side}_shoulder").id], d.xpos[mj.body(f"{side}_wrist").id]
        below, aside = sh[2] - wr[2], np.linalg.norm((wr - sh)[:2])
        assert below > 0.4 and np.degrees(np.arctan2(aside, below)) < 20, (side, below, aside)

def test_per_frame_jacobians_match_autodiff():
    """The analytic residual Jacobians of the per-frame Levenberg-Marquardt stage (point
    Jacobians through the pinhole projection, pose prior, active joint limits and floor rows)
    against forward-mode autodiff of the residuals along ``q (+) dq``, float64, at a pose with
    limits and floor rows active."""
    clip, _ = _walk()
    config = get_method("trajopt").make_config()
    with x64():
        model = character(clip.height_m, clip.mass_kg)
        rng = np.random.default_rng(0)
        q = np.asarray(clip.gt_q[10], np.float64).copy()
        q[model.topo.hinge_qadr] += rng.normal(0, 0.4, len(model.topo.hinge_qadr))  # some past their limits
        q[2] -= 0.05  # some sole points below the floor
        q = jnp.asarray(q)
        cam = ClipInputs.from_clip(clip).camera
        cam = cam.replace(intrinsics=jnp.asarray(cam.intrinsics, jnp.float64),
                          extrinsics=jnp.asarray(cam.extrinsics, jnp.float64))
        prior = jnp.asarray(rng.normal(0, 0.3, (25, 3)))
        # jitted: op-by-op float64 dispatch of these took 45 s of the suite
        uv, j_uv, other, j_other = jax.jit(lambda q: TO._frame_residuals(model, q, prior, cam, config))(q)
        assert int(jnp.sum(other[-8:] > 0)) > 0 and int(jnp.sum(other[75:-8] != 0)) > 0

        def residuals(dq):
            u, _, o, _ = TO._frame_residuals(model, P.integrate_positions(model, q, dq, 1.0), prior, cam, config)
            return jnp.concatenate([u.ravel(), o])

        auto = jax.jit(jax.jacfwd(residuals))(jnp.zeros(model.nv))
        analytic = jnp.concatenate([j_uv.reshape(-1, model.nv), j_other])
        np.testing.assert_allclose(np.asarray(analytic), np.asarray(auto), atol=1e-9 * float(jnp.max(jnp.abs(auto))))
        # the root-depth prior's row (the frame 30 % further than its track says)
        depth = jnp.log(q[:3] @ cam.extrinsics[2, :3] + cam.extrinsics[2, 3]) - 0.3
        _, _, o_d, j_d = jax.jit(lambda q: TO._frame_residuals(model, q, prior, cam, config, depth))(q)
        assert o_d.shape[0] == other.shape[0] + 1
        np.testing.assert_allclose(float(o_d[-1]), 0.3 * np.sqrt(config.w_depth) / config.depth_sigma, rtol=1e-9)
        auto_d = jax.jit(jax.jacfwd(lambda dq: TO._frame_residuals(
            model, P.integrate_positions(model, q, dq, 1.0), prior, cam, config, depth)[2][-1]))(jnp.zeros(model.nv))
        np.testing.assert_allclose(np.asarray(j_d[-1]), np.asarray(auto_d), atol=1e-12)
        # the labelled sites' robust sole-height rows (left heel and right toe labelled; the root
        # raised so that some labelled soles are above the floor, some below)
        lab = jnp.asarray([1.0, 0.0, 0.0, 1.0])
        q_c = q.at[2].add(0.07)
        _, _, o_c, j_c = jax.jit(lambda q: TO._frame_residuals(model, q, prior, cam, config, contacts=lab))(q_c)
        _, _, o_0, _ = jax.jit(lambda q: TO._frame_residuals(model, q, prior, cam, config))(q_c)
        rows = o_c[o_0.shape[0]:]
        assert rows.shape == (8,) and np.all(np.asarray(rows[2:6]) == 0) and np.any(np.asarray(rows) != 0)
        h = S.sole_points(model, P.forward_kinematics(model, q_c))[2]
        a, c = np.sqrt(config.w_contact_height) / config.contact_height_sigma, config.contact_robust_m
        want = a * np.asarray(h) * c / np.sqrt(c * c + np.asarray(h) ** 2)  # sqrt of Geman-McClure
        np.testing.assert_allclose(np.asarray(rows)[[0, 1, 6, 7]], want[[0, 1, 6, 7]], rtol=1e-9)
        auto_c = jax.jit(jax.jacfwd(lambda dq: TO._frame_residuals(
            model, P.integrate_positions(model, q_c, dq, 1.0), prior, cam, config, contacts=lab)[2]))(jnp.zeros(model.nv))
        np.testing.assert_allclose(np.asarray(j_c), np.asarray(auto_c), atol=1e-9 * float(jnp.max(jnp.abs(auto_c))))


def test_terrain_heights_and_their_jacobians():
    """With a scene (issue 21), the per-frame stage's floor and contact rows measure sole heights
    above the terrain: the rows are those of the scene's signed distance (itself tested against
    MuJoCo in test_scene.py) and their analytic Jacobians (the surface normal times the point
    Jacobians) match forward-mode autodiff along ``q (+) dq``, float64, with the left foot's soles
    3 cm inside a turned box and the right foot beside it; a scene without boxes is the floor."""
    clip, _ = _walk()
    config = get_method("trajopt").make_config()
    with x64():
        model = character(clip.height_m, clip.mass_kg)
        q = jnp.asarray(clip.gt_q[10], jnp.float64)
        pts = S.sole_points(model, P.forward_kinematics(model, q))[0]
        left = np.asarray(pts[:4])
        top = float(left[:, 2].mean()) + 0.03
        axis = left[2:, :2].mean(0) - left[:2, :2].mean(0)  # the left foot's heel -> toe, turned along it
        c, s = axis / np.linalg.norm(axis)
        scene = Scene(jnp.asarray([[*left[:, :2].mean(0), (top - 0.05) / 2]]),
                      jnp.asarray([[np.linalg.norm(axis) / 2 + 0.06, 0.1, (top + 0.05) / 2]]),
                      jnp.asarray([[[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]]))
        cam = ClipInputs.from_clip(clip).camera
        cam = cam.replace(intrinsics=jnp.asarray(cam.intrinsics, jnp.float64),
                          extrinsics=jnp.asarray(cam.extrinsics, jnp.float64))
        prior = jnp.zeros((25, 3))
        lab = jnp.ones(4)
        res = jax.jit(lambda q, sc: TO._frame_residuals(model, q, prior, cam, config, contacts=lab, scene=sc))
        _, _, o, j = res(q, scene)
        h = np.asarray(sdf(scene, pts))
        assert np.all(h[:4] < -0.01) and np.all(h[4:] > 0.0)  # left inside the box, right beside it
        want_c = np.asarray(TO.robust_height(jnp.asarray(h), config)[0])
        np.testing.assert_allclose(np.asarray(o[-8:]), want_c, rtol=1e-9)
        a_floor = np.sqrt(config.w_floor) / config.floor_sigma
        floor_rows = np.asarray(o[-16:-8])
        np.testing.assert_allclose(floor_rows, a_floor * np.maximum(config.floor_margin_m - h, 0.0), rtol=1e-9)
        auto = jax.jit(jax.jacfwd(lambda dq: TO._frame_residuals(
            model, P.integrate_positions(model, q, dq, 1.0), prior, cam, config, contacts=lab, scene=scene)[2]))(
            jnp.zeros(model.nv))
        np.testing.assert_allclose(np.asarray(j), np.asarray(auto), atol=1e-9 * float(jnp.max(jnp.abs(auto))))
        # no boxes: the floor, exactly as without a scene
        flat = res(q, Scene.empty(np.float64))
        plain = jax.jit(lambda q: TO._frame_residuals(model, q, prior, cam, config, contacts=lab))(q)
        for x, y in zip(flat, plain, strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("tile", [0, 5])
def test_per_frame_fit_recovers_poses_from_their_projections(tile):
    """Exact keypoints of ground-truth frames, a start 10 cm and about 10 degrees per joint away
    (root and hinges), the truth as prior: the per-frame Levenberg-Marquardt stage brings every
    frame back to within a pixel of its keypoints and 1 cm of its joints. Without the floor
    margin: the simulated soles rest at z = 0 (a few mm into MuJoCo's soft floor), where the
    default margin (5 mm) deliberately lifts them; the solver, not that choice, is under test.
    Fitted all at once and in tiles of 5 frames (two tiles and a remainder of 2). The prior is
    not turned (``prior_rotation`` "tpnet": the truth's orientation is the prior's): the solver's
    convergence is under test, and with the prior turned to each iterate the body's turn is
    held by the keypoints alone, which 30 iterations leave at 1.0009 px (docs/method.md, stop 57)."""
    clip, model = _walk()
    config = get_method("trajopt").make_config(floor_margin_m=0.0, prior_rotation="tpnet")
    prob, q, _ = _problem(model, clip, 20, 12, config)
    rng = np.random.default_rng(3)
    start = np.asarray(q).copy()
    start[:, :3] += rng.normal(0, 0.1, (12, 3))
    start[:, model.topo.hinge_qadr] += rng.normal(0, 0.15, (12, len(model.topo.hinge_qadr)))
    q1 = jax.jit(lambda s: TO.per_frame_fit(model, s, prob, config, 30, config.gm_scale_initial,
                                            config.gm_scale, tile=tile))(jnp.asarray(start))
    kp = lambda x: jax.vmap(lambda y: P.keypoints(model, y, "body25"))(x)  # noqa: E731
    cam = ClipInputs.from_clip(clip).camera
    px = np.linalg.norm(np.asarray(project(cam, kp(q1)) - prob.keypoints[..., :2]), axis=-1)
    assert px.max() < 1.0, px.max()
    err = np.linalg.norm(np.asarray(kp(q1) - kp(q)), axis=-1)
    assert err.max() < 0.01, err.max()


def test_depth_track_smoother_is_the_batch_least_squares():
    """The depth track's Rauch-Tung-Striebel smoother equals the batch solution of its model,
    computed here by dense least squares in float64: initial state ``s_0 ~ N(m, F P0 F^T + Q)``,
    ``s_{t+1} = F s_t + g a_t`` with white accelerations ``a_t ~ N(0, accel^2)``
    (``g = (1/2, 1)``), measurements ``y_t = s_t[0]`` with variance ``r_t``, some missing."""
    rng = np.random.default_rng(5)
    T, accel = 40, 0.02
    y = np.cumsum(np.cumsum(rng.normal(0, accel, T))) + rng.normal(0, 0.05, T) + 1.0
    r = rng.uniform(0.001, 0.01, T)
    r[[3, 10, 11, 12, 30, 39]] = np.inf  # unmeasured frames, the last among them
    with x64():
        got = np.asarray(TO._rts_smooth(jnp.asarray(y), jnp.asarray(r), jnp.asarray(accel)))
    seen = np.isfinite(r)
    m = np.array([np.sum(y[seen] / r[seen]) / np.sum(1 / r[seen]), 0.0])
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    g = np.array([0.5, 1.0])
    Q = accel**2 * np.outer(g, g)
    S0 = F @ np.diag([1e2, 1.0]) @ F.T + Q
    # variables: s_0 (2) and a_0..a_{T-2}; position x_t = row_t . z
    n = 2 + T - 1
    rows = np.zeros((T, n))
    Phi, Gam = np.eye(2), np.zeros((2, T - 1))
    for t in range(T):
        rows[t, :2], rows[t, 2:] = Phi[0], Gam[0]
        Phi, Gam = F @ Phi, F @ Gam
        if t < T - 1:
            Gam[:, t] += g
    L0 = np.linalg.cholesky(np.linalg.inv(S0))  # whitening of the initial state's prior
    A = np.concatenate([rows[seen] / np.sqrt(r[seen])[:, None],
                        np.concatenate([L0.T, np.zeros((2, T - 1))], 1),
                        np.concatenate([np.zeros((T - 1, 2)), np.eye(T - 1) / accel], 1)])
    b = np.concatenate([y[seen] / np.sqrt(r[seen]), L0.T @ m, np.zeros(T - 1)])
    want = rows @ np.linalg.lstsq(A, b, rcond=None)[0]
    np.testing.assert_allclose(got, want, atol=1e-8)


def test_keypoint_jitter_measures_white_noise_and_sets_the_reprojection_unit():
    """``keypoint_jitter_px`` recovers the standard deviation of white noise added to smooth
    keypoint tracks (within the sampling error of a median of ~13,000 values), ignores frames
    that are padding or unconfident (there the noise is 10x), and is 0 for noise-free straight
    lines; ``problem`` takes ``max(1 % of the person's height, noise_unit x jitter)``."""
    rng = np.random.default_rng(3)
    T, J, sigma = 300, 25, 2.5
    t = np.arange(T)[:, None, None] / 30.0
    base = rng.uniform(100, 500, (1, J, 2))
    smooth = base + 40 * np.sin(2 * np.pi * 0.5 * t + rng.uniform(0, 6, (1, J, 2)))  # 0.5 Hz swings
    kp = np.concatenate([smooth + rng.normal(0, sigma, (T, J, 2)), np.ones((T, J, 1))], -1)
    mask = np.ones(T, bool)
    got = float(TO.keypoint_jitter_px(jnp.asarray(kp), jnp.asarray(mask)))
    assert abs(got / sigma - 1) < 0.05, got
    wild = kp.copy()
    wild[250:, :, :2] += rng.normal(0, 10 * sigma, (50, J, 2))
    mask_pad = mask.copy()
    mask_pad[250:] = False
    assert float(TO.keypoint_jitter_px(jnp.asarray(wild), jnp.asarray(mask_pad))) == pytest.approx(
        float(TO.keypoint_jitter_px(jnp.asarray(kp[:250]), jnp.asarray(mask[:250]))), rel=1e-6)
    wild[:, :, 2] = np.where(np.arange(T)[:, None] >= 250, 0.05, 1.0)  # unconfident instead of padding
    assert float(TO.keypoint_jitter_px(jnp.asarray(wild), jnp.asarray(mask))) == pytest.approx(
        float(TO.keypoint_jitter_px(jnp.asarray(kp[:250]), jnp.asarray(mask[:250]))), rel=1e-6)
    line = np.concatenate([base + 3.0 * np.arange(T)[:, None, None], np.ones((T, J, 1))], -1)
    assert float(TO.keypoint_jitter_px(jnp.asarray(line), jnp.asarray(mask))) == pytest.approx(0.0, abs=1e-3)

    clip, model = _walk()
    inputs = ClipInputs.from_clip(clip)
    q_hat = jnp.asarray(clip.gt_q, jnp.float32)
    c = jnp.zeros((clip.num_frames, 4))
    kp = jnp.asarray(inputs.keypoints)
    m = jnp.asarray(inputs.mask)
    height, jitter = float(TO.person_height_px(kp, m)), float(TO.keypoint_jitter_px(kp, m))
    for k in (0.0, 1.5, 100.0):
        got = float(TO.problem(model, inputs, q_hat, c, TO.TrajOptConfig(noise_unit=k)).unit_px)
        assert got == pytest.approx(max(height / 100, k * jitter), rel=1e-5)


def test_depth_track_holds_frames_with_few_keypoints():
    """A person leaving the image: on the last 6 frames of a ground-truth window only the head
    and shoulders (8 keypoints) are seen, and the start (like TPNet's translation there) slides
    the body along the camera ray to 0.5 m from the camera; keypoints with 3 px noise, the
    prior's joints with 5 cm. The per-frame fit with the clip's depth track keeps every frame's
    root within 15 % of its true depth (the track carries the well-seen frames' depth across;
    without it these frames end at 52-86 %), and reprojects the seen keypoints within 10 px."""
    clip, model = _walk()
    config = get_method("trajopt").make_config(floor_margin_m=0.0)
    prob, q, inputs = _problem(model, clip, 20, 16, config)
    seen = np.zeros(25, bool)
    seen[[0, 1, 2, 5, 15, 16, 17, 18]] = True
    rng = np.random.default_rng(0)
    kp = np.asarray(prob.keypoints).copy()
    kp[..., :2] += rng.normal(0, 3, kp[..., :2].shape)
    kp[10:, ~seen, 2] = 0.0
    prob = prob.replace(keypoints=jnp.asarray(kp),
                        prior_rr=prob.prior_rr + jnp.asarray(rng.normal(0, 0.05, prob.prior_rr.shape), jnp.float32))
    E = np.asarray(inputs.extrinsics, np.float64)
    z_true = np.asarray(q[:, :3]) @ E[2, :3] + E[2, 3]
    start = np.asarray(q).copy()
    cam_pos = -E[:3, :3].T @ E[:3, 3]
    s = np.ones(16)
    s[10:] = np.linspace(0.8, 0.5 / z_true[-1], 6)  # towards the camera along the ray
    start[:, :3] = cam_pos + s[:, None] * (start[:, :3] - cam_pos)
    start = jnp.asarray(start, jnp.float32)

    def run(s):
        return TO.per_frame_fit(model, s, prob, config, 30, config.gm_scale_initial, config.gm_scale,
                                TO.depth_track(s, prob, config))

    q1 = np.asarray(jax.jit(run)(start))
    z1 = q1[:, :3] @ E[2, :3] + E[2, 3]
    assert np.all(np.abs(z1 / z_true - 1) < 0.15), z1 / z_true
    kp3 = jax.vmap(lambda x: P.keypoints(model, x, "body25"))(jnp.asarray(q1))
    px = np.linalg.norm(np.asarray(project(inputs.camera, kp3)) - kp[..., :2], axis=-1)
    assert px[10:, seen].max() < 10.0, px[10:, seen].max()


@pytest.mark.parametrize("linesearch", ["zoom", "backtracking"])
def test_lbfgs_reaches_the_minimum_of_an_ill_conditioned_quadratic(linesearch):
    """``trajopt.lbfgs`` (optax's L-BFGS with either line search, in preconditioned variables,
    the best iterate kept) reaches the closed-form minimiser x* = A^-1 b of a rotated quadratic
    whose curvatures span 1e4 (in 200 iterations: 60 leave 0.06, a diagonal preconditioner
    cannot undo a rotated spread), and reports the objective before and after."""
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(12, 12)))
    A = (Q * np.geomspace(1.0, 1e4, 12)) @ Q.T
    A = 0.5 * (A + A.T)
    b = rng.normal(size=12)
    xstar = np.linalg.solve(A, b)
    f = lambda x: 0.5 * x["v"] @ (A @ x["v"]) - b @ x["v"]  # noqa: E731
    with x64():
        x0 = {"v": jnp.zeros(12)}
        scale = {"v": jnp.asarray(1.0 / np.sqrt(np.diag(A)))}
        x, rep = jax.jit(lambda x0: TO.lbfgs(f, x0, 200, 10, scale, linesearch))(x0)
    np.testing.assert_allclose(np.asarray(x["v"]), xstar, atol=1e-4)
    assert float(rep.final) < float(rep.initial) and int(rep.iterations) == 200
    with pytest.raises(ValueError, match="unknown linesearch"):
        TO.lbfgs(f, x0, 2, 10, scale, "wolfe")


def _flat(x):
    return jnp.concatenate([x.root_pos, x.root_rot, x.hinges], -1)


def test_kinematic_normal_equations_gradient_matches_autodiff():
    """The whole-clip Gauss-Newton stage's gradient, assembled from the analytic point Jacobians
    term by term (robust reprojection with its IRLS weight, pose prior, active joint limits,
    labelled sole heights, the floor, joint accelerations, labelled soles still), equals
    reverse-mode autodiff of :func:`objective` in the variables of ``from_q`` (whose steps are
    ``q (+) dq``), float64, on a perturbed window: keypoints with outliers, some limits past,
    some soles below the floor, contacts labelled on some frames only, a padded tail."""
    clip, _ = _walk()
    config = get_method("trajopt").make_config()
    with x64():
        model = character(clip.height_m, clip.mass_kg)
        prob, q, _ = _problem(model, clip, 20, 10, config, jnp.float64)
        rng = np.random.default_rng(4)
        kp = np.asarray(prob.keypoints).copy()
        kp[..., :2] += rng.normal(0, 3.0, kp[..., :2].shape)
        kp[2, 4, :2] += 80.0  # an outlier: the Geman-McClure weight matters
        kp[..., 2] = rng.uniform(0.2, 1.0, kp[..., 2].shape)
        contacts = np.asarray(prob.contacts).copy()
        contacts[3:6] = 1.0 - contacts[3:6]
        q = np.asarray(q).copy()
        q[:, 7:] += rng.normal(0, 0.3, q[:, 7:].shape)
        q[:, 2] -= 0.03
        mask = np.arange(10) < 8
        prob = prob.replace(keypoints=jnp.asarray(kp), contacts=jnp.asarray(contacts), mask=jnp.asarray(mask),
                            length=jnp.asarray(8))
        q = jnp.asarray(q)
        x, base = TO.from_q(model, q)
        pr = prob.replace(base_quat=base)
        ne = jax.jit(lambda q: TO.kinematic_normal_equations(model, q, prob, config))(q)
        terms = jax.jit(lambda x: TO.objective_terms(model, x, pr, config, physics=False))(x)
        for name in ("limits", "floor", "contact_still", "contact_height"):
            assert float(terms[name]) > 0, name  # every kind of row is active
        auto = _flat(jax.jit(jax.grad(lambda x: TO.objective(model, x, pr, config, physics=False)))(x))
        np.testing.assert_allclose(np.asarray(ne.grad), np.asarray(auto), rtol=0,
                                   atol=1e-9 * float(jnp.max(jnp.abs(auto))))
        assert np.all(np.asarray(ne.grad[8:]) == 0)  # the padded frames


def test_kinematic_gauss_newton_matrix_is_the_hessian_at_zero_residuals():
    """Where every residual is zero, the Gauss-Newton matrix is the exact Hessian: a standing pose
    held for 5 frames, seen exactly (keypoints its projections), its own pose prior, its soles
    labelled (still) and lifted clear of the floor, hinges within their limits. The banded
    blocks, assembled densely, equal autodiff's Hessian of :func:`objective`, float64; the
    contact-height rows are off here (their residual, a height, is not zero) and their
    gradient is tested above. The prior's turn is held in both (a gradient stop in the
    objective; rows built with the turn held in :func:`kinematic_normal_equations`)."""
    clip, _ = _walk()
    with x64():
        model = character(clip.height_m, clip.mass_kg)
        config = get_method("trajopt").make_config(w_contact_height=0.0)
        q0 = np.asarray(clip.gt_q[20], np.float64).copy()
        lo, hi = np.asarray(model.q_lower)[model.topo.hinge_qadr], np.asarray(model.q_upper)[model.topo.hinge_qadr]
        q0[model.topo.hinge_qadr] = np.clip(q0[model.topo.hinge_qadr], lo + 0.01, hi - 0.01)
        q0[2] += 0.1
        q = jnp.asarray(np.repeat(q0[None], 5, 0))
        prob, _, _ = _problem(model, clip, 20, 5, config, jnp.float64)
        kp3 = jax.vmap(lambda x: P.keypoints(model, x, "body25"))(q)
        cam = TO.Camera(prob.intrinsics, jnp.zeros(2), prob.extrinsics)
        uv = project(cam, kp3)
        rr = kp3 - jnp.mean(kp3[:, np.asarray(TO.get_layout("body25").root_indices)], 1, keepdims=True)
        prob = prob.replace(keypoints=jnp.concatenate([uv, jnp.ones((5, 25, 1))], -1), prior_rr=rr,
                            contacts=jnp.ones((5, 4)))
        x, base = TO.from_q(model, q)
        pr = prob.replace(base_quat=base)
        ne = TO.kinematic_normal_equations(model, q, prob, config)
        assert float(jnp.max(jnp.abs(ne.grad))) < 1e-6
        n = model.nv

        def f(v):
            v = v.reshape(5, n)
            return TO.objective(model, TO.Trajectory(v[:, :3], v[:, 3:6], v[:, 6:]), pr, config, physics=False)

        hess = np.asarray(jax.jit(jax.hessian(f))(_flat(x).ravel()))
        dense = np.zeros((5 * n, 5 * n))
        blocks = np.asarray(ne.blocks)
        for d in range(3):
            for t in range(5 - d):
                dense[t * n:(t + 1) * n, (t + d) * n:(t + d + 1) * n] = blocks[d, t]
                dense[(t + d) * n:(t + d + 1) * n, t * n:(t + 1) * n] = blocks[d, t].T
        np.testing.assert_allclose(dense, hess, rtol=0, atol=1e-7 * np.abs(hess).max())


@pytest.mark.slow
def test_gauss_newton_stage_reaches_the_minimum_and_never_climbs():
    """The whole-clip Levenberg-Marquardt stage (``kinematic_solver="gauss_newton"``) from a start
    5 cm and about 0.1 rad per hinge off a window seen exactly, with its truth as prior and its
    contacts: 10 iterations reach the objective that 1,000 L-BFGS iterations reach (the
    reference minimiser; 60, the stage's default, leave it 40x higher), the joints end within 2
    cm of the truth (the objective's own minimum is not the simulated truth: its accelerations and
    soft-floor contacts cost), and the objective after every iteration is no higher than before
    it (a step that would raise it is refused)."""
    clip, model = _walk()
    config = get_method("trajopt").make_config(floor_margin_m=0.0)
    start = _quiet_window(clip, 24)
    prob, q, _ = _problem(model, clip, start, 24, config)
    rng = np.random.default_rng(7)
    q0 = np.asarray(q).copy()
    q0[:, :3] += rng.normal(0, 0.05, (24, 3))
    q0[:, model.topo.hinge_qadr] += rng.normal(0, 0.1, (24, len(model.topo.hinge_qadr)))
    run = jax.jit(lambda q, k: TO.gauss_newton(model, q, prob, config, k))  # k traced: one compile
    values = [float(run(jnp.asarray(q0), k)[1].final) for k in (0, 1, 2, 4, 10)]
    assert all(b <= a for a, b in zip(values, values[1:], strict=False)), values
    q1, rep = run(jnp.asarray(q0), 10)
    x0, base = TO.from_q(model, jnp.asarray(q0))
    pr = prob.replace(base_quat=base)
    _, ref = jax.jit(lambda x: TO.lbfgs(lambda y: TO.objective(model, y, pr, config, physics=False), x, 1000, 10,
                                        TO.diagonal_scale(model, x, pr, config)))(x0)
    assert float(rep.final) <= 1.05 * float(ref.final), (float(rep.final), float(ref.final))
    kp = lambda x: jax.vmap(lambda y: P.keypoints(model, y, "body25"))(x)  # noqa: E731
    err = np.linalg.norm(np.asarray(kp(q1) - kp(q)), axis=-1)
    assert err.mean() < 0.02, err.mean()
    with pytest.raises(ValueError, match="unknown kinematic_solver"):
        TO.fit(model, prob, q, config.replace(kinematic_solver="newton"))


def test_stencil_blocks_against_dense_assembly():
    """``_stencil_blocks`` (residual groups over consecutive frames -> upper block diagonals)
    against the dense ``sum_i w_i J_i^T J_i`` with each group's Jacobian placed at its frames."""
    rng = np.random.default_rng(2)
    T, F, R, n, K = 9, 4, 3, 5, 4
    N = T - F + 1
    J, w = rng.normal(size=(N, F, R, n)), rng.uniform(0.5, 2.0, N)
    blocks = np.asarray(TO._stencil_blocks(jnp.asarray(J), jnp.asarray(w), T, K, 0))
    dense = np.zeros((T * n, T * n))
    for i in range(N):
        Ji = np.zeros((R, T * n))
        for a in range(F):
            Ji[:, (i + a) * n:(i + a + 1) * n] = J[i, a]
        dense += w[i] * Ji.T @ Ji
    for d in range(K):
        for t in range(T - d):
            np.testing.assert_allclose(blocks[d, t], dense[t * n:(t + 1) * n, (t + d) * n:(t + d + 1) * n], atol=1e-4)


@pytest.mark.slow
def test_linearised_root_wrench_against_autodiff():
    """The physics curvature's model of the root wrench the motion needs, ``b_t ~ M(q_t)[:6] (dq_{t+1}
    - 2 dq_t + dq_{t-1}) fps^2 / (m g)``, against forward-mode autodiff of the wrench
    (:func:`geometry`'s dynamics: RNEA of the trajectory's finite differences) along random steps
    of a walk's frames, float64: within 5 % at 30 fps (the mass matrix's part dominates the
    configuration's and the velocities')."""
    clip, _ = _walk()
    config = get_method("trajopt").make_config()
    with x64():
        model = character(clip.height_m, clip.mass_kg)
        prob, q, _ = _problem(model, clip, 30, 7, config, jnp.float64)

        def need(dq):
            qq = jax.vmap(lambda a, b: P.integrate_positions(model, a, b, 1.0))(q, dq)
            return TO.geometry(model, qq, config.layout, dynamics=TO.dynamics_inputs(model, qq, prob, config)).dynamics.need

        rng = np.random.default_rng(5)
        weight = float(S.body_weight(model, jnp.float64))
        M6 = np.asarray(jax.vmap(lambda x: P.mass_matrix(model, x)[:6])(q)) * float(prob.fps) ** 2 / weight
        for _ in range(3):
            v = rng.normal(0, 0.01, (7, model.nv))
            _, auto = jax.jvp(need, (jnp.zeros((7, model.nv)),), (jnp.asarray(v),))
            auto = np.asarray(auto)[1:-1]
            model_ = np.einsum("tiv,tv->ti", M6[1:-1], v[2:] - 2 * v[1:-1] + v[:-2])
            assert np.linalg.norm(model_ - auto) < 0.05 * np.linalg.norm(auto), (
                np.linalg.norm(model_ - auto) / np.linalg.norm(auto))


@pytest.mark.slow
def test_banded_preconditioning_converges_faster():
    """L-BFGS in the variables of the stages' block-banded Gauss-Newton curvature
    (``precondition="banded"``) against the diagonal scale, the same iterations on a walk window
    seen with 2 px of noise from a start off the truth: both whole-clip stages end lower (the
    kinematic stage's objective and the physics stage's final one), and the joints no keypoint
    sees do not wander."""
    clip, model = _walk()
    start = _quiet_window(clip, 32)
    base = get_method("trajopt").make_config(kinematic_iterations=20, physics_iterations=20, precondition="diagonal")
    prob, q, _ = _problem(model, clip, start, 32, base)
    rng = np.random.default_rng(9)
    prob = prob.replace(keypoints=prob.keypoints.at[..., :2].add(jnp.asarray(rng.normal(0, 2.0, (32, 25, 2)),
                                                                               jnp.float32)))
    q0 = jnp.asarray(q).at[:, 7:].add(jnp.asarray(rng.normal(0, 0.1, (32, q.shape[1] - 7)), jnp.float32))
    run = jax.jit(lambda prob, q0, config: TO.fit(model, prob, q0, config), static_argnums=2)
    fit_d, fit_b = run(prob, q0, base), run(prob, q0, base.replace(precondition="banded"))
    diag, band = fit_d.diagnostics, fit_b.diagnostics
    # the wrists, which no keypoint sees (no curvature but the limits'): the banded variables'
    # floor keeps them from taking stray physics gradients (they move less than with the diagonal)
    wrists = [model.mj.jnt_qposadr[model.mj.joint(n).id]
              for n in ("left_wrist_x", "left_wrist_z", "right_wrist_x", "right_wrist_z")]
    moved = lambda f: float(np.abs(np.asarray(f.q)[:, wrists] - np.asarray(q0)[:, wrists]).mean())  # noqa: E731
    assert moved(fit_b) <= moved(fit_d), (moved(fit_b), moved(fit_d))
    assert float(band["objective_kinematic"]) < float(diag["objective_kinematic"]), (
        float(band["objective_kinematic"]), float(diag["objective_kinematic"]))
    assert float(band["objective_final"]) < float(diag["objective_final"]), (
        float(band["objective_final"]), float(diag["objective_final"]))
    with pytest.raises(ValueError, match="unknown precondition"):
        run(prob, q0, base.replace(precondition="cholesky"))


def test_a_clip_that_satisfies_the_physics_stays_put():
    """Exact keypoints, true contacts, the truth as prior and start: a window of a simulated clip
    where its physics holds without help stays where it is (joints within 2 cm), its forces
    carry the body (root residual below 5 % of body weight) and no sole is below the floor.
    Without the floor margin, which by design holds soles 5 mm above the floor, where the
    simulation's rest at z = 0 or a few mm into its soft floor (with it the joints move 1.5 cm)."""
    clip, model = _walk()
    frames = 40
    start = _quiet_window(clip, frames)
    config = get_method("trajopt").make_config(kinematic_iterations=15, physics_iterations=15, floor_margin_m=0.0)
    prob, q, inputs = _problem(model, clip, start, frames, config)

    @jax.jit
    def run(prob, q):
        out = TO.fit(model, prob, q, config)
        return out, TO.outputs(model, out.q, out.force, prob.mask, prob.fps)

    out, (qd, tau, grf, report) = run(prob, q)
    again, _ = run(prob, q)
    np.testing.assert_array_equal(np.asarray(again.q), np.asarray(out.q))  # same input, same result
    kp = lambda x: jax.vmap(lambda y: P.keypoints(model, y, "body25"))(x)  # noqa: E731
    moved = np.linalg.norm(np.asarray(kp(out.q) - kp(q)), axis=-1)
    # 1.4 cm measured since stop 55: the stages in their banded variables get close to the
    # energy's own minimum, which is not the simulated truth (its accelerations and soft-floor
    # contacts cost; test_gauss_newton_stage_reaches_the_minimum_and_never_climbs: 1.4 cm too)
    assert moved.mean() < 0.02, moved.mean()
    assert float(report["residual_mean_bw"]) < 0.05, report
    assert float(report["penetration_max_m"]) < 0.005, report
    W = model.total_mass * 9.81
    net = np.asarray(grf).sum(1)[:, 2] / W
    assert 0.8 < net[2:-2].mean() < 1.2  # walking: the feet carry about one body weight on average
    for k in ("objective_initial", "objective_final", "grad_norm", "iterations"):
        assert np.isfinite(float(out.diagnostics[k]))
    assert float(out.diagnostics["objective_final"]) <= float(out.diagnostics["objective_physics_initial"])


def test_window_plan_and_weights():
    """Windows cover the clip, the last ends at its end, and the cross-fade weights sum to one
    with linear ramps over the overlaps."""
    assert TO.window_starts(100, 0, 10) == (0,)
    assert TO.window_starts(100, 120, 10) == (0,)
    starts = TO.window_starts(100, 40, 10)
    assert starts == (0, 30, 60)
    w = TO.window_weights(100, starts, 40, 10)
    np.testing.assert_allclose(w.sum(0), 1.0)
    assert np.all(w[0, :30] == 1.0) and np.all(w[0, 40:] == 0.0)
    assert np.all(np.diff(w[1, 30:41]) >= 0)  # ramps up over the overlap
    with pytest.raises(ValueError, match="overlap"):
        TO.window_starts(100, 40, 40)


@pytest.mark.slow
def test_stitched_windows_equal_the_whole_clip_without_a_seam():
    """A clip fitted in overlapping windows agrees with the same clip fitted whole (joints within
    2 cm on average), and the stitch adds no jump: the largest joint acceleration of the stitched
    result is within 1.5x that of the whole-clip result."""
    clip, model = _walk()
    frames = 96
    config = get_method("trajopt").make_config(kinematic_iterations=30, physics_iterations=30)
    prob, q, _ = _problem(model, clip, 0, frames, config)
    q0 = q.at[:, 7:].add(0.05)  # start off the truth

    run = jax.jit(lambda prob, q0, config: TO.fit_clip(model, prob, q0, config))
    whole = run(prob, q0, config)
    stitched = run(prob, q0, config.replace(window=56, overlap=16))
    kp = lambda x: np.asarray(jax.vmap(lambda y: P.keypoints(model, y, "body25"))(x))  # noqa: E731
    a, b = kp(whole.q), kp(stitched.q)
    assert np.linalg.norm(a - b, axis=-1).mean() < 0.02
    acc = lambda k: np.linalg.norm(np.diff(k, 2, axis=0), axis=-1).max()  # noqa: E731
    assert acc(b) < 1.5 * acc(a) + 1e-3


def test_engine_gives_trajopt_whole_clips():
    """The batch engine runs a non-causal method on whole clips padded to its bucket (one chunk,
    no history), a causal one in chunks."""
    from jmocap.pipeline import Reconstructor

    clip, _ = _walk()  # 120 frames
    r = Reconstructor({}, get_method("trajopt").make_config(), method="trajopt", chunk=48, bucket=64)
    assert r.plan(clip) == (128,) and r.history == 0
    p = Reconstructor({}, get_method("pip").make_config(), method="pip", chunk=48, bucket=16)
    assert p.plan(clip) == (48, 48, 32)
