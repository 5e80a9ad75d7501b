"""jmocap.physics against its references: MuJoCo C (float64), MJX, and finite differences.

Tolerances: in float64 the dense formulation and MuJoCo C's recursive algorithms differ only
by rounding, so quantities agree to a relative 1e-9 (relative to max(1, |reference|)); in
float32 the cancellation in bias forces of a 73 kg body swinging at 2 rad/s leaves ~1e-5.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.test_util import check_grads

from conftest import TREE_XML, random_configurations, x64
from jmocap import physics as P
from jmocap.layouts import LAYOUTS
from jmocap.model import DEFAULT_MODEL_PATH, _import_mjx, load_model

N_CONFIGS = 50
RTOL64 = 1e-9


def rel_err(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


MODELS = {
    "tree": dict(path=TREE_XML),
    "humanoid": dict(path=None),
    "humanoid_1.50m": dict(path=None, height_m=1.5),
    "humanoid_1.95m_90kg": dict(path=None, height_m=1.95, mass_kg=90.0),
}


@pytest.fixture(scope="module", params=list(MODELS))
def model64(request):
    """Each test model, loaded with x64 on (its arrays float64)."""
    with x64():
        yield load_model(**MODELS[request.param])


def mujoco_reference(mj, qs, qds, taus=None):
    """Per-configuration reference quantities from MuJoCo C (constraints off)."""
    mj = _copy_without_constraints(mj)
    d = mujoco.MjData(mj)
    out = {k: [] for k in ("xpos", "xmat", "xipos", "site", "M", "h", "jacp", "jacr", "qacc")}
    for i, (q, qd) in enumerate(zip(qs, qds, strict=True)):
        d.qpos[:], d.qvel[:] = q, qd
        d.qfrc_applied[:] = 0 if taus is None else taus[i]
        mujoco.mj_forward(mj, d)
        M = np.zeros((mj.nv, mj.nv))
        mujoco.mj_fullM(mj, d, M)
        jp = np.zeros((mj.nsite, 3, mj.nv))
        jr = np.zeros((mj.nsite, 3, mj.nv))
        for s in range(mj.nsite):
            mujoco.mj_jacSite(mj, d, jp[s], jr[s], s)
        out["xpos"].append(d.xpos.copy())
        out["xmat"].append(d.xmat.reshape(-1, 3, 3).copy())
        out["xipos"].append(d.xipos.copy())
        out["site"].append(d.site_xpos.copy())
        out["M"].append(M)
        out["h"].append(d.qfrc_bias.copy())
        out["jacp"].append(jp)
        out["jacr"].append(jr)
        out["qacc"].append(d.qacc.copy())
    return {k: np.stack(v) for k, v in out.items()}


def _copy_without_constraints(mj):
    mj = mj.__copy__()
    mj.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    return mj


def _all_terms(model, q, qd, tau):
    kin = P.forward_kinematics(model, q)
    jacp, jacr = P.site_jacobian(model, q, tuple(range(model.topo.nsite)), kin=kin)
    qdd = P.forward_dynamics(model, q, qd, tau)
    return dict(
        xpos=kin.xpos,
        xmat=kin.xmat,
        xipos=kin.xipos,
        site=P.site_positions(model, q, kin=kin),
        M=P.mass_matrix(model, q, kin=kin),
        h=P.bias_forces(model, q, qd, kin=kin),
        jacp=jacp,
        jacr=jacr,
        qacc=qdd,
        tau_back=P.inverse_dynamics(model, q, qd, qdd),
    )


# One compiled function per (topology, dtype, batch): rescaled humanoids share it, since the
# model is a jit argument and its MjModel handle does not enter the cache key.
all_terms = jax.jit(jax.vmap(_all_terms, in_axes=(None, 0, 0, 0)))


# ---------------------------------------------------------------------------------------
# MuJoCo C, float64
# ---------------------------------------------------------------------------------------


def test_against_mujoco_c_float64(model64):
    with x64():
        mj = _copy_without_constraints(model64.mj)
        qs, qds = random_configurations(mj, N_CONFIGS, seed=1)
        taus = np.random.default_rng(3).normal(scale=20.0, size=qds.shape)
        ref = mujoco_reference(mj, qs, qds, taus)
        out = all_terms(model64, qs, qds, taus)
        for key in ("xpos", "xmat", "xipos", "site", "M", "h", "jacp", "jacr"):
            assert rel_err(out[key], ref[key]) < RTOL64, key
        # forward dynamics solves with the Cholesky factor: the error grows with cond(M)
        assert rel_err(out["qacc"], ref["qacc"]) < 1e-8
        assert rel_err(out["tau_back"], taus) < 1e-8
        d = mujoco.MjData(mj)
        for i in range(5):  # mj_inverse as a second reference for inverse dynamics
            d.qpos[:], d.qvel[:], d.qacc[:] = qs[i], qds[i], out["qacc"][i]
            mujoco.mj_inverse(mj, d)
            assert rel_err(out["tau_back"][i], d.qfrc_inverse) < 1e-8


inv_dyn = jax.jit(P.inverse_dynamics)


def test_rnea_against_mujoco_c(model64):
    """``rnea`` (no mass matrix) equals MuJoCo C's ``mj_rne`` with accelerations (plus the
    armature term, which mj_rne leaves to the constraint stage) and ``M qdd + h``."""
    with x64():
        mj = _copy_without_constraints(model64.mj)
        qs, qds = random_configurations(mj, 5, seed=4)
        qdds = np.random.default_rng(5).normal(scale=5.0, size=qds.shape)
        d = mujoco.MjData(mj)
        for q, qd, qdd in zip(qs, qds, qdds, strict=True):
            d.qpos[:], d.qvel[:] = q, qd
            mujoco.mj_forward(mj, d)
            d.qacc[:] = qdd
            ref = np.zeros(mj.nv)
            mujoco.mj_rne(mj, d, 1, ref)
            ref += mj.dof_armature * qdd
            out = np.asarray(P.rnea(model64, q, qd, qdd))
            assert rel_err(out, ref) < RTOL64
            assert rel_err(out, np.asarray(P.inverse_dynamics(model64, q, qd, qdd))) < RTOL64


def test_contact_forces_enter_as_jacobian_transpose():
    """J_c^T f against MuJoCo's mj_applyFT (a world force at a point of a body)."""
    with x64():
        model = load_model()
        mj = model.mj
        qs, qds = random_configurations(mj, 5, seed=4)
        rng = np.random.default_rng(5)
        d = mujoco.MjData(mj)
        for q, qd in zip(qs, qds, strict=True):
            f = rng.normal(scale=300.0, size=(4, 3))
            d.qpos[:], d.qvel[:] = q, qd
            mujoco.mj_forward(mj, d)
            qfrc = np.zeros(mj.nv)
            for i, s in enumerate(model.topo.contact_sites):
                mujoco.mj_applyFT(
                    mj, d, f[i], np.zeros(3), d.site_xpos[s], mj.site_bodyid[s], qfrc
                )
            tau0 = inv_dyn(model, q, qd, np.zeros(mj.nv), np.zeros((4, 3)))
            tau_f = inv_dyn(model, q, qd, np.zeros(mj.nv), f)
            assert rel_err(tau0 - tau_f, qfrc) < 1e-9
            assert P.contact_jacobian(model, q).shape == (12, mj.nv)


