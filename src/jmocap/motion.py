"""The result of a reconstruction: a :class:`Motion` (arrays over frames, MuJoCo conventions)."""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

Array = jnp.ndarray


@struct.dataclass
class Motion:
    """Per-frame reconstruction of one clip (leading axis T; a batch adds a leading axis B).

    Frames where ``mask`` is False are padding (batched clips of different lengths) and carry
    no meaning.
    """

    q: Array  # (T, nq) configuration: root pos (world), root quat wxyz, hinge angles
    qd: Array  # (T, nv) velocity: root linear (world), root angular (body), hinge rates
    tau: Array  # (T, nv) generalised forces tau*: joint torques, residual root force/torque in [:6]
    grf: Array  # (T, 4, 3) world-frame contact forces at (L heel, L toe, R heel, R toe)
    contact_prob: Array  # (T, 4) foot-contact probabilities, same order
    target_q: Array  # (T, nq) the kinematic target (TPNet output) the dynamics tracked
    mask: Array  # (T,) bool, True for real frames
    # (T,) bool, methods that solve an optimisation per frame: every solve of the frame was
    # certified optimal (KKT conditions checked); None for methods without one
    certified: Array | None = None
    # per-clip scalars (name -> () array; a batch adds a leading axis) that a method reports about
    # its solve, e.g. an optimiser's convergence report; None for methods without one
    diagnostics: dict[str, Array] | None = None
    # (T, 4, 4) world -> camera of every frame as the method estimated it (``dnd``, for a camera
    # whose motion is unknown): the camera the estimate's camera-frame pose is seen from; None:
    # the input's cameras
    camera_track: Array | None = None

    @property
    def num_frames(self) -> int:
        return int(self.q.shape[-2])

    @property
    def root_residual(self) -> Array:
        """(T, 6) the residual (virtual) root force and torque, tau*[:, :6]."""
        return self.tau[..., :6]
