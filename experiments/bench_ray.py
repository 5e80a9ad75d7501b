"""Scaling of ``jmocap reconstruct`` across Ray workers, beside the local engine, in one run.

Each configuration is the CLI itself in a subprocess (what a user runs), on the first ``--clips``
clips of an archive, into a fresh output folder, with one persistent XLA compilation cache shared
by all (``--cache-dir``; a first untimed pass of each configuration fills it, so the timed pass
loads its programs instead of compiling them, as a warm cluster would):

* ``local``: the local engine, one host device per core (``--host-devices 0``, its default);
* ``local, 1 device``: the local engine on one device (``--host-devices 1``);
* ``ray, W workers``: ``--engine ray --workers W`` on a local Ray instance, W = 1, 2.

Prints, per configuration: the run's seconds (``summary.json``), seconds per clip, frames/s and
the ratio to ``local``; for Ray also when it had connected, finished reading and sorting, and wrote
its first result (``summary.json`` ``ray.timing``). Then a projection for N machines from the
measured per-clip costs (docs/performance.md, "Archives larger than one machine").

Usage:  python experiments/bench_ray.py [--archive data/heldout] [--clips 40] [--method pip]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(args, name: str, extra: list[str], out: Path, cache: str) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "jmocap.cli", "reconstruct", args.archive, str(out), "--method", args.method,
           "--max-clips", str(args.clips), "--batch", str(args.batch), "--cache-dir", cache, "--quiet", *extra]
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    t = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t
    if p.returncode not in (0, 1):
        raise SystemExit(f"{name}: exit {p.returncode}\n{p.stderr[-3000:]}")
    s = json.loads((out / "summary.json").read_text())
    return {"name": name, "wall_s": wall, "seconds": s["run"]["seconds"], "clips": s["run"]["ok"] + s["run"]["failed"],
            "frames": s["run"]["frames"], "timing": s.get("ray", {}).get("timing")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/heldout")
    ap.add_argument("--clips", type=int, default=40)
    ap.add_argument("--method", default="pip")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    configs = [("local", ["--host-devices", "0"]), ("local, 1 device", ["--host-devices", "1"])]
    configs += [(f"ray, {w} worker{'s' * (w > 1)}", ["--engine", "ray", "--workers", str(w)]) for w in args.workers]
    with tempfile.TemporaryDirectory(prefix="jmocap-bench-ray-") as tmp:
        cache = str(Path(tmp) / "xla")
        for name, extra in configs:  # fill the compilation cache (untimed)
            run(args, name, extra, Path(tmp) / "warm", cache)
        rows = [run(args, name, extra, Path(tmp) / "out", cache) for name, extra in configs]
    base = rows[0]["seconds"]
    print(f"{args.method} on the first {args.clips} clips of {args.archive} ({rows[0]['frames']} frames), "
          f"batch {args.batch}, {os.cpu_count()} CPUs, warm compilation cache\n")
    print("| engine | s (run) | s / clip | frames/s | x local | Ray connected / read+sorted / first result (s) |")
    print("|---|---:|---:|---:|---:|---|")
    for r in rows:
        t = r["timing"]
        when = "" if not t else f"{t.get('start_s', 0):.1f} / {t.get('start_s', 0) + t.get('read_s', 0):.1f} / " \
                                f"{t.get('first_result_s', float('nan')):.1f}"
        print(f"| {r['name']} | {r['seconds']:.1f} | {r['seconds'] / r['clips']:.3f} | {r['frames'] / r['seconds']:.0f} "
              f"| {base / r['seconds']:.2f} | {when} |")
    ray_rows = [r for r in rows if r["timing"]]
    if ray_rows:
        r = ray_rows[-1]
        fixed = r["timing"].get("first_result_s", 0.0)
        per_clip = max(r["seconds"] - fixed, 1e-9) / r["clips"]
        print(f"\nprojection (from '{r['name']}'): a run costs about {fixed:.0f} s before its first result, then "
              f"{per_clip:.3f} s per clip on this machine; on N such machines about {fixed:.0f} s + "
              f"clips x {per_clip:.3f} / N s while the per-clip compute dominates.")


if __name__ == "__main__":
    main()
