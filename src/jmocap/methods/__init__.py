"""Reconstruction methods: one module per method, composed from :mod:`jmocap.methods.stages`.

========================  ==================================================================
``kinematic``             TPNet's target pose alone (:mod:`jmocap.methods.kinematic`)
``physcap``               Neural PhysCap's dynamic cycle (:mod:`jmocap.methods.physcap`)
``pip``                   PIP's dual PD + tracking QP: physical dynamics (:mod:`jmocap.methods.pip`)
``trajopt``               offline whole-clip fit + physics trajectory optimisation (:mod:`jmocap.methods.trajopt`)
``dnd``                   D&D for an unknown moving camera: inertial force control, PCT, attentive PD
                          (:mod:`jmocap.methods.dnd`); variants ``dnd_residual_force``,
                          ``dnd_discrete_contacts``, ``dnd_meta_pd`` (Tab. 3's ablations, each
                          with its own trained weights) and ``dnd_known_track``
``dnd_trajopt``           offline, unknown moving camera: D&D's camera track (or a still camera),
                          then trajopt under it (:mod:`jmocap.methods.dnd_trajopt`)
``mocon``                 offline: trajopt's fit tracked by a simulated character (MuJoCo C) with
                          Neural MoCon's sampling-based control (:mod:`jmocap.methods.mocon`);
                          variants ``mocon_prior`` (the learned distribution prior,
                          :mod:`jmocap.methods.mocon_prior`), ``mocon_uniform``,
                          ``mocon_no_interaction``, ``mocon_no_image`` (Tab. 3's ablations)
variants of ``physcap``   ``physionical`` (every stage on), ``fixed_gains``, ``no_grfnet``,
                          ``no_hard_constraint``, ``no_canonicalisation`` (the paper's ablations)
========================  ==================================================================

``resolve(name) -> (Method, config changes)``; ``get_method(name).reconstruct(params, model,
inputs, config)`` is the pure function of one clip. See :mod:`jmocap.methods.base`.
"""

from jmocap.methods import kinematic, physcap, pip, trajopt  # noqa: F401, I001  (registers the methods)
from jmocap.methods import dnd  # noqa: F401, E402  (registered after them: the listing's order)
from jmocap.methods import dnd_trajopt  # noqa: F401, E402
from jmocap.methods import mocon  # noqa: F401, E402
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
