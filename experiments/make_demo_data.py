"""Regenerate the demo sample shipped in the package (``src/jmocap/assets/demo/``).

    python experiments/make_demo_data.py

Three short synthetic clips (a walk, a run and a jump), tracked in MuJoCo simulation so that
they carry ground-truth joint torques and contact forces, seen by random static cameras with
detector-like 2D corruption. Each is exported as an OpenPose ``--write_json`` folder
(``demo/input/<name>/``, with its camera sidecar ``<name>.camera.json``), exactly as a user's
detector output would look; the ground truth goes to ``demo/ground_truth/<name>.npz``
(a jmocap clip file) for the demo's metrics. Deterministic: the seeds below fix everything.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from jmocap.data.clip import save_clip
from jmocap.data.formats import write_openpose_folder
from jmocap.data.synthetic import SynthConfig, generate_clip

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "src/jmocap/assets/demo"
CLIPS = (("walk", 0), ("run", 1), ("jump", 2))  # (motion kind, index)
SEED = 2024
FRAMES = 120


def main() -> None:
    if OUT.exists():
        shutil.rmtree(OUT)
    for kind, index in CLIPS:
        config = SynthConfig(frames=FRAMES, physics=True, kinds=(kind,))
        clip = generate_clip(SEED, index, config, name=f"demo_{kind}")
        write_openpose_folder(clip, OUT / "input" / clip.name)
        save_clip(OUT / "ground_truth" / f"{clip.name}.npz", clip)
        print(f"{clip.name}: {clip.num_frames} frames, height {clip.height_m} m")


if __name__ == "__main__":
    main()