def test_integrate_against_mujoco_c(model64):
    with x64():
        mj = model64.mj
        qs, qds = random_configurations(mj, 20, seed=6)
        qdd = np.random.default_rng(7).normal(size=qds.shape)
        dt = 0.011
        step = jax.jit(jax.vmap(P.integrate, in_axes=(None, 0, 0, 0, None)))
        q1, qd1 = step(model64, qs, qds, qdd, dt)
        for i in range(len(qs)):
            qd_ref = qds[i] + dt * qdd[i]
            q_ref = qs[i].copy()
            mujoco.mj_integratePos(mj, q_ref, qd_ref, dt)
            assert rel_err(qd1[i], qd_ref) < 1e-12
            assert rel_err(q1[i], q_ref) < 1e-12
        quat = np.asarray(q1)[:, 3:7]
        np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-14)


def test_keypoints_are_layout_sites():
    with x64():
        model = load_model()
        mj = model.mj
        qs, _ = random_configurations(mj, 3, seed=8)
        d = mujoco.MjData(mj)
        for layout in LAYOUTS.values():
            if not layout.sited:  # BlazePose-33's face corners and fingers: no 3D keypoints, said so
                with pytest.raises(ValueError, match="has none for"):
                    P.keypoints(model, qs[0], layout.name)
                continue
            ids = [mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, s) for s in layout.sites]
            kps = jax.jit(jax.vmap(lambda q, name=layout.name: P.keypoints(model, q, name)))(qs)
            for q, kp in zip(qs, kps, strict=True):
                d.qpos[:] = q
                mujoco.mj_kinematics(mj, d)
                assert kp.shape == (layout.num_joints, 3)
                assert rel_err(kp, d.site_xpos[ids]) < RTOL64


