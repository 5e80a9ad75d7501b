"""The contact estimator under a moving camera: as seen, and with each window stabilised.

    .venv/bin/python experiments/contacts_moving_camera.py [ARCHIVE ...]

For every clip of each archive (default ``data/heldout_moving`` and ``data/heldout``: the same
motions filmed by moving and by static cameras, docs/evaluation.md "Moving cameras"), the shipped
contact MLP's voted labels (``estimate_contacts``, ``> 0.5``) against the clip's ``gt_contacts``,
pooled over every real frame as F1 (%):

* ``as seen``: the keypoints as the moving camera saw them (what the MLP was trained on, for static
  cameras);
* ``TPNet depth``: every window moved into its target frame's camera with TPNet's root depth per
  frame (``estimate_contacts(..., depth=...)``, what ``trajopt`` and ``pip`` do);
* ``true depth``: the same with the ground truth's root depth (how much the depth's error costs).
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np

from jmocap.data.clip import load_clip
from jmocap.evaluate import method_config
from jmocap.inputs import ClipInputs
from jmocap.methods import contact_estimation as CE
from jmocap.methods import stages as S
from jmocap.pipeline import padded_length, subject_model
from jmocap.weights import load_run_params

ROOT = Path(__file__).resolve().parents[1]


def main(archives: list[str]) -> None:
    params, base = load_run_params(None, method="physcap")
    cfg = method_config(base, "trajopt")
    contact_params = CE.contact_params(params)
    estimate = jax.jit(CE.estimate_contacts, static_argnames=("layout", "mirror"))
    depth_of = jax.jit(lambda p, m, i: S.target_pose(p, m, i, cfg).trans_cam[:, 2])
    print("| archive | as seen | TPNet depth | true depth |\n|---|---:|---:|---:|")
    for archive in archives:
        counts = {k: np.zeros(3) for k in ("as seen", "TPNet depth", "true depth")}
        for path in sorted(Path(archive).glob("*.npz")):
            clip = load_clip(path)
            T, L = clip.num_frames, padded_length(clip.num_frames)
            inputs = ClipInputs.from_clip(clip, L)
            E = clip.world_to_camera()
            true = np.einsum("ti,ti->t", clip.gt_q[:, :3], E[:, 2, :3]) + E[:, 2, 3]
            true = np.concatenate([true, np.full(L - T, true[-1])]).astype(np.float32)
            depths = {"as seen": None, "TPNet depth": depth_of(params, subject_model(clip), inputs), "true depth": true}
            y = clip.gt_contacts > 0.5
            for key, depth in depths.items():
                p = np.asarray(estimate(contact_params, inputs, "body25", True, depth))[:T] > 0.5
                counts[key] += [np.sum(p & y), np.sum(p & ~y), np.sum(~p & y)]
        f1 = {k: 100.0 * 2 * tp / (2 * tp + fp + fn) for k, (tp, fp, fn) in counts.items()}
        print(f"| `{archive}` | " + " | ".join(f"{v:.2f}" for v in f1.values()) + " |")


if __name__ == "__main__":
    main(sys.argv[1:] or [str(ROOT / "data/heldout_moving"), str(ROOT / "data/heldout")])
