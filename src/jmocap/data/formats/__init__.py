"""Readers and writers of 2D keypoint formats (and one 3D reference format).

Readers return a :class:`Keypoints2D` (keypoints + layout + whatever the file says about the
video: fps, image size, camera); :meth:`Keypoints2D.to_clip` (or :func:`read_clip`, which also
dispatches on the path) turns it into a :class:`~jmocap.data.clip.Clip` with a camera.

One module per format family (details, joint orders and examples in ``docs/formats.md``):

* :mod:`~jmocap.data.formats.openpose`: OpenPose ``--write_json`` folders (JSON ``version`` 1.3
  files, BODY_25 model): :func:`read_openpose_folder`, :func:`write_openpose_folder`.
* :mod:`~jmocap.data.formats.coco`: COCO keypoint results (the ``loadRes`` list format) and
  COCO annotation files: :func:`read_coco_json`, :func:`write_coco_results`.
* :mod:`~jmocap.data.formats.mmpose`: MMPose 1.x inferencer predictions (``pred_out_dir``:
  video list of ``frame_id``/``instances``, single-image list of instances) and the ``demo/*``
  ``--save-predictions`` files (``meta_info`` + ``instance_info``): :func:`read_mmpose_json`,
  :func:`write_mmpose_json`.
* :mod:`~jmocap.data.formats.videopose3d`: VideoPose3D ``data_2d_<dataset>_<detector>.npz``:
  :func:`read_videopose3d`, :func:`iter_videopose3d`, :func:`write_videopose3d`.
* :mod:`~jmocap.data.formats.arrays`: plain arrays ``.npy`` / ``.npz`` of (T, J, 2|3)
  keypoints (Human3.6M-17 order by default): :func:`read_keypoint_array`.
* :mod:`~jmocap.data.formats.amass`: AMASS-style ``.npz`` with 3D joints (``joints`` or
  ``Jtr``): :func:`read_amass_joints`.
* :mod:`~jmocap.data.formats.camera_file`: the camera sidecar ``<clip>.camera.json``:
  :func:`read_camera_json`, :func:`write_camera_json`, :func:`sidecar_path`, :func:`find_sidecar`.
* jmocap clips (``.npz``, see :mod:`jmocap.data.clip`).

Shared by all of them: :mod:`~jmocap.data.formats.keypoints` (:class:`Keypoints2D`),
:mod:`~jmocap.data.formats.person` (:func:`select_person`),
:mod:`~jmocap.data.formats.common` (errors, JSON input, :func:`clean_keypoints`,
:func:`safe_name`) and :mod:`~jmocap.data.formats.safe_pickle` (pickled ``.npz`` members read
without running anything: :func:`load_npz_pickled`). This module dispatches on
the path: :func:`read_keypoints`, :func:`read_clip`.

Confidence handling, the same for every reader: a joint is *missing* (confidence 0, x = y = 0)
when its confidence is 0 or negative, when any of x, y, confidence is NaN/inf, or when its
coordinates are exactly (0, 0) (the "no detection" value of OpenPose and COCO). Confidences are
clipped to [0, 1] (some heatmap detectors report maxima slightly above 1).

Errors raise :class:`FormatError` (a ``ValueError``) naming the file, the frame and the field.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.clip import FORMAT as CLIP_FORMAT
from jmocap.data.clip import Clip, ClipFormatError, FormatError, load_clip
from jmocap.data.formats.amass import SMPL_JOINT_NAMES, Joints3D, read_amass_joints
from jmocap.data.formats.arrays import read_keypoint_array
from jmocap.data.formats.camera_file import (
    SIDECAR_KEYS,
    Y_UP_TO_Z_UP,
    camera_track_of,
    distort_normalized,
    find_sidecar,
    read_camera_json,
    rodrigues,
    sidecar_path,
    undistort_points,
    write_camera_json,
)
from jmocap.data.formats.coco import read_coco_json, write_coco_results
from jmocap.data.formats.common import _READ_ERRORS, _ferr, _load_json, clean_keypoints, safe_name
from jmocap.data.formats.imu_datasets import (
    DATASET_FPS,
    DIP_IMU_MASK,
    DIP_IMU_SENSORS,
    TOTALCAPTURE_DIP_MASK,
    read_dip_imu,
    read_imu,
    read_totalcapture_dip,
)
from jmocap.data.formats.keypoints import DEFAULT_FPS, Keypoints2D, undistort_keypoints
from jmocap.data.formats.mmpose import read_mmpose_json, write_mmpose_json
from jmocap.data.formats.openpose import (
    OPENPOSE_FILE_RE,
    OPENPOSE_VERSION,
    read_openpose_folder,
    write_openpose_folder,
)
from jmocap.data.formats.person import Candidate, select_person
from jmocap.data.formats.safe_pickle import (
    MAX_PICKLE_DEPTH,
    RestrictedUnpickler,
    load_npz_pickled,
    load_pickle_file,
    plain_data,
)
from jmocap.data.formats.videopose3d import (
    H36M_CAMERAS,
    H36M_FPS,
    iter_videopose3d,
    read_videopose3d,
    write_videopose3d,
)


def _json_kind(data) -> str:
    if isinstance(data, dict):
        if "people" in data:
            return "openpose"
        if "instance_info" in data:
            return "mmpose"
        if "annotations" in data:
            return "coco"
        return "unknown"
    if isinstance(data, list):
        if not data:
            return "empty"
        first = data[0]
        if isinstance(first, dict):
            if "image_id" in first:
                return "coco"
            if "instances" in first or "keypoint_scores" in first:
                return "mmpose"
    return "unknown"


def _npz_fields(path: Path) -> list[str]:
    """The array names of an ``.npz``, from its zip directory (nothing is decompressed or
    unpickled; numpy's loader would try a non-zip file as a pickle). FormatError when the file
    is not a zip."""
    try:
        with zipfile.ZipFile(path) as z:
            return [n.removesuffix(".npy") for n in z.namelist()]
    except (*_READ_ERRORS, zipfile.LargeZipFile) as e:
        raise _ferr(path, f"not a readable .npz file ({e})") from None


def read_keypoints(path: str | os.PathLike, **kwargs) -> Keypoints2D:
    """Read any supported 2D keypoint file or folder, dispatching on what ``path`` is.

    * a folder of ``*_keypoints.json`` files (or one such file): OpenPose;
    * a ``.json``: COCO results / annotations or MMPose predictions, by content;
    * an ``.npz``: VideoPose3D (has ``positions_2d``) or a keypoint array;
    * a ``.npy``: a keypoint array.

    ``kwargs`` go to the format's reader (e.g. ``person=``, ``layout=``, ``subject=``).
    jmocap clip files are read by :func:`read_clip`.
    """
    path = Path(path)
    if path.is_dir():
        return read_openpose_folder(path, **kwargs)
    if not path.exists():
        raise FileNotFoundError(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        if path.name.endswith("_keypoints.json"):
            return read_openpose_folder(path, **kwargs)
        kind = _json_kind(_load_json(path))
        if kind == "openpose":
            return read_openpose_folder(path, **kwargs)
        if kind == "coco":
            return read_coco_json(path, **kwargs)
        if kind == "mmpose":
            return read_mmpose_json(path, **kwargs)
        if kind == "empty":
            raise _ferr(path, "is an empty list: no detections in any frame")
        raise _ferr(
            path, "is not a recognised keypoint JSON (OpenPose, COCO results/annotations, MMPose)"
        )
    if suffix == ".npz":
        files = _npz_fields(path)
        if "format" in files:
            raise _ferr(path, "is a jmocap clip; use read_clip", field="format")
        if "positions_2d" in files:
            return read_videopose3d(path, **kwargs)
        return read_keypoint_array(path, **kwargs)
    if suffix == ".npy":
        return read_keypoint_array(path, **kwargs)
    raise _ferr(
        path, f"unknown keypoint file type {suffix!r} (expected a folder, .json, .npz or .npy)"
    )


def read_clip(
    path: str | os.PathLike,
    *,
    fps: float | None = None,
    image_size: Sequence[int] | None = None,
    intrinsics: Sequence[float] | None = None,
    extrinsics: np.ndarray | None = None,
    name: str | None = None,
    camera_json: str | os.PathLike | None = None,
    **reader_kwargs,
) -> Clip:
    """Read any supported file/folder as a :class:`Clip`.

    A jmocap clip ``.npz`` is loaded as is (:func:`~jmocap.data.clip.load_clip`); everything
    else goes through :func:`read_keypoints` and :meth:`Keypoints2D.to_clip`. The camera sidecar
    ``camera_json`` defaults to :func:`sidecar_path` (``<clip>.camera.json`` next to the file or
    folder; for a folder also ``<folder>/camera.json``) when it exists. Precedence: arguments,
    then sidecar, then the file's own values, then defaults (see :meth:`Keypoints2D.to_clip`).
    """
    path = Path(path)
    if camera_json is None:
        camera_json = find_sidecar(path)
    if path.suffix.lower() == ".npz" and path.is_file():
        if "format" in _npz_fields(path):
            clip = load_clip(path)
            side = read_camera_json(camera_json) if camera_json is not None else {}
            changes: dict[str, Any] = {}
            for key, arg in (
                ("fps", fps),
                ("image_size", image_size),
                ("intrinsics", intrinsics),
                ("extrinsics", extrinsics),
                ("height_m", None),
                ("mass_kg", None),
            ):
                v = arg if arg is not None else side.get(key)
                if v is not None:
                    changes[key] = v
            if extrinsics is None and side.get("camera_track") is not None:  # a moving camera
                changes["camera_track"] = camera_track_of(side, camera_json, clip.num_frames)
            elif "extrinsics" in changes:  # a static camera given for the clip: it replaces any track
                changes["camera_track"] = None
            if name is not None:
                changes["name"] = name
            if side.get("distortion") is not None:  # lens distortion: to the ideal pinhole's pixels
                from jmocap.data.formats.keypoints import undistort_keypoints

                intr = changes.get("intrinsics", clip.intrinsics)
                changes["keypoints"] = undistort_keypoints(clip.keypoints, intr, side["distortion"])
                changes["meta"] = {**clip.meta, "undistorted": [float(v) for v in side["distortion"]]}
            return clip.replace(**changes) if changes else clip
    kp = read_keypoints(path, **reader_kwargs)
    return kp.to_clip(
        fps=fps,
        image_size=image_size,
        intrinsics=intrinsics,
        extrinsics=extrinsics,
        name=name,
        camera_json=camera_json,
    )


__all__ = [
    "camera_track_of",
    "Candidate",
    "clean_keypoints",
    "CLIP_FORMAT",
    "DATASET_FPS",
    "ClipFormatError",
    "DEFAULT_FPS",
    "DIP_IMU_MASK",
    "DIP_IMU_SENSORS",
    "distort_normalized",
    "find_sidecar",
    "FormatError",
    "H36M_CAMERAS",
    "H36M_FPS",
    "iter_videopose3d",
    "Joints3D",
    "Keypoints2D",
    "load_npz_pickled",
    "load_pickle_file",
    "MAX_PICKLE_DEPTH",
    "OPENPOSE_FILE_RE",
    "OPENPOSE_VERSION",
    "plain_data",
    "read_amass_joints",
    "read_camera_json",
    "read_clip",
    "read_coco_json",
    "read_dip_imu",
    "read_imu",
    "read_keypoint_array",
    "read_keypoints",
    "read_mmpose_json",
    "read_openpose_folder",
    "read_totalcapture_dip",
    "read_videopose3d",
    "RestrictedUnpickler",
    "rodrigues",
    "safe_name",
    "select_person",
    "SIDECAR_KEYS",
    "sidecar_path",
    "SMPL_JOINT_NAMES",
    "TOTALCAPTURE_DIP_MASK",
    "undistort_keypoints",
    "undistort_points",
    "write_camera_json",
    "write_coco_results",
    "write_mmpose_json",
    "write_openpose_folder",
    "write_videopose3d",
    "Y_UP_TO_Z_UP",
]
