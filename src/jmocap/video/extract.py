"""From a video file to jmocap clips: detection, tracking, flip repair, BODY_25, camera.

:func:`extract_clips` streams the video once through BlazePose and the tracker
(:mod:`jmocap.video.tracking`), repairs each track's left/right flips
(:func:`~jmocap.video.flips.repair_flips`), maps BlazePose's 33 landmarks to BODY_25
(:func:`~jmocap.video.mapping.to_body25`) and writes, per chosen person, a jmocap clip
``<out>/<video stem>_p<K>.npz`` and its camera sidecar ``<video stem>_p<K>.camera.json``.
:func:`write_overlays` draws the reconstructions over the video (:func:`jmocap.viz.render_overlay`).
``jmocap video`` (``jmocap.cli``) runs both with ``jmocap reconstruct`` in between.

The clip covers its track's first to last frame (``meta["first_frame"]`` is the video frame of
its frame 0); frames inside where the track was lost are all-missing (confidence 0). Besides
the ``jmocap-clip-1`` fields it carries the raw BlazePose output, ignored by jmocap's readers:
``blazepose_landmarks`` (T, 33, 5) float32 (x, y image pixels; z relative depth in pixels;
visibility and presence probabilities; after flip repair; zeros where lost),
``blazepose_score`` (T,) the pose-presence score (0 where lost) and ``blazepose_swapped`` (T,)
the frames whose left and right the repair exchanged.

The camera: ``camera`` (any sidecar :func:`~jmocap.data.formats.read_camera_json` reads: K,
distortion, R/t, rvec/tvec, ...; its width and height must be the video's) or else jmocap's
default intrinsics (f = 1000 px, principal point at the image centre) recorded in the clip's
``meta["assumed"]``; without extrinsics, ``jmocap reconstruct`` estimates the camera's tilt and
height from the person (``jmocap.methods.floor``; the result's ``extrinsics_source``). Lens distortion is removed from the keypoints (as the sidecar readers
do); the overlay is drawn through the pinhole camera. A camera file whose extrinsics are given
per frame (a moving camera's track: one per frame of the video) gives each person's clip the
cameras of its own frames (``camera_track``), and the overlay draws frame t from camera t.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.camera import default_intrinsics
from jmocap.data.clip import Clip, clip_to_arrays, load_clip
from jmocap.data.formats import (
    read_camera_json,
    safe_name,
    sidecar_path,
    undistort_keypoints,
    write_camera_json,
)
from jmocap.io import atomic_write, atomic_write_npz
from jmocap.video.blazepose import BlazePose
from jmocap.video.flips import repair_flips, swap_left_right
from jmocap.video.mapping import to_body25
from jmocap.video.reader import VideoError, iter_frames, probe_video
from jmocap.video.tracking import Track, TrackOptions, track_people

__all__ = ["DETECTOR", "NoPersonError", "VideoOptions", "choose_tracks", "extract_clips", "track_arrays",
           "write_overlays"]

DETECTOR = "BlazePose GHUM full (mediapipe 0.10.21 models, LiteRT)"
SUMMARY_FORMAT = "jmocap-video-1"


class NoPersonError(VideoError):
    """The video was read, but no track of a person was found (or none of the chosen one)."""


@dataclass(frozen=True)
class VideoOptions:
    """Options of :func:`extract_clips` (``jmocap video --help``)."""

    person: str = "largest"  # "largest", "all", or a track number K (as text or int)
    fps: float | None = None  # overrides the camera file's and the video's frame rate
    camera: str | os.PathLike | None = None  # a camera sidecar file
    height_m: float | None = None  # the subject's height (m), written into the clip
    track: TrackOptions = field(default_factory=TrackOptions)
    repair_flips: bool = True
    swap_cost: float = 0.01  # flips.repair_flips: price of one swapped frame (body scales)
    threads: int | None = None  # LiteRT threads per model

    def person_choice(self) -> str | int:
        p = str(self.person).strip().lower()
        if p in ("largest", "all"):
            return p
        try:
            k = int(p)
        except ValueError:
            raise ValueError(f"person must be 'largest', 'all' or a track number >= 0, got {self.person!r}") from None
        if k < 0:
            raise ValueError(f"person must be 'largest', 'all' or a track number >= 0, got {self.person!r}")
        return k


def _camera(video: Path, size: tuple[int, int], options: VideoOptions):
    """(intrinsics, extrinsics | None, distortion | None, fps | None, assumed list, record, camera
    track | None): a camera file whose extrinsics are given per frame is a moving camera's track,
    one per frame of the video."""
    if options.camera is None:
        return default_intrinsics(*size), None, None, None, ["intrinsics"], {"camera": "assumed"}, None
    side = read_camera_json(options.camera)
    if tuple(side["image_size"]) != tuple(size):
        w, h = side["image_size"]
        raise VideoError(f"{options.camera}: field 'width': the camera file is for {w}x{h} images, "
                         f"the video {video} is {size[0]}x{size[1]}")
    rec = {"camera": str(options.camera), "camera_convention": side["convention"]}
    return side["intrinsics"], side["extrinsics"], side["distortion"], side["fps"], [], rec, side.get("camera_track")


def track_arrays(track: Track) -> dict[str, np.ndarray]:
    """A track as arrays over its frames ``start .. end``: ``observed`` (T,) bool, ``points``
    (T, 39, 2), ``z``, ``visibility``, ``presence`` (T, 39), ``score`` (T,); zeros where lost."""
    T = track.end - track.start + 1
    out = {
        "observed": np.zeros(T, bool),
        "points": np.zeros((T, 39, 2)),
        "z": np.zeros((T, 39)),
        "visibility": np.zeros((T, 39)),
        "presence": np.zeros((T, 39)),
        "score": np.zeros(T),
    }
    for t, r in zip(track.frames, track.results, strict=True):
        i = t - track.start
        out["observed"][i] = True
        out["points"][i] = r.points
        out["z"][i] = r.z
        out["visibility"][i] = r.visibility
        out["presence"][i] = r.presence
        out["score"][i] = r.score
    return out


def choose_tracks(tracks: list[Track], person: str | int, where: str) -> list[int]:
    """Indices into ``tracks`` of the chosen person(s): ``"largest"`` the track with the largest
    sum over its frames of the body's size in pixels (seen largest and longest), ``"all"``
    every track, ``K`` the K-th (tracks are numbered by first frame, then left to right)."""
    if not tracks:
        return []
    if person == "all":
        return list(range(len(tracks)))
    if person == "largest":
        return [int(np.argmax([tr.size() for tr in tracks]))]
    if person >= len(tracks):
        raise NoPersonError(f"{where}: --person {person}: only {len(tracks)} track(s) found (0..{len(tracks) - 1}: "
                            + ", ".join(f"{k}: frames {tr.start}-{tr.end}" for k, tr in enumerate(tracks)) + ")")
    return [int(person)]


def extract_clips(video: str | os.PathLike, out: str | os.PathLike, options: VideoOptions = VideoOptions(),
                  progress: Callable[[int, int | None], None] | None = None) -> dict[str, Any]:
    """Detect and track the people of ``video``, write the chosen ones' clips into ``out``.

    Returns the summary (also the caller's to write): ``video``, ``frames``, ``fps`` and
    ``fps_source`` (``argument`` / ``camera file`` / ``video``), ``size``, ``tracks`` (one entry
    per track: ``person`` K, ``start``, ``end``, ``frames_with_pose``, ``frames_lost``,
    ``flipped_frames``, ``size_px``, ``clip`` when written), ``clips`` (the written clip paths),
    ``assumed``, ``seconds`` and ``ms_per_frame`` of the detection and tracking, the tracker's
    statistics. Raises ``FileNotFoundError``, :class:`VideoError` (unreadable video, camera file
    of another size), :class:`NoPersonError` (nobody found), ``FormatError`` (a bad camera file).
    ``progress(frame, total)`` is called after each frame (total: the container's estimate).
    """
    video = Path(video)
    out = Path(out)
    person = options.person_choice()
    info = probe_video(video)
    intr, extr, dist, side_fps, assumed, cam_record, track = _camera(video, info.size, options)
    if options.fps is not None:
        fps, fps_source = float(options.fps), "argument"
    elif side_fps is not None:
        fps, fps_source = float(side_fps), "camera file"
    elif info.fps is not None:
        fps, fps_source = info.fps, "video"
    else:
        raise VideoError(f"{video}: the video does not give its frame rate; pass --fps")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")

    t0 = time.perf_counter()
    estimator = BlazePose(threads=options.threads)
    cb = (lambda t: progress(t + 1, info.frames)) if progress is not None else None
    tracks, stats = track_people(iter_frames(video), estimator, options.track, progress=cb)
    seconds = time.perf_counter() - t0
    n = stats["frames"]
    if n == 0:
        raise VideoError(f"{video}: the video has no frames")
    where = str(video)
    if not tracks:
        raise NoPersonError(
            f"{where}: no person found in {n} frames (detector score >= {options.track.min_detection_score}, "
            f"pose presence >= {options.track.min_presence}, at least {options.track.min_frames} frames)")
    chosen = choose_tracks(tracks, person, where)
    if track is not None and len(track) != n:
        raise VideoError(f"{options.camera}: field 'extrinsics': the camera track has {len(track)} frames but the "
                         f"video {video} has {n}: one camera per frame of the video")

    stem = safe_name(video.stem, max_bytes=80)
    summary: dict[str, Any] = {
        "format": SUMMARY_FORMAT, "video": str(video), "frames": n, "fps": fps, "fps_source": fps_source,
        "size": list(info.size), "detector": DETECTOR, "person": str(person), **cam_record,
        "assumed": assumed, "tracks": [], "clips": [], "seconds": round(seconds, 3),
        "ms_per_frame": round(1000.0 * seconds / n, 2), "tracker": stats,
    }
    for k, tr in enumerate(tracks):
        a = track_arrays(tr)
        obs = a["observed"]
        swapped = np.zeros(len(obs), bool)
        if options.repair_flips:
            swapped[obs] = repair_flips(a["points"][obs, :33], a["visibility"][obs, :33] * a["presence"][obs, :33],
                                        np.nonzero(obs)[0], swap_cost=options.swap_cost)
            for key in ("points", "z", "visibility", "presence"):
                a[key][swapped, :33] = swap_left_right(a[key][swapped, :33], axis=1)
        entry = {"person": k, "start": tr.start, "end": tr.end, "frames_with_pose": int(obs.sum()),
                 "frames_lost": int((~obs).sum()), "flipped_frames": int(swapped.sum()),
                 "size_px": round(tr.size() / len(tr.frames), 1)}
        summary["tracks"].append(entry)
        if k not in chosen:
            continue
        conf = a["visibility"] * a["presence"]
        kp = to_body25(a["points"][:, :33], conf[:, :33])
        kp[~obs] = 0.0
        if dist is not None:
            kp = undistort_keypoints(kp, intr, dist)
        name = f"{stem}_p{k}"
        meta = {
            "source": str(video), "first_frame": int(tr.start), "generator": "jmocap video",
            "detector": DETECTOR, "person": k, "frames_lost": entry["frames_lost"],
            "flipped_frames": entry["flipped_frames"], "fps_source": fps_source,
            "video_frames": n, **cam_record,
        }
        if assumed:
            meta["assumed"] = list(assumed)
        if dist is not None:
            meta["undistorted"] = [float(v) for v in dist]
        own = None if track is None else track[tr.start:tr.start + len(kp)]  # the person's frames' cameras
        clip = Clip(name=name, layout="body25", fps=fps, keypoints=kp, intrinsics=intr,
                    image_size=np.asarray(info.size), extrinsics=extr if own is None else own[0], camera_track=own,
                    height_m=options.height_m, meta=meta)
        raw = np.concatenate([a["points"][:, :33], a["z"][:, :33, None], a["visibility"][:, :33, None],
                              a["presence"][:, :33, None]], axis=-1)
        arrays = clip_to_arrays(clip)
        arrays.update(blazepose_landmarks=raw.astype(np.float32), blazepose_score=a["score"].astype(np.float32),
                      blazepose_swapped=swapped)
        path = out / f"{name}.npz"
        atomic_write_npz(path, arrays)
        write_camera_json(sidecar_path(path), clip)
        entry["clip"] = name
        summary["clips"].append(str(path))
    return summary


def write_summary(path: str | os.PathLike, summary: dict) -> Path:
    """``summary`` as indented JSON, atomically."""
    return atomic_write(path, json.dumps(summary, indent=1, sort_keys=False) + "\n")


def write_overlays(video: str | os.PathLike, clips: list[str | os.PathLike], results_dir: str | os.PathLike,
                   out: str | os.PathLike, *, max_side: int = 1280) -> list[Path]:
    """Per clip with a result in ``results_dir``: ``<out>/<clip name>_overlay.mp4``, the whole
    video with the reconstructed character drawn over the frames of its track and the clip's
    2D keypoints (:func:`jmocap.viz.render_overlay`); videos larger than ``max_side`` pixels
    are drawn at that size (longest side). The video is streamed again for each clip."""
    from jmocap import viz
    from jmocap.camera import Camera
    from jmocap.results import load_result, result_model

    written = []
    for clip_path in clips:
        clip = load_clip(clip_path)
        res_path = Path(results_dir) / f"{clip.name}.npz"
        if not res_path.is_file():
            continue
        r = load_result(res_path)
        model = result_model(r)
        W, H = (int(v) for v in r["image_size"])
        k = min(1.0, max_side / max(W, H))
        fx, fy, cx, cy = (float(v) for v in r["intrinsics"])
        w2, h2 = max(8, round(W * k)), max(8, round(H * k))
        sx, sy = w2 / W, h2 / H
        extrinsics = r["camera_track"] if r.get("camera_track") is not None else r["extrinsics"]  # moving: per frame
        cam = Camera.from_intrinsics(fx * sx, fy * sy, cx * sx, cy * sy, w2, h2, extrinsics=extrinsics,
                                     dtype=np.float64)
        kp = np.array(clip.keypoints, np.float64)
        kp[..., 0] *= sx
        kp[..., 1] *= sy
        frames = iter_frames(video) if k == 1.0 else (_resize(f, w2, h2) for f in iter_frames(video))
        path = Path(out) / f"{clip.name}_overlay.mp4"
        viz.render_overlay(path, model, r["q"], frames, cam, float(r["fps"]), keypoints2d=kp,
                           first_frame=int(clip.meta.get("first_frame", 0)), layout=clip.layout)
        written.append(path)
    return written


def _resize(frame: np.ndarray, w: int, h: int) -> np.ndarray:
    import cv2

    return cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA)
