"""Is a valid clip also one that can be reconstructed? Ranges, visibility and camera placement.

A :class:`~jmocap.data.clip.Clip` that constructs is well-formed (shapes, dtypes, finite values,
confidences in [0, 1]). :func:`check_reconstructable` asks the next question, before the clip
joins a batch, so that absurd input fails alone with a message naming file, frame and field
instead of producing a result 5e9 m away, or failing its batch-mates:

========================  ==========================================  =========================
what                      error when                                  warning when
========================  ==========================================  =========================
fps                       outside [1, 1000]                           outside [10, 240]
image size                a side outside [16, 32768] px
intrinsics                horizontal or vertical field of view        principal point outside
                          outside [0.5, 170] deg; fx / fy outside     the image
                          [0.5, 2]; principal point further than one
                          image size outside the image
extrinsics (camera)       camera centre more than 1 km from the       camera centre more than
                          world origin, or more than 0.1 m below the  100 m away, or above 50 m
                          floor (z < -0.1); a camera track's every
                          frame (the first such frame named)
height_m / mass_kg        outside [0.5, 2.5] m / [10, 300] kg         outside [1.2, 2.2] m /
                          (the character cannot be scaled so far)     [30, 200] kg
keypoints                 a visible coordinate beyond 1e6 px; fewer   a quarter of the visible
                          than 2 usable frames, or fewer than 5 % of  points outside the image;
                          frames usable (a usable frame has at least  frames without a usable
                          5 joints with confidence >= 0.05)           detection (listed)
name                      a path component longer than 251 bytes
                          (UTF-8) or not a file name
========================  ==========================================  =========================

Frames without a usable detection are reconstructed from their neighbours (held before the
first and after the last usable frame, i.e. extrapolated); the warning lists them as frame
ranges. Camera values that were assumed rather than read (``Clip.meta["assumed"]``, image size,
extrinsics) are warnings too. The thresholds are module constants, documented in
docs/formats.md ("Validation").
"""

from __future__ import annotations

import math
from pathlib import PurePosixPath

import numpy as np

from jmocap.data.clip import Clip, FormatError

FPS_RANGE = (1.0, 1000.0)
FPS_USUAL = (10.0, 240.0)
IMAGE_SIDE_RANGE = (16, 32768)
FOV_RANGE_DEG = (0.5, 170.0)
ASPECT_RANGE = (0.5, 2.0)
CAMERA_MAX_DISTANCE_M = 1000.0
CAMERA_USUAL_DISTANCE_M = 100.0
CAMERA_MIN_Z_M = -0.1
CAMERA_USUAL_MAX_Z_M = 50.0
HEIGHT_RANGE_M = (0.5, 2.5)
HEIGHT_USUAL_M = (1.2, 2.2)
MASS_RANGE_KG = (10.0, 300.0)
MASS_USUAL_KG = (30.0, 200.0)
MAX_COORD_PX = 1e6
VISIBLE_CONFIDENCE = 0.05
USABLE_JOINTS = 5
MIN_USABLE_FRAMES = 2
MIN_USABLE_SHARE = 0.05
OUTSIDE_IMAGE_WARN_SHARE = 0.25
MAX_NAME_BYTES = 251


def frame_ranges(frames: np.ndarray, limit: int = 8) -> str:
    """``[0, 1, 2, 7]`` -> ``"0-2, 7"`` (at most ``limit`` ranges, then ``"..."``)."""
    frames = np.asarray(frames, int)
    if frames.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(frames) != 1)
    starts = np.concatenate([[frames[0]], frames[breaks + 1]])
    ends = np.concatenate([frames[breaks], [frames[-1]]])
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in zip(starts, ends, strict=True)]
    return ", ".join(parts[:limit]) + (", ..." if len(parts) > limit else "")


