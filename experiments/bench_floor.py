"""What the floor estimate of an uncalibrated clip costs (``jmocap.methods.floor``), side by side
in one run: the shipped estimate (TPNet, the per-frame fit, the plane), the same without the
per-frame fit (TPNet's pose as it is), and TPNet alone (what every video method runs anyway);
seconds per clip after compilation (compile time reported separately), and the ratios.

    .venv/bin/python experiments/bench_floor.py [--archive data/heldout] [--clips 8] [--frames 240]
"""

from __future__ import annotations

import argparse
import time

import jax

from jmocap.evaluate import select_clips
from jmocap.inputs import ClipInputs
from jmocap.methods import floor as F
from jmocap.methods import stages as S
from jmocap.pipeline import subject_model
from jmocap.weights import default_params


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--clips", type=int, default=8)
    ap.add_argument("--frames", type=int, default=240)
    args = ap.parse_args(argv)
    params, cfg = default_params("kinematic")
    clips = [c for c in select_clips(args.archive) if c.num_frames >= args.frames][: args.clips]
    if not clips:
        raise SystemExit(f"{args.archive}: no clip of {args.frames} frames")
    clips = [c.slice(0, args.frames) for c in clips]

    def tpnet(p, m, i):
        return S.target_pose(p, m, i, cfg).trans_cam

    def plane_only(p, m, i):
        return F.floor_from_target(m, S.target_pose(p, m, i, cfg), i.mask).extrinsics

    def shipped(p, m, i):
        return F.estimate_floor(p, m, i, cfg).extrinsics

    rows = {}
    for name, fn in (("TPNet alone", tpnet), ("TPNet + plane (no per-frame fit)", plane_only),
                     ("estimate (TPNet + per-frame fit + plane)", shipped)):
        f = jax.jit(fn)
        inputs = [ClipInputs.from_clip(c.replace(extrinsics=None)) for c in clips]
        models = [subject_model(c) for c in clips]
        t0 = time.perf_counter()
        jax.block_until_ready(f(params, models[0], inputs[0]))
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for m, i in zip(models, inputs, strict=True):
            jax.block_until_ready(f(params, m, i))
        rows[name] = (compile_s, (time.perf_counter() - t0) / len(clips))
    base = rows["TPNet alone"][1]
    print(f"{len(clips)} clips of {args.frames} frames from {args.archive}, {jax.devices()[0].platform}")
    print("| what | compile s | s / clip | x TPNet alone |")
    print("|---|---:|---:|---:|")
    for name, (c, s) in rows.items():
        print(f"| {name} | {c:.1f} | {s:.3f} | {s / base:.1f} |")


if __name__ == "__main__":
    main()
