"""Every keypoint layout through the shipped weights: what the joints a layout lacks cost.

    .venv/bin/python experiments/eval_layouts.py --archive data/heldout --methods kinematic pip
    .venv/bin/python experiments/eval_layouts.py --archive data/val --max-clips 16 --out /tmp/layouts.md

Each clip's BODY_25 keypoints are given as a COCO-17 and a Human3.6M-17 detector would give
them (``jmocap.layouts.conversion`` to that layout and back to BODY_25, exactly what
``jmocap reconstruct`` does with a clip of that layout: the joints the layout lacks missing, the
midpoints derived), and every method is evaluated (``jmocap.evaluate``, the metrics of
``jmocap eval``) against the *same* BODY_25 ground truth, feet included, so the rows compare.
Prints a markdown table (and writes it with ``--out``): per layout and method, MPJPE,
PA-MPJPE, root error, reprojection error, foot skate, contact F1, and the MPJPE relative to the
BODY_25 row (the learned-stage issue asks for every layout within 15 %).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax

from jmocap import evaluate as E
from jmocap.layouts import through_layout
from jmocap.weights import default_config_fields, default_params

LAYOUTS = ("body25", "coco17", "h36m17")
KEYS = (("mpjpe_mm", "MPJPE (mm)"), ("pa_mpjpe_mm", "PA-MPJPE (mm)"), ("root_err_mm", "root (mm)"),
        ("reproj_input_px", "reprojection (px)"), ("skate_pct", "skate (%)"), ("contact_f1_pct", "contact F1 (%)"))


def as_layout(clip, layout: str):
    """The clip's BODY_25 keypoints as ``layout``'s detector would give them, back in BODY_25
    (the ground truth untouched)."""
    return clip if layout == clip.layout else clip.replace(keypoints=through_layout(clip.keypoints, clip.layout, layout))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archive", default="data/val")
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", nargs="*", default=["kinematic", "pip"])
    ap.add_argument("--layouts", nargs="*", default=list(LAYOUTS))
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--out", default=None, help="also write the table to this markdown file")
    ap.add_argument("--params", default=None,
                    help="parameters to evaluate instead of the shipped ones (a params .msgpack or a training "
                         "checkpoint); the shipped config")
    args = ap.parse_args(argv)
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/jmocap/xla-dev"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    params, _ = default_params("pip")
    if args.params:
        from flax import serialization

        raw = serialization.msgpack_restore(Path(args.params).read_bytes())
        params = raw["params"] if "stage" in raw else raw
    base = default_config_fields()
    clips = E.select_clips(args.archive, args.max_clips, args.seed)
    rows, ref = [], {}
    t_all = time.perf_counter()
    for layout in args.layouts:
        t0 = time.perf_counter()
        res = E.evaluate(args.archive, params, base,
                         E.EvalConfig(methods=tuple(args.methods), batch_size=args.batch_size, progress=False),
                         clips=[as_layout(c, layout) for c in clips])
        for f in res.failures:
            print("FAILED", layout, f)
        for m in args.methods:
            s = res.summary[m]
            if layout == "body25":
                ref[m] = s["mpjpe_mm"]
            rel = (f"{100 * (s['mpjpe_mm'] / ref[m] - 1):+.1f} %" if m in ref else "")
            rows.append((layout, m, *(s.get(k, float("nan")) for k, _ in KEYS), rel))
        print(f"{layout}: {time.perf_counter() - t0:.0f} s", flush=True)
    head = "| layout | method | " + " | ".join(n for _, n in KEYS) + " | MPJPE vs BODY_25 |"
    lines = [f"Archive `{args.archive}`, {len(clips)} clips; `python experiments/eval_layouts.py "
             f"--archive {args.archive}" + (f" --max-clips {args.max_clips}" if args.max_clips else "")
             + f" --methods {' '.join(args.methods)}` ({time.perf_counter() - t_all:.0f} s).", "",
             head, "|" + "---|" * (len(KEYS) + 3)]
    for r in rows:
        lines.append(f"| {r[0]} | `{r[1]}` | " + " | ".join(f"{v:.1f}" for v in r[2:-1]) + f" | {r[-1]} |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
