"""The shipped default weights: saving (float16 msgpack) and loading.

``default_params()`` returns the parameters and the :class:`~jmocap.cycle.CycleConfig` they were
trained with, from ``jmocap/assets/``; ``experiments/train_default.py --ship`` writes them.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
from flax import serialization

ASSETS = Path(__file__).resolve().parent / "assets"
DEFAULT_PARAMS = ASSETS / "default_params.msgpack"
DEFAULT_CONFIG = ASSETS / "default_cycle_config.json"


def cycle_config_from_json(d: dict):
    from jmocap.cycle import CycleConfig
    from jmocap.nets import NetConfig

    d = dict(d)
    if "nets" in d:
        d["nets"] = NetConfig(**d["nets"])
    return CycleConfig(**d)


def ship_params(params, cycle_config, source: str = "") -> None:
    """Write ``params`` (as float16, halving the size) and their config into the package."""
    from jmocap.train import _atomic_write

    half = jax.tree.map(lambda x: np.asarray(x, np.float16), params)
    _atomic_write(DEFAULT_PARAMS, serialization.msgpack_serialize(half))
    meta = {"cycle": dataclasses.asdict(cycle_config), "trained_by": source}
    _atomic_write(DEFAULT_CONFIG, json.dumps(meta, indent=2).encode())


def load_params(path: str | Path):
    """Parameters from a msgpack file (float16 or float32) as float32 numpy arrays."""
    raw = serialization.msgpack_restore(Path(path).read_bytes())
    return jax.tree.map(lambda x: np.asarray(x, np.float32), raw)


def default_params():
    """``(params, CycleConfig)`` of the shipped default model."""
    if not DEFAULT_PARAMS.exists():
        raise FileNotFoundError(
            f"no shipped weights at {DEFAULT_PARAMS}; train them with experiments/train_default.py --ship"
        )
    meta = json.loads(DEFAULT_CONFIG.read_text())
    return load_params(DEFAULT_PARAMS), cycle_config_from_json(meta["cycle"])
