"""The evaluation harness: run methods over an archive of clips with ground truth and tabulate
every metric of :mod:`jmocap.metrics` per method (``jmocap eval``).

Methods are the registered methods and variants of :mod:`jmocap.methods` (each variant a config
change of its method, on top of the config the weights were trained with), plus a reference:

=======================  ===================================================================
``kinematic``            TPNet's target pose alone
``physcap``              the dynamic cycle with the weights' own config (the shipped default)
``physionical``          the full pipeline (every stage on, DyNet gains)
``fixed_gains``          no DyNet: PD gains fixed at k_p_ini (PhysCap-like)
``no_grfnet``            no contact forces
``no_hard_constraint``   no foot-floor projection
``no_canonicalisation``  C_T reads K_rr instead of K_c; the paper retrains for this ablation:
                         give it its own weights (``method_params``)
``ground_truth``         the clip's ground-truth arrays through the same metrics (sanity row)
=======================  ===================================================================

Reconstruction is the method's ``reconstruct``, ``vmap``-ed over a batch of clips padded to one
common length (the frame mask marks real frames) and jitted once per method and config
structure; every clip is reconstructed with its subject's character
(:func:`jmocap.pipeline.subject_model`: scaled to the clip's height and mass where it gives
them; scaled copies share a topology, so they stack into one batched model pytree). The result
is a deterministic function of the archive, the parameters and the seed (which picks the clips
when ``max_clips`` is below the archive size).

Per clip, :func:`jmocap.metrics.evaluate_arrays` gives a flat dict; a method's value of a
metric is the mean over the clips that have it (the max for ``grf_max_pct_bw``): every clip
counts equally. A clip whose estimate is not finite is recorded as failed and skipped.
"""

from __future__ import annotations

import csv
import functools
import io
import json
import os
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jmocap import methods as methods_
from jmocap import metrics as M
from jmocap.data.archive import Archive
from jmocap.data.clip import Clip
from jmocap.inputs import ClipInputs
from jmocap.inputs import stack as stack_inputs
from jmocap.io import atomic_write
from jmocap.model import Model, character
from jmocap.pipeline import subject_model
from jmocap.progress import Progress
from jmocap.subject import resolve_subject

#: the reference row: the ground truth through the same metrics
GROUND_TRUTH = "ground_truth"


def method_names() -> tuple[str, ...]:
    """Every name ``jmocap eval --methods`` accepts: registered methods and variants, then
    ``ground_truth``."""
    return (*methods_.method_names(), GROUND_TRUTH)


def method_config(base, method: str, own: bool = False):
    """The config of ``method`` (a registered method or variant): the fields of ``base`` (the
    config the weights were trained with, of which the method takes those it takes from
    weights, ``Method.from_weights``; or, ``own``, a config of this method itself, taken whole;
    a config object or a flat dict) with the variant's changes; ``None`` for ``ground_truth``."""
    if method == GROUND_TRUTH:
        return None
    m, changes = methods_.resolve(method)
    fields = base if isinstance(base, dict) else methods_.config_dict(base)
    return m.make_config(fields if own else m.weights_config(fields), **changes)


@dataclass(frozen=True)
class EvalConfig:
    methods: tuple[str, ...] = field(default_factory=method_names)
    batch_size: int = 8
    max_clips: int | None = None
    seed: int = 0
    progress: bool = True
    max_frames: int | None = None  # crop every clip to its first frames (quick checks)
    # the height the estimates are made with: "given" (the clip's, as the ground truth's), "auto"
    # (estimated from the 2D evidence, jmocap.subject, as for a clip without one) or "nominal"
    # (the 1.75 m / 73 kg character); the ground truth always uses the clip's own subject
    subject_height: str = "given"
    # the camera the estimates are made with: "given" (the clip's true extrinsics), "estimate"
    # (withheld: the floor estimated from the 2D evidence, jmocap.methods.floor, as for an
    # uncalibrated video; the default camera where the estimate is not usable) or "default" (withheld:
    # the documented default camera, jmocap.camera.default_extrinsics). Estimates made with a
    # withheld camera are moved into the true world through the camera before scoring (the same
    # image, so the same camera-frame motion): every metric then also scores the floor's estimate.
    # "static": a moving camera's track withheld, its first frame taken as a static camera (what
    # a method that ignores the camera's motion makes of the clip: the moving-camera baseline).
    camera: str = "given"


