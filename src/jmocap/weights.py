"""Parameters of the methods' networks: the shipped default weights, files, and their config.

``default_params()`` returns the shipped parameters and the config they were trained with
(``jmocap/assets/``; ``experiments/train_default.py --ship`` writes them);
:func:`load_run_params` resolves what a command line asks for (a weights file, a config given
as JSON text or a file, a method) into ``(params, config)``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization

from jmocap import methods
from jmocap.io import atomic_write
from jmocap.model import DEFAULT_MODEL_PATH, character

ASSETS = Path(__file__).resolve().parent / "assets"
DEFAULT_PARAMS = ASSETS / "default_params.msgpack"
DEFAULT_CONFIG = ASSETS / "default_cycle_config.json"


def save_params(path: str | os.PathLike, params) -> None:
    """Write ``params`` (float32 msgpack) atomically."""
    atomic_write(path, serialization.msgpack_serialize(jax.tree.map(np.asarray, params)))


def load_params(path: str | os.PathLike):
    """Parameters from a msgpack file (float16 or float32) as float32 numpy arrays."""
    raw = serialization.msgpack_restore(Path(path).read_bytes())
    return jax.tree.map(lambda x: np.asarray(x, np.float32), raw)


def ship_params(params, config, source: str = "") -> None:
    """Write ``params`` (as float16, halving the size) and their config into the package."""
    half = jax.tree.map(lambda x: np.asarray(x, np.float16), params)
    atomic_write(DEFAULT_PARAMS, serialization.msgpack_serialize(half))
    meta = {"cycle": methods.config_dict(config), "trained_by": source}
    atomic_write(DEFAULT_CONFIG, json.dumps(meta, indent=2).encode())


def default_config_fields() -> dict[str, Any]:
    """The config fields the shipped weights were trained with (a flat dict)."""
    return dict(json.loads(DEFAULT_CONFIG.read_text())["cycle"])


def default_params(method: str = methods.DEFAULT_METHOD):
    """``(params, config)`` of the shipped default model for ``method`` (a method or variant)."""
    if not DEFAULT_PARAMS.exists():
        raise FileNotFoundError(
            f"no shipped weights at {DEFAULT_PARAMS}; train them with experiments/train_default.py --ship"
        )
    m, changes = methods.resolve(method)
    return load_params(DEFAULT_PARAMS), m.make_config(m.weights_config(default_config_fields()), **changes)


def _config_overrides(config: str) -> dict[str, Any]:
    """Config fields from JSON text or a JSON file: config fields, a training ``config.json``
    (its ``cycle`` part) or the shipped config file."""
    text = Path(config).read_text() if not config.lstrip().startswith("{") else config
    try:
        over = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"--config: not valid JSON: {e}") from None
    if not isinstance(over, dict):
        raise ValueError("--config: must be a JSON object")
    over = over.get("cycle", over)
    if not isinstance(over, dict):
        raise ValueError("--config: its 'cycle' entry must be a JSON object")
    return dict(over)


def load_run_params(params_path: str | os.PathLike | None = None, config: str | None = None,
                    method: str = methods.DEFAULT_METHOD):
    """``(params, config)`` for ``method``: the shipped weights or a msgpack file, with
    ``config`` (JSON text or a JSON file, read as overrides) applied on top of the config the
    weights came with (the shipped config; a params file gets the ``config.json`` next to it,
    a training run's folder, or the defaults). Of the weights' config the method takes only the
    fields it takes from weights (``Method.from_weights``: for ``pip`` and ``trajopt`` the
    learned stage's, not physcap's cycle settings); every field of ``config`` applies. The
    method's variant changes come last."""
    m, changes = methods.resolve(method)
    if params_path is None:
        params, base = default_params()[0], default_config_fields()
    else:
        params, base = load_params(params_path), {}
        beside = Path(params_path).with_name("config.json")
        if beside.is_file():
            base = _config_overrides(str(beside))
    base = m.weights_config(base)
    over = _config_overrides(config) if config is not None else {}
    nets = {**base.get("nets", {}), **over.pop("nets", {})}
    fields = {**base, **over}
    if nets:
        fields["nets"] = nets
    try:
        cfg = m.make_config(fields, **changes)
    except (TypeError, ValueError) as e:
        raise ValueError(f"--config: {e}") from None
    return params, cfg


def params_sha256(params) -> str:
    """Identity of a parameter pytree: sha256 over its leaf paths, shapes and float32 values."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        a = np.ascontiguousarray(np.asarray(leaf, np.float32))
        h.update(f"{jax.tree_util.keystr(path)}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def model_sha256(path: str | os.PathLike = DEFAULT_MODEL_PATH) -> str:
    """Identity of the character's MJCF file."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_params(params, config, method: str = methods.DEFAULT_METHOD) -> None:
    """Raise ``ValueError`` when ``params`` lack a network ``method`` needs, or have shapes other
    than ``config`` implies."""
    m = methods.get_method(method)
    want = jax.eval_shape(lambda: m.init_params(jax.random.PRNGKey(0), character(), config))
    got_leaves = {jax.tree_util.keystr(p): np.shape(x) for p, x in jax.tree_util.tree_flatten_with_path(params)[0]}
    for p, x in jax.tree_util.tree_flatten_with_path(want)[0]:
        k = jax.tree_util.keystr(p)
        if getattr(p[0], "key", None) in m.shipped_networks and p[0].key not in params:
            continue  # the method loads these from its own shipped file
        if k not in got_leaves:
            raise ValueError(f"the parameters have no {k} (shape {x.shape}) that the config needs")
        if tuple(got_leaves[k]) != tuple(x.shape):
            raise ValueError(
                f"the parameters do not fit the config: {k} has shape {tuple(got_leaves[k])}, "
                f"the config needs {tuple(x.shape)} (pass the config they were trained with: --config)"
            )


__all__ = [
    "DEFAULT_CONFIG",
    "DEFAULT_PARAMS",
    "check_params",
    "default_config_fields",
    "default_params",
    "load_params",
    "load_run_params",
    "model_sha256",
    "params_sha256",
    "save_params",
    "ship_params",
]
