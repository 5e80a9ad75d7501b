"""OpenPose ``--write_json`` folders (JSON ``version`` 1.3 files, BODY_25 model).

:func:`read_openpose_folder`, :func:`write_openpose_folder`.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from jmocap.data.clip import Clip
from jmocap.data.formats.camera_file import sidecar_path, write_camera_json
from jmocap.data.formats.common import (
    _atomic_write_text,
    _ferr,
    _fill_gaps,
    _flat_triplets,
    _load_json,
    _number,
    clean_keypoints,
)
from jmocap.data.formats.keypoints import Keypoints2D
from jmocap.data.formats.person import Candidate, select_person
from jmocap.layouts import get_layout

OPENPOSE_FILE_RE = re.compile(r"^(?P<name>.*?)_?(?P<frame>\d+)_keypoints\.json$")
OPENPOSE_VERSION = 1.3


def _openpose_people(data, path, frame, J, layout_desc) -> list[Candidate]:
    """The people of one OpenPose frame file, as candidates (people with no visible joint
    left out).

    Checked: the file is an object with a ``people`` list (and a numeric ``version`` when it
    has one); each person is an object with ``pose_keypoints_2d``, a flat list of ``3 * J``
    numbers (``null`` = missing) or empty (body not detected); ``person_id``, when present, is
    an integer or a list whose first element is one (negative = no tracker id).
    """
    if not isinstance(data, dict) or "people" not in data:
        raise _ferr(path, "not an OpenPose keypoints file (no 'people' list)", frame, "people")
    if "version" in data:
        _number(data["version"], path, "version", frame)
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
        pid = _number(pid, path, f"people[{p}].person_id", frame, integer=True)
        cands.append(Candidate(kp, float(kp[:, 2].sum()) / J, pid if pid >= 0 else None))
    return cands


def read_openpose_folder(
    folder: str | os.PathLike, *, person: str = "track", name: str | None = None
) -> Keypoints2D:
    """Read an OpenPose ``--write_json`` folder (BODY_25 model, JSON version 1.x).

    Files ``<video>_<frame:012d>_keypoints.json`` are ordered by the frame number in the file
    name (gaps become all-missing frames, within the ``max_frame_gap`` / ``max_frames`` limits of
    :mod:`jmocap.data.limits`); ``people[*].pose_keypoints_2d`` is the flat
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
        frame = int(m.group("frame"))  # (a file name is too short to exceed int's digit limit)
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


__all__ = [
    "OPENPOSE_FILE_RE",
    "OPENPOSE_VERSION",
    "read_openpose_folder",
    "write_openpose_folder",
]