@dataclass
class EvalResult:
    """Per-method aggregates, per-clip metrics, failures and (for requested clips) the motions."""

    archive: str
    clips: list[str]
    methods: tuple[str, ...]
    summary: dict[str, dict[str, float]]  # method -> metric -> value over clips
    counts: dict[str, dict[str, int]]  # method -> metric -> number of clips with a value
    per_clip: dict[str, dict[str, dict[str, float]]]  # method -> clip -> metric -> value
    failures: list[dict[str, str]] = field(default_factory=list)
    motions: dict[str, dict[str, dict[str, np.ndarray]]] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------
# parameters
# ---------------------------------------------------------------------------------------


def random_params(seed: int, config=None) -> dict:
    """Freshly initialised parameters of every network (smoke tests of the harness; not a
    method): those of ``physcap`` (TPNet, DyNet, GRFNet), which every method's subset of."""
    m = methods_.get_method("physcap")
    return m.init_params(jax.random.PRNGKey(seed), character(), config or m.config_type())


# ---------------------------------------------------------------------------------------
# clips and batches
# ---------------------------------------------------------------------------------------


def select_clips(archive: str | os.PathLike, max_clips: int | None = None, seed: int = 0) -> list[Clip]:
    """The archive's clips (manifest order); with ``max_clips`` a seeded random subset of them,
    still in archive order."""
    with Archive(archive) as a:
        names = a.names()
        if max_clips is not None and max_clips < len(names):
            pick = np.sort(np.random.default_rng(seed).choice(len(names), max_clips, replace=False))
            names = [names[i] for i in pick]
        return [a.load(n) for n in names]


def _stack(trees):
    return jax.tree.map(lambda *xs: np.stack(xs), *trees)


def _pad_edge(a: np.ndarray, length: int) -> np.ndarray:
    """Frames padded to ``length`` by repeating the last one (finite, physically harmless)."""
    a = np.asarray(a)
    return np.concatenate([a, np.repeat(a[-1:], length - a.shape[0], 0)]) if a.shape[0] < length else a


@dataclass
class _Batch:
    clips: list[Clip]  # the real clips (the batch may be padded with repeats of the last)
    inputs: ClipInputs  # (B, L, ...)
    models: Model  # batched estimate models
    gt: list[dict[str, np.ndarray]]  # per real clip: (L, ...) ground truth, incl. derived quantities
    half_width: np.ndarray  # (B,) sole half-width of the estimate models
    # (B, 4, 4) the clips' true extrinsics where the estimates used others (EvalConfig.camera)
    true_extrinsics: np.ndarray | None = None
    # the estimate models one by one (B of them; a host-simulated method reads each clip's own)
    estimates: list[Model] | None = None


@functools.lru_cache(maxsize=8)
def _batched_quantities(layout: str) -> Callable:
    def quantities(model, q, fps, half_width):
        return M.motion_quantities(model, q, fps, layout, half_width)

    return jax.jit(jax.vmap(quantities))


@functools.lru_cache(maxsize=16)
def _batched_reconstruct(method: str) -> Callable:
    """``jit(vmap(reconstruct))`` of a method over clips (the config traced, shared by all)."""
    return jax.jit(jax.vmap(methods_.get_method(method).reconstruct, in_axes=(None, 0, 0, None)))


