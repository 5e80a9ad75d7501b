"""Reading a video file frame by frame (ffmpeg through ``imageio-ffmpeg``), never all at once.

:func:`probe_video` reads what the container says (frame rate, size, duration);
:func:`iter_frames` streams the frames as (H, W, 3) uint8 RGB arrays from an ffmpeg subprocess,
so a long video costs one frame of memory. Errors name the file (and the frame, for a video that
breaks off): :class:`VideoError`, a ``ValueError``; a missing file is a ``FileNotFoundError``.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jmocap.video.blazepose import _import

__all__ = ["VideoError", "VideoInfo", "iter_frames", "probe_video"]


class VideoError(ValueError):
    """A file that is not a readable video, or a video that breaks off (names file and frame)."""


@dataclass(frozen=True)
class VideoInfo:
    """What the container says: ``fps`` (None when it gives none), ``size`` (width, height)
    pixels, ``frames`` (an estimate from the duration: the number actually read may differ),
    ``codec``."""

    path: Path
    fps: float | None
    size: tuple[int, int]
    frames: int | None
    codec: str


def _ffmpeg_message(e: Exception) -> str:
    """The useful part of an imageio-ffmpeg error: its first line and ffmpeg's last line."""
    text = str(e).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("===")]
    first = lines[0] if lines else type(e).__name__
    last = lines[-1] if len(lines) > 1 else ""
    return first + (f" ({last})" if last and last != first and "version" not in last else "")


def _reader(path: Path):
    ffmpeg = _import("imageio_ffmpeg", "reading a video (jmocap video)")
    with warnings.catch_warnings():
        # JAX warns on any fork; ffmpeg is exec'd straight away, which is safe
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
        gen = ffmpeg.read_frames(str(path), pix_fmt="rgb24")
        try:
            meta = next(gen)
        except (OSError, RuntimeError, StopIteration) as e:
            gen.close()
            raise VideoError(f"{path}: not a readable video file: {_ffmpeg_message(e)}") from None
    return gen, meta


def _check_path(path) -> Path:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such video file")
    if path.is_dir():
        raise VideoError(f"{path}: is a folder, not a video file")
    if not os.access(path, os.R_OK):
        raise VideoError(f"{path}: not readable (permission denied)")
    return path


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """The frame rate, size and estimated frame count of a video file (reads no frame)."""
    path = _check_path(path)
    gen, meta = _reader(path)
    gen.close()
    size = tuple(int(v) for v in meta.get("size") or (0, 0))
    if len(size) != 2 or min(size) <= 0:
        raise VideoError(f"{path}: not a readable video file: no video stream with a frame size")
    fps = meta.get("fps")
    fps = float(fps) if fps and math.isfinite(float(fps)) and float(fps) > 0 else None
    duration = meta.get("duration")
    frames = int(round(float(duration) * fps)) if fps and duration and math.isfinite(float(duration)) else None
    return VideoInfo(path=path, fps=fps, size=(size[0], size[1]), frames=frames, codec=str(meta.get("codec", "")))


def iter_frames(path: str | os.PathLike) -> Iterator[np.ndarray]:
    """The frames of a video, (H, W, 3) uint8 RGB, streamed. A video that breaks off in the
    middle of a frame raises :class:`VideoError` naming the frame."""
    path = _check_path(path)
    gen, meta = _reader(path)
    w, h = (int(v) for v in meta["size"])
    t = 0
    try:
        while True:
            try:
                with warnings.catch_warnings():
                    warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
                    buf = next(gen)
            except StopIteration:
                return
            except (OSError, RuntimeError) as e:
                raise VideoError(f"{path}: frame {t}: cannot be decoded: {_ffmpeg_message(e)}") from None
            if len(buf) != w * h * 3:
                raise VideoError(f"{path}: frame {t}: has {len(buf)} bytes, expected {w * h * 3} ({w}x{h} RGB)")
            yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)
            t += 1
    finally:
        gen.close()
