"""PhysCapConfig.physics_backend: the "mjx" backend (M, h, J_c from MJX's own functions) against
the default "jmocap" backend (physics.smooth_dynamics), one cycle_step from the same state.

Reference: MJX is an independent implementation of the same MuJoCo quantities, so the two steps
must agree to rounding. Tolerances, relative to each output's largest entry: float64 1e-10
(observed 2e-14: M, h and J_c agree to ~1e-15 and one step amplifies that by the PD gains and
M^-1); float32 1e-4 (observed 1e-5: M and h agree to ~1e-7 relative, amplified alike).
The MJX step compiles for one to two minutes on 2 cores, so only the float32 step runs by default.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import x64
from jmocap.methods.physcap import CycleState, PhysCapConfig, cycle_step, init_params
from jmocap.methods.stages import mjx_smooth_dynamics
from jmocap.model import load_model
from jmocap.physics import smooth_dynamics


def _state(model, seed, dtype):
    """A pose near the floor with two feet in contact, a target pose nearby, random velocity."""
    rng = np.random.default_rng(seed)
    q = np.array(model.mj.qpos0, np.float64)
    q[2] = 0.95  # standing height of the default humanoid: the feet touch the floor
    hq = model.topo.hinge_qadr
    q[hq] += rng.normal(scale=0.05, size=hq.size)
    q_hat = q.copy()
    q_hat[hq] += rng.normal(scale=0.1, size=hq.size)
    q_hat[:3] += rng.normal(scale=0.02, size=3)
    qd = rng.normal(scale=0.5, size=model.nv)
    grf = rng.normal(scale=50.0, size=(4, 3))
    state = CycleState(jnp.asarray(q, dtype), jnp.asarray(qd, dtype), jnp.asarray(grf, dtype))
    prob = jnp.asarray([0.9, 0.8, 0.7, 0.2], dtype)  # three points in contact, one not
    return state, jnp.asarray(q_hat, dtype), prob


def _steps(model, dtype, seed=0):
    params = init_params(jax.random.PRNGKey(seed), model)
    state, q_hat, prob = _state(model, seed, dtype)
    dt = jnp.asarray(1.0 / 180.0, dtype)
    step = jax.jit(cycle_step)
    out = {}
    for backend in ("jmocap", "mjx"):
        cfg = PhysCapConfig(physics_backend=backend)
        out[backend] = jax.tree.map(np.asarray, step(params, model, state, q_hat, prob, dt, cfg))
    return out


def _compare(out, rtol):
    ref = jax.tree.leaves(out["jmocap"])
    got = jax.tree.leaves(out["mjx"])
    assert len(ref) == len(got)
    worst = 0.0
    for a, b in zip(ref, got, strict=True):
        assert np.all(np.isfinite(b))
        scale = max(float(np.max(np.abs(a))), 1.0)
        worst = max(worst, float(np.max(np.abs(b - a))) / scale)
        np.testing.assert_allclose(b, a, rtol=0, atol=rtol * scale)
    print(f"largest deviation relative to the output's scale: {worst:.1e} (tolerance {rtol:.0e})")


@pytest.mark.slow
def test_mjx_backend_terms_match_smooth_dynamics():
    with x64():
        model = load_model(with_mjx=True)
        state, _, _ = _state(model, 1, jnp.float64)
        M, h, Jc = jax.jit(mjx_smooth_dynamics)(model, state.q, state.qd)
        dyn = jax.jit(smooth_dynamics)(model, state.q, state.qd)
        for a, b in ((dyn.M, M), (dyn.h, h), (dyn.Jc, Jc)):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-10 * max(float(jnp.max(jnp.abs(a))), 1.0))


@pytest.mark.slow  # MJX's cycle step compiles for about a minute per dtype on 2 cores
def test_mjx_backend_step_matches_jmocap_float64():
    with x64():
        model = load_model(with_mjx=True)
        _compare(_steps(model, jnp.float64), 1e-10)


def test_mjx_backend_step_matches_jmocap_float32():
    model = load_model(with_mjx=True)
    _compare(_steps(model, jnp.float32), 1e-4)


def test_bad_backend_and_missing_mjx_model():
    model = load_model(with_mjx=False)
    state, q_hat, prob = _state(model, 0, jnp.float32)
    params = init_params(jax.random.PRNGKey(0), model)
    with pytest.raises(ValueError, match="with_mjx=True"):
        cycle_step(params, model, state, q_hat, prob, 1.0 / 180.0, PhysCapConfig(physics_backend="mjx"))
    with pytest.raises(ValueError, match="physics_backend"):
        cycle_step(params, model, state, q_hat, prob, 1.0 / 180.0, PhysCapConfig(physics_backend="mujoco"))