def _estimate_subject(clip: Clip, how: str) -> Clip:
    """The clip as the estimate sees it (:attr:`EvalConfig.subject_height`)."""
    if how == "given":
        return clip
    if how not in ("auto", "nominal"):
        raise ValueError(f"subject_height must be 'given', 'auto' or 'nominal', got {how!r}")
    return resolve_subject(clip.replace(height_m=None, mass_kg=None), how)


def _prepare(clips: list[Clip], length: int, size: int, subject_height: str = "given") -> _Batch:
    padded = clips + [clips[-1]] * (size - len(clips))
    inputs = stack_inputs([ClipInputs.from_clip(c, length) for c in padded])
    estimates = [subject_model(_estimate_subject(c, subject_height)) for c in padded]
    models = _stack(estimates)
    subjects = [subject_model(c) for c in padded]
    fps = np.array([c.fps for c in padded], np.float32)
    layout = padded[0].layout
    gt_q = np.stack([_pad_edge(c.gt_q, length) for c in padded]).astype(np.float32)
    gt_hw = np.array([M.sole_half_width(m) for m in subjects], np.float32)
    qty = jax.device_get(_batched_quantities(layout)(_stack(subjects), gt_q, fps, gt_hw))
    gt = []
    for i, c in enumerate(clips):
        g = {k: v[i] for k, v in qty.items()}
        for key, fld in (("keypoints3d", "gt_keypoints3d"), ("grf", "gt_grf"), ("tau", "gt_tau"),
                         ("contacts", "gt_contacts")):
            if getattr(c, fld) is not None:  # the clip's own arrays where it has them
                g[key] = _pad_edge(getattr(c, fld), length)
        gt.append(g)
    hw = np.array([M.sole_half_width(m) for m in estimates], np.float32)
    return _Batch(clips, inputs, models, gt, hw, estimates=estimates)


def _evaluate_clip(clip: Clip, pred: dict, gt: dict, length: int, pred_mass: float,
                   static_camera: bool = False) -> dict[str, float]:
    """The clip's metrics, plus the method's own per-clip report (``Motion.diagnostics``, e.g.
    ``pip``'s tracking failures) as ``diag_<name>`` entries (per clip only: not summarised).
    ``static_camera``: the estimate took a moving camera's first frame for all its frames (its
    camera-frame metrics see it through that camera)."""
    mask = np.arange(length) < clip.num_frames
    pred = dict(pred)
    diagnostics = pred.pop("diagnostics", None) or {}
    own_track = pred.pop("camera_track", None)
    camera = M.clip_camera(clip, length)
    pred_camera = camera.replace(extrinsics=camera.extrinsics[0]) if static_camera and clip.moving_camera else None
    if own_track is not None and clip.moving_camera:  # the method estimated the camera's motion
        pred_camera = camera.replace(extrinsics=jax.numpy.asarray(own_track))
    out = M.evaluate_arrays(
        pred, gt, fps=clip.fps, mask=mask, camera=camera, root=clip.layout_spec.root_indices,
        pred_mass=pred_mass, gt_mass=clip.mass_kg or subject_model(clip).total_mass, pred_camera=pred_camera,
        scene=clip.scene,
    )
    return {**out, **{f"diag_{k}": float(v) for k, v in diagnostics.items()}}


@functools.lru_cache(maxsize=4)
def _batched_floor() -> Callable:
    from jmocap.methods import floor as F

    return jax.jit(jax.vmap(F.estimate_floor, in_axes=(None, 0, 0, None)))


