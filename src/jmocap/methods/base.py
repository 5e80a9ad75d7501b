"""What every reconstruction method provides, and the registry that names them.

A method is a set of pure functions over one clip (``jax.vmap`` them over clips, ``jax.jit``
them once per shape):

* ``reconstruct(params, model, inputs, config) -> Motion`` -- a whole clip;
* ``reconstruct_chunk(params, model, inputs, carry, first, config, history)`` -- one chunk of a
  long clip with the method's state carried across chunks (:mod:`jmocap.pipeline` runs clips of
  any length in bounded memory with it); must agree with ``reconstruct`` to float rounding;
* ``init_carry(model, config)`` -- a zero state of the carried pytree (its shapes);
* ``history(config)`` -- how many frames of input before a chunk the chunk needs;
* ``lookahead(config)`` -- how many frames of input *after* a chunk it needs (0 for a causal
  method; a fixed-latency method, e.g. ``pip`` with a centred contact window, reads a few; the
  chunk's inputs are then ``history + L + lookahead`` frames and its output ``L`` frames);
* ``init_params(key, model, config)`` -- fresh parameters of the method's networks.

``config`` is a :mod:`flax.struct` dataclass: fields marked static (stage choice, iteration
counts, layout, network sizes) are part of the compiled program; every other field is a traced
leaf (gains, friction, recovery factors), so it can change without recompiling and be
differentiated (docs/architecture.md, "system identification").

Methods register themselves by name (:func:`register`); *variants* are named config changes of a
method (the paper's ablations). ``jmocap reconstruct --method``, ``jmocap eval --methods`` and
the demo all resolve names with :func:`resolve`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flax import serialization, struct


def static(default: Any) -> Any:
    """A config field that is part of the program's structure (a jit cache key, not traced)."""
    return struct.field(pytree_node=False, default=default)


def static_fields(config_type: type) -> tuple[str, ...]:
    """Names of the static (structural) fields of a config type."""
    return tuple(f.name for f in dataclasses.fields(config_type) if not f.metadata.get("pytree_node", True))


def traced_fields(config_type: type) -> tuple[str, ...]:
    """Names of the traced (differentiable) fields of a config type."""
    return tuple(f.name for f in dataclasses.fields(config_type) if f.metadata.get("pytree_node", True))


def load_float32_params(path) -> dict:
    """Network variables from a msgpack file (float16 or float32) as float32 numpy arrays: the
    networks a method ships apart from the default weights (:func:`jmocap.weights.load_params`,
    which the methods layer may not import)."""
    import jax
    import numpy as np

    raw = serialization.msgpack_restore(Path(path).read_bytes())
    return jax.tree.map(lambda x: np.asarray(x, np.float32), raw)


def whole_clip(reconstruct: Callable) -> dict[str, Any]:
    """The chunking functions of a non-causal method (``trajopt``, ``dnd``), for
    ``Method(..., **whole_clip(reconstruct))``: a whole clip is one chunk (the engine runs such
    methods on whole clips padded to a bucket), no history, no carried state."""
    import jax.numpy as jnp

    def init_carry(model, config=None, dtype=jnp.float32):
        return jnp.zeros((), dtype)

    def reconstruct_chunk(params, model, inputs, carry, first, config, history: int):
        return carry, reconstruct(params, model, inputs, config)

    return dict(reconstruct_chunk=reconstruct_chunk, init_carry=init_carry, history=lambda config: 0, causal=False)


