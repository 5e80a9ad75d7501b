"""VideoPose3D 2D files ``data_2d_<dataset>_<detector>.npz`` (Human3.6M cameras attached).

:func:`read_videopose3d`, :func:`iter_videopose3d`, :func:`write_videopose3d`. The only reader
of the package that unpickles (``positions_2d`` is a pickled dict): that happens in
:func:`_load_videopose3d` and nowhere else.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from jmocap.data.clip import FormatError
from jmocap.data.formats.common import _READ_ERRORS, _check_nonempty, _ferr, clean_keypoints
from jmocap.data.formats.keypoints import Keypoints2D
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
    try:
        with np.load(path, allow_pickle=True) as npz:
            if "positions_2d" not in npz.files:
                raise _ferr(
                    path, "not a VideoPose3D 2D file (no 'positions_2d')", field="positions_2d"
                )
            positions = npz["positions_2d"].item()
            metadata = npz["metadata"].item() if "metadata" in npz.files else {}
    except FormatError:
        raise
    except _READ_ERRORS as e:
        raise _ferr(path, f"not a readable .npz file: {e}") from None
    if not isinstance(positions, dict):
        raise _ferr(
            path, "must be a dict subject -> action -> [per-camera arrays]", field="positions_2d"
        )
    if not isinstance(metadata, dict):
        raise _ferr(path, "must be a dict", field="metadata")
    name = metadata.get("layout_name", "h36m")
    if name not in _VP3D_LAYOUTS:
        raise _ferr(
            path,
            f"layout {name!r} is not supported (supported: {sorted(_VP3D_LAYOUTS)})",
            field="metadata.layout_name",
        )
    layout = get_layout(_VP3D_LAYOUTS[name])
    nj = metadata.get("num_joints", layout.num_joints)
    if nj != layout.num_joints:
        raise _ferr(
            path,
            f"is {nj}, but layout {name!r} has {layout.num_joints} joints",
            field="metadata.num_joints",
        )
    return positions, metadata, layout


def _vp3d_entry(path, positions, metadata, layout, subject, action, cam) -> Keypoints2D:
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
    a = np.asarray(arrays[cam])
    if (
        a.ndim != 3
        or a.shape[1] != layout.num_joints
        or a.shape[2] not in (2, 3)
        or a.dtype.kind not in "fiu"
    ):
        raise _ferr(
            path,
            f"has shape {a.shape} ({a.dtype}), expected (T, {layout.num_joints}, 2|3)",
            field=fieldname,
        )
    _check_nonempty(path, a.shape[0])
    kp = clean_keypoints(a)
    fps = None
    size = intr = None
    vm = metadata.get("video_metadata", {})
    if isinstance(vm, dict) and subject in vm and isinstance(vm[subject], dict):
        w, h = vm[subject].get("w"), vm[subject].get("h")
        if w and h:
            size = (int(w), int(h))
        fps = vm[subject].get("fps")
    elif (
        metadata.get("layout_name", "h36m") == "h36m"
        and re.fullmatch(r"S\d+", str(subject))
        and cam < 4
    ):
        _, intr, size = H36M_CAMERAS[cam]
        intr = np.asarray(intr, np.float64)
        fps = H36M_FPS
    name = f"{subject}_{action}_{cam}".replace(" ", "_").replace("/", "_")
    return Keypoints2D(
        keypoints=kp,
        layout=layout.name,
        name=name,
        frame_ids=np.arange(kp.shape[0]),
        fps=fps,
        image_size=size,
        intrinsics=intr,
        source=str(path),
        meta={
            "format": "videopose3d",
            "subject": str(subject),
            "action": str(action),
            "camera": int(cam),
        },
    )


def iter_videopose3d(path: str | os.PathLike) -> Iterator[Keypoints2D]:
    """Every (subject, action, camera) sequence of a VideoPose3D 2D file, in file order.

    ``positions_2d`` is a pickled dict ``subject -> action -> [array (T, J, 2) per camera]``
    (loaded with ``allow_pickle=True``: read trusted files only); ``metadata`` has
    ``layout_name`` (``h36m`` -> ``h36m17``; ``coco`` -> ``coco17``), ``num_joints``,
    ``keypoints_symmetry`` and, for ``prepare_data_2d_custom.py`` files, ``video_metadata``
    (``{video: {"w", "h"}}``). For Human3.6M subjects (``S1`` ... ``S11``, h36m layout) the
    four published Human3.6M camera calibrations (:data:`H36M_CAMERAS`) and 50 fps are
    attached; custom videos get their image size from ``video_metadata``.
    """
    path = Path(path)
    positions, metadata, layout = _load_videopose3d(path)
    for subject, actions in positions.items():
        for action, arrays in actions.items():
            n = len(arrays) if isinstance(arrays, (list, tuple)) else 1
            for cam in range(n):
                yield _vp3d_entry(path, positions, metadata, layout, subject, action, cam)


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
    arrays = positions[subject][action]
    n = len(arrays) if isinstance(arrays, (list, tuple)) else 1
    camera = choose(range(n), camera, "camera")
    return _vp3d_entry(path, positions, metadata, layout, subject, action, camera)


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
    # numpy's savez; jmocap reads such files only with an explicit opt-in (docs/formats.md)
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
