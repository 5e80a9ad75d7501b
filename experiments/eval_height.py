"""The subject-height estimator (jmocap.subject) on a synthetic archive, and what it is worth.

    .venv/bin/jmocap data synth --out data/height --clips 120 --seed 321      # 5-10 s clips, 2D noise
    .venv/bin/python experiments/eval_height.py data/height
    .venv/bin/python experiments/eval_height.py data/height --methods kinematic --max-clips 40

1. The estimate against each clip's true height (cm): bias, mean and median absolute error,
   90th percentile and worst, overall and per motion kind, beside the nominal 1.75 m character's
   error; and how many clips got no estimate (with the reasons).
2. With ``--methods``: ``jmocap.evaluate`` three times, the estimates made with the clips' true
   heights (``given``), estimated ones (``auto``) and the nominal character (``nominal``); the
   ground truth is always the true subject. Prints MPJPE, PA-MPJPE, the global root error and
   the reprojection error per variant.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from jmocap.constants import DEFAULT_HEIGHT_M
from jmocap.data.archive import Archive
from jmocap.subject import estimate_height


def _row(label: str, err_cm: np.ndarray, nominal_cm: np.ndarray) -> str:
    a = np.abs(err_cm)
    return (f"| {label} | {a.size} | {err_cm.mean():+.1f} | {a.mean():.1f} | {np.median(a):.1f} | "
            f"{np.percentile(a, 90):.1f} | {a.max():.1f} | {np.abs(nominal_cm).mean():.1f} |")


def estimator_table(archive: str, max_clips: int | None) -> str:
    err, nominal, kinds, failed = [], [], [], []
    for i, clip in enumerate(Archive(archive)):
        if max_clips is not None and i >= max_clips:
            break
        est = estimate_height(clip.replace(height_m=None, mass_kg=None))
        if est.height_m is None:
            failed.append(f"{clip.name}: {est.reason}")
            continue
        err.append(100 * (est.height_m - clip.height_m))
        nominal.append(100 * (DEFAULT_HEIGHT_M - clip.height_m))
        kinds.append(clip.meta.get("kind", "?"))
    err, nominal = np.array(err), np.array(nominal)
    lines = ["| clips | n | bias cm | mean abs cm | median abs cm | p90 abs cm | worst cm | nominal 1.75 m: mean abs cm |",
             "|---|---|---|---|---|---|---|---|", _row("all", err, nominal)]
    by = defaultdict(list)
    for k, e, n in zip(kinds, err, nominal, strict=True):
        by[k].append((e, n))
    for k in sorted(by):
        e, n = np.array(by[k]).T
        lines.append(_row(k, e, n))
    lines.append(f"\nno estimate: {len(failed)} clips" + "".join(f"\n  {f}" for f in failed))
    return "\n".join(lines)


def method_table(archive: str, methods: list[str], max_clips: int | None, batch: int) -> str:
    from jmocap.evaluate import EvalConfig, evaluate
    from jmocap.weights import load_run_params

    params, base = load_run_params(None, method="physcap")
    lines = ["| method | height | MPJPE mm | PA-MPJPE mm | root err mm | reproj. px |", "|---|---|---|---|---|---|"]
    for how in ("given", "auto", "nominal"):
        cfg = EvalConfig(tuple(methods), batch, max_clips, 0, False, subject_height=how)
        res = evaluate(archive, params, base, cfg)
        for m in methods:
            s = res.summary[m]
            lines.append(f"| {m} | {how} | {s['mpjpe_mm']:.1f} | {s['pa_mpjpe_mm']:.1f} | "
                         f"{s['root_err_mm']:.1f} | {s['reproj_input_px']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("archive")
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--methods", nargs="*", default=[])
    ap.add_argument("--batch-size", type=int, default=8)
    args = ap.parse_args()
    print(estimator_table(args.archive, args.max_clips))
    if args.methods:
        print()
        print(method_table(args.archive, args.methods, args.max_clips, args.batch_size))


if __name__ == "__main__":
    main()
