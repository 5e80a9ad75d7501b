"""Calling the package's JAX functions from the numpy generator, in float64 on the CPU.

The generator is numpy / MuJoCo C code. Where it needs what the package implements in JAX and
the call is cheap (fixed shapes, a few calls per clip: the look-at camera of
``jmocap.camera``), it calls that code through :func:`np64` rather than keeping a numpy copy.
The call runs with x64 switched on for its duration only and on the host CPU, so a clip's
numbers depend neither on the process's ``jax_enable_x64`` setting nor on an accelerator being
present (the generator's determinism, ``docs/data.md``). Pass a ``jax.jit``-ed function: an
eager call compiles every primitive for every new shape (seconds on a 2-core CPU); per-frame
arrays whose length changes with the clip stay numpy (:mod:`~.rotations`, :mod:`~.cameras`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


@functools.cache
def _host_cpu():
    """The host CPU device, or None (JAX's default device) where no CPU backend is enabled."""
    try:
        return jax.devices("cpu")[0]
    except RuntimeError:
        return None


def np64(fn: Callable[..., Any], *args) -> Any:
    """``fn(*args)`` with every argument as a float64 JAX array; the result (a pytree of
    arrays) comes back as float64 numpy arrays (writable copies)."""
    with jax.enable_x64(True), jax.default_device(_host_cpu()):
        out = fn(*(jnp.asarray(np.asarray(a, np.float64)) for a in args))
        return jax.tree.map(np.array, out)
