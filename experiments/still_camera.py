"""How still D&D's estimated camera is on still and moving cameras: whether a threshold on its
speed and turning rate could tell them apart (it cannot: docs/method.md, "Offline D&D", which is
why ``dnd_trajopt`` compares two fits instead, ``experiments/choose_camera.py``).

    .venv/bin/python experiments/still_camera.py --archive data/val_moving [--archive data/train_moving --max-clips 80]

Per clip: the true track's and D&D's estimated track's mean centre speed (m/s) and turning rate
(deg/s) (:func:`jmocap.methods.dnd_trajopt.track_motion_stats`); then, per camera kind, the
range of the estimates, and how many clips each threshold pair calls still.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict

import jax
import jax.numpy as jnp
import numpy as np

from jmocap.data.archive import Archive
from jmocap.inputs import ClipInputs
from jmocap.methods import dnd_trajopt as DT
from jmocap.methods.dnd import estimate_track
from jmocap.model import load_model
from jmocap.weights import load_run_params


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--archive", action="append", required=True)
    ap.add_argument("--max-clips", type=int, default=0)
    ap.add_argument("--out", default=None, help="write the per-clip rows as JSON lines here")
    args = ap.parse_args()
    model = load_model()
    params, config = load_run_params(None, method="dnd_trajopt")

    @jax.jit
    def stats(inputs):
        est = estimate_track(params, model, inputs, config)
        mask = jnp.asarray(inputs.mask)
        return DT.track_motion_stats(est, mask, inputs.fps), DT.track_motion_stats(
            jnp.asarray(inputs.world_to_camera()), mask, inputs.fps)

    rows = []
    for path in args.archive:
        archive = Archive(path)
        names = archive.names()[: args.max_clips or None]
        for name in names:
            clip = archive.load(name)
            kind = (clip.meta or {}).get("camera", {}).get("kind", "static")
            T = clip.keypoints.shape[0]
            inputs = ClipInputs.from_clip(clip, length=((T + 63) // 64) * 64)
            (es, et), (ts, tt) = stats(inputs)
            rows.append(dict(archive=path, clip=name, camera=kind, est_speed=float(es), est_turn=float(et),
                             true_speed=float(ts), true_turn=float(tt)))
            print(f"{path} {name} {kind:9s} est {float(es):5.2f} m/s {float(et):5.1f} deg/s  "
                  f"true {float(ts):5.2f} m/s {float(tt):5.1f} deg/s", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
    by = defaultdict(list)
    for r in rows:
        by[r["camera"]].append(r)
    print("\nper camera kind: clips, estimated speed (m/s) min / median / max, turn (deg/s) min / median / max")
    for kind, rs in sorted(by.items()):
        s = np.array([r["est_speed"] for r in rs])
        t = np.array([r["est_turn"] for r in rs])
        print(f"{kind:9s} {len(rs):3d}  {s.min():.2f} / {np.median(s):.2f} / {s.max():.2f}   "
              f"{t.min():.1f} / {np.median(t):.1f} / {t.max():.1f}")
    print("\nclips called still (speed < s and turn < r): still cameras / moving cameras")
    for s in (0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5):
        for t in (1.0, 2.0, 3.0, 5.0):
            still = [r for r in rows if r["est_speed"] < s and r["est_turn"] < t]
            a = sum(r["camera"] == "static" for r in still)
            print(f"  s {s:.2f} r {t:.0f}: {a} / {by['static'].__len__()} still, "
                  f"{len(still) - a} / {len(rows) - len(by['static'])} moving")


if __name__ == "__main__":
    main()