def check_name(name: str, where: str) -> None:
    """A clip name must make file names under OUTPUT: relative, no ``.``/``..`` components, no
    NUL, each component at most :data:`MAX_NAME_BYTES` bytes (room for ``.npz`` / ``.bvh``)."""
    parts = PurePosixPath(name).parts
    if (not parts or name.startswith("/") or "\\" in name or "\0" in name or any(p in (".", "..") for p in parts)
            or PurePosixPath(name).as_posix() != name):
        raise FormatError(f"{where}: field 'name': {name!r} cannot be a file name under the output folder")
    for p in parts:
        n = len(p.encode("utf-8", "surrogateescape"))
        if n > MAX_NAME_BYTES:
            raise FormatError(
                f"{where}: field 'name': the component {p[:40]!r}... is {n} bytes long; result file names "
                f"must stay under 255 bytes (at most {MAX_NAME_BYTES} for the name, plus the suffix); rename the file"
            )


def _in(v: float, lo: float, hi: float) -> bool:
    return lo <= v <= hi


def check_reconstructable(clip: Clip, where: str) -> list[str]:
    """Raise :class:`FormatError` (file, frame, field) when ``clip`` cannot give a meaningful
    reconstruction; return the warnings (strings) for what is implausible but usable."""
    warnings: list[str] = []
    check_name(clip.name, where)

    fps = clip.fps
    if not _in(fps, *FPS_RANGE):
        raise FormatError(f"{where}: field 'fps': {fps:g} frames per second is outside {list(FPS_RANGE)}")
    if not _in(fps, *FPS_USUAL):
        warnings.append(f"fps {fps:g} is unusual for video (outside {list(FPS_USUAL)})")

    w, h = (int(v) for v in clip.image_size)
    if not (_in(w, *IMAGE_SIDE_RANGE) and _in(h, *IMAGE_SIDE_RANGE)):
        raise FormatError(
            f"{where}: field 'image_size': {w}x{h} px has a side outside {list(IMAGE_SIDE_RANGE)}"
        )
    fx, fy, cx, cy = (float(v) for v in clip.intrinsics)
    fov_x, fov_y = (math.degrees(2 * math.atan2(s / 2, f)) for s, f in ((w, fx), (h, fy)))
    if not (_in(fov_x, *FOV_RANGE_DEG) and _in(fov_y, *FOV_RANGE_DEG)):
        raise FormatError(
            f"{where}: field 'intrinsics': fx = {fx:g}, fy = {fy:g} px give a field of view of "
            f"{fov_x:.3g} x {fov_y:.3g} deg on a {w}x{h} image, outside {list(FOV_RANGE_DEG)} deg"
        )
    if not _in(fx / fy, *ASPECT_RANGE):
        raise FormatError(f"{where}: field 'intrinsics': fx / fy = {fx / fy:.3g} is outside {list(ASPECT_RANGE)}")
    if not (_in(cx, -w, 2 * w) and _in(cy, -h, 2 * h)):
        raise FormatError(
            f"{where}: field 'intrinsics': the principal point ({cx:g}, {cy:g}) is more than an image "
            f"size outside the {w}x{h} image"
        )
    if not (_in(cx, 0, w) and _in(cy, 0, h)):
        warnings.append(f"the principal point ({cx:g}, {cy:g}) is outside the {w}x{h} image")

    if clip.extrinsics is not None:
        # every frame's camera of a moving one (its track), else the one camera
        moving = clip.camera_track is not None
        E = clip.camera_track if moving else clip.extrinsics[None]
        centres = -np.einsum("tji,tj->ti", E[:, :3, :3], E[:, :3, 3])
        dists = np.linalg.norm(centres, axis=-1)
        field = "camera_track" if moving else "extrinsics"

        def at(f: int) -> str:
            return f"{where}: frame {f}: field {field!r}" if moving else f"{where}: field {field!r}"

        if (dists > CAMERA_MAX_DISTANCE_M).any():
            f = int(np.argmax(dists > CAMERA_MAX_DISTANCE_M))
            raise FormatError(
                f"{at(f)}: the camera is {dists[f]:.4g} m from the world origin "
                f"(more than {CAMERA_MAX_DISTANCE_M:g} m)"
            )
        if (centres[:, 2] < CAMERA_MIN_Z_M).any():
            f = int(np.argmax(centres[:, 2] < CAMERA_MIN_Z_M))
            raise FormatError(
                f"{at(f)}: the camera is {-centres[f, 2]:.3g} m below the floor "
                f"(world z = {centres[f, 2]:.3g} m; z is up and the floor is z = 0)"
            )
        dist, high = float(dists.max()), float(centres[:, 2].max())
        if dist > CAMERA_USUAL_DISTANCE_M or high > CAMERA_USUAL_MAX_Z_M:
            warnings.append(f"the camera is far away: {dist:.3g} m from the origin, {high:.3g} m high"
                            + (" (at its farthest and highest)" if moving else ""))

    for key, (lo, hi), (ulo, uhi), unit in (
        ("height_m", HEIGHT_RANGE_M, HEIGHT_USUAL_M, "m"),
        ("mass_kg", MASS_RANGE_KG, MASS_USUAL_KG, "kg"),
    ):
        v = getattr(clip, key)
        if v is None:
            continue
        if not _in(v, lo, hi):
            raise FormatError(f"{where}: field {key!r}: {v:g} {unit} is outside [{lo:g}, {hi:g}] {unit}")
        if not _in(v, ulo, uhi):
            warnings.append(f"{key} {v:g} {unit} is unusual (outside [{ulo:g}, {uhi:g}])")

    kp = clip.keypoints
    conf = kp[..., 2]
    visible = conf >= VISIBLE_CONFIDENCE
    big = visible & (np.abs(kp[..., :2]) > MAX_COORD_PX).any(axis=-1)
    if big.any():
        f = int(np.argmax(big.any(axis=1)))
        raise FormatError(
            f"{where}: frame {f}: field 'keypoints': a visible joint at {kp[f][big[f]][0, :2].tolist()} px, "
            f"beyond {MAX_COORD_PX:g} px"
        )
    usable = visible.sum(axis=1) >= USABLE_JOINTS
    T = clip.num_frames
    n_usable = int(usable.sum())
    need = max(MIN_USABLE_FRAMES, math.ceil(MIN_USABLE_SHARE * T))
    if T >= MIN_USABLE_FRAMES and n_usable < need:
        raise FormatError(
            f"{where}: field 'keypoints': {n_usable} of {T} frames have a usable detection (at least "
            f"{USABLE_JOINTS} joints with confidence >= {VISIBLE_CONFIDENCE}); at least {need} are needed"
        )
    if T < MIN_USABLE_FRAMES and n_usable < T:
        raise FormatError(
            f"{where}: frame 0: field 'keypoints': no usable detection (at least {USABLE_JOINTS} joints "
            f"with confidence >= {VISIBLE_CONFIDENCE})"
        )
    if n_usable < T:
        missing = np.flatnonzero(~usable)
        first, last = int(np.argmax(usable)), int(T - 1 - np.argmax(usable[::-1]))
        extrapolated = int(first + (T - 1 - last))
        warnings.append(
            f"{T - n_usable} of {T} frames have no usable detection (frames {frame_ranges(missing)}); "
            f"they are filled from their neighbours"
            + (f", {extrapolated} of them extrapolated (before frame {first} or after {last})" if extrapolated else "")
        )
    inside = (
        (kp[..., 0] >= 0) & (kp[..., 0] <= w) & (kp[..., 1] >= 0) & (kp[..., 1] <= h)
    )
    n_vis = int(visible.sum())
    outside = int((visible & ~inside).sum())
    if n_vis and outside > OUTSIDE_IMAGE_WARN_SHARE * n_vis:
        warnings.append(f"{outside} of {n_vis} visible keypoints are outside the {w}x{h} image")

    assumed = list(clip.meta.get("assumed", []))
    if clip.meta.get("assumed_image_size"):
        assumed.append("image_size")
    if clip.extrinsics is None:
        assumed.append("extrinsics")
    if assumed:
        warnings.append(f"camera values assumed, not read from the input: {', '.join(sorted(set(assumed)))}")
    return warnings


__all__ = ["check_name", "check_reconstructable", "frame_ranges"]
