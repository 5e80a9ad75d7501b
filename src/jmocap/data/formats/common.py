"""What every keypoint reader shares: errors, JSON input, atomic text output, missing joints.

* :class:`FormatError` messages name the file, the frame and the field (:func:`_ferr`);
* :func:`clean_keypoints` applies the missing-joint rules, the same for every reader: a joint is
  *missing* (confidence 0, x = y = 0) when its confidence is 0 or negative, when any of x, y,
  confidence is NaN/inf, or when its coordinates are exactly (0, 0) (the "no detection" value of
  OpenPose and COCO); confidences are clipped to [0, 1];
* JSON input (:func:`_load_json`): size, nesting depth and parse errors become format errors;
  values are checked to be of their JSON type (:func:`_number`, :func:`_nested_numbers`,
  :func:`_flat_triplets`): a number is a JSON number (not a string like ``"30"``, not ``true``);
* frame numbering: gaps in a source's frame numbers become all-missing frames (:func:`_fill_gaps`),
  within :mod:`jmocap.data.limits`;
* :func:`safe_name`: a clip name usable as one file-name component.

The underscore names are shared by the format modules of this package only.
"""

from __future__ import annotations

import hashlib
import math
import pickle
import re
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data import limits
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
    """Parse the JSON file ``path``; every problem is a :class:`FormatError` naming the file
    (and ``frame`` when given).

    Checked: the file size (:func:`jmocap.data.limits.check_file_size`), then by
    :func:`jmocap.data.limits.parse_json`: UTF-8, valid JSON, nesting within ``max_json_depth``
    (nesting too deep for Python's parser says so too), integers within Python's digit limit.
    """
    where = f"{path}: frame {frame}" if frame is not None else str(path)
    limits.check_file_size(path, where)
    with open(path, "rb") as f:
        raw = f.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise _ferr(path, f"not a UTF-8 text file: {e}", frame) from None
    return limits.parse_json(text, where)


def _is_number(v) -> bool:
    """Whether ``v`` is a JSON number (``int`` or ``float``; a numpy number from a pickle or an
    ``.npz`` counts too), not a ``bool``, a string or anything else."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(
        v, (bool, np.bool_)
    )


def _type_name(v) -> str:
    """What a wrong value is, for messages: ``"a string '30'"``, ``"a boolean"``, ``"a list"``."""
    if isinstance(v, (bool, np.bool_)):
        return f"a boolean ({str(bool(v)).lower()})"
    if isinstance(v, str):
        return f"a string {v[:40]!r}"
    if v is None:
        return "null"
    names = {dict: "an object", list: "a list", int: "an integer", float: "a number"}
    return names.get(type(v), f"a {type(v).__name__}")


def _number(
    v,
    path,
    field,
    frame=None,
    *,
    integer: bool = False,
    positive: bool = False,
    nonnegative: bool = False,
    finite: bool = True,
    maximum: float | None = None,
) -> float | int:
    """``v`` checked to be a JSON number (:func:`_is_number`): ``int`` when ``integer`` (an
    integral float such as ``640.0`` is accepted), else ``float``. Also checked on request:
    finite (default), > 0, >= 0, <= ``maximum``. A :class:`FormatError` naming file, frame and
    field otherwise."""
    if not _is_number(v):
        raise _ferr(path, f"must be a number, got {_type_name(v)}", frame, field)
    try:
        x = float(v)
    except OverflowError:
        x = math.inf if v > 0 else -math.inf
    if finite and not math.isfinite(x):
        raise _ferr(path, f"must be a finite number, got {v!r}", frame, field)
    if integer:
        if not math.isfinite(x) or x != math.floor(x):
            raise _ferr(path, f"must be an integer, got {v!r}", frame, field)
        x = int(v)
    if positive and not x > 0:
        raise _ferr(path, f"must be > 0, got {v!r}", frame, field)
    if nonnegative and not x >= 0:
        raise _ferr(path, f"must be >= 0, got {v!r}", frame, field)
    if maximum is not None and x > maximum:
        raise _ferr(path, f"must be at most {maximum}, got {v!r}", frame, field)
    return x


def _list_depth(values) -> int:
    """How many list levels ``values`` has along its first elements (``[[1, 2]]`` -> 2)."""
    d = 0
    while isinstance(values, list) and values:
        values, d = values[0], d + 1
    return d + (1 if isinstance(values, list) else 0)


def _nested_numbers(values, ndim, path, field, frame=None, *, allow_null=False) -> np.ndarray:
    """A JSON array of arrays (``ndim`` levels, every row the same length) of numbers ->
    float64 ndarray. Every leaf must be a JSON number (:func:`_is_number`; ``null`` -> NaN with
    ``allow_null``); an integer too large for a float becomes inf. A :class:`FormatError`
    naming file, frame and field otherwise."""

    def walk(v, d):
        if d == ndim:
            if v is None and allow_null:
                return math.nan
            if not _is_number(v):
                raise _ferr(
                    path, f"must contain only numbers, found {_type_name(v)}", frame, field
                )
            try:
                return float(v)
            except OverflowError:
                return math.inf if v > 0 else -math.inf
        if not isinstance(v, list):
            what = "a list of numbers" if d + 1 == ndim else "a list of lists"
            raise _ferr(path, f"must be {what}, found {_type_name(v)}", frame, field)
        return [walk(x, d + 1) for x in v]

    rows = walk(values, 0)
    try:
        return np.array(rows, dtype=np.float64)
    except ValueError:
        raise _ferr(path, "has rows of different lengths", frame, field) from None


def _atomic_write_text(path: Path, text: str) -> None:
    """Write UTF-8 text atomically (:func:`jmocap.io.atomic_write`), creating the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, text)


