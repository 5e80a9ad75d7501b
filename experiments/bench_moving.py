"""Seconds per clip of the methods for a moving camera of unknown track, side by side in one run:
``trajopt`` (the camera taken as still), ``dnd``, ``dnd_trajopt_estimated`` (trajopt under D&D's
track) and ``dnd_trajopt`` (both hypotheses), with the ratio to ``trajopt``.

    .venv/bin/python experiments/bench_moving.py [--frames 300] [--clips 4]

Clips are the held-out moving archive's (``data/heldout_moving``, docs/evaluation.md), cropped or
edge-padded to ``--frames``, one clip per call (batch 1; a batch of clips runs one clip after
another in trajopt's program, docs/performance.md section 7). For each method: the compile time
(first call, reported separately), then the mean wall time per clip over ``--clips`` clips.
Every method reads the first frame's camera only.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jmocap.data.archive import Archive
from jmocap.inputs import ClipInputs
from jmocap.pipeline import subject_model
from jmocap.weights import load_run_params

METHODS = ("trajopt", "dnd", "dnd_trajopt_estimated", "dnd_trajopt")


def bench_clips(archive: str, n: int, frames: int):
    """``(ClipInputs, Model)`` of the first ``n`` clips of an archive, cropped or edge-padded to
    ``frames`` frames (keypoints and camera track), each with its subject's character."""
    arch = Archive(archive)
    out = []
    for name in arch.names()[:n]:
        clip = arch.load(name)
        idx = np.minimum(np.arange(frames), clip.num_frames - 1)
        inputs = ClipInputs.from_clip(clip)
        inputs = inputs.replace(keypoints=inputs.keypoints[idx], mask=np.ones(frames, bool),
                                camera_track=inputs.camera_track[idx])
        out.append((inputs, subject_model(clip)))
    return out


def time_methods(names, clips) -> list[tuple[str, float, float]]:
    """``(name, compile s, mean s per clip)`` of each method or variant (the shipped weights,
    the variant's change applied) over ``clips``, a list of ``(ClipInputs, Model)``, one clip
    per call: the first call's time is the compile time, then every clip is timed."""
    from jmocap.methods import get_method

    rows = []
    for name in names:
        params, config = load_run_params(None, method=name)
        method = get_method(name)
        fn = jax.jit(lambda p, m, i, c, method=method: method.reconstruct(p, m, i, c))
        t0 = time.perf_counter()
        jax.block_until_ready(fn(params, clips[0][1], clips[0][0], config).q)
        compile_s = time.perf_counter() - t0
        times = []
        for inputs, model in clips:
            t0 = time.perf_counter()
            jax.block_until_ready(fn(params, model, inputs, config).q)
            times.append(time.perf_counter() - t0)
        rows.append((name, compile_s, float(np.mean(times))))
        print(f"{name}: compile {compile_s:.0f} s, {rows[-1][2]:.2f} s per clip", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout_moving")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--methods", nargs="+", default=list(METHODS))
    args = ap.parse_args()
    clips = [(inputs.with_static_camera(np.asarray(inputs.camera_track)[0]), model)  # the first camera only
             for inputs, model in bench_clips(args.archive, args.clips, args.frames)]
    rows = time_methods(args.methods, clips)
    ref = dict((r[0], r[2]) for r in rows).get("trajopt")
    print(f"\n{args.frames}-frame clips, batch 1, {len(clips)} clips\n\n| method | compile s | s / clip | x trajopt |\n|---|---:|---:|---:|")
    for name, c, s in rows:
        print(f"| `{name}` | {c:.0f} | {s:.2f} | {s / ref:.2f} |" if ref else f"| `{name}` | {c:.0f} | {s:.2f} | |")


if __name__ == "__main__":
    main()