def _withhold_camera(batch: _Batch, how: str, params, base: dict) -> dict[str, dict[str, float]]:
    """Replace the batch's extrinsics by the default camera or the floor estimated from its 2D
    keypoints (:attr:`EvalConfig.camera`); returns per clip what the estimate got."""
    from jmocap.camera import default_extrinsics

    if how == "static":  # a moving camera's track withheld: its first frame, as a static camera
        batch.inputs = batch.inputs.with_static_camera(batch.inputs.extrinsics)
        return {}
    true = np.asarray(batch.inputs.extrinsics)
    default = np.broadcast_to(default_extrinsics().astype(np.float32), true.shape)
    report: dict[str, dict[str, float]] = {}
    if how == "default":
        used = default.copy()
    elif how == "estimate":
        if params is None:
            raise ValueError("camera='estimate' needs the learned stage's parameters")
        est = jax.device_get(_batched_floor()(params, batch.models, batch.inputs, method_config(base, "kinematic")))
        usable = np.asarray(est.usable, bool)
        used = np.where(usable[:, None, None], np.asarray(est.extrinsics, np.float32), default)
        for i, c in enumerate(batch.clips):
            R, t = true[i, :3, :3], true[i, :3, 3]
            up = np.asarray(est.up[i], np.float64)
            report[c.name] = {
                "usable": float(usable[i]),
                "up_error_deg": float(np.degrees(np.arccos(np.clip(up @ R[:, 2] / np.linalg.norm(up), -1, 1)))),
                "height_error_m": float(est.height_m[i] - (-R.T @ t)[2]),
            }
    else:
        raise ValueError(f"camera must be 'given', 'static', 'estimate' or 'default', got {how!r}")
    batch.inputs = batch.inputs.with_static_camera(used.astype(np.float32))
    batch.true_extrinsics = true
    return report


def _ground_truth_pred(gt_i: dict) -> dict:
    p = dict(gt_i)
    if "contacts" in p:
        p["contact_prob"] = p.pop("contacts")
    return p


# ---------------------------------------------------------------------------------------
# the harness
# ---------------------------------------------------------------------------------------


