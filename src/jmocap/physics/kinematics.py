"""Forward kinematics, sites, keypoints and Jacobians, as dense level-by-level JAX.

The tree is processed in three vectorised stages, never one body or dof at a time:

1. *Local transforms* of every body at once: the body's offset in its parent frame followed by
   its hinge/slide joints in order (MuJoCo's ``mj_kinematics`` rule, joint anchors and
   reference angles included). Unused joint slots are identity rotations.
2. *World transforms*, one tree level per step (about 8 steps for a human), each step a batched
   gather-compose-scatter over all bodies of that level.
3. *Motion subspaces*: every dof's spatial axis ``cdof`` (6-vector ``[angular; linear]``, in
   world orientation, about the spatial origin ``origin``: the first floating body's position,
   which keeps float32 cancellation small, as MuJoCo's centre-of-mass frame does).

Everything else (Jacobians, mass matrix, bias forces) is dense linear algebra with static
masks built from the topology.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from jmocap.layouts import Layout, get_layout
from jmocap.model import SLOT_HINGE, SLOT_SLIDE, Model
from jmocap.physics.rotations import axis_angle_to_mat, quat_normalize, quat_to_mat

Array = jnp.ndarray


@struct.dataclass
class Kinematics:
    """Result of :func:`forward_kinematics` (all world frame)."""

    xpos: Array  # (nbody, 3) body frame origins
    xmat: Array  # (nbody, 3, 3) body frame orientations
    xipos: Array  # (nbody, 3) centres of mass
    ximat: Array  # (nbody, 3, 3) principal inertia frames
    cdof: Array  # (nv, 6) dof motion axes [angular; linear] about `origin`
    origin: Array  # (3,) spatial origin of cdof


def _dtype(x) -> jnp.dtype:
    dt = jnp.result_type(x)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def _c(x, dtype) -> Array:
    return jnp.asarray(x, dtype)


def forward_kinematics(model: Model, q: Array) -> Kinematics:
    """Body poses, centres of mass and dof axes for configuration ``q`` (nq,)."""
    topo = model.topo
    dtype = _dtype(q)
    q = jnp.asarray(q, dtype)
    nbody = topo.nbody
    slot_type = np.asarray(topo.slot_type)
    slot_qadr = np.asarray(topo.slot_qadr)

    # ---- stage 1: local transforms (relative to the parent frame) ---------------------
    R = _c(model.body_rot, dtype)
    t = _c(model.body_pos, dtype)
    slot_axis = _c(model.slot_axis, dtype)
    slot_pos = _c(model.slot_pos, dtype)
    theta = jnp.where(
        slot_type != 0, q[np.maximum(slot_qadr, 0)] - _c(model.slot_qpos0, dtype), 0.0
    )  # (nbody, nslot)
    hinge = jnp.asarray(slot_type == SLOT_HINGE)
    slide = jnp.asarray(slot_type == SLOT_SLIDE)
    local_axis, local_anchor = [], []
    for s in range(topo.nslot):
        anchor = t + jnp.einsum("bij,bj->bi", R, slot_pos[:, s])
        axis = jnp.einsum("bij,bj->bi", R, slot_axis[:, s])
        local_axis.append(axis)
        local_anchor.append(anchor)
        rot = axis_angle_to_mat(slot_axis[:, s], jnp.where(hinge[:, s], theta[:, s], 0.0))
        R = R @ rot
        t = anchor - jnp.einsum("bij,bj->bi", R, slot_pos[:, s])
        t = t + jnp.where(slide[:, s, None], axis * theta[:, s, None], 0.0)
    local_axis = jnp.stack(local_axis, 1)  # (nbody, nslot, 3), parent frame
    local_anchor = jnp.stack(local_anchor, 1)

    # floating bodies: pose straight from q (MuJoCo ignores their body offset)
    if topo.free_body:
        fb = np.asarray(topo.free_body)
        fq = np.asarray(topo.free_qadr)
        quat = quat_normalize(q[fq[:, None] + np.arange(3, 7)])
        R = R.at[fb].set(quat_to_mat(quat))
        t = t.at[fb].set(q[fq[:, None] + np.arange(3)])

    # ---- stage 2: world transforms, level by level -------------------------------------
    parent = np.asarray(topo.body_parent)
    xmat = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (nbody, 3, 3))
    xpos = jnp.zeros((nbody, 3), dtype)
    for level in topo.levels:
        p = parent[level]
        # (an elementwise product-sum, not `@`: a matmul here hit an XLA verifier error under
        # nested vmap, batch over clips of batch over frames; jax 0.10)
        xmat = xmat.at[level].set(jnp.sum(xmat[p][..., :, :, None] * R[level][..., None, :, :], -2))
        xpos = xpos.at[level].set(xpos[p] + jnp.einsum("bij,bj->bi", xmat[p], t[level]))

    xipos = xpos + jnp.einsum("bij,bj->bi", xmat, _c(model.body_ipos, dtype))
    ximat = xmat @ _c(model.body_irot, dtype)

    # ---- stage 3: dof motion axes --------------------------------------------------------
    origin = xpos[topo.free_body[0]] if topo.free_body else jnp.zeros(3, dtype)
    cdof = jnp.zeros((topo.nv, 6), dtype)
    used = slot_type != 0
    if used.any():
        b_idx, s_idx = np.nonzero(used)
        dofs = np.asarray(topo.slot_dof)[b_idx, s_idx]
        pm = xmat[parent[b_idx]]
        axis_w = jnp.einsum("nij,nj->ni", pm, local_axis[b_idx, s_idx])
        anchor_w = xpos[parent[b_idx]] + jnp.einsum("nij,nj->ni", pm, local_anchor[b_idx, s_idx])
        is_hinge = (slot_type[b_idx, s_idx] == SLOT_HINGE)[:, None]
        ang = jnp.where(is_hinge, axis_w, 0.0)
        lin = jnp.where(is_hinge, jnp.cross(anchor_w - origin, axis_w), axis_w)
        cdof = cdof.at[dofs].set(jnp.concatenate([ang, lin], -1))
    for b, d in zip(topo.free_body, topo.free_dof, strict=True):
        eye = jnp.eye(3, dtype=dtype)
        axes = xmat[b].T  # rows: the body's x, y, z axes in world
        lin_rot = jnp.cross(xpos[b] - origin, axes)
        block = jnp.concatenate(
            [
                jnp.concatenate([jnp.zeros((3, 3), dtype), eye], -1),  # translations
                jnp.concatenate([axes, lin_rot], -1),  # rotations about body axes
            ],
            0,
        )
        cdof = cdof.at[d : d + 6].set(block)
    return Kinematics(xpos=xpos, xmat=xmat, xipos=xipos, ximat=ximat, cdof=cdof, origin=origin)


def site_positions(model: Model, q: Array, site_ids=None, *, kin: Kinematics | None = None) -> Array:
    """World positions of sites (default: all), (nsite, 3)."""
    kin = forward_kinematics(model, q) if kin is None else kin
    ids = np.arange(model.topo.nsite) if site_ids is None else np.asarray(site_ids, int)
    body = np.asarray(model.topo.site_body)[ids]
    local = _c(model.site_pos, kin.xpos.dtype)[ids]
    return kin.xpos[body] + jnp.einsum("sij,sj->si", kin.xmat[body], local)


def keypoints(model: Model, q: Array, layout: str | Layout, *, kin: Kinematics | None = None) -> Array:
    """3D keypoints (J, 3) of a layout (``body25``, ``coco17``, ``h36m17``, ``halpe26``) in world
    frame; a layout with joints that are no site of the character (``blazepose33``) raises."""
    layout = get_layout(layout)
    layout.require_sites("3D keypoints")
    return site_positions(model, q, model.site_ids(layout.sites), kin=kin)


def point_jacobian(model: Model, kin: Kinematics, points: Array, bodies) -> tuple[Array, Array]:
    """World-frame Jacobians of points rigidly attached to ``bodies``.

    Args:
      kin: from :func:`forward_kinematics`.
      points: (P, 3) world positions; bodies: (P,) static body ids.
    Returns:
      ``(jacp, jacr)``, each (P, 3, nv): linear velocity of each point and angular velocity of
      its body (``mj_jac`` conventions).
    """
    bodies = np.asarray(bodies, int)
    mask = jnp.asarray(model.topo.dof_moves_body[bodies], kin.cdof.dtype)  # (P, nv)
    ang = kin.cdof[:, :3]  # (nv, 3)
    lin = kin.cdof[:, 3:]
    r = points - kin.origin  # (P, 3)
    # v(p) = v(origin) + w x (p - origin)
    jp = lin[None] + jnp.cross(ang[None], r[:, None, :])  # (P, nv, 3)
    jacp = jnp.swapaxes(jp, 1, 2) * mask[:, None, :]
    jacr = jnp.swapaxes(jnp.broadcast_to(ang, jp.shape), 1, 2) * mask[:, None, :]
    return jacp, jacr


def site_jacobian(
    model: Model, q: Array, site_ids, *, kin: Kinematics | None = None
) -> tuple[Array, Array]:
    """``(jacp, jacr)`` of sites, each (S, 3, nv) (``mj_jacSite``)."""
    kin = forward_kinematics(model, q) if kin is None else kin
    ids = np.asarray(site_ids, int)
    pos = site_positions(model, q, ids, kin=kin)
    return point_jacobian(model, kin, pos, np.asarray(model.topo.site_body)[ids])


def contact_jacobian(model: Model, q: Array, *, kin: Kinematics | None = None) -> Array:
    """Stacked linear Jacobians of the four foot contact sites, (4*3, nv).

    Rows 3i..3i+2 belong to contact point i in the order of ``jmocap.CONTACT_SITES``
    (left heel, left toe, right heel, right toe).
    """
    if not model.topo.contact_sites:
        raise ValueError("model has no foot contact sites (jmocap.CONTACT_SITES)")
    jacp, _ = site_jacobian(model, q, model.topo.contact_sites, kin=kin)
    return jacp.reshape(-1, model.nv)
