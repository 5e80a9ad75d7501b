"""What every keypoint reader shares: errors, JSON input, atomic text output, missing joints.

* :class:`FormatError` messages name the file, the frame and the field (:func:`_ferr`);
* :func:`clean_keypoints` applies the missing-joint rules, the same for every reader: a joint is
  *missing* (confidence 0, x = y = 0) when its confidence is 0 or negative, when any of x, y,
  confidence is NaN/inf, or when its coordinates are exactly (0, 0) (the "no detection" value of
  OpenPose and COCO); confidences are clipped to [0, 1];
* frame numbering: gaps in a source's frame numbers become all-missing frames (:func:`_fill_gaps`).

The underscore names are shared by the format modules of this package only.
"""

from __future__ import annotations

import json
import pickle
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import FormatError
from jmocap.io import atomic_write

# what a damaged .npz/.npy can raise while being read (BadZipFile, zlib.error, pickle errors, ...);
# FileNotFoundError is let through
_READ_ERRORS = (
    OSError,
    ValueError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
    pickle.UnpicklingError,
    KeyError,
    AttributeError,
)


def clean_keypoints(kp: np.ndarray) -> np.ndarray:
    """Apply the missing-joint rules to (..., J, 2|3) keypoints; returns (..., J, 3) float32.

    (..., 2) input gets confidence 1. A joint becomes missing (all zeros) when its confidence is
    <= 0, when x, y or confidence is not finite, or when (x, y) == (0, 0). Confidences are
    clipped to [0, 1].
    """
    kp = np.asarray(kp, dtype=np.float64)
    if kp.shape[-1] == 2:
        kp = np.concatenate([kp, np.ones(kp.shape[:-1] + (1,))], axis=-1)
    elif kp.shape[-1] != 3:
        raise ValueError(f"keypoints must have 2 or 3 values per joint, got shape {kp.shape}")
    finite = np.isfinite(kp).all(axis=-1)
    with np.errstate(invalid="ignore"):
        conf = np.where(finite, kp[..., 2], 0.0)
        at_origin = (kp[..., 0] == 0) & (kp[..., 1] == 0)
        ok = finite & (conf > 0) & ~at_origin
    out = np.zeros(kp.shape, np.float32)
    out[ok, :2] = kp[ok, :2]
    out[ok, 2] = np.clip(conf[ok], 0.0, 1.0)
    return out


def _ferr(path, msg, frame=None, field=None) -> FormatError:
    parts = [str(path)]
    if frame is not None:
        parts.append(f"frame {frame}")
    if field is not None:
        parts.append(f"field {field!r}")
    return FormatError(": ".join(parts) + ": " + msg)


def _load_json(path: Path, frame=None):
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise _ferr(path, f"not valid JSON: {e}", frame) from None
    except UnicodeDecodeError as e:
        raise _ferr(path, f"not a UTF-8 text file: {e}", frame) from None


def _atomic_write_text(path: Path, text: str) -> None:
    """Write UTF-8 text atomically (:func:`jmocap.io.atomic_write`), creating the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, text)


def _flat_triplets(values, J, path, frame, fieldname, layout_desc) -> np.ndarray:
    """A flat [x, y, c] * J list -> (J, 3); FormatError on bad length or non-numbers."""
    if not isinstance(values, list):
        raise _ferr(
            path, f"must be a list of numbers, got {type(values).__name__}", frame, fieldname
        )
    if len(values) != 3 * J:
        raise _ferr(
            path,
            f"has {len(values)} values, expected {3 * J} ({layout_desc}: x, y, c for {J} joints)",
            frame,
            fieldname,
        )
    try:
        arr = np.array([np.nan if v is None else v for v in values], dtype=np.float64)
    except (TypeError, ValueError):
        raise _ferr(path, "contains values that are not numbers", frame, fieldname) from None
    return arr.reshape(J, 3)


def _fill_gaps(
    frame_ids: Sequence[int], per_frame: Sequence[Any], path, empty: Any
) -> tuple[np.ndarray, list[Any]]:
    """Sort by frame id, fill missing ids with ``empty``; FormatError on duplicates."""
    order = np.argsort(np.asarray(frame_ids), kind="stable")
    ids = [int(frame_ids[i]) for i in order]
    for a, b in zip(ids, ids[1:], strict=False):
        if a == b:
            raise _ferr(path, f"frame number {a} appears more than once", a)
    if not ids:
        return np.zeros(0, np.int64), []
    full = list(range(ids[0], ids[-1] + 1))
    by_id = {int(frame_ids[i]): per_frame[i] for i in order}
    return np.asarray(full, np.int64), [by_id.get(f, empty) for f in full]


def _check_nonempty(path, T):
    if T == 0:
        raise _ferr(path, "contains no frames")


__all__ = ["clean_keypoints"]
