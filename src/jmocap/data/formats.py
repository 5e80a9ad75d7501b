"""Readers and writers of 2D keypoint formats (and one 3D reference format).

Readers return a :class:`Keypoints2D` (keypoints + layout + whatever the file says about the
video: fps, image size, camera); :meth:`Keypoints2D.to_clip` (or :func:`read_clip`, which also
dispatches on the path) turns it into a :class:`~jmocap.data.clip.Clip` with a camera.

Supported formats (details, joint orders and examples in ``docs/formats.md``):

* OpenPose ``--write_json`` folders (JSON ``version`` 1.3 files, BODY_25 model):
  :func:`read_openpose_folder`, :func:`write_openpose_folder`.
* COCO keypoint results (the ``loadRes`` list format) and COCO annotation files:
  :func:`read_coco_json`, :func:`write_coco_results`.
* MMPose 1.x inferencer predictions (``pred_out_dir``: video list of ``frame_id``/``instances``,
  single-image list of instances) and the ``demo/*`` ``--save-predictions`` files
  (``meta_info`` + ``instance_info``): :func:`read_mmpose_json`, :func:`write_mmpose_json`.
* VideoPose3D ``data_2d_<dataset>_<detector>.npz``: :func:`read_videopose3d`,
  :func:`iter_videopose3d`.
* Plain arrays ``.npy`` / ``.npz`` of (T, J, 2|3) keypoints (Human3.6M-17 order by default):
  :func:`read_keypoint_array`.
* AMASS-style ``.npz`` with 3D joints (``joints`` or ``Jtr``): :func:`read_amass_joints`.
* jmocap clips (``.npz``, see :mod:`jmocap.data.clip`).

Confidence handling, the same for every reader: a joint is *missing* (confidence 0, x = y = 0)
when its confidence is 0 or negative, when any of x, y, confidence is NaN/inf, or when its
coordinates are exactly (0, 0) (the "no detection" value of OpenPose and COCO). Confidences are
clipped to [0, 1] (some heatmap detectors report maxima slightly above 1).

Errors raise :class:`FormatError` (a ``ValueError``) naming the file, the frame and the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pickle
import re
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jmocap.camera import default_intrinsics
from jmocap.data.clip import FORMAT as CLIP_FORMAT
from jmocap.data.clip import Clip, ClipFormatError, FormatError, load_clip
from jmocap.layouts import get_layout

DEFAULT_FPS = 30.0

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

# SMPL body joint names (AMASS ``Jtr`` order; SMPL-H/X continue with hand joints after 22)
SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)


# --------------------------------------------------------------------------------------------
# Keypoints2D: what a reader returns
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Keypoints2D:
    """2D keypoints read from a file, plus what the file says about the video.

    ``keypoints`` (T, J, 3) float32 ``x, y`` pixels and confidence in [0, 1] (0 = missing, then
    x = y = 0); ``frame_ids`` (T,) the source frame numbers (consecutive: gaps in the source are
    filled with missing frames); ``fps``, ``image_size``, ``intrinsics``, ``extrinsics`` are
    ``None`` when the file does not say.
    """

    keypoints: np.ndarray
    layout: str
    name: str
    frame_ids: np.ndarray
    fps: float | None = None
    image_size: tuple[int, int] | None = None
    intrinsics: np.ndarray | None = None
    extrinsics: np.ndarray | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    def replace(self, **changes) -> Keypoints2D:
        return dataclasses.replace(self, **changes)

    def to_clip(
        self,
        *,
        fps: float | None = None,
        image_size: Sequence[int] | None = None,
        intrinsics: Sequence[float] | None = None,
        extrinsics: np.ndarray | None = None,
        name: str | None = None,
        camera_json: str | os.PathLike | None = None,
    ) -> Clip:
        """A :class:`Clip`; arguments override the file's own values.

        Precedence for each of fps / image size / intrinsics / extrinsics: the argument, then
        ``camera_json`` (a sidecar, see :func:`read_camera_json`), then the file's own value,
        then the default: ``fps`` 30 (:data:`DEFAULT_FPS`), intrinsics
        :func:`jmocap.camera.default_intrinsics` (f = 1000 px, principal point at the image
        centre), no extrinsics. There is no default image size: without one a
        :class:`FormatError` asks for it. Defaults that were used are listed in
        ``clip.meta["assumed"]``.
        """
        side = read_camera_json(camera_json) if camera_json is not None else {}
        where = self.source or self.name
        assumed = []

        def pick(arg, key, own):
            if arg is not None:
                return arg
            if side.get(key) is not None:
                return side[key]
            return own

        size = pick(image_size, "image_size", self.image_size)
        if size is None:
            raise FormatError(
                f"{where}: no image size: the format does not store one; pass image_size=(width, "
                f"height) or write a sidecar camera file {sidecar_path(where).name if self.source else '<clip>.camera.json'}"
            )
        size = tuple(int(v) for v in size)
        intr = pick(intrinsics, "intrinsics", self.intrinsics)
        if intr is None:
            intr = default_intrinsics(*size)
            assumed.append("intrinsics")
        extr = pick(extrinsics, "extrinsics", self.extrinsics)
        f = pick(fps, "fps", self.fps)
        if f is None:
            f = DEFAULT_FPS
            assumed.append("fps")
        meta = dict(self.meta)
        meta.setdefault("source", self.source)
        meta["first_frame"] = int(self.frame_ids[0]) if len(self.frame_ids) else 0
        if assumed:
            meta["assumed"] = assumed
        return Clip(
            name=name if name is not None else self.name,
            layout=self.layout,
            fps=float(f),
            keypoints=self.keypoints,
            intrinsics=np.asarray(intr, np.float64),
            image_size=np.asarray(size),
            extrinsics=None if extr is None else np.asarray(extr, np.float64),
            meta=meta,
        )


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


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
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


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


# --------------------------------------------------------------------------------------------
# person selection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidate:
    """One detected person in one frame: cleaned (J, 3) keypoints, a score, optional track id."""

    keypoints: np.ndarray
    score: float
    track_id: int | None = None


def _pose_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance of joints visible in both poses, in units of ``b``'s bounding-box diagonal.

    1.0 (the cap) when they share no visible joint.
    """
    common = (a[:, 2] > 0) & (b[:, 2] > 0)
    vis_b = b[:, 2] > 0
    if not common.any():
        return 1.0
    pts = b[vis_b, :2]
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) if len(pts) > 1 else 0.0
    scale = max(diag, 1.0)
    d = float(np.mean(np.linalg.norm(a[common, :2] - b[common, :2], axis=-1))) / scale
    return min(d, 1.0)


