"""Physical constants and conventions named once for the whole package.

Everything here is also stated by the character's MJCF (``assets/mjcf/humanoid.xml``):
tests/test_constants.py checks each value against the compiled MuJoCo model.
"""

from __future__ import annotations

#: gravitational acceleration (m/s^2), acting along world -z (the MJCF's ``<option gravity>``);
#: a subject's body weight is ``mass * GRAVITY``
GRAVITY: float = 9.81

#: the floor's normal in the world frame (z-up, floor z = 0)
FLOOR_NORMAL: tuple[float, float, float] = (0.0, 0.0, 1.0)

#: the nominal standing height (m) of the unscaled character (``load_model()``); clips without
#: a subject height are reconstructed with it
DEFAULT_HEIGHT_M: float = 1.75

#: the foot contact points, in the order used everywhere (contact labels, contact-Jacobian
#: rows, GRF arrays): left heel, left toe, right heel, right toe
CONTACT_SITES: tuple[str, ...] = (
    "contact_left_heel",
    "contact_left_toe",
    "contact_right_heel",
    "contact_right_toe",
)

#: the friction coefficient of every foot-floor contact, used by the simulator that makes the
#: synthetic ground truth (the MJCF's floor ``friction``), the generator and every estimator
FRICTION_MU: float = 0.8

#: the friction cone's linearisation, the same everywhere: MuJoCo's ``pyramidal`` cone for
#: ``condim=3`` (the MJCF's ``<option cone>``), whose four edges are ``n +- mu t1`` and
#: ``n +- mu t2``; a force f is admissible when ``|f_t1| + |f_t2| <= mu f_n`` (inscribed in the
#: Coulomb cone, touching it along the tangent axes). ``physics.friction_pyramid_edges`` /
#: ``friction_pyramid_rows`` give its edge and facet forms.
FRICTION_CONE: str = "pyramidal"

#: number of foot contact points (the leading axis of a frame's GRF array, ``(4, 3)``)
NUM_CONTACTS: int = len(CONTACT_SITES)

__all__ = ["CONTACT_SITES", "DEFAULT_HEIGHT_M", "FLOOR_NORMAL", "FRICTION_CONE", "FRICTION_MU", "GRAVITY",
           "NUM_CONTACTS"]
