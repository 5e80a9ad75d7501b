"""VideoPose3D 2D files ``data_2d_<dataset>_<detector>.npz`` (Human3.6M cameras attached).

:func:`read_videopose3d`, :func:`iter_videopose3d`, :func:`write_videopose3d`. ``positions_2d``
and ``metadata`` are pickled dicts; :func:`_load_videopose3d` reads them with the restricted
unpickler of :mod:`jmocap.data.formats.safe_pickle` (arrays, dicts, lists, strings and numbers
only: a pickle that names anything else, e.g. ``os.system``, is refused, never run).
"""

from __future__ import annotations

import os
import re
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from jmocap.data import limits
from jmocap.data.clip import MAX_IMAGE_SIDE, FormatError
from jmocap.data.formats.common import (
    _READ_ERRORS,
    _check_nonempty,
    _ferr,
    _nested_numbers,
    _number,
    _type_name,
    clean_keypoints,
    safe_name,
)
from jmocap.data.formats.keypoints import Keypoints2D
from jmocap.data.formats.safe_pickle import load_npz_pickled
from jmocap.layouts import get_layout

# Human3.6M camera intrinsics (fx, fy, cx, cy) and resolution (w, h), in the order of the
# per-camera lists of VideoPose3D's data_2d_h36m_*.npz (its common/h36m_dataset.py).
H36M_CAMERAS: tuple[tuple[str, tuple[float, float, float, float], tuple[int, int]], ...] = (
    (
        "54138969",
        (1145.0494384765625, 1143.7811279296875, 512.54150390625, 515.4514770507812),
        (1000, 1002),
    ),
    (
        "55011271",
        (1149.6756591796875, 1147.5916748046875, 508.8486328125, 508.0649108886719),
        (1000, 1000),
    ),
    (
        "58860488",
        (1149.1407470703125, 1148.7989501953125, 519.8158569335938, 501.40264892578125),
        (1000, 1000),
    ),
    (
        "60457274",
        (1145.5113525390625, 1144.77392578125, 514.9682006835938, 501.88201904296875),
        (1000, 1002),
    ),
)
H36M_FPS = 50.0


_VP3D_LAYOUTS = {"h36m": "h36m17", "coco": "coco17"}


def _load_videopose3d(path: Path):
    """``(positions, metadata, layout)`` of a VideoPose3D file, read without running pickles.

    Checked: the file and member sizes and the restricted unpickling
    (:func:`~jmocap.data.formats.safe_pickle.load_npz_pickled`); ``positions_2d`` is a dict
    subject -> dict action -> list of per-camera arrays (or one array); ``metadata`` a dict whose
    ``layout_name`` is supported and whose ``num_joints`` (an integer) matches the layout.
    """
    try:
        loaded = load_npz_pickled(path, ("positions_2d", "metadata"), str(path))
    except FormatError:
        raise
    except (*_READ_ERRORS, zipfile.LargeZipFile) as e:
        raise _ferr(path, f"not a readable .npz file: {e}") from None
    if "positions_2d" not in loaded:
        raise _ferr(path, "not a VideoPose3D 2D file (no 'positions_2d')", field="positions_2d")
    positions = loaded["positions_2d"]
    metadata = loaded.get("metadata", {})
    if not isinstance(positions, dict):
        raise _ferr(
            path,
            f"must be a dict subject -> action -> [per-camera arrays], got {_type_name(positions)}",
            field="positions_2d",
        )
    for subject, actions in positions.items():
        if not isinstance(actions, dict):
            raise _ferr(
                path,
                f"must be a dict action -> [per-camera arrays], got {_type_name(actions)}",
                field=f"positions_2d[{subject!r}]",
            )
        for action, arrays in actions.items():
            if not isinstance(arrays, (list, tuple, np.ndarray)):
                raise _ferr(
                    path,
                    f"must be a list of per-camera arrays, got {_type_name(arrays)}",
                    field=f"positions_2d[{subject!r}][{action!r}]",
                )
    if not isinstance(metadata, dict):
        raise _ferr(path, f"must be a dict, got {_type_name(metadata)}", field="metadata")
    name = metadata.get("layout_name", "h36m")
    if not isinstance(name, str) or name not in _VP3D_LAYOUTS:
        raise _ferr(
            path,
            f"layout {name!r} is not supported (supported: {sorted(_VP3D_LAYOUTS)})",
            field="metadata.layout_name",
        )
    layout = get_layout(_VP3D_LAYOUTS[name])
    nj = _number(
        metadata.get("num_joints", layout.num_joints), path, "metadata.num_joints", integer=True
    )
    if nj != layout.num_joints:
        raise _ferr(
            path,
            f"is {nj}, but layout {name!r} has {layout.num_joints} joints",
            field="metadata.num_joints",
        )
    return positions, metadata, layout


