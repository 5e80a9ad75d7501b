"""Pure-JAX rigid-body physics over a :class:`jmocap.Model` (MuJoCo conventions)."""

from jmocap.physics.contact import (
    ContactPoints,
    contact_constraints,
    contact_points,
    foot_corner_points,
    friction_cone_loss,
    project_friction_pyramid,
    project_velocity,
)
from jmocap.physics.dynamics import (
    SmoothDynamics,
    bias_forces,
    cho_solve,
    cholesky,
    forward_dynamics,
    integrate,
    integrate_positions,
    inverse_dynamics,
    mass_inverse,
    mass_matrix,
    smooth_dynamics,
)
from jmocap.physics.kinematics import (
    Kinematics,
    contact_jacobian,
    forward_kinematics,
    keypoints,
    point_jacobian,
    site_jacobian,
    site_positions,
)
from jmocap.physics.qp import solve_projection

__all__ = [
    "ContactPoints",
    "contact_constraints",
    "contact_points",
    "foot_corner_points",
    "friction_cone_loss",
    "project_friction_pyramid",
    "project_velocity",
    "solve_projection",
    "Kinematics",
    "SmoothDynamics",
    "bias_forces",
    "cho_solve",
    "cholesky",
    "contact_jacobian",
    "forward_dynamics",
    "forward_kinematics",
    "integrate",
    "integrate_positions",
    "inverse_dynamics",
    "keypoints",
    "mass_inverse",
    "mass_matrix",
    "point_jacobian",
    "site_jacobian",
    "site_positions",
    "smooth_dynamics",
]
