"""Readers of the public IMU datasets PIP and TransPose use, into :class:`~jmocap.data.imu.IMUClip`.

* **DIP-IMU** (Huang et al. 2018), one Python-2 pickle per sequence (``s_01/01.pkl`` ...): a dict
  with ``imu_ori`` (T, 17, 3, 3), ``imu_acc`` (T, 17, 3) and ``gt`` (T, 72) SMPL pose
  (axis-angle), at 60 Hz. Its 17 sensors are, in order, :data:`DIP_IMU_SENSORS`; PIP and
  TransPose take :data:`DIP_IMU_MASK` = 7, 8, 11, 12, 0, 2 (left / right lower arm, left /
  right lower leg, head, pelvis), jmocap's :data:`~jmocap.data.imu.SENSORS` order. Source:
  ``imu_mask = [7, 8, 11, 12, 0, 2]`` in ``process_dipimu`` of ``preprocess.py`` in
  github.com/Xinyu-Yi/TransPose and github.com/Xinyu-Yi/PIP.
* **TotalCapture** (Trumble et al. 2017) as preprocessed in DIP's format (DIP's download
  ``TotalCapture_Real_60FPS``): one pickle per sequence with ``ori`` (T, 6, 3, 3), ``acc``
  (T, 6, 3) and ``gt`` (T, 72), its six sensors stored as left lower leg, right lower leg, left
  forearm, right forearm, head, pelvis; PIP / TransPose reorder them with
  :data:`TOTALCAPTURE_DIP_MASK` = 2, 3, 0, 1, 4, 5 (``process_totalcapture`` in the same files).

Both store orientations already calibrated to the bones (TransPose / PIP feed them to their
networks as bone orientations, as their synthetic data's joint rotations) and free
accelerations (gravity removed), both in SMPL's world (y up). So the clip's calibration is
``world_from_inertial = bone_from_sensor = SMPL_TO_JMOCAP`` (SMPL's axes x left, y up,
z forward -> jmocap's y, z, x): :meth:`IMUClip.calibrated` then gives the bones in jmocap's world
and in the frames of jmocap's bodies (``R_WB = M R M^T``). ``gt`` becomes ``gt_smpl_pose`` as
stored (SMPL's world). PIP also removes a constant per-sequence accelerometer bias from
TotalCapture by comparing with accelerations synthesised on the SMPL mesh; that needs the SMPL
body model, which jmocap does not ship, so it is not done here (``meta["note"]`` says so).

Nothing is unpickled as such: the files are read by :func:`~jmocap.data.formats.safe_pickle.
load_pickle_file` (numpy arrays, dicts, strings and numbers only; a crafted pickle cannot run
code). Dropouts (NaN readings; DIP-IMU has them) are filled by the gap rule of
:func:`jmocap.data.imu.readings_with_gaps` or refused (``gaps="error"``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.data.formats.safe_pickle import load_pickle_file
from jmocap.data.imu import (
    DEFAULT_MAX_GAP,
    NUM_SENSORS,
    SMPL_TO_JMOCAP,
    IMUClip,
    IMUClipFormatError,
    is_imu_clip_file,
    load_imu_clip,
    read_imu_json,
    readings_with_gaps,
)
from jmocap.data.limits import FormatError

DIP_IMU_SENSORS = ("head", "sternum", "pelvis", "lshoulder", "rshoulder", "lupperarm", "rupperarm",
                   "llowerarm", "rlowerarm", "lupperleg", "rupperleg", "llowerleg", "rlowerleg", "lhand",
                   "rhand", "lfoot", "rfoot")
#: DIP-IMU's sensors of jmocap's six (TransPose / PIP ``imu_mask``)
DIP_IMU_MASK = (7, 8, 11, 12, 0, 2)
#: TotalCapture (DIP's format) -> jmocap's order (TransPose / PIP ``process_totalcapture``)
TOTALCAPTURE_DIP_MASK = (2, 3, 0, 1, 4, 5)
#: frame rate of both datasets as DIP distributes them
DATASET_FPS = 60.0

_SOURCE = "github.com/Xinyu-Yi/TransPose and github.com/Xinyu-Yi/PIP, preprocess.py"


def _array(doc: dict, key: str, where: str) -> np.ndarray:
    if key not in doc:
        raise IMUClipFormatError(f"{where}: missing field {key!r} (keys: {sorted(map(str, doc))[:12]})")
    a = doc[key]
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "iuf":
        raise IMUClipFormatError(f"{where}: field {key!r} must be a numeric array, got "
                                 f"{getattr(a, 'dtype', type(a).__name__)}")
    return a.astype(np.float64)


def _read_dip_format(path, ori_key: str, acc_key: str, n_source: int, mask: tuple[int, ...], dataset: str,
                     *, name, fps, gaps, max_gap, ground_truth) -> IMUClip:
    path = Path(path)
    where = str(path)
    doc = load_pickle_file(path, where, field="pickle")
    if not isinstance(doc, dict):
        raise IMUClipFormatError(f"{where}: expected a pickled dict ({dataset}), got {type(doc).__name__}")
    doc = {(k.decode("latin-1") if isinstance(k, bytes) else k): v for k, v in doc.items()}
    ori = _array(doc, ori_key, where)
    acc = _array(doc, acc_key, where)
    if ori.ndim == 3 and ori.shape[2] == 9:
        ori = ori.reshape(ori.shape[0], ori.shape[1], 3, 3)
    if ori.ndim != 4 or ori.shape[1:] != (n_source, 3, 3):
        raise IMUClipFormatError(f"{where}: field {ori_key!r} must have shape (T, {n_source}, 3, 3) ({dataset}), "
                                 f"got {ori.shape}")
    if acc.shape != (ori.shape[0], n_source, 3):
        raise IMUClipFormatError(f"{where}: field {acc_key!r} must have shape ({ori.shape[0]}, {n_source}, 3) "
                                 f"({dataset}; T as {ori_key!r}), got {acc.shape}")
    if ori.shape[0] == 0:
        raise IMUClipFormatError(f"{where}: contains no frames")
    ori, acc = ori[:, list(mask)], acc[:, list(mask)]
    meta: dict[str, Any] = {
        "dataset": dataset, "source": where, "source_sensor_indices": list(mask),
        "sensor_indices_from": _SOURCE,
        "frames": "orientations of the bones and free accelerations in SMPL's world (y up); "
                  "calibration maps both to jmocap's",
    }
    gt = None
    if ground_truth and "gt" in doc:
        gt = _array(doc, "gt", where)
        if gt.ndim == 3 and gt.shape[1:] == (24, 3):
            gt = gt.reshape(len(gt), 72)
        if gt.ndim != 2 or gt.shape[1] != 72:
            raise IMUClipFormatError(f"{where}: field 'gt' must have shape (T, 72) (SMPL axis-angle), got {gt.shape}")
        if len(gt) != len(ori):  # TransPose / PIP cut both to the shorter (TotalCapture's differ)
            n = min(len(gt), len(ori))
            meta["truncated"] = {"imu_frames": int(len(ori)), "gt_frames": int(len(gt)), "kept": int(n)}
            ori, acc, gt = ori[:n], acc[:n], gt[:n]
        bad = ~np.isfinite(gt).all(axis=1)
        if bad.any():
            raise IMUClipFormatError(f"{where}: field 'gt' has non-finite values, first at frame "
                                     f"{int(np.argmax(bad))} (ground_truth=False reads the IMU data alone)")
    src = (ori_key, acc_key)
    ori, acc, filled, gap_meta = readings_with_gaps(ori, acc, where, gaps, max_gap, fields=src)
    meta.update(gap_meta)
    if dataset == "TotalCapture":
        meta["note"] = ("accelerations as distributed: PIP removes a constant per-sequence bias against "
                        "SMPL-synthesised accelerations, which needs the SMPL model (not done)")
    M = SMPL_TO_JMOCAP
    name = name or path.stem
    try:
        return IMUClip(
            name=name, fps=fps, ori=ori, acc=acc, filled=filled,
            world_from_inertial=M, bone_from_sensor=np.tile(M, (NUM_SENSORS, 1, 1)),
            gt_smpl_pose=gt, meta=meta,
        )
    except FormatError as e:
        raise type(e)(f"{where}: {str(e).removeprefix(f'IMU clip {name!r}: ')}") from None


def read_dip_imu(path: str | os.PathLike, *, name: str | None = None, fps: float = DATASET_FPS,
                 gaps: str = "fill", max_gap: int = DEFAULT_MAX_GAP, ground_truth: bool = True) -> IMUClip:
    """One DIP-IMU sequence (``s_XX/NN.pkl``): the six sensors of :data:`DIP_IMU_MASK`, the SMPL
    pose ``gt`` as ``gt_smpl_pose`` (``ground_truth=False`` leaves it out). Dropouts (NaN) are
    filled (``gaps="fill"``, at most ``max_gap`` frames in a row) or refused (``gaps="error"``);
    ``meta["gaps"]`` and ``clip.filled`` say where."""
    return _read_dip_format(path, "imu_ori", "imu_acc", len(DIP_IMU_SENSORS), DIP_IMU_MASK, "DIP-IMU",
                            name=name, fps=fps, gaps=gaps, max_gap=max_gap, ground_truth=ground_truth)


def read_totalcapture_dip(path: str | os.PathLike, *, name: str | None = None, fps: float = DATASET_FPS,
                          gaps: str = "fill", max_gap: int = DEFAULT_MAX_GAP,
                          ground_truth: bool = True) -> IMUClip:
    """One TotalCapture sequence in DIP's format (``ori``, ``acc``, ``gt``), sensors reordered by
    :data:`TOTALCAPTURE_DIP_MASK`; a ``gt`` of another length than the readings cuts both to the
    shorter (as TransPose / PIP do; ``meta["truncated"]``)."""
    return _read_dip_format(path, "ori", "acc", NUM_SENSORS, TOTALCAPTURE_DIP_MASK, "TotalCapture",
                            name=name, fps=fps, gaps=gaps, max_gap=max_gap, ground_truth=ground_truth)


def read_imu(path: str | os.PathLike, **kw) -> IMUClip:
    """An IMU clip from any supported file: a ``jmocap-imu-clip-1`` ``.npz``, the JSON layout,
    or a DIP-IMU / TotalCapture (DIP format) pickle (``.pkl``, told apart by their keys)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        if kw:
            raise TypeError(f"read_imu: a .npz IMU clip takes no options, got {sorted(kw)}")
        if not is_imu_clip_file(path):
            raise IMUClipFormatError(f"{path}: not a jmocap-imu-clip-1 .npz")
        return load_imu_clip(path)
    if suffix == ".json":
        return read_imu_json(path, **kw)
    if suffix in (".pkl", ".pickle"):
        doc = load_pickle_file(path, str(path), field="pickle")
        keys = set(doc) if isinstance(doc, dict) else set()
        keys = {k.decode("latin-1") if isinstance(k, bytes) else k for k in keys}
        if {"imu_ori", "imu_acc"} <= keys:
            return read_dip_imu(path, **kw)
        if {"ori", "acc"} <= keys:
            return read_totalcapture_dip(path, **kw)
        raise IMUClipFormatError(f"{path}: not a DIP-IMU ('imu_ori', 'imu_acc') or TotalCapture ('ori', 'acc') "
                                 f"pickle")
    raise IMUClipFormatError(f"{path}: not an IMU file jmocap reads (.npz, .json, .pkl)")


__all__ = [
    "DATASET_FPS",
    "DIP_IMU_MASK",
    "DIP_IMU_SENSORS",
    "TOTALCAPTURE_DIP_MASK",
    "read_dip_imu",
    "read_imu",
    "read_totalcapture_dip",
]