def _cameras(arrays) -> int:
    """How many camera sequences an action entry holds (a list per camera, or one array)."""
    return len(arrays) if isinstance(arrays, (list, tuple)) else 1


def _vp3d_names(positions) -> dict[tuple, tuple[str, str | None]]:
    """``(subject, action, camera) -> (name, renamed_from)`` for every sequence, in file order.

    The name is ``<subject>_<action>_<camera>`` made a safe file-name component
    (:func:`~jmocap.data.formats.common.safe_name`). Names are unique within the file, compared
    without case (so their result files cannot collide on a case-insensitive file system):
    a later sequence whose name is taken gets ``~2``, ``~3``, ... (the first suffix not taken
    by any name of the file), and ``renamed_from`` is the name it would have had.
    """
    keys, natural = [], []
    for subject, actions in positions.items():
        for action, arrays in actions.items():
            for cam in range(_cameras(arrays)):
                keys.append((subject, action, cam))
                natural.append(safe_name(f"{subject}_{action}_{cam}"))
    taken = {n.casefold() for n in natural}
    used: set[str] = set()
    out = {}
    for key, name in zip(keys, natural, strict=True):
        final, k = name, 1
        while final.casefold() in used or (final != name and final.casefold() in taken):
            k += 1
            final = f"{name}~{k}"
        used.add(final.casefold())
        out[key] = (final, None if final == name else name)
    return out


def _vp3d_video(path, metadata, subject):
    """``(found, image_size, fps)`` from ``metadata["video_metadata"][subject]`` (custom
    videos); ``found`` is False when the file has no entry for ``subject`` (then both are
    ``None``). Checked: ``video_metadata`` is a dict of dicts, ``w``, ``h`` are positive
    integers and ``fps`` a positive finite number (each optional)."""
    vm = metadata.get("video_metadata", {})
    if not isinstance(vm, dict):
        raise _ferr(path, f"must be a dict, got {_type_name(vm)}", field="metadata.video_metadata")
    if subject not in vm:
        return False, None, None
    entry = vm[subject]
    field = f"metadata.video_metadata[{subject!r}]"
    if not isinstance(entry, dict):
        raise _ferr(path, f"must be a dict with 'w', 'h', got {_type_name(entry)}", field=field)
    size = fps = None
    w, h = entry.get("w"), entry.get("h")
    if w is not None and h is not None:
        size = tuple(
            _number(v, path, f"{field}.{k}", integer=True, positive=True, maximum=MAX_IMAGE_SIDE)
            for k, v in (("w", w), ("h", h))
        )
    if entry.get("fps") is not None:
        fps = _number(entry["fps"], path, f"{field}.fps", positive=True)
    return True, size, fps


def _vp3d_entry(path, positions, metadata, layout, subject, action, cam, names) -> Keypoints2D:
    arrays = positions[subject][action]
    if not isinstance(arrays, (list, tuple)):
        arrays = [arrays]
    if not (0 <= cam < len(arrays)):
        raise _ferr(
            path,
            f"camera index {cam} out of range (0..{len(arrays) - 1}) for {subject}/{action}",
            field="positions_2d",
        )
    fieldname = f"positions_2d[{subject!r}][{action!r}][{cam}]"
    a = arrays[cam]
    if isinstance(a, list):  # nested lists instead of an array
        a = _nested_numbers(a, 3, path, fieldname)
    if (
        not isinstance(a, np.ndarray)
        or a.ndim != 3
        or a.shape[1] != layout.num_joints
        or a.shape[2] not in (2, 3)
        or a.dtype.kind not in "fiu"
    ):
        what = f"shape {a.shape} ({a.dtype})" if isinstance(a, np.ndarray) else _type_name(a)
        raise _ferr(
            path,
            f"has {what}, expected an array (T, {layout.num_joints}, 2|3) of numbers",
            field=fieldname,
        )
    _check_nonempty(path, a.shape[0])
    limits.check_frames(a.shape[0], f"{path}: {fieldname}")
    kp = clean_keypoints(a)
    found, size, fps = _vp3d_video(path, metadata, subject)
    intr = None
    if (
        not found
        and metadata.get("layout_name", "h36m") == "h36m"
        and re.fullmatch(r"S\d+", str(subject))
        and cam < 4
    ):
        _, intr, size = H36M_CAMERAS[cam]
        intr = np.asarray(intr, np.float64)
        fps = H36M_FPS
    name, renamed_from = names[(subject, action, cam)]
    meta = {
        "format": "videopose3d",
        "subject": str(subject),
        "action": str(action),
        "camera": int(cam),
    }
    if renamed_from is not None:
        meta["renamed_from"] = renamed_from
    return Keypoints2D(
        keypoints=kp,
        layout=layout.name,
        name=name,
        frame_ids=np.arange(kp.shape[0]),
        fps=fps,
        image_size=size,
        intrinsics=intr,
        source=str(path),
        meta=meta,
    )


