"""Scoring results made earlier against any 3D ground truth: ``jmocap score RESULTS GT``.

The ground truth needs only the joints it has (a motion-capture system's 16 joints, a dataset's
17): a **joint file** (``.npz`` or ``.json``, schema ``jmocap-gt-joints-1``, docs/formats.md):

==================  ============  =============================================================
key                 shape         meaning
==================  ============  =============================================================
``joint_names``     (J,) str      names of the result's keypoint layout (e.g. BODY_25's
                                  ``"RKnee"``; :func:`jmocap.layouts.get_layout`), any subset
``joints3d``        (T, J, 3)     world positions (m); NaN (JSON ``null``) where a joint is
                                  missing in a frame
``fps``             ()            frames per second (must equal the result's)
``world_up``        () optional   ``"z"`` (jmocap's world, default) or ``"y"`` (y-up:
                                  ``(x, y, z) -> (x, -z, y)``, as the camera files)
``floor_height``    () optional   the floor's coordinate along the up axis (default 0)
``frame_offset``    () optional   the result's frame of the ground truth's frame 0 (default 0)
``contacts``        (T, 4) opt.   foot contacts, 0/1, at left heel, left toe, right heel, right
                                  toe (:data:`jmocap.constants.CONTACT_SITES`): foot skate and
                                  floating of the result's feet
``foot_grf``        (T, 2, 3) opt.  measured ground reaction force per foot (N; left, right;
                                  force plates), NaN where not measured: the result's net GRF
                                  error and per-foot vertical correlation
``mass_kg``         () optional   the subject's mass (the ground truth's body weight for % BW;
                                  default: the result's)
==================  ============  =============================================================

A jmocap clip ``.npz`` with ``gt_keypoints3d`` is ground truth too (every joint of its layout).

Every metric runs on the joints the ground truth has, with a per-joint mask (a joint missing in
a frame drops only that joint there, :func:`jmocap.metrics.mpjpe` and friends): root-aligned
MPJPE (the layout's root joints, or the mean of the joints present in both when the ground
truth lacks the root), PA-MPJPE (Procrustes on the present joints), absolute MPJPE, the root's
world error, e_smooth / sigma_smooth, acceleration error, and from the result alone its jitter
and foot metrics (non-penetration, penetration > 3 cm).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import FormatError
from jmocap.data.formats.camera_file import Y_UP_TO_Z_UP
from jmocap.layouts import get_layout

GT_FORMAT = "jmocap-gt-joints-1"
#: score keys -> (label, unit), in table order
SCORES = {
    "mpjpe_mm": ("MPJPE (root-aligned)", "mm"),
    "pa_mpjpe_mm": ("PA-MPJPE", "mm"),
    "mpjpe_abs_mm": ("MPJPE (absolute, world)", "mm"),
    "root_err_mm": ("root position error", "mm"),
    "e_smooth_mm": ("e_smooth", "mm"),
    "accel_err_m_s2": ("acceleration error", "m/s^2"),
    "jitter_km_s3": ("jitter (result)", "km/s^3"),
    "pnp_pct": ("non-penetration (result)", "%"),
    "skate_pct": ("foot skate (>2 cm in contact)", "%"),
    "float_pct": ("foot floating (>3 cm in contact)", "%"),
    "grf_err_pct_bw": ("net GRF error", "% BW"),
    "foot_grf_corr": ("per-foot vertical GRF correlation", ""),
    "penetrate_pct": ("feet > 3 cm under the floor (result)", "%"),
    "frames": ("frames scored", ""),
    "joints": ("joints scored", ""),
}


def load_ground_truth(path: str | os.PathLike) -> dict[str, Any]:
    """Read a ground-truth joint file (module docstring) or a jmocap clip with
    ``gt_keypoints3d``: ``{"names": [J], "joints3d": (T, J, 3) in jmocap's world, "fps",
    "frame_offset"}``. Errors name the file and the field."""
    path = Path(path)
    where = str(path)
    if path.suffix.lower() == ".json":
        from jmocap.data.formats.common import _load_json

        data = _load_json(path)
        if not isinstance(data, dict):
            raise FormatError(f"{where}: a ground-truth joint file must be a JSON object")
        if "joints3d" in data:
            data["joints3d"] = np.asarray([[[math.nan if v is None else v for v in p] for p in f]
                                           for f in data["joints3d"]], np.float64)
    elif path.suffix.lower() == ".npz":
        from jmocap.data import limits

        data = dict(limits.load_npz(path, where))
        if "gt_keypoints3d" in data and "joints3d" not in data:  # a jmocap clip
            from jmocap.data.clip import load_clip

            clip = load_clip(path)
            if clip.gt_keypoints3d is None:
                raise FormatError(f"{where}: field 'gt_keypoints3d': the clip has no 3D ground truth")
            return {"names": list(get_layout(clip.layout).joints), "joints3d": np.asarray(clip.gt_keypoints3d, float),
                    "fps": float(clip.fps), "frame_offset": 0, "contacts": clip.gt_contacts,
                    "foot_grf": None if clip.gt_foot_force is None else np.asarray(clip.gt_foot_force, float),
                    "mass_kg": clip.mass_kg}
    else:
        raise FormatError(f"{where}: a ground-truth joint file is .npz or .json")
    known = {"format", "joint_names", "joints3d", "fps", "world_up", "floor_height", "frame_offset", "name",
             "contacts", "foot_grf", "mass_kg"}
    for k in data:
        if k not in known:
            raise FormatError(f"{where}: field {k!r}: unknown key (known: {', '.join(sorted(known))})")
    for k in ("joint_names", "joints3d", "fps"):
        if k not in data:
            raise FormatError(f"{where}: field {k!r}: missing")
    names = [str(n) for n in np.asarray(data["joint_names"]).reshape(-1).tolist()]
    X = np.asarray(data["joints3d"], np.float64)
    if X.ndim != 3 or X.shape[1:] != (len(names), 3) or X.shape[0] < 1:
        raise FormatError(f"{where}: field 'joints3d' must be (T, J={len(names)}, 3), got {X.shape}")
    if len(set(names)) != len(names):
        raise FormatError(f"{where}: field 'joint_names' has duplicates")
    if np.isinf(X).any():
        raise FormatError(f"{where}: field 'joints3d' has infinite values (use NaN for missing)")
    fps = float(np.asarray(data["fps"]))
    if not (math.isfinite(fps) and fps > 0):
        raise FormatError(f"{where}: field 'fps' must be positive, got {fps}")
    up = str(np.asarray(data.get("world_up", "z")))
    if up not in ("z", "y"):
        raise FormatError(f"{where}: field 'world_up' must be \"z\" or \"y\", got {up!r}")
    floor = float(np.asarray(data.get("floor_height", 0.0)))
    if up == "y":
        X = X @ Y_UP_TO_Z_UP.T
    X = X - np.array([0.0, 0.0, floor])
    off = int(np.asarray(data.get("frame_offset", 0)))
    out = {"names": names, "joints3d": X, "fps": fps, "frame_offset": off, "contacts": None, "foot_grf": None,
           "mass_kg": None}
    if data.get("contacts") is not None:
        c = np.asarray(data["contacts"], np.float64)
        if c.shape != (len(X), 4) or not np.isin(c, (0.0, 1.0)).all():
            raise FormatError(f"{where}: field 'contacts' must be (T={len(X)}, 4) of 0/1, got shape {c.shape}")
        out["contacts"] = c
    if data.get("foot_grf") is not None:
        f = np.asarray([[[math.nan if v is None else v for v in foot] for foot in fr] for fr in data["foot_grf"]]
                       if isinstance(data["foot_grf"], list) else data["foot_grf"], np.float64)
        if f.shape != (len(X), 2, 3) or np.isinf(f).any():
            raise FormatError(f"{where}: field 'foot_grf' must be (T={len(X)}, 2, 3) finite or NaN, got {f.shape}")
        out["foot_grf"] = f @ Y_UP_TO_Z_UP.T if up == "y" else f
    if data.get("mass_kg") is not None:
        mass = float(np.asarray(data["mass_kg"]))
        if not (math.isfinite(mass) and mass > 0):
            raise FormatError(f"{where}: field 'mass_kg' must be positive, got {mass}")
        out["mass_kg"] = mass
    return out


def score_result(result: dict[str, Any], gt: dict[str, Any], *, where: str = "result") -> dict[str, float]:
    """Scores (:data:`SCORES`) of a result (:func:`jmocap.results.load_result`) against a
    ground truth (:func:`load_ground_truth`), on the frames both have and the joints the
    ground truth has. Foot heights are measured against the input's terrain where the result
    carries one (``scene``, :mod:`jmocap.scene`), else against the floor."""
    import jax
    import jax.numpy as jnp

    from jmocap import metrics as M
    from jmocap.results import result_model

    layout = result.get("layout")
    if layout is None or result.get("keypoints3d") is None:
        raise ValueError(f"{where}: the result has no 'keypoints3d' / 'layout' to score")
    L = get_layout(layout)
    unknown = [n for n in gt["names"] if n not in L.joints]
    if unknown:
        raise ValueError(f"{where}: ground-truth joints {unknown} are not joints of the result's layout "
                         f"{layout!r} ({', '.join(L.joints)})")
    fps = float(result["fps"])
    if abs(fps - gt["fps"]) > 1e-6 * fps:
        raise ValueError(f"{where}: the result has {fps} fps, the ground truth {gt['fps']} (no resampling)")
    pred_all = np.asarray(result["keypoints3d"], np.float64)
    T = len(pred_all)
    off = gt["frame_offset"]
    a, b = max(off, 0), min(T, off + len(gt["joints3d"]))
    if b - a < 3:
        raise ValueError(f"{where}: the result (frames 0..{T - 1}) and the ground truth (from frame {off}) "
                         f"share {max(b - a, 0)} frames; 3 are needed")
    idx = [L.joints.index(n) for n in gt["names"]]
    pred = pred_all[a:b][:, idx]
    g = gt["joints3d"][a - off:b - off]
    present = np.isfinite(g).all(-1)
    root = [gt["names"].index(L.joints[r]) for r in L.root_indices if L.joints[r] in gt["names"]]
    if len(root) != len(L.root_indices):
        root = list(range(len(idx)))  # no root joint: align the mean of the joints present in both
    gz = np.where(present[..., None], g, 0.0)
    f32 = jnp.float32
    P, G, m = jnp.asarray(pred, f32), jnp.asarray(gz, f32), jnp.asarray(present)
    out = {
        "mpjpe_mm": M.mpjpe(P, G, m, root=tuple(root)),
        "pa_mpjpe_mm": M.pa_mpjpe(P, G, m),
        "mpjpe_abs_mm": M.mpjpe(P, G, m, align="none"),
        "root_err_mm": M.root_translation_error(P, G, m, root=tuple(root)),
        "e_smooth_mm": M.smoothness_error(P, G, m)[0],
        "accel_err_m_s2": M.acceleration_error(P, G, fps, m),
        "jitter_km_s3": M.jitter(jnp.asarray(pred_all, f32), fps),
    }
    if result.get("q") is not None:  # the contact sites of the result's motion (MuJoCo C kinematics)
        from jmocap.model import site_trajectory

        model = result_model(result)
        feet = site_trajectory(model.mj, result["q"], model.topo.contact_sites)
        # heights against the input's terrain where the result carries one (jmocap.scene)
        scene = None if result.get("scene") is None else jax.tree.map(lambda x: np.asarray(x, np.float32),
                                                                      result["scene"])
        out["pnp_pct"] = M.non_penetration(jnp.asarray(feet, f32), None, scene)
        out["penetrate_pct"] = M.foot_penetration(jnp.asarray(feet, f32), None, scene)
        if gt.get("contacts") is not None:
            c = jnp.asarray(gt["contacts"][a - off:b - off], f32)
            out["skate_pct"] = M.foot_skate(jnp.asarray(feet[a:b], f32), c)
            out["float_pct"] = M.foot_floating(jnp.asarray(feet[a:b], f32), c, None, scene)
    forces = bool(result.get("forces_estimated", True)) and result.get("grf") is not None
    if gt.get("foot_grf") is not None and forces:
        from jmocap.constants import GRAVITY

        mass = float(result.get("mass_kg") or result_model(result).total_mass)
        gt_mass = gt.get("mass_kg") or mass
        fg = gt["foot_grf"][a - off:b - off]
        measured = np.isfinite(fg).all((-1, -2))
        g4 = np.zeros((len(fg), 4, 3))
        g4[:, 0], g4[:, 2] = np.nan_to_num(fg[:, 0]), np.nan_to_num(fg[:, 1])  # a foot's force at its heel
        pg = jnp.asarray(np.asarray(result["grf"], np.float64)[a:b], f32)
        out["grf_err_pct_bw"] = M.grf_error(pg, jnp.asarray(g4, f32), mass * GRAVITY, gt_mass * GRAVITY, measured)
        out["foot_grf_corr"] = M.foot_grf_correlation(pg, jnp.asarray(g4, f32), measured)
    scores = {k: float(v) for k, v in out.items()}
    scores["frames"] = float(np.any(present, -1).sum())
    scores["joints"] = float(len(idx))
    return scores


def _gt_for(gt_path: Path, name: str) -> Path | None:
    if gt_path.is_file():
        return gt_path
    for ext in (".npz", ".json"):
        p = gt_path / f"{name}{ext}"
        if p.is_file():
            return p
    return None


def score_results(results: str | os.PathLike, gt: str | os.PathLike) -> tuple[dict[str, dict], list[str]]:
    """Score every result file of ``results`` (a file or a folder) against ``gt`` (one file, or a
    folder with ``<name>.npz`` / ``<name>.json`` per clip). Returns ({clip: scores}, problems:
    one ``"file: reason"`` line per clip that could not be scored)."""
    from jmocap.results import load_result

    rp, gp = Path(results), Path(gt)
    if not gp.exists():
        raise FileNotFoundError(f"no ground truth at {gp}")
    files = [rp] if rp.is_file() else sorted(rp.glob("*.npz")) if rp.is_dir() else None
    if files is None:
        raise FileNotFoundError(f"no result file or folder at {rp}")
    rows, problems = {}, []
    for f in files:
        try:
            r = load_result(f)
            name = r.get("name") or f.stem
            g = _gt_for(gp, name)
            if g is None:
                problems.append(f"{f}: no ground truth {name}.npz / {name}.json in {gp}")
                continue
            rows[name] = score_result(r, load_ground_truth(g), where=str(f))
        except (FormatError, ValueError) as e:
            problems.append(f"{f}: {e}")
    return rows, problems


def scores_table(rows: dict[str, dict]) -> str:
    """Markdown: a row per clip and the mean over clips."""
    keys = [k for k in SCORES if any(k in r for r in rows.values())]
    head = ["clip"] + [f"{SCORES[k][0]} ({SCORES[k][1]})" if SCORES[k][1] else SCORES[k][0] for k in keys]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def fmt(v):
        return "-" if v is None or not math.isfinite(v) else (f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}")

    for name, r in rows.items():
        lines.append("| " + " | ".join([name] + [fmt(r.get(k)) for k in keys]) + " |")
    if len(rows) > 1:
        mean = {k: float(np.nanmean([r.get(k, np.nan) for r in rows.values()])) for k in keys}
        lines.append("| **mean** | " + " | ".join(fmt(mean[k]) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def write_scores(rows: dict[str, dict], out: str | os.PathLike) -> list[Path]:
    """``OUT/scores.md`` and ``OUT/scores.json``."""
    from jmocap.io import atomic_write

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return [atomic_write(out / "scores.md", scores_table(rows)),
            atomic_write(out / "scores.json", json.dumps(rows, indent=1))]


__all__ = ["GT_FORMAT", "SCORES", "load_ground_truth", "score_result", "score_results", "scores_table",
           "write_scores"]
