"""Reconstruction methods: one module per method, composed from :mod:`jmocap.methods.stages`.

========================  ==================================================================
``kinematic``             TPNet's target pose alone (:mod:`jmocap.methods.kinematic`)
``physcap``               Neural PhysCap's dynamic cycle (:mod:`jmocap.methods.physcap`)
``pip``                   PIP's dual PD + tracking QP: physical dynamics (:mod:`jmocap.methods.pip`)
``trajopt``               offline whole-clip fit + physics trajectory optimisation (:mod:`jmocap.methods.trajopt`)
variants of ``physcap``   ``physionical`` (every stage on), ``fixed_gains``, ``no_grfnet``,
                          ``no_hard_constraint``, ``no_canonicalisation`` (the paper's ablations)
========================  ==================================================================

``resolve(name) -> (Method, config changes)``; ``get_method(name).reconstruct(params, model,
inputs, config)`` is the pure function of one clip. See :mod:`jmocap.methods.base`.
"""

from jmocap.methods import kinematic, physcap, pip, trajopt  # noqa: F401  (registers the methods)
from jmocap.methods.base import (
    Method,
    Variant,
    config_dict,
    describe,
    get_method,
    method_names,
    register,
    register_variant,
    resolve,
    static,
    static_fields,
    traced_fields,
)
from jmocap.methods.kinematic import KinematicConfig
from jmocap.methods.physcap import PhysCapConfig

#: the method ``jmocap reconstruct`` and the demo use unless told otherwise
DEFAULT_METHOD = "pip"

__all__ = [
    "DEFAULT_METHOD",
    "KinematicConfig",
    "Method",
    "PhysCapConfig",
    "Variant",
    "config_dict",
    "describe",
    "get_method",
    "method_names",
    "register",
    "register_variant",
    "resolve",
    "static",
    "static_fields",
    "traced_fields",
]
