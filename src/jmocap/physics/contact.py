"""Foot-floor contact: contact points, the hard no-penetration projection, friction helpers.

The paper's constrained pose update (Sec. 3.4.4, eqs. 14-16): after forward dynamics and the
velocity update, the generalised velocity is projected so that no active contact point moves
into the floor::

    qd* = argmin 1/2 ||qd* - qd||_W^2   s.t.   n . (J_i qd*) >= beta max(0, -z_i) / dt   (active i)

* ``W`` is the mass matrix (``metric="mass"``: the admissible velocity closest in kinetic energy,
  i.e. the velocity after a perfectly inelastic impulse at the contacts) or the identity
  (``metric="identity"``: the paper's eq. 15 literally).
* ``n`` is the floor normal, ``z_i`` the signed height of point i above the floor plane and
  ``beta`` in [0, 1] a penetration-recovery factor: 0 is the paper's constraint (a touching
  point must not move into the floor); ``beta > 0`` also pushes a penetrating point out by the
  fraction ``beta`` of its depth within the next step (Baumgarte-style stabilisation).
* ``active`` is a per-point mask, or a weight such as a contact probability, which is
  thresholded at 0.5: the constraint is hard, so it is either imposed or not. Its gradient
  with respect to the weight is therefore zero; contact probabilities are trained by their own
  loss (the paper's L_b).

The QP is solved exactly by :func:`jmocap.physics.qp.solve_projection` given the Cholesky factor
of W (or ``W^-1``); pass ``chol`` when the mass matrix was already factorised (the dynamic cycle
does), so the projection never refactorises it.

Contact point sets: by default the four foot sites (left heel, left toe, right heel, right toe,
``jmocap.CONTACT_SITES``). :func:`foot_corner_points` builds PIP's variant (the four corners of a
square under each foot joint); any :class:`ContactPoints` of up to 16 points works.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from jmocap.model import Model
from jmocap.physics.dynamics import cholesky, mass_matrix
from jmocap.physics.kinematics import Kinematics, _c, forward_kinematics, point_jacobian
from jmocap.physics.qp import (
    friction_cone_loss,
    friction_pyramid_rows,
    project_friction_pyramid,
    solve_projection,
    tangent_basis,
)

Array = jnp.ndarray

FLOOR_NORMAL = (0.0, 0.0, 1.0)
MAX_CONTACT_POINTS = 16

__all__ = [
    "ContactPoints",
    "contact_points",
    "contact_constraints",
    "foot_corner_points",
    "friction_cone_loss",
    "friction_pyramid_rows",
    "project_friction_pyramid",
    "project_velocity",
    "sole_half_width",
    "solve_projection",
    "tangent_basis",
]


@dataclass(frozen=True)
class ContactPoints:
    """Static description of contact points: each a fixed offset in a body frame."""

    bodies: tuple[int, ...]
    offsets: tuple[tuple[float, float, float], ...]
    names: tuple[str, ...] = ()
    # when the points are model sites: their ids, and the offsets are read from the (traced)
    # model at call time, so one ContactPoints serves every scaled copy of a character
    site_ids: tuple[int, ...] = ()

    def __post_init__(self):
        if len(self.bodies) != len(self.site_ids or self.offsets):
            raise ValueError("ContactPoints: one offset (or site) per body is required")
        if not 0 < len(self.bodies) <= MAX_CONTACT_POINTS:
            raise ValueError(f"ContactPoints: 1 to {MAX_CONTACT_POINTS} points, got {len(self.bodies)}")

    def __len__(self) -> int:
        return len(self.bodies)

    @staticmethod
    def from_sites(model: Model, site_ids) -> ContactPoints:
        ids = tuple(int(s) for s in site_ids)
        return ContactPoints(
            bodies=tuple(model.topo.site_body[s] for s in ids),
            offsets=(),
            names=tuple(model.topo.site_names[s] for s in ids),
            site_ids=ids,
        )


def sole_half_width(model: Model) -> float:
    """Half the width (m) of the character's soles: the largest lateral half-size of the box
    geoms on the bodies that carry the foot contact sites (0 when there are none). Read from the
    compiled MuJoCo model, so it follows a rescaled character."""
    import mujoco

    mj = model.mj
    bodies = {model.topo.site_body[s] for s in model.topo.contact_sites}
    sizes = [
        float(mj.geom_size[g, 1])
        for g in range(mj.ngeom)
        if int(mj.geom_bodyid[g]) in bodies and int(mj.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_BOX)
    ]
    return max(sizes, default=0.0)


def default_contact_points(model: Model) -> ContactPoints:
    """The four foot contact sites (left heel, left toe, right heel, right toe)."""
    if not model.topo.contact_sites:
        raise ValueError("model has no foot contact sites (jmocap.CONTACT_SITES)")
    return ContactPoints.from_sites(model, model.topo.contact_sites)


def foot_corner_points(
    model: Model, bodies=("left_ankle", "right_ankle"), half_size: float = 0.1
) -> ContactPoints:
    """PIP's contact points: four corners of a (2 half_size)-wide square per foot body.

    The square lies in the body's horizontal (x, y) plane at the height of the body's lowest
    contact site (the sole), centred below the body origin. The offsets are constants of this
    ``model``: build the points again for a rescaled character.
    """
    sole = {}
    for s in model.topo.contact_sites:
        b = model.topo.site_body[s]
        sole[b] = min(sole.get(b, np.inf), float(model.mj.site_pos[s][2]))
    out_b, out_o, names = [], [], []
    for name in bodies:
        b = model.body_id(name)
        z = sole.get(b, 0.0)
        for sx in (-1, 1):
            for sy in (-1, 1):
                out_b.append(b)
                out_o.append((sx * half_size, sy * half_size, z))
                names.append(f"{name}_corner_{'b' if sx < 0 else 'f'}{'r' if sy < 0 else 'l'}")
    return ContactPoints(tuple(out_b), tuple(out_o), tuple(names))


def contact_points(
    model: Model,
    q: Array,
    *,
    points: ContactPoints | None = None,
    normal=FLOOR_NORMAL,
    floor_height: float = 0.0,
    kin: Kinematics | None = None,
) -> tuple[Array, Array]:
    """World positions (C, 3) and signed heights above the floor (C,) of the contact points."""
    kin = forward_kinematics(model, q) if kin is None else kin
    points = default_contact_points(model) if points is None else points
    dtype = kin.xpos.dtype
    bodies = np.asarray(points.bodies, int)
    if points.site_ids:
        offsets = _c(model.site_pos, dtype)[np.asarray(points.site_ids)]
    else:
        offsets = _c(np.asarray(points.offsets, np.float64), dtype)
    pos = kin.xpos[bodies] + jnp.einsum("cij,cj->ci", kin.xmat[bodies], offsets)
    n = _unit(normal, dtype)
    return pos, pos @ n - floor_height


def contact_constraints(
    model: Model,
    q: Array,
    active: Array,
    *,
    dt: float,
    beta: float = 0.0,
    points: ContactPoints | None = None,
    normal=FLOOR_NORMAL,
    floor_height: float = 0.0,
    kin: Kinematics | None = None,
) -> tuple[Array, Array]:
    """Rows ``G`` (C, nv) and bounds ``lower`` (C,) of the constraint ``G qd >= lower``.

    Inactive points get a zero row and bound 0, which constrains nothing.
    """
    kin = forward_kinematics(model, q) if kin is None else kin
    points = default_contact_points(model) if points is None else points
    pos, height = contact_points(
        model, q, points=points, normal=normal, floor_height=floor_height, kin=kin
    )
    jacp, _ = point_jacobian(model, kin, pos, points.bodies)  # (C, 3, nv)
    n = _unit(normal, pos.dtype)
    G = jnp.einsum("k,ckv->cv", n, jacp)
    lower = beta * jnp.maximum(0.0, -height) / dt
    on = _active_mask(active, len(points))
    return jnp.where(on[:, None], G, 0.0), jnp.where(on, lower, 0.0)


def project_velocity(
    model: Model,
    q: Array,
    qd: Array,
    active: Array,
    *,
    dt: float,
    metric: str = "mass",
    beta: float = 0.0,
    points: ContactPoints | None = None,
    normal=FLOOR_NORMAL,
    floor_height: float = 0.0,
    Minv: Array | None = None,
    chol: Array | None = None,
    kin: Kinematics | None = None,
) -> Array:
    """The admissible velocity closest to ``qd`` (paper eq. 15; see the module docstring).

    Args:
      q, qd: configuration (nq,) and velocity (nv,) to project.
      active: (C,) bool mask or weights in [0, 1] (thresholded at 0.5) of the points to constrain.
      dt: the step that the velocity will be integrated over (for the recovery term).
      metric: ``"mass"`` (W = M(q)) or ``"identity"`` (W = I, the paper's eq. 15).
      beta: penetration-recovery factor in [0, 1].
      points: contact points (default: the four foot sites).
      Minv: M(q)^-1 if already known (metric ``"mass"`` only).
      chol: the lower Cholesky factor of M(q) if already known (metric ``"mass"`` only; the
        cheaper form: only L^-1 G^T is computed). Without ``Minv`` or ``chol``, M is built and
        factorised here.
      kin: forward kinematics at q if already known.
    Returns:
      qd* (nv,); exactly ``qd`` when it already satisfies every active constraint.
    """
    if metric not in ("mass", "identity"):
        raise ValueError(f"metric must be 'mass' or 'identity', got {metric!r}")
    kin = forward_kinematics(model, q) if kin is None else kin
    dtype = kin.cdof.dtype
    qd = jnp.asarray(qd, dtype)
    G, lower = contact_constraints(
        model, q, active, dt=dt, beta=beta, points=points, normal=normal,
        floor_height=floor_height, kin=kin,
    )
    if Minv is not None and chol is not None:
        raise ValueError("give at most one of Minv and chol")
    if metric == "identity":
        return solve_projection(jnp.eye(model.nv, dtype=dtype), G, qd, lower)
    if Minv is not None:
        return solve_projection(jnp.asarray(Minv, dtype), G, qd, lower)
    L = cholesky(mass_matrix(model, q, kin=kin)) if chol is None else jnp.asarray(chol, dtype)
    return solve_projection(None, G, qd, lower, chol=L)


def _active_mask(active, n: int) -> Array:
    a = jnp.asarray(active)
    if a.shape != (n,):
        raise ValueError(f"active must have shape ({n},) (one entry per contact point), got {a.shape}")
    return a if a.dtype == jnp.bool_ else a > 0.5


def _unit(normal, dtype) -> Array:
    n = jnp.asarray(normal, dtype)
    return n / jnp.linalg.norm(n)