# ---------------------------------------------------------------------------------------
# MJX
# ---------------------------------------------------------------------------------------


def mjx_terms(model, q, qd):
    mjx = _import_mjx()
    mx = model.mjx
    d = mjx.make_data(mx).replace(qpos=q, qvel=qd)
    d = mjx.kinematics(mx, d)
    d = mjx.com_pos(mx, d)
    d = mjx.crb(mx, d)
    d = mjx.com_vel(mx, d)
    d = mjx.rne(mx, d)
    return dict(xpos=d.xpos, xmat=d.xmat, xipos=d.xipos, site=d.site_xpos, M=mjx.full_m(mx, d), h=d.qfrc_bias)


# slow: the same quantities are checked against MuJoCo C in float64 above, and MJX's against
# jmocap's through a whole cycle step (float32) in test_physcap_backend.py
@pytest.mark.slow
@pytest.mark.parametrize("name", ["tree", "humanoid"])
def test_against_mjx(name):
    with x64():
        model = load_model(**MODELS[name], with_mjx=True)
        qs, qds = random_configurations(model.mj, 8, seed=9)
        ref = jax.jit(jax.vmap(lambda q, qd: mjx_terms(model, q, qd)))(qs, qds)
        out = all_terms(model, qs, qds, np.zeros_like(qds))
        for key in ("xpos", "xipos", "site", "M", "h"):
            assert rel_err(out[key], ref[key]) < RTOL64, key
        assert rel_err(out["xmat"], ref["xmat"].reshape(out["xmat"].shape)) < RTOL64


# ---------------------------------------------------------------------------------------
# float32 (the default) and batching
# ---------------------------------------------------------------------------------------


smooth = jax.jit(jax.vmap(P.smooth_dynamics, in_axes=(None, 0, 0)))


def test_float32_default_matches_mujoco():
    model = load_model()
    qs, qds = random_configurations(model.mj, 16, seed=10)
    ref = mujoco_reference(model.mj, qs, qds)
    dyn = smooth(model, qs.astype(np.float32), qds.astype(np.float32))
    assert dyn.M.dtype == jnp.float32
    assert rel_err(dyn.M, ref["M"]) < 1e-5
    assert rel_err(dyn.h, ref["h"]) < 1e-5
    jc_ref = ref["jacp"][:, list(model.topo.contact_sites)].reshape(len(qs), 12, -1)
    assert rel_err(dyn.Jc, jc_ref) < 1e-5