def evaluate(
    archive: str | os.PathLike,
    params: dict | None,
    base=None,
    config: EvalConfig | None = None,
    *,
    method_params: dict[str, tuple[dict, Any]] | None = None,
    keep_motions: Collection[str] = (),
    clips: Sequence[Clip] | None = None,
) -> EvalResult:
    """Run ``config.methods`` over the archive's clips (or ``clips``) and compute every metric.

    ``params`` and ``base`` are the shared weights and the config they were trained with
    (a config object or flat dict of fields; default: ``PhysCapConfig()``); ``config`` the harness settings (default ``EvalConfig()``);
    ``method_params`` gives a method its own ``(params, config)`` (e.g. ``no_canonicalisation``
    trained without canonicalisation). ``keep_motions`` names clips whose estimated arrays
    (``q``, ``grf``, ``tau``, ``contact_prob``) are kept in ``result.motions[method][clip]``.
    Clips need ``gt_q`` and ``gt_keypoints3d`` (others are skipped and recorded as failures).
    """
    base = methods_.config_dict(base or methods_.PhysCapConfig()) if not isinstance(base, dict) else base
    config = config or EvalConfig()
    for m in config.methods:
        method_config(base, m)  # validates the name
    if config.batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {config.batch_size}")
    clips = list(clips) if clips is not None else select_clips(archive, config.max_clips, config.seed)
    if config.max_frames is not None:
        clips = [c.slice(0, config.max_frames) for c in clips]
    failures: list[dict[str, str]] = []
    usable = []
    for c in clips:
        if c.gt_q is None or c.gt_keypoints3d is None:
            failures.append({"method": "*", "clip": c.name, "error": "no ground truth (gt_q, gt_keypoints3d)"})
        else:  # in the layout the methods read (jmocap.layouts.conversion; absent joints unscored)
            usable.append(c.to_layout(base.get("layout", "body25")))
    if not usable:
        raise ValueError(f"{archive}: no clip with ground truth to evaluate")
    length = max(c.num_frames for c in usable)
    B = min(config.batch_size, len(usable))
    batches = [_prepare(usable[i : i + B], length, B, config.subject_height) for i in range(0, len(usable), B)]
    floor: dict[str, dict[str, float]] = {}
    if config.camera != "given":
        if config.subject_height == "auto" and config.camera != "static":
            raise ValueError("subject_height='auto' measures the subject against the true camera; with "
                             f"camera={config.camera!r} use 'given' or 'nominal'")
        for b in batches:
            floor.update(_withhold_camera(b, config.camera, params, base))

    per_clip: dict[str, dict[str, dict[str, float]]] = {m: {} for m in config.methods}
    motions: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    bar = Progress(len(config.methods) * len(batches), "eval", enabled=config.progress, unit="batch")
    for method in config.methods:
        bar.set_label(method)
        cfg = method_config(base, method)
        m_params = params
        if method_params and method in method_params:
            m_params, own = method_params[method]
            cfg = method_config(own, method, own=True)
        if cfg is not None and m_params is None:
            raise ValueError(f"method {method!r} needs parameters")
        for batch in batches:
            try:
                preds = _predict(m_params, batch, method, cfg)
            except Exception as e:  # a batch run records the failure and goes on (DESIGN)
                failures += [{"method": method, "clip": c.name, "error": f"{type(e).__name__}: {e}"}
                             for c in batch.clips]
                bar.update(1)
                continue
            for clip, gt, (pred, mass, own) in zip(batch.clips, batch.gt, preds, strict=True):
                try:
                    per_clip[method][clip.name] = _evaluate_clip(clip, pred, gt, length, mass,
                                                                 config.camera == "static" and cfg is not None)
                except ValueError as e:
                    failures.append({"method": method, "clip": clip.name, "error": str(e)})
                if clip.name in keep_motions and own:
                    motions.setdefault(method, {})[clip.name] = {k: v[: clip.num_frames] for k, v in own.items()}
            bar.update(1)
    bar.close()
    summary, counts = aggregate(per_clip)
    info = {
        "frames": int(sum(c.num_frames for c in usable)),
        "padded_length": length,
        "batch_size": B,
        "base_config": base,
        "method_configs": {m: (None if method_config(base, m) is None else
                               methods_.config_dict(method_config(base, m)))
                           for m in config.methods},
        "own_params": sorted(method_params or {}),
        "seed": config.seed,
        "max_frames": config.max_frames,
        "camera": config.camera,
        **({"floor": floor} if floor else {}),
    }
    return EvalResult(str(archive), [c.name for c in usable], tuple(config.methods), summary, counts,
                      per_clip, failures, motions, info)


def _predict(params, batch: _Batch, method: str, cfg) -> list[tuple[dict, float, dict]]:
    """Per real clip of the batch: (the arrays evaluate_arrays reads, the estimate's mass, the
    estimated motion's own arrays)."""
    if cfg is None:  # ground truth through the metrics
        out = []
        for i, c in enumerate(batch.clips):
            pred = _ground_truth_pred(batch.gt[i])
            out.append((pred, c.mass_kg or subject_model(c).total_mass, {}))
        return out
    host = methods_.get_method(method).host
    if host is not None:  # simulated on the host (mocon), clip by clip: the real clips only
        n, B = len(batch.clips), len(batch.estimates)
        motion = host(params, batch.estimates[:n], jax.tree.map(lambda x: x[:n], batch.inputs), cfg)
        motion = jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[-1:], B - n, 0)]), motion)
    else:
        motion = _batched_reconstruct(methods_.get_method(method).name)(params, batch.models, batch.inputs, cfg)
    if batch.true_extrinsics is not None:  # made with another camera: into the true world
        motion = _to_true_world(motion, batch.inputs.extrinsics, batch.true_extrinsics)
    # (a non-finite estimate gives non-finite quantities, which evaluate_arrays reports)
    qty = _batched_quantities(batch.clips[0].layout)(batch.models, motion.q, batch.inputs.fps,
                                                   batch.half_width)
    qty, motion = jax.device_get((qty, motion))
    out = []
    for i, clip in enumerate(batch.clips):
        pred = {k: v[i] for k, v in qty.items()}
        pred["contact_prob"] = motion.contact_prob[i]
        if motion.diagnostics is not None:
            pred["diagnostics"] = {k: v[i] for k, v in motion.diagnostics.items()}
        if motion.camera_track is not None:
            pred["camera_track"] = motion.camera_track[i]
        if methods_.get_method(method).estimates_forces:  # the kinematic method estimates none
            pred["grf"] = motion.grf[i]
            pred["tau"] = motion.tau[i]
        own = {"q": motion.q[i], "grf": motion.grf[i], "tau": motion.tau[i],
               "contact_prob": motion.contact_prob[i], "keypoints3d": pred["keypoints3d"]}
        out.append((pred, subject_model(clip).total_mass, own))
    return out