def select_person(
    frames: Sequence[Sequence[Candidate]], num_joints: int, mode: str = "track"
) -> tuple[np.ndarray, np.ndarray]:
    """Pick one person per frame; returns ((T, J, 3) keypoints, (T,) picked index or -1).

    ``mode="best"``: the highest-scoring person of each frame, independently.

    ``mode="track"`` (default): the first frame with anyone picks the highest score; later
    frames keep following the last picked person:

    1. if the last pick had a tracker id (OpenPose ``person_id``, MMPose ``track_id``) and a
       candidate has the same id, that candidate;
    2. otherwise the candidate minimising ``d - 0.5 * score / max_score``, where ``d`` is the
       mean image distance of the joints visible in both poses, divided by the bounding-box
       diagonal of the last pick and capped at 1 (1 also when no joint is shared).

    The last pick is kept across frames where nobody is detected. Frames with no candidate
    are all-missing (confidence 0).
    """
    if mode not in ("track", "best"):
        raise ValueError(f"person selection mode must be 'track' or 'best', got {mode!r}")
    T = len(frames)
    out = np.zeros((T, num_joints, 3), np.float32)
    picked = np.full(T, -1, np.int64)
    prev: Candidate | None = None
    for t, cands in enumerate(frames):
        if not cands:
            continue
        scores = np.array([c.score for c in cands], dtype=np.float64)
        if mode == "best" or prev is None:
            i = int(np.argmax(scores))
        else:
            i = -1
            if prev.track_id is not None:
                same = [k for k, c in enumerate(cands) if c.track_id == prev.track_id]
                if same:
                    i = max(same, key=lambda k: scores[k])
            if i < 0:
                smax = scores.max() if scores.max() > 0 else 1.0
                cost = [
                    _pose_distance(c.keypoints, prev.keypoints) - 0.5 * s / smax
                    for c, s in zip(cands, scores, strict=True)
                ]
                i = int(np.argmin(cost))
        out[t] = cands[i].keypoints
        picked[t] = i
        prev = cands[i]
    return out, picked


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


# --------------------------------------------------------------------------------------------
# OpenPose
# --------------------------------------------------------------------------------------------

OPENPOSE_FILE_RE = re.compile(r"^(?P<name>.*?)_?(?P<frame>\d+)_keypoints\.json$")
OPENPOSE_VERSION = 1.3


def _openpose_people(data, path, frame, J, layout_desc) -> list[Candidate]:
    if not isinstance(data, dict) or "people" not in data:
        raise _ferr(path, "not an OpenPose keypoints file (no 'people' list)", frame, "people")
    people = data["people"]
    if not isinstance(people, list):
        raise _ferr(path, f"must be a list, got {type(people).__name__}", frame, "people")
    cands = []
    for p, person in enumerate(people):
        fname = f"people[{p}].pose_keypoints_2d"
        if not isinstance(person, dict) or "pose_keypoints_2d" not in person:
            raise _ferr(path, "missing", frame, fname)
        values = person["pose_keypoints_2d"]
        if isinstance(values, list) and len(values) == 0:
            continue  # body not requested / not found for this person
        kp = clean_keypoints(_flat_triplets(values, J, path, frame, fname, layout_desc))
        if not (kp[:, 2] > 0).any():
            continue
        pid = person.get("person_id", -1)
        if isinstance(pid, list):
            pid = pid[0] if pid else -1
        track = int(pid) if isinstance(pid, (int, float)) and pid >= 0 else None
        cands.append(Candidate(kp, float(kp[:, 2].sum()) / J, track))
    return cands