def test_vmap_matches_single_evaluation():
    model = load_model()
    qs, qds = random_configurations(model.mj, 4, seed=11)
    batch = smooth(model, qs, qds)
    single_fn = jax.jit(P.smooth_dynamics)
    for i in range(len(qs)):
        single = single_fn(model, qs[i], qds[i])
        np.testing.assert_allclose(batch.M[i], single.M, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(batch.h[i], single.h, rtol=1e-5, atol=1e-4)


# ---------------------------------------------------------------------------------------
# gradients against finite differences
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, n_configs", [pytest.param("tree", 1, marks=pytest.mark.slow), ("humanoid", 1),
                        pytest.param("humanoid", 3, marks=pytest.mark.slow)]
)
def test_gradients_match_finite_differences(name, n_configs):
    with x64():
        model = load_model(**MODELS[name], with_mjx=False)
        qs, qds = random_configurations(model.mj, n_configs, seed=12)
        rng = np.random.default_rng(13)
        nc = 3 * len(model.topo.contact_sites)

        # one function with every differentiated output, so check_grads compiles it once
        @jax.jit
        def fn(q, qd, tau, f, qdd):
            return (
                P.mass_matrix(model, q),
                P.bias_forces(model, q, qd),
                P.forward_dynamics(model, q, qd, tau, f if nc else None),
                P.integrate(model, q, qd, qdd, 0.01),
            )

        for q, qd in zip(qs, qds, strict=True):
            args = (
                q,
                qd,
                rng.normal(scale=10.0, size=model.nv),
                rng.normal(scale=100.0, size=nc),
                rng.normal(size=model.nv),
            )
            check_grads(fn, args, order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5, eps=1e-6)


def test_gradient_finite_at_rest():
    """Zero velocity, identity root: no NaN from norms of zero vectors (quaternion exp)."""
    model = load_model(with_mjx=False)
    q = jnp.asarray(model.keyframe("stand"), jnp.float32)
    qd = jnp.zeros(model.nv)

    def loss(q, qd):
        qdd = P.forward_dynamics(model, q, qd, jnp.zeros(model.nv))
        q1, qd1 = P.integrate(model, q, qd, qdd, 0.01)
        return jnp.sum(q1**2) + jnp.sum(qd1**2)

    g = jax.jit(jax.grad(loss, argnums=(0, 1)))(q, qd)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)


# ---------------------------------------------------------------------------------------
# scaling
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("height, mass", [(1.5, None), (1.95, None), (1.62, 55.0), (None, 90.0)])
def test_scaled_model_has_requested_height_and_mass(height, mass):
    from jmocap.model import nominal_height

    base = load_model(with_mjx=False)
    m = load_model(height_m=height, mass_kg=mass, with_mjx=False)
    if height is not None:
        assert nominal_height(m.mj) == pytest.approx(height, rel=1e-9)
    assert m.total_mass == pytest.approx(mass if mass else base.total_mass, rel=1e-9)
    # inertia scales as mass * length^2
    s = (height / nominal_height(base.mj)) if height else 1.0
    k = (mass / base.total_mass) if mass else 1.0
    np.testing.assert_allclose(m.body_inertia, base.body_inertia * k * s * s, rtol=1e-9)
    # feet stay on the floor in the scaled standing keyframe
    d = mujoco.MjData(m.mj)
    d.qpos[:] = m.keyframe("stand")
    mujoco.mj_kinematics(m.mj, d)
    np.testing.assert_allclose(d.site_xpos[list(m.topo.contact_sites), 2], 0.0, atol=1e-9)


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_model(tmp_path / "missing.xml")
    with pytest.raises(ValueError, match="height_m"):
        load_model(height_m=17.5)
    with pytest.raises(ValueError, match="mass_kg"):
        load_model(mass_kg=-3)
    ball = tmp_path / "ball.xml"
    ball.write_text(
        '<mujoco><worldbody><body><joint name="b" type="ball"/><geom size=".1"/></body>'
        "</worldbody></mujoco>"
    )
    with pytest.raises(ValueError, match="ball joint"):
        load_model(ball)
    model = load_model(DEFAULT_MODEL_PATH, with_mjx=False)
    with pytest.raises(ValueError, match="contact_force"):
        P.forward_dynamics(model, model.keyframe("stand"), np.zeros(model.nv), np.zeros(model.nv), np.zeros(5))


def test_joint_limits_are_read_from_the_model():
    model = load_model(with_mjx=False)
    mj = model.mj
    for j in range(1, mj.njnt):  # every hinge of the humanoid is limited
        a = mj.jnt_qposadr[j]
        assert (model.q_lower[a], model.q_upper[a]) == tuple(mj.jnt_range[j])
    assert np.all(np.isinf(model.q_lower[:7])) and np.all(np.isinf(model.q_upper[:7]))
