"""The shipped TPNet reads its input: its joint angles move with the motion.

Until 2026-12-03 the shipped joint-angle network had every unit of its last hidden layer
negative on every input (a dead ReLU layer), so TPNet gave one constant pose whatever the
keypoints (its per-frame hinge angles had a standard deviation of 6e-7 rad over a clip) and no
test noticed. Reference: the demo clips' ground-truth joint angles (the simulated motion the
2D keypoints were made from). Thresholds are about half of what the weights shipped on
2026-12-03 reach (std ratio 0.58 / 0.72 / 1.03; knee correlation 0.45 / 0.42 / 0.88 for walk,
run, jump).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jmocap.data.clip import load_clip
from jmocap.demo import demo_assets
from jmocap.inputs import ClipInputs
from jmocap.methods.stages import target_pose
from jmocap.model import character
from jmocap.weights import default_params


@pytest.mark.parametrize("name", ["walk", "run", "jump"])
def test_tpnet_joint_angles_follow_the_motion(name):
    params, config = default_params("kinematic")
    clip = load_clip(demo_assets() / "ground_truth" / f"demo_{name}.npz").slice(0, 90)  # one shape: one compile
    model = character(clip.height_m, clip.mass_kg)
    q = np.asarray(jax.jit(lambda p, m, i: target_pose(p, m, i, config).q_hat)(params, model, ClipInputs.from_clip(clip)))
    hinges, truth = q[:, 7:], np.asarray(clip.gt_q)[:, 7:]
    # the angles vary over the clip about as much as the truth's
    assert hinges.std(0).mean() > 0.3 * truth.std(0).mean()
    # and with it: the knees' flexion correlates with the truth's
    names = [model.mj.joint(j).name for j in range(1, model.mj.njnt)]
    r = [np.corrcoef(hinges[:, names.index(k)], truth[:, names.index(k)])[0, 1]
         for k in ("left_knee_y", "right_knee_y")]
    assert np.mean(r) > 0.2, r
