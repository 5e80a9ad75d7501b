"""Shared fixtures and the suite's one persistent compilation cache; x64 is switched on per test."""

from __future__ import annotations

import contextlib
import gc
import os
import tempfile
import warnings
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


def mujoco_com(mj: mujoco.MjModel, q) -> np.ndarray:
    """Whole-body centre of mass (T, 3) of configurations (T, nq) by MuJoCo C (``subtree_com``
    of the world body)."""
    d = mujoco.MjData(mj)
    out = []
    for x in np.asarray(q, np.float64):
        d.qpos[:] = x
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        out.append(d.subtree_com[0].copy())
    return np.array(out)


def central_diff(f, x, eps: float = 1e-6):
    """Jacobian of a numpy-valued ``f`` at ``x`` (float64) by central differences, shaped
    (out..., in...): the finite-difference reference of the gradient tests."""
    x = np.asarray(x, np.float64)
    cols = []
    for i in range(x.size):
        dx = np.zeros(x.size)
        dx[i] = eps
        dx = dx.reshape(x.shape)
        cols.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps))
    return np.stack(cols, -1).reshape(np.shape(f(x)) + x.shape)


# ---- one persistent compilation cache for the whole suite ------------------------------
#
# Tests in different modules (and the CLI subprocesses some of them start) compile the same
# programs under different Python functions; only jax's persistent, HLO-keyed cache can share
# them, and across runs it turns most of the suite's compile time into file reads.  One
# directory serves the whole session: $JMOCAP_TEST_XLA_CACHE if set, else the user's cache
# folder ($XDG_CACHE_HOME or ~/.cache)/jmocap/xla-tests, beside the CLI's own cache
# (~/.cache/jmocap/xla), so that a fresh clone on a machine that ran the suite before starts
# warm (jax keys every entry by the program, the compile options and the jax/jaxlib versions,
# so an entry is never reused for another program or version; `make clean-cache` empties it).
# pytest-xdist workers share it: an entry is written once per key, zlib-compressed, so a read
# racing a write fails to decompress (checksum) and jax recompiles with a warning.

XLA_CACHE_ENV = "JMOCAP_TEST_XLA_CACHE"
_SUITE_CACHE: dict[str, str] = {}


def _configure_compilation_cache(path: str) -> None:
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_compilation_cache_dir", path)
    # cache every program that took noticeable time (default 1 s): the suite is mostly
    # sub-second compiles of small jitted checks, which a second run then reads back
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    compilation_cache.reset_cache()


def user_cache_dir() -> Path:
    """($XDG_CACHE_HOME or ~/.cache)/jmocap/xla-tests."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jmocap" / "xla-tests"


def pytest_configure(config):
    path = os.environ.get(XLA_CACHE_ENV) or str(user_cache_dir())
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: a cache for this run only
        path = tempfile.mkdtemp(prefix="jmocap-xla-")
    _SUITE_CACHE["path"] = path
    _configure_compilation_cache(path)


@pytest.fixture(scope="session")
def xla_cache() -> str:
    """The suite's persistent compilation cache directory (pass it to CLI subprocesses as
    ``--cache-dir`` so that they share the suite's compiled programs)."""
    return _SUITE_CACHE["path"]


# ---- compiled programs are freed after each module --------------------------------------
#
# Every live compiled program keeps about three memory mappings (its code, read-only data and
# data pages).  jax keeps every program it compiled, so one process running the whole suite
# (~20k programs) reached Linux's per-process limit vm.max_map_count (65530); the next compile
# then failed to map memory ("LLVM compilation error: Cannot allocate memory") and XLA's CPU
# compiler segfaulted instead of raising (jax/jaxlib 0.10.2; reproducer and numbers in
# docs/performance.md).  Dropping jax's in-memory caches after each module bounds the count
# by the largest module; programs a later module needs again come back from the persistent
# cache above.


def _memory_mappings() -> tuple[int, int] | None:
    """(mappings of this process, the system's limit), or None where /proc is not there."""
    try:
        with open("/proc/self/maps", "rb") as f:
            n = sum(1 for _ in f)
        return n, int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


@pytest.fixture(autouse=True, scope="module")
def _module_boundary():
    """After each module: free its compiled programs, and put the suite's compilation cache
    back if a CLI command run in-process pointed jax elsewhere (its ``--cache-dir``)."""
    yield
    jax.clear_caches()
    gc.collect()
    maps = _memory_mappings()
    if maps is not None and maps[0] > maps[1] // 2:
        warnings.warn(f"{maps[0]} memory mappings after freeing compiled programs (limit "
                      f"{maps[1]}): something keeps compiled programs alive across modules",
                      stacklevel=1)
    if jax.config.jax_compilation_cache_dir != _SUITE_CACHE["path"]:
        _configure_compilation_cache(_SUITE_CACHE["path"])