def read_openpose_folder(
    folder: str | os.PathLike, *, person: str = "track", name: str | None = None
) -> Keypoints2D:
    """Read an OpenPose ``--write_json`` folder (BODY_25 model, JSON version 1.x).

    Files ``<video>_<frame:012d>_keypoints.json`` are ordered by the frame number in the file
    name (gaps become all-missing frames); ``people[*].pose_keypoints_2d`` is the flat
    ``[x, y, c] * 25`` BODY_25 list. One person per frame is chosen by :func:`select_person`
    (``person="track"`` or ``"best"``); a frame with nobody is all-missing. OpenPose stores no
    fps, image size or camera. A single ``*_keypoints.json`` file is read as a one-frame clip.
    """
    folder = Path(folder)
    layout = get_layout("body25")
    if folder.is_file():
        files = [folder]
    elif folder.is_dir():
        files = sorted(p for p in folder.iterdir() if p.name.endswith("_keypoints.json"))
    else:
        raise FileNotFoundError(folder)
    if not files:
        raise _ferr(folder, "contains no OpenPose '*_keypoints.json' files")
    ids, per_frame, prefixes = [], [], set()
    for p in files:
        m = OPENPOSE_FILE_RE.match(p.name)
        if not m:
            raise _ferr(p, "file name does not end in '_<frame number>_keypoints.json'")
        frame = int(m.group("frame"))
        prefixes.add(m.group("name"))
        data = _load_json(p, frame)
        per_frame.append(_openpose_people(data, p, frame, layout.num_joints, "BODY_25"))
        ids.append(frame)
    frame_ids, per_frame = _fill_gaps(ids, per_frame, folder, [])
    kp, picked = select_person(per_frame, layout.num_joints, person)
    if name is None:
        name = prefixes.pop() if len(prefixes) == 1 and next(iter(prefixes)) else folder.stem
    return Keypoints2D(
        keypoints=kp,
        layout="body25",
        name=name,
        frame_ids=frame_ids,
        source=str(folder),
        meta={
            "format": "openpose",
            "person_selection": person,
            "max_people": int(max((len(c) for c in per_frame), default=0)),
        },
    )


def _openpose_frame_json(kp: np.ndarray | None) -> str:
    people = []
    if kp is not None:
        flat = [float(v) for v in np.asarray(kp, np.float32).reshape(-1)]
        people.append(
            {
                "person_id": [-1],
                "pose_keypoints_2d": flat,
                "face_keypoints_2d": [],
                "hand_left_keypoints_2d": [],
                "hand_right_keypoints_2d": [],
                "pose_keypoints_3d": [],
                "face_keypoints_3d": [],
                "hand_left_keypoints_3d": [],
                "hand_right_keypoints_3d": [],
            }
        )
    return json.dumps({"version": OPENPOSE_VERSION, "people": people})