@jax.jit
def _to_true_world(motion, used, true):
    from jmocap.methods import floor as F

    return jax.vmap(lambda m, a, b: F.move_motion(m, *F.change_world(a, b)))(motion, used, true)


def aggregate(per_clip: dict[str, dict[str, dict[str, float]]]):
    """Per method and metric: the mean (or, for ``aggregate="max"`` metrics, the max) over the
    clips that have the metric, and how many clips that is."""
    summary: dict[str, dict[str, float]] = {}
    counts: dict[str, dict[str, int]] = {}
    for method, clips in per_clip.items():
        summary[method], counts[method] = {}, {}
        for key, info in M.METRICS.items():
            vals = [r[key] for r in clips.values() if key in r]
            if vals:
                summary[method][key] = float(np.max(vals) if info.aggregate == "max" else np.mean(vals))
                counts[method][key] = len(vals)
    return summary, counts


# ---------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------

_ARROW = {"lower": "↓", "higher": "↑", "100": "→100"}


def _fmt(v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v:.1f}" if abs(v) >= 100 else f"{v:.2f}" if abs(v) >= 1 else f"{v:.3g}"


def markdown_table(result: EvalResult) -> str:
    """One table: a row per metric (label, unit, which way is better, source), a column per method."""
    methods = result.methods
    head = "| metric | unit | | source | " + " | ".join(f"`{m}`" for m in methods) + " |"
    sep = "|---|---|---|---|" + "---:|" * len(methods)
    rows = [head, sep]
    for key, info in M.METRICS.items():
        vals = [result.summary.get(m, {}).get(key) for m in methods]
        if all(v is None for v in vals):
            continue
        rows.append(f"| {info.label} | {info.unit} | {_ARROW[info.better]} | {info.source} | "
                    + " | ".join(_fmt(v) for v in vals) + " |")
    n = [len(result.per_clip.get(m, {})) for m in methods]
    rows.append("| clips evaluated | | | | " + " | ".join(str(k) for k in n) + " |")
    return "\n".join(rows) + "\n"


def markdown_report(result: EvalResult, title: str = "jmocap evaluation") -> str:
    lines = [
        f"# {title}", "",
        f"Archive `{result.archive}`: {len(result.clips)} clips, {result.info.get('frames', 0)} frames; "
        f"seed {result.info.get('seed')}.", "",
        markdown_table(result), "",
        "Values are means over clips (max GRF: the max); – = not applicable (the method "
        "estimates no such quantity, or its inputs are missing). The kinematic method estimates no "
        "forces: its GRF statistics are the forces its motion implies (inverse dynamics), as "
        "Rempe et al. report for their kinematic baseline. Definitions: docs/evaluation.md.",
    ]
    if result.info.get("own_params"):
        lines += ["", "Methods with their own weights: " + ", ".join(result.info["own_params"]) + "."]
    if result.failures:
        lines += ["", f"{len(result.failures)} failures (clip skipped for that method):", ""]
        lines += [f"- `{f['method']}` / `{f['clip']}`: {f['error']}" for f in result.failures[:20]]
    return "\n".join(lines) + "\n"