@dataclass(frozen=True)
class Method:
    """A registered reconstruction method (see the module docstring for the signatures)."""

    name: str
    summary: str
    paper: str
    config_type: type
    reconstruct: Callable
    reconstruct_chunk: Callable
    init_carry: Callable
    history: Callable[[Any], int]
    init_params: Callable
    #: frames of input after a chunk that the chunk needs (see the module docstring)
    lookahead: Callable[[Any], int] = lambda config: 0
    #: whether the method estimates forces and torques (its Motion's grf / tau mean something)
    estimates_forces: bool = True
    #: whether the method runs chunk by chunk (frame t depends on frames <= t + lookahead(config):
    #: streaming-capable with that latency); False: whole clips only (trajopt)
    causal: bool = True
    #: the config fields this method takes from the config its weights were trained with (the
    #: shipped ``default_cycle_config.json``, a training run's ``config.json``): ``None``, every
    #: field it knows; else only these (e.g. the learned stage's), so that another method's
    #: settings in a shared file (physcap's ``iterations``) do not replace this method's defaults
    from_weights: tuple[str, ...] | None = None
    #: top-level entries of the parameters that the method loads from its own shipped file when
    #: the parameters lack them (``dnd``'s networks, trained apart from the default weights)
    shipped_networks: tuple[str, ...] = ()
    #: a method that simulates on the host (MuJoCo C, ``mocon``): ``host(params, models, inputs,
    #: config) -> Motion`` of a batch (``models`` one :class:`~jmocap.model.Model` per clip,
    #: ``inputs`` stacked, numpy in and out), which the engine and the evaluation call instead of
    #: ``jit(vmap(reconstruct))``; None for the pure-JAX methods
    host: Callable | None = None

    def weights_config(self, fields: Mapping[str, Any] | None) -> dict[str, Any]:
        """The part of a weights' training config (a flat dict of fields) this method takes."""
        fields = dict(fields or {})
        if self.from_weights is None:
            return fields
        return {k: v for k, v in fields.items() if k in self.from_weights}

    def make_config(self, fields: Mapping[str, Any] | None = None, **changes: Any):
        """The method's config from a flat dict of fields (e.g. the JSON shipped with weights)
        plus ``changes``. Fields of other registered methods' configs are ignored (a shared
        config file serves every method); a field no method knows raises ``ValueError``."""
        from jmocap.nets import NetConfig

        merged = {**dict(fields or {}), **changes}
        known = {f.name for f in dataclasses.fields(self.config_type)}
        everyone = set().union(*({f.name for f in dataclasses.fields(m.config_type)} for m in _METHODS.values()))
        everyone |= LEGACY_FIELDS
        unknown = sorted(set(merged) - everyone)
        if unknown:
            raise ValueError(f"unknown config fields {unknown} (method {self.name!r} knows {sorted(known)})")
        kw = {k: v for k, v in merged.items() if k in known}
        if isinstance(kw.get("nets"), Mapping):
            kw["nets"] = NetConfig(**kw["nets"])
        return self.config_type(**kw)


#: fields of older config files that are no longer config fields (accepted and ignored)
LEGACY_FIELDS = frozenset({"kinematic_only"})

_METHODS: dict[str, Method] = {}


@dataclass(frozen=True)
class Variant:
    """A named config change of a registered method (e.g. one of the paper's ablations)."""

    name: str
    method: str
    changes: Mapping[str, Any] = field(default_factory=dict)
    summary: str = ""


_VARIANTS: dict[str, Variant] = {}


def register(method: Method) -> Method:
    if method.name in _METHODS or method.name in _VARIANTS:
        raise ValueError(f"a method or variant named {method.name!r} is registered already")
    _METHODS[method.name] = method
    return method


def register_variant(variant: Variant) -> Variant:
    if variant.name in _METHODS or variant.name in _VARIANTS:
        raise ValueError(f"a method or variant named {variant.name!r} is registered already")
    if variant.method not in _METHODS:
        raise ValueError(f"variant {variant.name!r}: no method {variant.method!r}")
    _VARIANTS[variant.name] = variant
    return variant


def method_names() -> tuple[str, ...]:
    """Registered methods, then variants, in registration order."""
    return tuple(_METHODS) + tuple(_VARIANTS)


def get_method(name: str) -> Method:
    """A registered method by name (variants resolve to their method)."""
    return resolve(name)[0]


def resolve(name: str) -> tuple[Method, dict[str, Any]]:
    """``(method, config changes)`` of a method or variant name."""
    if name in _METHODS:
        return _METHODS[name], {}
    if name in _VARIANTS:
        v = _VARIANTS[name]
        return _METHODS[v.method], dict(v.changes)
    raise ValueError(f"unknown method {name!r}; known: {', '.join(method_names())}")


def describe(name: str) -> str:
    if name in _METHODS:
        return _METHODS[name].summary
    return _VARIANTS[name].summary


def config_dict(config) -> dict[str, Any]:
    """A config as a flat JSON-able dict (nested NetConfig as a dict)."""
    return dataclasses.asdict(config)