def write_openpose_folder(
    clip: Clip | Keypoints2D,
    folder: str | os.PathLike,
    *,
    name: str | None = None,
    first_frame: int = 0,
    write_camera: bool = True,
) -> Path:
    """Write a BODY_25 clip as an OpenPose ``--write_json`` folder (as if from the detector).

    One file ``<name>_<frame:012d>_keypoints.json`` per frame (frame numbers from
    ``first_frame``), JSON ``{"version": 1.3, "people": [...]}`` with one person carrying
    ``pose_keypoints_2d`` (missing joints 0, 0, 0) and the empty face/hand/3D arrays OpenPose
    writes when those are disabled; a frame with no visible joint has ``"people": []``. Each
    file is written atomically. With ``write_camera`` (and a :class:`Clip`), the camera and fps
    go to the sidecar ``<folder>.camera.json``.
    """
    if clip.layout != "body25":
        raise ValueError(f"OpenPose BODY_25 output needs a body25 clip, got layout {clip.layout!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    name = clip.name if name is None else name
    kp = np.asarray(clip.keypoints, np.float32)
    for t in range(kp.shape[0]):
        frame_kp = kp[t].copy()
        frame_kp[frame_kp[:, 2] <= 0] = 0.0
        visible = (frame_kp[:, 2] > 0).any()
        _atomic_write_text(
            folder / f"{name}_{first_frame + t:012d}_keypoints.json",
            _openpose_frame_json(frame_kp if visible else None),
        )
    if write_camera and isinstance(clip, Clip):
        write_camera_json(sidecar_path(folder), clip)
    return folder


# --------------------------------------------------------------------------------------------
# COCO
# --------------------------------------------------------------------------------------------


def _frame_index(image_ids, frame_of, path):
    if frame_of is None:
        bad = [i for i in image_ids if not isinstance(i, int) or isinstance(i, bool)]
        if bad:
            raise _ferr(
                path,
                f"image_id {bad[0]!r} is not an integer; pass frame_of= to map image ids to frames",
                field="image_id",
            )
        return list(image_ids)
    out = []
    for i in image_ids:
        try:
            f = frame_of(i) if callable(frame_of) else frame_of[i]
        except (KeyError, IndexError):
            raise _ferr(
                path, f"image_id {i!r} is not in the frame_of mapping", field="image_id"
            ) from None
        out.append(int(f))
    return out


def _group_frames(path, frame_ids, cands_by_entry, fill_from_zero):
    by_frame: dict[int, list[Candidate]] = {}
    for f, c in zip(frame_ids, cands_by_entry, strict=True):
        by_frame.setdefault(f, [])
        if c is not None:
            by_frame[f].append(c)
    ids = sorted(by_frame)
    if not ids:
        return np.zeros(0, np.int64), []
    if fill_from_zero and ids[0] > 0:
        by_frame.setdefault(0, [])
        ids = [0] + ids
    return _fill_gaps(ids, [by_frame[i] for i in ids], path, [])


def read_coco_json(
    path: str | os.PathLike,
    *,
    frame_of: Mapping | Callable | None = None,
    person: str = "track",
    name: str | None = None,
    layout: str = "coco17",
) -> Keypoints2D:
    """Read COCO-17 keypoints: a results list or an annotation file.

    * Results (what ``COCO.loadRes`` / COCO keypoint evaluation read): a JSON list of
      ``{"image_id": int, "category_id": 1, "keypoints": [x, y, v] * 17, "score": float}``;
      ``v`` is the keypoint confidence. Several entries per image are several people
      (:func:`select_person`, score = ``score``).
    * Annotations (``person_keypoints_*.json``): a dict with ``images`` and ``annotations``;
      ``v`` is the visibility flag (0 not labelled, 1 labelled but occluded, 2 visible): v > 0
      gives confidence 1. The frame order is the ``images`` order unless ``frame_of`` is given.

    Frames: by default the image id *is* the frame number (ids are integers, the clip spans the
    smallest to the largest id present, gaps become missing frames); ``frame_of`` (a mapping or
    a function image_id -> frame number) overrides this. ``category_id`` other than 1 (person)
    is skipped. No fps, image size or camera is stored (COCO image entries' ``width``/``height``
    are used when present and all equal).
    """
    path = Path(path)
    data = _load_json(path)
    J = get_layout(layout).num_joints
    image_size = None
    if isinstance(data, dict) and "annotations" in data:
        entries = data["annotations"]
        kind = "coco_annotations"
        images = data.get("images") or []
        if frame_of is None and images:
            order = {
                img["id"]: k
                for k, img in enumerate(images)
                if isinstance(img, dict) and "id" in img
            }
            frame_of = order
        sizes = {(img.get("width"), img.get("height")) for img in images if isinstance(img, dict)}
        if len(sizes) == 1:
            w, h = sizes.pop()
            if isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0:
                image_size = (w, h)
    elif isinstance(data, list):
        entries = data
        kind = "coco_results"
    else:
        raise _ferr(path, "not a COCO keypoint results list or annotation file")
    if not isinstance(entries, list):
        raise _ferr(path, "must be a list", field="annotations")
    image_ids, cands = [], []
    for k, e in enumerate(entries):
        if not isinstance(e, dict) or "image_id" not in e:
            raise _ferr(path, f"entry {k} has no 'image_id'", field="image_id")
        image_ids.append(e["image_id"])
    frames = _frame_index(image_ids, frame_of, path)
    for k, (e, f) in enumerate(zip(entries, frames, strict=True)):
        if e.get("category_id", 1) != 1:
            cands.append(None)
            continue
        if "keypoints" not in e:
            raise _ferr(path, f"entry {k} has no keypoints", f, "keypoints")
        kp = _flat_triplets(e["keypoints"], J, path, f, f"[{k}].keypoints", f"COCO-{J}")
        if kind == "coco_annotations":
            vis = np.nan_to_num(kp[:, 2]) > 0
            kp[:, 2] = vis.astype(np.float64)
            score = float(vis.sum()) / J
        else:
            score = e.get("score")
            if score is None:
                score = float(np.nanmean(np.clip(kp[:, 2], 0, 1)))
            try:
                score = float(score)
            except (TypeError, ValueError):
                raise _ferr(
                    path, f"entry {k}: score {score!r} is not a number", f, "score"
                ) from None
        kp = clean_keypoints(kp)
        track = e.get("track_id")
        cands.append(
            Candidate(
                kp,
                score if np.isfinite(score) else 0.0,
                int(track) if isinstance(track, int) and track >= 0 else None,
            )
            if (kp[:, 2] > 0).any()
            else None
        )
    frame_ids, per_frame = _group_frames(path, frames, cands, fill_from_zero=False)
    _check_nonempty(path, len(frame_ids))
    kp, _ = select_person(per_frame, J, person)
    return Keypoints2D(
        keypoints=kp,
        layout=layout,
        name=name or path.stem,
        frame_ids=frame_ids,
        image_size=image_size,
        source=str(path),
        meta={"format": kind, "person_selection": person},
    )


def write_coco_results(
    clip: Clip | Keypoints2D, path: str | os.PathLike, *, first_image_id: int = 0
) -> Path:
    """Write a coco17 clip as a COCO keypoint results list (image_id = first_image_id + frame).

    ``keypoints`` is ``[x, y, confidence] * 17`` (missing joints 0, 0, 0) and ``score`` the mean
    confidence of the visible joints; frames with no visible joint are left out, as a detector
    with no detection would.
    """
    if clip.layout != "coco17":
        raise ValueError(f"COCO results need a coco17 clip, got layout {clip.layout!r}")
    out = []
    for t, kp in enumerate(np.asarray(clip.keypoints, np.float32)):
        vis = kp[:, 2] > 0
        if not vis.any():
            continue
        kp = kp.copy()
        kp[~vis] = 0.0
        out.append(
            {
                "image_id": first_image_id + t,
                "category_id": 1,
                "keypoints": [float(v) for v in kp.reshape(-1)],
                "score": float(kp[vis, 2].mean()),
            }
        )
    path = Path(path)
    _atomic_write_text(path, json.dumps(out))
    return path


# --------------------------------------------------------------------------------------------
# MMPose
# --------------------------------------------------------------------------------------------


def _mmpose_instance(inst, path, frame, fieldname, J) -> Candidate | None:
    if not isinstance(inst, dict) or "keypoints" not in inst:
        raise _ferr(path, "instance has no 'keypoints'", frame, fieldname)
    try:
        xy = np.array(inst["keypoints"], dtype=np.float64)
    except (TypeError, ValueError):
        raise _ferr(
            path, "is not a (K, 2) list of numbers", frame, fieldname + ".keypoints"
        ) from None
    if xy.ndim == 3 and xy.shape[0] == 1:  # some versions keep a leading instance axis
        xy = xy[0]
    if xy.ndim != 2 or xy.shape != (J, 2):
        raise _ferr(
            path,
            f"has shape {xy.shape}, expected ({J}, 2) (2D predictions; 3D ones are not supported)",
            frame,
            fieldname + ".keypoints",
        )
    scores = inst.get("keypoint_scores")
    if scores is None:
        sc = np.ones(J)
    else:
        try:
            sc = np.array(scores, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise _ferr(
                path, "is not a list of numbers", frame, fieldname + ".keypoint_scores"
            ) from None
        if sc.shape != (J,):
            raise _ferr(
                path, f"has {sc.size} values, expected {J}", frame, fieldname + ".keypoint_scores"
            )
    kp = clean_keypoints(np.concatenate([xy[:, :2], sc[:, None]], axis=1))
    if not (kp[:, 2] > 0).any():
        return None
    score = inst.get("bbox_score")
    if isinstance(score, list):
        score = score[0] if score else None
    if not isinstance(score, (int, float)) or not np.isfinite(score):
        score = float(kp[:, 2].sum()) / J
    track = inst.get("track_id")
    return Candidate(
        kp, float(score), int(track) if isinstance(track, int) and track >= 0 else None
    )


def read_mmpose_json(
    path: str | os.PathLike,
    *,
    layout: str = "coco17",
    person: str = "track",
    name: str | None = None,
) -> Keypoints2D:
    """Read MMPose (1.x) 2D predictions.

    Accepted layouts of the JSON (``MMPoseInferencer(..., pred_out_dir=...)`` and the
    ``demo/*.py --save-predictions`` scripts of MMPose 1.0 - 1.3):

    * video: ``[{"frame_id": int, "instances": [inst, ...]}, ...]``;
    * demo scripts: ``{"meta_info": {...}, "instance_info": [<the video list above>]}``;
    * single image: ``[inst, ...]`` (a one-frame clip);

    with ``inst = {"keypoints": [[x, y]] * K, "keypoint_scores": [s] * K, "bbox": ...,
    "bbox_score": s}`` (``track_id`` used when present). ``K`` must match ``layout`` (17 for the
    default COCO-trained models; pass ``layout="h36m17"`` for Human3.6M-trained 2D models).
    The person score is ``bbox_score`` (else the mean keypoint score); one person per frame is
    chosen by :func:`select_person`. No fps, image size or camera is stored.
    """
    path = Path(path)
    data = _load_json(path)
    J = get_layout(layout).num_joints
    kind = "mmpose"
    if isinstance(data, dict) and "instance_info" in data:
        data = data["instance_info"]
        kind = "mmpose_demo"
    if not isinstance(data, list):
        raise _ferr(path, "not an MMPose prediction file (expected a list of frames or instances)")
    if data and all(isinstance(d, dict) and "instances" in d for d in data):
        frames, cands = [], []
        for k, d in enumerate(data):
            f = d.get("frame_id", k)
            if not isinstance(f, int):
                raise _ferr(path, f"frame_id {f!r} is not an integer", k, "frame_id")
            insts = d["instances"]
            if not isinstance(insts, list):
                raise _ferr(path, "must be a list", f, "instances")
            frames.append(f)
            cands.append(
                [
                    c
                    for i, inst in enumerate(insts)
                    if (c := _mmpose_instance(inst, path, f, f"instances[{i}]", J)) is not None
                ]
            )
        frame_ids, per_frame = _fill_gaps(frames, cands, path, [])
    else:
        kind = "mmpose_image"
        frame_ids = np.zeros(1, np.int64)
        per_frame = [
            [
                c
                for i, inst in enumerate(data)
                if (c := _mmpose_instance(inst, path, 0, f"[{i}]", J)) is not None
            ]
        ]
    _check_nonempty(path, len(frame_ids))
    kp, _ = select_person(per_frame, J, person)
    return Keypoints2D(
        keypoints=kp,
        layout=layout,
        name=name or path.stem,
        frame_ids=frame_ids,
        source=str(path),
        meta={"format": kind, "person_selection": person},
    )


def write_mmpose_json(clip: Clip | Keypoints2D, path: str | os.PathLike) -> Path:
    """Write a clip as an MMPose inferencer video prediction file (one instance per frame).

    ``[{"frame_id": t, "instances": [{"keypoints": (J, 2), "keypoint_scores": (J,),
    "bbox": [[x1, y1, x2, y2]], "bbox_score": mean visible confidence}]}]``; frames with no
    visible joint have ``"instances": []``; missing joints are written as (0, 0) with score 0.
    """
    out = []
    for t, kp in enumerate(np.asarray(clip.keypoints, np.float32)):
        vis = kp[:, 2] > 0
        insts = []
        if vis.any():
            kp = kp.copy()
            kp[~vis] = 0.0
            lo, hi = kp[vis, :2].min(axis=0), kp[vis, :2].max(axis=0)
            insts.append(
                {
                    "keypoints": [[float(x), float(y)] for x, y in kp[:, :2]],
                    "keypoint_scores": [float(s) for s in kp[:, 2]],
                    "bbox": [[float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]],
                    "bbox_score": float(kp[vis, 2].mean()),
                }
            )
        out.append({"frame_id": t, "instances": insts})
    path = Path(path)
    _atomic_write_text(path, json.dumps(out))
    return path


# --------------------------------------------------------------------------------------------
# VideoPose3D
# --------------------------------------------------------------------------------------------

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
    from jmocap.data.clip import atomic_write_npz

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
    return atomic_write_npz(path, arrays)


# --------------------------------------------------------------------------------------------
# plain arrays (Human3.6M-17 order by default)
# --------------------------------------------------------------------------------------------

_ARRAY_KEYS = ("keypoints", "keypoints_2d", "kp2d", "joints_2d", "poses_2d", "pose_2d")


def read_keypoint_array(
    path: str | os.PathLike,
    *,
    layout: str = "h36m17",
    key: str | None = None,
    name: str | None = None,
) -> Keypoints2D:
    """Read a (T, J, 2) or (T, J, 3) pixel array from ``.npy`` or ``.npz`` (no pickle).

    The joint order is ``layout`` (default ``h36m17``: Hip, RHip, RKnee, RFoot, LHip, LKnee,
    LFoot, Spine, Thorax, Neck/Nose, Head, LShoulder, LElbow, LWrist, RShoulder, RElbow,
    RWrist). (T, J, 2) arrays get confidence 1; NaN or (0, 0) joints are missing. In an .npz,
    the array is ``key``, else the first of ``keypoints``, ``keypoints_2d``, ``kp2d``,
    ``joints_2d``, ``poses_2d``, ``pose_2d`` present, else the file's only array. Optional
    scalar entries ``fps`` and ``image_size`` (2,) / ``intrinsics`` (4,) are used when present.
    """
    path = Path(path)
    lay = get_layout(layout)
    extras: dict[str, np.ndarray] = {}
    try:
        if path.suffix == ".npy":
            a = np.load(path, allow_pickle=False)
            fieldname = "<array>"
        else:
            with np.load(path, allow_pickle=False) as npz:
                files = list(npz.files)
                if key is None:
                    key = next((k for k in _ARRAY_KEYS if k in files), None)
                    if key is None:
                        if len(files) != 1:
                            raise _ferr(
                                path, f"has arrays {files}; pass key= to choose the keypoints"
                            )
                        key = files[0]
                if key not in files:
                    raise _ferr(path, f"has no array {key!r} (arrays: {files})", field=key)
                a = npz[key]
                fieldname = key
                extras = {k: npz[k] for k in ("fps", "image_size", "intrinsics") if k in files}
    except FormatError:
        raise
    except _READ_ERRORS as e:
        raise _ferr(path, f"not a readable numpy file: {e}") from None
    if (
        a.ndim != 3
        or a.shape[1] != lay.num_joints
        or a.shape[2] not in (2, 3)
        or a.dtype.kind not in "fiu"
    ):
        raise _ferr(
            path,
            f"has shape {a.shape} ({a.dtype}), expected (T, {lay.num_joints}, 2|3) for layout "
            f"{lay.name!r}",
            field=fieldname,
        )
    _check_nonempty(path, a.shape[0])
    if a.shape[2] == 3:
        conf = a[..., 2]
        with np.errstate(invalid="ignore"):
            bad = np.isfinite(conf) & ((conf < 0) | (conf > 1.5))
        if bad.any():
            f = int(np.argmax(bad.any(axis=1)))
            raise _ferr(
                path, f"confidence {conf[f][bad[f]][0]} is far outside [0, 1]", f, fieldname
            )
    fps = float(extras["fps"]) if "fps" in extras else None
    size = tuple(int(v) for v in extras["image_size"]) if "image_size" in extras else None
    intr = np.asarray(extras["intrinsics"], np.float64) if "intrinsics" in extras else None
    return Keypoints2D(
        keypoints=clean_keypoints(a),
        layout=lay.name,
        name=name or path.stem,
        frame_ids=np.arange(a.shape[0]),
        fps=fps,
        image_size=size,
        intrinsics=intr,
        source=str(path),
        meta={"format": "array"},
    )


# --------------------------------------------------------------------------------------------
# AMASS-style 3D joints
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Joints3D:
    """3D reference joints: ``joints`` (T, J, 3) float64 in the file's frame and units."""

    joints: np.ndarray
    fps: float
    joint_names: tuple[str, ...] | None
    source: str = ""


def read_amass_joints(path: str | os.PathLike) -> Joints3D:
    """Read 3D joints from an AMASS-style ``.npz``.

    AMASS itself stores SMPL(-H/X) parameters (``poses``, ``trans``, ``betas``,
    ``mocap_framerate``); this reader needs files where the joints were already computed:
    an array ``joints`` or ``Jtr`` of shape (T, J, 3), and the frame rate in
    ``mocap_framerate`` (AMASS SMPL+H), ``mocap_frame_rate`` (AMASS SMPL-X) or ``fps``. The
    joints are returned as stored (AMASS: metres, z-up world, like jmocap). For J = 22 / 24 the
    SMPL joint names are attached (:data:`SMPL_JOINT_NAMES`); for 52 (SMPL-H) the first 22.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            files = list(npz.files)
            key = "joints" if "joints" in files else ("Jtr" if "Jtr" in files else None)
            if key is None:
                raise _ferr(
                    path,
                    f"has no 'joints' or 'Jtr' array (arrays: {files}); AMASS SMPL parameters "
                    "need a body model to give joints",
                    field="joints",
                )
            J = np.asarray(npz[key], np.float64)
            fkey = next(
                (k for k in ("mocap_framerate", "mocap_frame_rate", "fps") if k in files), None
            )
            if fkey is None:
                raise _ferr(
                    path,
                    "has no frame rate ('mocap_framerate', 'mocap_frame_rate' or 'fps')",
                    field="mocap_framerate",
                )
            fps = float(npz[fkey])
    except FormatError:
        raise
    except _READ_ERRORS as e:
        raise _ferr(path, f"not a readable .npz file: {e}") from None
    if J.ndim != 3 or J.shape[2] != 3:
        raise _ferr(path, f"has shape {J.shape}, expected (T, J, 3)", field=key)
    _check_nonempty(path, J.shape[0])
    bad = ~np.isfinite(J)
    if bad.any():
        raise _ferr(
            path, "has non-finite values", int(np.argmax(bad.reshape(len(J), -1).any(axis=1))), key
        )
    if not (np.isfinite(fps) and fps > 0):
        raise _ferr(path, f"is {fps}, expected > 0", field=fkey)
    n = J.shape[1]
    names = SMPL_JOINT_NAMES[:n] if n in (22, 24) else (SMPL_JOINT_NAMES[:22] if n == 52 else None)
    if n == 52:
        names = names + tuple(f"hand_{i}" for i in range(30))
    return Joints3D(joints=J, fps=fps, joint_names=names, source=str(path))


# --------------------------------------------------------------------------------------------
# camera sidecar
# --------------------------------------------------------------------------------------------


def sidecar_path(path: str | os.PathLike) -> Path:
    """The camera sidecar of a clip path: ``walk.npz`` / ``walk.json`` / ``walk/`` -> ``walk.camera.json``."""
    p = Path(path)
    stem = p.name if p.is_dir() or not p.suffix else p.stem
    return p.with_name(stem + ".camera.json")


def read_camera_json(path: str | os.PathLike) -> dict[str, Any]:
    """Read a camera sidecar: ``{"fx", "fy", "cx", "cy", "width", "height"}`` plus optional
    ``"extrinsics"`` (4x4 nested list, world->camera, OpenCV axes) and ``"fps"``.

    Returns ``{"intrinsics": (4,), "image_size": (w, h), "extrinsics": (4, 4) | None,
    "fps": float | None}``.
    """
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, dict):
        raise _ferr(path, "a camera file must be a JSON object")
    out: dict[str, Any] = {}
    try:
        intr = [float(data[k]) for k in ("fx", "fy", "cx", "cy")]
    except KeyError as e:
        raise _ferr(path, "missing", field=e.args[0]) from None
    except (TypeError, ValueError):
        raise _ferr(path, "fx, fy, cx, cy must be numbers", field="fx") from None
    if not all(math.isfinite(v) for v in intr) or intr[0] <= 0 or intr[1] <= 0:
        raise _ferr(path, f"intrinsics {intr} must be finite with fx, fy > 0", field="fx")
    out["intrinsics"] = np.asarray(intr, np.float64)
    try:
        w, h = data["width"], data["height"]
    except KeyError as e:
        raise _ferr(path, "missing", field=e.args[0]) from None
    if not (
        isinstance(w, (int, float))
        and isinstance(h, (int, float))
        and w > 0
        and h > 0
        and w == int(w)
        and h == int(h)
    ):
        raise _ferr(path, f"image size ({w!r}, {h!r}) must be positive integers", field="width")
    out["image_size"] = (int(w), int(h))
    E = data.get("extrinsics")
    if E is not None:
        try:
            E = np.asarray(E, np.float64)
        except (TypeError, ValueError):
            raise _ferr(path, "must be a 4x4 list of numbers", field="extrinsics") from None
        if E.shape != (4, 4) or not np.isfinite(E).all():
            raise _ferr(
                path, f"must be a finite 4x4 matrix, got shape {E.shape}", field="extrinsics"
            )
    out["extrinsics"] = E
    fps = data.get("fps")
    if fps is not None:
        if not isinstance(fps, (int, float)) or not fps > 0:
            raise _ferr(path, f"must be a positive number, got {fps!r}", field="fps")
        fps = float(fps)
    out["fps"] = fps
    return out


def write_camera_json(path: str | os.PathLike, clip: Clip) -> Path:
    """Write the camera (and fps) of ``clip`` as a sidecar JSON, atomically."""
    fx, fy, cx, cy = (float(v) for v in clip.intrinsics)
    w, h = (int(v) for v in clip.image_size)
    data: dict[str, Any] = {
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "width": w,
        "height": h,
        "fps": float(clip.fps),
    }
    if clip.extrinsics is not None:
        data["extrinsics"] = np.asarray(clip.extrinsics, np.float64).tolist()
    path = Path(path)
    _atomic_write_text(path, json.dumps(data, indent=1))
    return path


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------


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
        try:
            with np.load(path, allow_pickle=False) as npz:
                files = list(npz.files)
        except _READ_ERRORS as e:
            raise _ferr(path, f"not a readable .npz file: {e}") from None
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
        for cand in (sidecar_path(path), path / "camera.json" if path.is_dir() else None):
            if cand is not None and cand.is_file():
                camera_json = cand
                break
    if path.suffix.lower() == ".npz" and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as npz:
                is_clip = "format" in npz.files
        except _READ_ERRORS as e:
            raise _ferr(path, f"not a readable .npz file: {e}") from None
        if is_clip:
            clip = load_clip(path)
            side = read_camera_json(camera_json) if camera_json is not None else {}
            changes: dict[str, Any] = {}
            for key, arg in (
                ("fps", fps),
                ("image_size", image_size),
                ("intrinsics", intrinsics),
                ("extrinsics", extrinsics),
            ):
                v = arg if arg is not None else side.get(key)
                if v is not None:
                    changes[key] = v
            if name is not None:
                changes["name"] = name
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
    "CLIP_FORMAT",
    "DEFAULT_FPS",
    "H36M_CAMERAS",
    "H36M_FPS",
    "SMPL_JOINT_NAMES",
    "Candidate",
    "ClipFormatError",
    "FormatError",
    "Joints3D",
    "Keypoints2D",
    "clean_keypoints",
    "iter_videopose3d",
    "read_amass_joints",
    "read_camera_json",
    "read_clip",
    "read_coco_json",
    "read_keypoint_array",
    "read_keypoints",
    "read_mmpose_json",
    "read_openpose_folder",
    "read_videopose3d",
    "select_person",
    "sidecar_path",
    "write_camera_json",
    "write_coco_results",
    "write_mmpose_json",
    "write_openpose_folder",
    "write_videopose3d",
]
