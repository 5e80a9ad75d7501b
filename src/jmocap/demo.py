"""``jmocap demo``: the whole pipeline on the sample shipped in the package.

The sample (``jmocap/assets/demo/``, made by ``experiments/make_demo_data.py``) is three short
synthetic clips — a walk, a run and a jump — exported as OpenPose ``--write_json`` folders with
camera sidecars, exactly as a detector's output would be, plus their ground truth (joint
angles, 3D joints, contact labels, and joint torques and contact forces from the MuJoCo
tracking simulation). The demo

1. reconstructs the input folder with the shipped default weights (:mod:`jmocap.batch`: result
   ``.npz`` + BVH per clip, manifest, summary),
2. scores every clip against its ground truth (:mod:`jmocap.metrics`), for the dynamic-cycle
   result (the shipped config: fixed PD gains) and for TPNet's kinematic target in the same
   result file (``target_q``, the kinematic-only baseline), and writes ``metrics.md`` /
   ``metrics.json``,
3. renders the walking clip (MP4, front and side views with GRF arrows and contacts, plus the
   input view with the 2D keypoints) and plots its vertical GRF against the ground truth.
   This step needs the optional ``viz`` extra (``pip install 'jmocap[viz]'``); without it
   the demo says so and skips the video and the plot (results and metrics are unaffected).

Everything goes into one output folder (default ``demo_out/``); re-running resumes the
reconstruction and redoes the rest.
"""

from __future__ import annotations

import json
import shutil
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

DEMO_METRICS = (
    "mpjpe_mm", "pa_mpjpe_mm", "root_err_mm", "e_smooth_mm", "jitter_km_s3", "mpe_mm",
    "pnp_pct", "skate_pct", "grf_err_pct_bw", "root_residual_pct_bw", "contact_f1_pct",
)


def demo_assets() -> Path:
    """The folder of the shipped demo sample (``input/`` and ``ground_truth/``)."""
    return Path(str(resources.files("jmocap") / "assets" / "demo"))


def run_demo(
    out: str | Path = "demo_out",
    *,
    params_path: str | None = None,
    render: bool = True,
    progress: bool = True,
    log=print,
) -> dict[str, Any]:
    """Run the demo into ``out``; returns ``{"summary", "metrics", "files"}``."""
    from jmocap.batch import BatchOptions, reconstruct_archive
    from jmocap.data.clip import load_clip
    from jmocap.methods import DEFAULT_METHOD
    from jmocap.metrics import METRICS, evaluate_motion
    from jmocap.progress import Progress
    from jmocap.results import load_result, result_model
    from jmocap.weights import load_run_params

    t0 = time.perf_counter()
    out = Path(out)
    assets = demo_assets()
    params, config = load_run_params(params_path, method=DEFAULT_METHOD)
    # the demo's outputs are derived: a previous demo's (another version, method or config) are
    # replaced, not resumed (resuming refuses a folder written with other settings)
    for sub in ("results", "export"):
        if (out / sub).is_dir():
            log(f"jmocap demo: replacing the previous demo output {out / sub}")
            shutil.rmtree(out / sub)
    log(f"jmocap demo: reconstructing {assets / 'input'} -> {out / 'results'}")
    bar = (lambda n: Progress(n, "reconstruct")) if progress else None
    summary = reconstruct_archive(
        assets / "input", out / "results", params, config, BatchOptions(bvh=True), method=DEFAULT_METHOD,
        progress=bar,
    )
    if summary.get("failed"):
        raise RuntimeError(f"demo: {summary['failed']} clip(s) failed, see {out / 'results' / 'manifest.jsonl'}")

    rows: dict[str, dict[str, dict[str, float]]] = {}
    results = {}
    for gt_file in sorted((assets / "ground_truth").glob("*.npz")):
        clip = load_clip(gt_file)
        r = load_result(out / "results" / f"{clip.name}.npz")
        results[clip.name] = (clip, r)
        model = result_model(r)
        # the method's motion, and the kinematic reference it tracked (its result's target_q: for
        # pip the pose fitted to the 2D keypoints, for physcap TPNet's target)
        rows[clip.name] = {
            DEFAULT_METHOD: evaluate_motion(
                clip, q=r["q"], grf=r["grf"], tau=r["tau"], contact_prob=r["contact_prob"], model=model
            ),
            "reference": evaluate_motion(clip, q=r["target_q"], contact_prob=r["contact_prob"], model=model),
        }
    table = _metrics_table(rows, METRICS)
    (out / "metrics.md").write_text(table)
    (out / "metrics.json").write_text(json.dumps(rows, indent=1))
    files = [out / "metrics.md", out / "metrics.json"]

    # what other tools open: OpenSim files and an animated glTF per clip, one viewer page
    from jmocap.export import export_result
    from jmocap.export.viewer import write_viewer

    for name, (_, r) in results.items():
        files += export_result(r, name, out / "export", ("opensim", "glb"))
    files.append(write_viewer(out / "results", out / "viewer.html", title="jmocap demo")[0])

    if render:
        from jmocap.viz import VIZ_INSTALL, missing_viz_packages

        missing = missing_viz_packages()
        if missing:
            log(f"jmocap demo: video and force plot skipped: they need {', '.join(missing)} "
                f"(the viz extra: {VIZ_INSTALL})")
            render = False
    if render:
        from jmocap.viz import plot_forces, render_result

        name = "demo_walk" if "demo_walk" in results else next(iter(results))
        clip, r = results[name]
        log(f"jmocap demo: rendering {name}")
        model = result_model(r)
        files += render_result(out / "results" / f"{name}.npz", out / f"{name}.mp4", model=model)
        files.append(
            plot_forces(out / f"{name}_forces.png", r["grf"], r["fps"], gt_grf=clip.gt_grf, tau=r["tau"], model=model)
        )
    seconds = time.perf_counter() - t0
    log("\n" + table)
    log(f"jmocap demo: {summary['ok']} clips, {summary['frames']} frames in {seconds:.0f} s -> {out}/")
    for f in files:
        log(f"  {f}")
    return {"summary": summary, "metrics": rows, "files": [str(f) for f in files]}


def _metrics_table(rows: dict[str, dict[str, dict[str, float]]], info) -> str:
    """Markdown: one row per (clip, method), the headline metrics as columns."""
    keys = [k for k in DEMO_METRICS if any(k in m for r in rows.values() for m in r.values())]
    head = ["clip", "method"] + [f"{info[k].label} ({info[k].unit})" if k in info else k for k in keys]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for clip, methods in rows.items():
        for method, m in methods.items():
            vals = [_fmt(m.get(k)) for k in keys]
            lines.append("| " + " | ".join([clip, method, *vals]) + " |")
    return "\n".join(lines) + "\n"


def _fmt(x) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.3g}" if abs(x) < 100 else f"{x:.0f}"
