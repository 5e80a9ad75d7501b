"""Pure-JAX rigid-body physics over a :class:`jmocap.Model` (MuJoCo conventions)."""

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

__all__ = [
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