def csv_table(result: EvalResult) -> str:
    buf = io.StringIO()
    keys = [k for k in M.METRICS if any(k in result.summary.get(m, {}) for m in result.methods)]
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method", "clips", *keys])
    for m in result.methods:
        s = result.summary.get(m, {})
        w.writerow([m, len(result.per_clip.get(m, {})), *(repr(s[k]) if k in s else "" for k in keys)])
    return buf.getvalue()


def result_json(result: EvalResult) -> dict:
    return {
        "archive": result.archive,
        "clips": result.clips,
        "methods": list(result.methods),
        "summary": result.summary,
        "counts": result.counts,
        "per_clip": result.per_clip,
        "failures": result.failures,
        "metrics": {k: v._asdict() for k, v in M.METRICS.items()},
        "info": result.info,
    }


def write_outputs(result: EvalResult, out: str | os.PathLike, title: str = "jmocap evaluation") -> list[Path]:
    """``out/metrics.md``, ``out/metrics.csv``, ``out/metrics.json`` (each written atomically)."""
    out = Path(out)
    files = [(out / "metrics.md", markdown_report(result, title)), (out / "metrics.csv", csv_table(result)),
             (out / "metrics.json", json.dumps(result_json(result), indent=1, sort_keys=False) + "\n")]
    for path, text in files:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, text)
    return [p for p, _ in files]


# ---------------------------------------------------------------------------------------
# command line (registered in jmocap.cli)
# ---------------------------------------------------------------------------------------


def resolve_params(args) -> tuple[dict, Any, str]:
    """(params, config, description) from --params / --random-init / the shipped weights
    (:func:`jmocap.weights.load_run_params`)."""
    from jmocap.weights import load_run_params

    if args.params and args.random_init:
        raise ValueError("--params and --random-init exclude each other")
    if args.random_init:
        return random_params(args.seed), methods_.PhysCapConfig(), f"random init (seed {args.seed})"
    params, cfg = load_run_params(args.params, method="physcap")  # a run's config.json next to the file, if any
    return params, cfg, str(args.params) if args.params else "shipped default weights"


def cmd_eval(args) -> int:
    import sys

    from jmocap.data.archive import ArchiveError
    from jmocap.weights import load_run_params

    try:
        methods = tuple(m for item in (args.methods or method_names()) for m in item.split(",") if m)
        for m in methods:
            method_config({}, m)
        if args.max_clips is not None and args.max_clips < 1:
            raise ValueError("--max-clips must be >= 1")
        params, base, source = resolve_params(args)
        own = {}
        for item in args.method_params:
            name, _, path = item.partition("=")
            if name not in method_names() or name == GROUND_TRUTH or not path:
                raise ValueError(f"--method-params expects METHOD=PATH with a known method, got {item!r}")
            own[name] = load_run_params(path, method=name)
        cfg = EvalConfig(methods, args.batch_size, args.max_clips, args.seed, not args.quiet,
                         subject_height=getattr(args, "subject_height", "given"),
                         camera=getattr(args, "camera", "given"))
        result = evaluate(args.archive, params, base, cfg, method_params=own)
    except (ValueError, FileNotFoundError, ArchiveError) as e:
        print(f"jmocap eval: {e}", file=sys.stderr)
        return 1
    result.info["params"] = source
    paths = write_outputs(result, args.out)
    print(f"jmocap eval: {len(result.clips)} clips x {len(methods)} methods ({source}), "
          f"{len(result.failures)} failures -> " + ", ".join(str(p) for p in paths))
    return 0


__all__ = [
    "GROUND_TRUTH",
    "EvalConfig",
    "EvalResult",
    "aggregate",
    "cmd_eval",
    "csv_table",
    "evaluate",
    "markdown_report",
    "markdown_table",
    "method_config",
    "method_names",
    "random_params",
    "result_json",
    "select_clips",
    "write_outputs",
]
