"""Shared fixtures: models are loaded once per session; x64 is switched on per module."""

from __future__ import annotations

import contextlib
from pathlib import Path

import jax
import mujoco
import numpy as np
import pytest

ASSETS = Path(__file__).parent / "assets"
TREE_XML = ASSETS / "tree.xml"


@contextlib.contextmanager
def x64():
    """Run a block with float64 enabled, restoring the previous setting afterwards."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", old)


@pytest.fixture
def enable_x64():
    with x64():
        yield


def random_configurations(mj: mujoco.MjModel, n: int, seed: int = 0):
    """Random (q, qd) pairs: random root pose and velocity, joint angles inside their limits."""
    rng = np.random.default_rng(seed)
    qs, qds = [], []
    for _ in range(n):
        q = np.array(mj.qpos0, dtype=np.float64)
        for j in range(mj.njnt):
            a = mj.jnt_qposadr[j]
            t = mj.jnt_type[j]
            if t == mujoco.mjtJoint.mjJNT_FREE:
                q[a : a + 3] = rng.uniform([-3, -3, 0.5], [3, 3, 1.5])
                quat = rng.normal(size=4)
                q[a + 3 : a + 7] = quat / np.linalg.norm(quat)
            elif mj.jnt_limited[j]:
                lo, hi = mj.jnt_range[j]
                q[a] = rng.uniform(lo, hi)
            else:
                q[a] = rng.uniform(-np.pi, np.pi)
        qs.append(q)
        qds.append(rng.normal(scale=2.0, size=mj.nv))
    return np.stack(qs), np.stack(qds)


@pytest.fixture(scope="module")
def xla_cache(tmp_path_factory):
    """A persistent compilation cache for one test module (and the subprocesses it starts):
    programs compiled again under other Python functions, or in another process, are reused."""
    from jax.experimental.compilation_cache import compilation_cache

    path = str(tmp_path_factory.mktemp("xla_cache"))
    old = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", path)
    compilation_cache.reset_cache()
    yield path
    jax.config.update("jax_compilation_cache_dir", old)
    compilation_cache.reset_cache()


@pytest.fixture(autouse=True, scope="module")
def _no_persistent_compilation_cache():
    """CLI commands run in-process switch on jax's persistent compilation cache (their
    ``--cache-dir`` default); keep that from leaking into later test modules."""
    yield
    if jax.config.jax_compilation_cache_dir:
        from jax.experimental.compilation_cache import compilation_cache

        jax.config.update("jax_compilation_cache_dir", None)
        compilation_cache.reset_cache()
