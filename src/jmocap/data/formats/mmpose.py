"""MMPose 1.x 2D predictions.

The inferencer's ``pred_out_dir`` files (video: list of ``frame_id``/``instances``; single
image: list of instances) and the ``demo/*`` ``--save-predictions`` files (``meta_info`` +
``instance_info``): :func:`read_mmpose_json`, :func:`write_mmpose_json`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from jmocap.data.clip import Clip
from jmocap.data.formats.common import (
    _atomic_write_text,
    _check_nonempty,
    _ferr,
    _fill_gaps,
    _list_depth,
    _load_json,
    _nested_numbers,
    _number,
    _type_name,
    clean_keypoints,
)
from jmocap.data.formats.keypoints import Keypoints2D
from jmocap.data.formats.person import Candidate, select_person
from jmocap.layouts import get_layout


def _mmpose_instance(inst, path, frame, fieldname, J) -> Candidate | None:
    """One MMPose instance as a candidate (None when no joint is visible).

    Checked: ``keypoints`` is a (K, 2) list of number pairs (or (1, K, 2)) with K = ``J``;
    ``keypoint_scores``, when present, K numbers (or [[K numbers]]); ``bbox_score`` a number
    (or a list whose first element is one); ``track_id`` an integer. Everything a JSON number
    (not a string or a boolean); a :class:`FormatError` naming file, frame and field otherwise.
    """
    if not isinstance(inst, dict) or "keypoints" not in inst:
        raise _ferr(path, "instance has no 'keypoints'", frame, fieldname)
    kps = inst["keypoints"]
    depth = _list_depth(kps)
    if depth not in (2, 3):
        raise _ferr(
            path,
            f"must be a ({J}, 2) list of [x, y] pairs, got {_type_name(kps)} nested {depth} deep",
            frame,
            fieldname + ".keypoints",
        )
    xy = _nested_numbers(kps, depth, path, fieldname + ".keypoints", frame)
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
        depth = _list_depth(scores)
        if depth not in (1, 2):
            raise _ferr(
                path, f"must be a list of {J} numbers", frame, fieldname + ".keypoint_scores"
            )
        sc = _nested_numbers(scores, depth, path, fieldname + ".keypoint_scores", frame)
        sc = sc.reshape(-1)
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
    if score is not None:
        score = _number(score, path, fieldname + ".bbox_score", frame, finite=False)
    if score is None or not np.isfinite(score):
        score = float(kp[:, 2].sum()) / J
    track = inst.get("track_id")
    if track is not None:
        track = _number(track, path, fieldname + ".track_id", frame, integer=True)
    return Candidate(kp, float(score), track if track is not None and track >= 0 else None)


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
    chosen by :func:`select_person`. No fps, image size or camera is stored. Values must have
    their JSON types (numbers are JSON numbers, ``frame_id`` / ``track_id`` integers), else a
    :class:`FormatError` names the file, the frame and the field.
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
            if not isinstance(f, int) or isinstance(f, bool):
                raise _ferr(path, f"must be an integer, got {_type_name(f)}", k, "frame_id")
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


__all__ = ["read_mmpose_json", "write_mmpose_json"]
