"""``mocon``: sampling-based control of a simulated character (issue 21, item 3).

References: MuJoCo C (the centre of mass of the simulated states, ``mj_subtreeCoM``) for Newton's
law with the simulator's recorded contact forces, the character's own MuJoCo model for the
simulated one, MJX for the MuJoCo C rollouts (slow), and the clip's ground truth for the
tracking. The tracked reference here is a synthetic clip's ground truth (its simulated motion and
torques), so these tests do not compile ``trajopt``; the slow end-to-end test runs the method
through ``jmocap reconstruct``'s engine on a terrain clip.
"""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest

from conftest import mujoco_com, x64
from jmocap.constants import GRAVITY
from jmocap.data import synthetic as S
from jmocap.inputs import ClipInputs
from jmocap.methods import get_method
from jmocap.methods import mocon as MC
from jmocap.motion import Motion
from jmocap.pipeline import subject_model
from jmocap.scene import boxes, height_above

FAST = dict(samples=16, window_frames=3, lookahead_frames=6, threads=2)


def _reference(clip) -> Motion:
    """A clip's ground truth as a reference Motion (velocities by MuJoCo's finite differences)."""
    model = subject_model(clip)
    q = np.asarray(clip.gt_q, np.float64)
    qd = np.zeros((len(q), model.nv))
    for t in range(1, len(q)):
        mujoco.mj_differentiatePos(model.mj, qd[t], 1.0 / clip.fps, q[t - 1], q[t])
    qd[0] = qd[1]
    T = len(q)
    return Motion(q.astype(np.float32), qd.astype(np.float32), np.asarray(clip.gt_tau, np.float32),
                  np.asarray(clip.gt_grf, np.float32), np.asarray(clip.gt_contacts, np.float32),
                  q.astype(np.float32), np.ones(T, bool))


@pytest.fixture(scope="module")
def walk():
    return S.generate_clip(1, 0, S.SynthConfig(frames=60, kinds=("walk",), physics=True))


@pytest.fixture(scope="module")
def tracked(walk):
    config = MC.MoconConfig(**FAST)
    return MC.track(subject_model(walk), ClipInputs.from_clip(walk), _reference(walk), config)


def test_the_simulated_character_is_the_reconstructions(walk):
    model = subject_model(walk)
    scene = S.generate_clip(5, 1, S.SynthConfig(frames=60, terrain=("step_up",))).scene
    sim = MC.Simulation(model, scene, walk.fps, MC.MoconConfig())
    np.testing.assert_allclose(sim.mj.body_mass, model.mj.body_mass, rtol=1e-12)
    np.testing.assert_allclose(sim.mj.body_pos, model.mj.body_pos, atol=1e-12)
    hinges = int(np.sum(model.mj.jnt_type == mujoco.mjtJoint.mjJNT_HINGE))
    assert sim.mj.nu == hinges and sim.mj.nq == model.nq
    # the scene's boxes are ground geoms; each foot owns geoms
    assert sim.ground.sum() == 1 + len(boxes(scene))
    assert (sim.geom_foot == 0).any() and (sim.geom_foot == 1).any()
    assert sim.n * sim.dt == pytest.approx(1.0 / walk.fps) and sim.dt <= MC.MoconConfig().max_dt


def test_no_root_force_and_newtons_law_with_the_simulators_forces(walk, tracked):
    """The root is never actuated (tau[:, :6] is exactly 0) and the recorded contact forces are
    what moves the centre of mass: m (com'' + g) = sum of the four sites' forces at every
    interior frame (central differences of MuJoCo C's centre of mass), to 2 % of body weight."""
    m = tracked
    assert int(m.diagnostics["mocon_resets"]) == 0
    np.testing.assert_array_equal(m.tau[:, :6], 0.0)
    model = subject_model(walk)
    com = mujoco_com(model.mj, np.asarray(m.q, np.float64))
    mass = float(np.sum(model.mj.body_mass))
    acc = (com[2:] - 2 * com[1:-1] + com[:-2]) * walk.fps**2
    need = mass * (acc + np.array([0.0, 0.0, GRAVITY]))
    got = np.asarray(m.grf, np.float64).sum(1)[1:-1]
    err = np.linalg.norm(got - need, axis=-1) / (mass * GRAVITY)
    assert np.percentile(err, 95) < 0.02, err.max()
    # labels are the forces: a site in contact carries force
    assert np.all((m.contact_prob > 0) == (m.grf[..., 2] > 0.01 * mass * GRAVITY))