def iter_videopose3d(path: str | os.PathLike) -> Iterator[Keypoints2D]:
    """Every (subject, action, camera) sequence of a VideoPose3D 2D file, in file order.

    ``positions_2d`` is a pickled dict ``subject -> action -> [array (T, J, 2) per camera]``
    (read by a restricted unpickler that rebuilds only arrays, dicts, lists, strings and
    numbers: :mod:`jmocap.data.formats.safe_pickle`); ``metadata`` has
    ``layout_name`` (``h36m`` -> ``h36m17``; ``coco`` -> ``coco17``), ``num_joints``,
    ``keypoints_symmetry`` and, for ``prepare_data_2d_custom.py`` files, ``video_metadata``
    (``{video: {"w", "h"}}``). For Human3.6M subjects (``S1`` ... ``S11``, h36m layout) the
    four published Human3.6M camera calibrations (:data:`H36M_CAMERAS`) and 50 fps are
    attached; custom videos get their image size from ``video_metadata``.

    Names are ``<subject>_<action>_<camera>``, made safe as a file-name component and unique
    within the file (a later sequence whose name is taken gets ``~2``, ... and
    ``meta["renamed_from"]``; see :func:`_vp3d_names`).
    """
    path = Path(path)
    positions, metadata, layout = _load_videopose3d(path)
    names = _vp3d_names(positions)
    for subject, action, cam in names:
        yield _vp3d_entry(path, positions, metadata, layout, subject, action, cam, names)


def read_videopose3d(
    path: str | os.PathLike,
    subject: str | None = None,
    action: str | None = None,
    camera: int | None = None,
) -> Keypoints2D:
    """One (subject, action, camera) sequence of a VideoPose3D 2D file (see :func:`iter_videopose3d`).

    Arguments left ``None`` are allowed only when the file has exactly one choice for them.
    """
    path = Path(path)
    positions, metadata, layout = _load_videopose3d(path)

    def choose(options, value, what):
        options = list(options)
        if value is None:
            if len(options) != 1:
                raise _ferr(
                    path,
                    f"has {len(options)} {what}s ({options[:8]}...); choose one",
                    field="positions_2d",
                )
            return options[0]
        if value not in options:
            raise _ferr(
                path, f"has no {what} {value!r} (available: {options[:20]})", field="positions_2d"
            )
        return value

    subject = choose(positions.keys(), subject, "subject")
    action = choose(positions[subject].keys(), action, "action")
    camera = choose(range(_cameras(positions[subject][action])), camera, "camera")
    names = _vp3d_names(positions)
    return _vp3d_entry(path, positions, metadata, layout, subject, action, camera, names)


def write_videopose3d(
    path: str | os.PathLike,
    sequences: Mapping[str, Mapping[str, Sequence[np.ndarray]]],
    layout: str = "h36m17",
    video_metadata: Mapping | None = None,
) -> Path:
    """Write a VideoPose3D-style 2D file (``positions_2d`` + ``metadata``), atomically.

    ``sequences`` is ``subject -> action -> [(T, J, 2) array per camera]``.
    """
    from jmocap.io import atomic_writer

    lay = get_layout(layout)
    inv = {v: k for k, v in _VP3D_LAYOUTS.items()}
    if lay.name not in inv:
        raise ValueError(f"VideoPose3D files support layouts {sorted(inv)}, got {lay.name!r}")
    left = [l for l, _ in lay.flip_pairs]
    right = [r for _, r in lay.flip_pairs]
    metadata = {
        "layout_name": inv[lay.name],
        "num_joints": lay.num_joints,
        "keypoints_symmetry": [left, right],
    }
    if video_metadata is not None:
        metadata["video_metadata"] = dict(video_metadata)
    positions = {
        s: {a: [np.asarray(x, np.float32) for x in cams] for a, cams in acts.items()}
        for s, acts in sequences.items()
    }
    arrays = {
        "positions_2d": np.array(positions, dtype=object),
        "metadata": np.array(metadata, dtype=object),
    }
    # the format is a pickled dict by definition (VideoPose3D's own files are): written with
    # numpy's savez; jmocap reads it back with its restricted unpickler (safe_pickle.py)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_writer(path) as f:
        np.savez_compressed(f, **arrays)
    return path


__all__ = [
    "H36M_CAMERAS",
    "H36M_FPS",
    "iter_videopose3d",
    "read_videopose3d",
    "write_videopose3d",
]
