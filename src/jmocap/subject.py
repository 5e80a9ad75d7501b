"""The subject a clip is reconstructed with: its height from the input, the command line, or an
estimate from the 2D evidence over the clip (issue 15, "subject size").

The character's size matters to every method: the 2D keypoints fix the person's angular size,
so a character 10 % too tall is placed about 10 % too far from the camera (root error), and its
bones do not fit the evidence. A clip gives its subject's height when its file (a jmocap clip)
or its sidecar (``height_m``, ``mass_kg``) says so; ``jmocap reconstruct --height-m`` sets it for
every clip; otherwise :func:`estimate_height` measures it.

**The estimator** (single view, calibrated camera, flat floor at z = 0). One view fixes a
person's height only up to the scale of the scene; the floor removes the ambiguity. So it needs
the camera's extrinsics (from the clip or its sidecar; with the *assumed* default camera there
is no floor to measure against, and the nominal character is used). Per frame:

1. *Where the person stands*: each foot's detected keypoints (ankle, heel, toes) are
   back-projected onto the horizontal plane at that keypoint's height in the standing pose (the
   character's, scaled to the current estimate); a foot's ground point is their mean. A lifted
   foot lands further from the camera along its ray than it is (the camera looks down at it),
   so the nearer of the two feet is the one standing on the floor.
2. *How tall the person is there*: for each upper-body keypoint (nose, eyes, ears, head top,
   neck, thorax, shoulders), the point of its ray closest to the vertical line through the ground
   point gives that keypoint's height above the floor; divided by the keypoint's height in the
   character's standing pose (as a share of stature) it is one estimate of the stature. The
   frame's estimate is their median.

The clip's estimate is the :data:`PERCENTILE`-th percentile of the frames' (people stand
upright in most frames of most clips; bending, crouching and sitting only lower the per-frame
values, noise spreads them both ways), iterated :data:`ITERATIONS` times (the foot heights in
step 1 scale with the estimate). Frames need confident detections (``>= MIN_CONFIDENCE``) of a
foot and of at least two upper-body keypoints; a clip needs ``MIN_FRAMES`` such frames (and 10 %
of its frames), and an estimate inside :data:`PLAUSIBLE_M`, else the nominal character is used
and the reason recorded. Its error on synthetic clips is in docs/evaluation.md.

Everything here is host-side numpy (one pass over the keypoints per clip, before batching).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import mujoco
import numpy as np

from jmocap.constants import DEFAULT_HEIGHT_M
from jmocap.data.clip import Clip
from jmocap.layouts import get_layout

#: the upper-body keypoints whose height above the floor measures the stature
UPPER_SITES = ("kp_nose", "kp_left_eye", "kp_right_eye", "kp_left_ear", "kp_right_ear", "kp_head_top",
               "kp_neck", "kp_thorax", "kp_left_shoulder", "kp_right_shoulder")
#: each foot's keypoints (left, right)
FOOT_SITES = (("kp_left_ankle", "kp_left_heel", "kp_left_big_toe", "kp_left_small_toe"),
              ("kp_right_ankle", "kp_right_heel", "kp_right_big_toe", "kp_right_small_toe"))
MIN_CONFIDENCE = 0.3
MIN_FRAMES = 10
MIN_FRAME_SHARE = 0.1
PERCENTILE = 75.0
ITERATIONS = 3
#: estimates outside this range (m) are refused (the nominal character is used)
PLAUSIBLE_M = (1.2, 2.2)

#: where a clip's height came from (the result's ``height_source``)
HEIGHT_SOURCES = ("input", "argument", "estimated", "nominal")


@dataclass(frozen=True)
class HeightEstimate:
    """:func:`estimate_height`'s answer: ``height_m`` (None when there is none, then ``reason``
    says why), the frames it used, and the spread (m) of their estimates (16th-84th percentile)."""

    height_m: float | None
    frames: int
    spread_m: float | None = None
    reason: str | None = None


@functools.lru_cache(maxsize=1)
def standing_shares() -> dict[str, float]:
    """Each keypoint site's height above the floor in the character's standing pose (keyframe
    ``stand``), as a share of its stature (the head top's height)."""
    from jmocap.model import load_model

    mj = load_model().mj
    kid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_KEY, "stand")
    d = mujoco.MjData(mj)
    mujoco.mj_resetDataKeyframe(mj, d, kid)
    mujoco.mj_kinematics(mj, d)
    names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(mj.nsite)]
    z = {n: float(d.site_xpos[i, 2]) for i, n in enumerate(names) if n and n.startswith("kp_")}
    return {n: v / z["kp_head_top"] for n, v in z.items()}