def _flat_triplets(values, J, path, frame, fieldname, layout_desc) -> np.ndarray:
    """A flat ``[x, y, c] * J`` list -> (J, 3) float64; each value a JSON number or ``null``
    (NaN: a missing joint). FormatError on a non-list, a bad length or other values."""
    if not isinstance(values, list):
        raise _ferr(
            path, f"must be a list of numbers, got {_type_name(values)}", frame, fieldname
        )
    if len(values) != 3 * J:
        raise _ferr(
            path,
            f"has {len(values)} values, expected {3 * J} ({layout_desc}: x, y, c for {J} joints)",
            frame,
            fieldname,
        )
    return _nested_numbers(values, 1, path, fieldname, frame, allow_null=True).reshape(J, 3)


def _fill_gaps(
    frame_ids: Sequence[int], per_frame: Sequence[Any], path, empty: Any
) -> tuple[np.ndarray, list[Any]]:
    """Sort by frame number and fill missing numbers with ``empty``.

    Checked: every frame number is a non-negative integer (``int`` or numpy integer, not a
    ``bool``), none appears twice, consecutive numbers are at most ``max_frame_gap`` apart
    (:func:`jmocap.data.limits.check_frame_gap`) and the filled clip has at most
    ``max_frames`` frames (:func:`jmocap.data.limits.check_frames`). FormatError otherwise.
    """
    for f in frame_ids:
        if not isinstance(f, (int, np.integer)) or isinstance(f, (bool, np.bool_)):
            raise _ferr(path, f"frame number {f!r} is not an integer")
        if f < 0:
            raise _ferr(path, f"frame number {f} is negative", int(f))
    ids = sorted(int(f) for f in frame_ids)
    for a, b in zip(ids, ids[1:], strict=False):
        if a == b:
            raise _ferr(path, f"frame number {a} appears more than once", a)
        limits.check_frame_gap(a, b, str(path))
    if not ids:
        return np.zeros(0, np.int64), []
    limits.check_frames(ids[-1] - ids[0] + 1, str(path))
    full = list(range(ids[0], ids[-1] + 1))
    by_id = {int(f): x for f, x in zip(frame_ids, per_frame, strict=True)}
    return np.asarray(full, np.int64), [by_id.get(f, empty) for f in full]


def _check_nonempty(path, T):
    if T == 0:
        raise _ferr(path, "contains no frames")


_UNSAFE_CHARS = re.compile(r"[\x00-\x1f\x7f/\\]")


def safe_name(name: str, max_bytes: int = 100) -> str:
    """``name`` made usable as one file-name component, deterministically.

    Spaces, ``/``, ``\\``, NUL and other control characters become ``_``; leading dots become
    ``_`` (no hidden files, no ``.`` / ``..``); an empty name becomes ``_``; characters that
    cannot be UTF-8 encoded (lone surrogates) become ``?``. A name longer than ``max_bytes``
    bytes of UTF-8 is cut (at a character boundary) and given ``-`` and the first 8 hex digits
    of the SHA-256 of the whole name, so two long names that share a prefix stay different.
    """
    text = str(name).encode("utf-8", "replace").decode("utf-8")
    text = _UNSAFE_CHARS.sub("_", text.replace(" ", "_"))
    stripped = text.lstrip(".")
    text = "_" * (len(text) - len(stripped)) + stripped or "_"
    raw = text.encode("utf-8")
    if len(raw) > max_bytes:
        digest = hashlib.sha256(str(name).encode("utf-8", "surrogatepass")).hexdigest()[:8]
        text = raw[: max_bytes - 9].decode("utf-8", "ignore") + "-" + digest
    return text


__all__ = ["clean_keypoints", "safe_name"]