def test_it_tracks_the_reference_and_stays_out_of_the_floor(walk, tracked):
    model = subject_model(walk)
    ref = _reference(walk)
    from jmocap import physics as P

    kp = np.asarray(jax.vmap(lambda q: P.keypoints(model, q, walk.layout))(tracked.q))
    kp_ref = np.asarray(jax.vmap(lambda q: P.keypoints(model, q, walk.layout))(ref.q))
    assert np.mean(np.linalg.norm(kp - kp_ref, axis=-1)) < 0.08
    sites = np.asarray(jax.vmap(lambda q: P.site_positions(model, q, model.topo.contact_sites))(tracked.q))
    assert height_above(None, sites.reshape(-1, 3)).min() > -0.01


def test_deterministic_in_its_seed(walk, tracked):
    again = MC.track(subject_model(walk), ClipInputs.from_clip(walk), _reference(walk), MC.MoconConfig(**FAST))
    for a, b in zip(jax.tree.leaves(tracked), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_mocon_cannot_be_traced_and_says_so(walk):
    method = get_method("mocon")
    assert method.host is not None and not method.causal
    inputs = jax.tree.map(np.asarray, ClipInputs.from_clip(walk))
    with pytest.raises(TypeError, match="host"):
        jax.jit(method.reconstruct, static_argnums=3)({}, subject_model(walk), inputs, MC.MoconConfig())


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="backend"):
        MC.check_config(MC.MoconConfig(backend="warp"))
    with pytest.raises(ValueError, match="sampling"):
        MC.check_config(MC.MoconConfig(sampling="cma"))


@pytest.mark.slow
def test_mjx_rollouts_agree_with_mujoco_c(walk):
    """The two backends simulate the same samples from the same state: MJX against MuJoCo C
    over two frames of 16 random servo corrections (float64)."""
    model = subject_model(walk)
    sim = MC.Simulation(model, None, walk.fps, MC.MoconConfig())
    d = mujoco.MjData(sim.mj)
    ref = _reference(walk)
    d.qpos[:], d.qvel[:] = ref.q[10], ref.qd[10]
    mujoco.mj_forward(sim.mj, d)
    rng = np.random.default_rng(0)
    steps = 2 * sim.n
    ctrl = np.asarray(ref.q[10], np.float64)[sim.hinge_q][None, None] + 0.1 * rng.normal(size=(16, 1, sim.mj.nu))
    controls = np.concatenate([np.broadcast_to(ctrl, (16, steps, sim.mj.nu)), np.zeros((16, steps, sim.mj.nv))], -1)
    ends = np.array([sim.n - 1, 2 * sim.n - 1])
    qc, vc = MC.MujocoRollouts(sim.mj, 2)(d, controls, ends)
    with x64():
        qx, vx = MC.MjxRollouts(sim.mj)(d, controls, ends)
    root = np.linalg.norm(qx[..., :3] - qc[..., :3], axis=-1)  # (16, 2) m
    hinge = np.abs(qx[..., 7:] - qc[..., 7:])  # rad
    print(f"MJX - MuJoCo C: root {np.median(root):.2e} median, {root[:, 0].max():.2e} / {root.max():.2e} max "
          f"(frame 1 / 2); hinges {np.median(hinge):.2e} median, {hinge.max():.2e} max")
    # the two constraint solvers differ: most samples agree to float rounding, a few drift apart
    # by millimetres in a contact-rich frame (measured: 3 mm after two frames, 1 in 16 samples)
    assert np.median(root) < 1e-4 and np.median(hinge) < 1e-3
    assert root[:, 0].max() < 2e-3 and root.max() < 1e-2 and hinge.max() < 0.05
    assert np.isfinite(vx).all()


@pytest.mark.slow
def test_mocon_through_the_engine_on_terrain(tmp_path):
    """``jmocap reconstruct``'s engine runs mocon on a terrain clip: every field, no root force,
    nothing inside the scene beyond MuJoCo's soft contact."""
    from jmocap import physics as P
    from jmocap import weights
    from jmocap.pipeline import Reconstructor

    clip = S.generate_clip(5, 1, S.SynthConfig(frames=60, physics=True, terrain=("stairs_down",)))
    params, config = weights.load_run_params(None, method="mocon")
    config = config.replace(**FAST)
    (res,) = Reconstructor(params, config, method="mocon", batch=1).run([clip])
    assert res["q"].shape[0] == res["grf"].shape[0] == res["keypoints3d"].shape[0] == clip.num_frames
    np.testing.assert_array_equal(res["tau"][:, :6], 0.0)
    assert "mocon_resets" in res["diagnostics"]
    model = subject_model(clip)
    sites = np.asarray(jax.vmap(lambda q: P.site_positions(model, q, model.topo.contact_sites))(res["q"]))
    assert height_above(clip.scene, sites.reshape(-1, 3)).min() > -0.02
