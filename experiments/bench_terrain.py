"""Seconds per clip of ``trajopt`` on terrain clips, with their scene (every height a signed
distance to the floor and the boxes) and without it (``trajopt_no_scene``: the floor ``z = 0``,
the flat-floor program), side by side in one run, with the ratio.

    .venv/bin/python experiments/bench_terrain.py [--frames 300] [--clips 4]

Clips are the held-out terrain archive's (``data/heldout_terrain``, docs/evaluation.md
"Terrain"), cropped or edge-padded to ``--frames``, one clip per call (batch 1). For each: the
compile time (first call, reported separately), then the mean wall time per clip over ``--clips``
clips. Scenes are padded to 8 boxes (``jmocap.inputs.scene_slots``).
"""

from __future__ import annotations

import argparse

from bench_moving import bench_clips, time_methods

METHODS = ("trajopt_no_scene", "trajopt")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout_terrain")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--clips", type=int, default=4)
    args = ap.parse_args()
    clips = bench_clips(args.archive, args.clips, args.frames)
    rows = time_methods(METHODS, clips)
    ref = rows[0][2]
    print(f"\n{args.frames}-frame clips, batch 1, {len(clips)} clips\n\n"
          f"| method | compile s | s / clip | x `{rows[0][0]}` |\n|---|---:|---:|---:|")
    for name, c, s in rows:
        print(f"| `{name}` | {c:.0f} | {s:.2f} | {s / ref:.2f} |")


if __name__ == "__main__":
    main()