def _rays(clip: Clip) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre of every frame (T, 3) (a moving camera's track, else the one camera) and
    unit world-frame ray directions (T, J, 3) of the keypoints."""
    fx, fy, cx, cy = (float(v) for v in clip.intrinsics)
    E = np.asarray(clip.world_to_camera(), np.float64)
    R, t = E[:, :3, :3], E[:, :3, 3]
    kp = np.asarray(clip.keypoints, np.float64)
    d_cam = np.stack([(kp[..., 0] - cx) / fx, (kp[..., 1] - cy) / fy, np.ones(kp.shape[:2])], -1)
    d = np.einsum("tji,tkj->tki", R, d_cam)  # R^T d for each ray
    return -np.einsum("tji,tj->ti", R, t), d / np.linalg.norm(d, axis=-1, keepdims=True)


def _per_frame(clip: Clip, height: float, centre: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """The stature (m) measured in each frame at the current estimate ``height`` (NaN: no
    measurement); steps 1 and 2 of the module docstring."""
    lay = get_layout(clip.layout)
    share = standing_shares()
    conf = np.asarray(clip.keypoints[..., 2], np.float64)
    T = conf.shape[0]
    # 1. each foot's ground point: its keypoints' rays onto the planes at their standing heights
    grounds = []
    for sites in FOOT_SITES:
        idx = [i for i, s in enumerate(lay.sites) if s in sites]
        pts = np.full((T, max(len(idx), 1), 2), np.nan)
        for k, i in enumerate(idx):
            dz = rays[:, i, 2]
            with np.errstate(invalid="ignore", divide="ignore"):
                s = (share[lay.sites[i]] * height - centre[:, 2]) / np.where(np.abs(dz) > 1e-9, dz, np.nan)
            ok = (conf[:, i] >= MIN_CONFIDENCE) & (s > 0)
            hit = centre[:, :2] + s[:, None] * rays[:, i, :2]
            pts[ok, k] = hit[ok]
        n = np.sum(np.isfinite(pts[..., 0]), axis=1)
        mean = np.nansum(np.nan_to_num(pts, nan=0.0), axis=1) / np.maximum(n, 1)[:, None]
        grounds.append(np.where((n > 0)[:, None], mean, np.nan))
    g = np.stack(grounds, 1)  # (T, 2 feet, 2)
    dist = np.linalg.norm(g - centre[:, None, :2], axis=-1)
    near = np.argmin(np.where(np.isnan(dist), np.inf, dist), axis=1)
    ground = g[np.arange(T), near]  # (T, 2); NaN where neither foot was seen
    # 2. each upper-body keypoint's height on the vertical line through the ground point: the
    # closest points of the ray c + s d and the line (gx, gy, 0) + u z
    upper = [i for i, s in enumerate(lay.sites) if s in UPPER_SITES]
    est = np.full((T, len(upper)), np.nan)
    w = np.concatenate([centre[:, :2] - ground, centre[:, 2:3]], -1)
    for k, i in enumerate(upper):
        d = rays[:, i]
        den = 1.0 - d[:, 2] ** 2  # |d| = 1; 0 only for a vertical ray
        with np.errstate(invalid="ignore", divide="ignore"):
            s = (d[:, 2] * w[:, 2] - np.einsum("tk,tk->t", d, w)) / np.where(den > 1e-6, den, np.nan)
        z = centre[:, 2] + s * d[:, 2]
        ok = (conf[:, i] >= MIN_CONFIDENCE) & (s > 0) & np.isfinite(z)
        est[ok, k] = z[ok] / share[lay.sites[i]]
    n = np.sum(np.isfinite(est), axis=1)
    per_frame = np.full(T, np.nan)
    rows = n >= 2
    per_frame[rows] = np.nanmedian(est[rows], axis=1)
    return per_frame


def estimate_height(clip: Clip) -> HeightEstimate:
    """The subject's stature (m) from the clip's 2D keypoints and calibrated camera (see the
    module docstring), or ``height_m=None`` with the reason."""
    if clip.extrinsics is None:
        return HeightEstimate(None, 0, reason="no camera extrinsics (the floor is unknown)")
    lay = get_layout(clip.layout)
    if not any(s in UPPER_SITES for s in lay.sites) or not any(s in FOOT_SITES[0] for s in lay.sites):
        return HeightEstimate(None, 0, reason=f"layout {clip.layout} has no feet or no upper-body keypoints")
    centre, rays = _rays(clip)
    height, need = DEFAULT_HEIGHT_M, max(MIN_FRAMES, math.ceil(MIN_FRAME_SHARE * clip.num_frames))
    for _ in range(ITERATIONS):  # the foot planes of step 1 scale with the estimate
        per_frame = _per_frame(clip, height, centre, rays)
        good = per_frame[np.isfinite(per_frame)]
        if good.size < need:
            return HeightEstimate(None, int(good.size),
                                  reason=f"{good.size} frames with a foot and the upper body detected (needs {need})")
        height = float(np.percentile(good, PERCENTILE))
    if not (PLAUSIBLE_M[0] <= height <= PLAUSIBLE_M[1]):
        return HeightEstimate(None, int(good.size), reason=f"the estimate {height:.2f} m is implausible")
    lo, hi = np.percentile(good, [16, 84])
    return HeightEstimate(round(height, 3), int(good.size), spread_m=round(float(hi - lo), 3))


def resolve_subject(clip: Clip, height_m: float | str | None = "auto", mass_kg: float | None = None) -> Clip:
    """The clip with the height (and mass) it is reconstructed with, and where the height came
    from in ``meta["height_source"]`` (:data:`HEIGHT_SOURCES`; an estimate's frames and spread in
    ``meta["height_estimate"]``).

    ``height_m``: a number (every clip gets it, over the clip's own), ``"auto"`` (the clip's own,
    else :func:`estimate_height`, else the nominal character) or ``"nominal"`` (the clip's own,
    else the nominal character; no estimate). ``mass_kg``: a number overrides the clip's."""
    meta = dict(clip.meta)
    changes: dict = {}
    if isinstance(height_m, str):
        if height_m not in ("auto", "nominal"):
            raise ValueError(f"height_m must be a number, 'auto' or 'nominal', got {height_m!r}")
        if clip.height_m is not None:
            meta["height_source"] = "input"
        elif height_m == "auto":
            est = estimate_height(clip)
            meta["height_estimate"] = {k: v for k, v in dataclasses.asdict(est).items() if v is not None}
            if est.height_m is not None:
                changes["height_m"] = est.height_m
                meta["height_source"] = "estimated"
            else:
                meta["height_source"] = "nominal"
        else:
            meta["height_source"] = "nominal"
    elif height_m is not None:
        changes["height_m"] = float(height_m)
        meta["height_source"] = "argument"
    else:
        meta["height_source"] = "input" if clip.height_m is not None else "nominal"
    if mass_kg is not None:
        changes["mass_kg"] = float(mass_kg)
    return clip.replace(meta=meta, **changes)


__all__ = ["HEIGHT_SOURCES", "HeightEstimate", "estimate_height", "resolve_subject", "standing_shares"]
