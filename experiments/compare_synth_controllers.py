"""Compare the synthetic generator's physics controllers on its own clips (docs/data.md, "The
sampling controller" table).

For each kind and seed, ``generate_clip(seed, 0, SynthConfig(frames=F, kinds=(kind,),
physics=True, physics_cfg=...))`` and one row per (controller, kind): seconds per clip, frames
with a root residual, mean residual force, the simulated root's distance from the plan (mean /
max), root orientation and hinge errors (``meta["physics"]["tracking_*"]``), ground-truth jitter
(``jmocap.metrics.jitter`` of ``gt_keypoints3d``), attempts redrawn and backtracks.

    python experiments/compare_synth_controllers.py --kinds walk,run --seeds 0-5 \
        --controller sampling --set sigma=0.1 other_sigma=0.3

``--set`` changes ``SamplingConfig`` fields (``--qp-set`` ``PhysicsConfig`` ones), parsed as
``experiments/ablate_pip.py``'s ``parse_set`` does (a tuple field takes a JSON list). Deterministic
in the seeds (the rollouts are: tests/test_synthetic_physics.py); wall time is the machine's.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.data.synthetic.physics import PhysicsConfig, SamplingConfig
from jmocap.metrics import jitter


def _seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def row(controller: str, kind: str, seeds: list[int], frames: int, sampling: dict, physics: dict) -> dict:
    cfg = PhysicsConfig(controller=controller, sampling=SamplingConfig(**sampling), **physics)
    stats = []
    for seed in seeds:
        t0 = time.perf_counter()
        clip = generate_clip(seed, 0, SynthConfig(frames=frames, kinds=(kind,), physics=True, physics_cfg=cfg))
        el = time.perf_counter() - t0
        p = clip.meta["physics"]
        stats.append(dict(
            seconds=el,
            residual_frames=p["residual_frame_share"], residual_bw=100 * p["residual_force_mean"],
            root_mean=p["tracking_root_mm"], root_max=p["tracking_root_max_mm"],
            orientation=p["tracking_root_deg"], hinges=p["tracking_joint_deg"],
            jitter=float(jitter(np.asarray(clip.gt_keypoints3d), clip.fps)),
            attempts=int(clip.meta["attempt"]), backtracks=int(p.get("backtracks", 0)),
        ))
    mean = {k: float(np.mean([s[k] for s in stats])) for k in stats[0] if k not in ("attempts", "backtracks")}
    mean["root_max"] = float(np.max([s["root_max"] for s in stats]))
    mean["attempts"] = int(sum(s["attempts"] for s in stats))
    mean["backtracks"] = int(sum(s["backtracks"] for s in stats))
    return dict(controller=controller, kind=kind, clips=len(seeds), per_clip=stats, **mean)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", default="walk,run")
    ap.add_argument("--seeds", default="0-5", help="e.g. 0-5 or 0,3,7")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--controller", default="sampling", choices=("qp", "sampling"))
    ap.add_argument("--set", nargs="*", default=[], help="SamplingConfig fields, name=value")
    ap.add_argument("--qp-set", nargs="*", default=[], help="PhysicsConfig fields, name=value")
    ap.add_argument("--label", default="")
    ap.add_argument("--json", help="append the rows here as JSON lines")
    args = ap.parse_args(argv)
    from ablate_pip import parse_set

    sampling = parse_set(args.set, SamplingConfig())
    physics = parse_set(args.qp_set, PhysicsConfig())
    print("| controller | kind | clips | s / clip | frames with residual | residual force (% BW) | root off the plan, "
          "mean / max (mm) | root orientation (deg) | hinges (deg) | GT jitter (km/s^3) | attempts redrawn | backtracks |")
    for kind in args.kinds.split(","):
        r = row(args.controller, kind, _seeds(args.seeds), args.frames, sampling, physics)
        r["label"], r["sampling"], r["physics"] = args.label, sampling, physics
        name = args.controller + (f" {args.label}" if args.label else "")
        print(f"| {name} | {kind} | {r['clips']} | {r['seconds']:.0f} | {100 * r['residual_frames']:.0f} % | "
              f"{r['residual_bw']:.1f} | {r['root_mean']:.0f} / {r['root_max']:.0f} | {r['orientation']:.1f} | "
              f"{r['hinges']:.1f} | {r['jitter']:.3f} | {r['attempts']} | {r['backtracks']} |", flush=True)
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps(r) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
