"""COCO keypoints: the results list (what ``COCO.loadRes`` reads) and annotation files.

:func:`read_coco_json`, :func:`write_coco_results`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from jmocap.data.clip import MAX_IMAGE_SIDE, Clip
from jmocap.data.formats.common import (
    _atomic_write_text,
    _check_nonempty,
    _ferr,
    _fill_gaps,
    _flat_triplets,
    _load_json,
    _number,
    _type_name,
    clean_keypoints,
)
from jmocap.data.formats.keypoints import Keypoints2D
from jmocap.data.formats.person import Candidate, select_person
from jmocap.layouts import get_layout

#: the number of keypoint values per entry -> the layout a results list is in, when not given
LAYOUT_OF_LENGTH = {51: "coco17", 78: "halpe26"}


def _numbered_frame(image_id) -> int | None:
    """The frame number of an image id that is a numbered frame file, as AlphaPose writes them
    for a video (``"12.jpg"``), else None."""
    if isinstance(image_id, str):
        stem, dot, ext = image_id.rpartition(".")
        if dot and stem.isdigit() and ext.isalpha() and len(stem) <= 9:
            return int(stem)
    return None


def _frame_index(image_ids, frame_of, path):
    """Frame numbers of the entries' image ids: the ids themselves (integers, not booleans or
    strings), numbered frame files (``"12.jpg"``: frame 12, AlphaPose's ids for a video's
    frames) or ``frame_of[id]`` / ``frame_of(id)``; FormatError naming the bad id."""
    if frame_of is None:
        numbered = [_numbered_frame(i) for i in image_ids]
        if image_ids and all(n is not None for n in numbered):
            return numbered
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
        except (KeyError, IndexError, TypeError):
            raise _ferr(
                path, f"image_id {i!r} is not in the frame_of mapping", field="image_id"
            ) from None
        out.append(int(f))
    return out


def _layout_of(data) -> str:
    """The layout of a results list or annotation file from its first entry's keypoints
    (:data:`LAYOUT_OF_LENGTH`; COCO-17 otherwise, whose reader then names what is wrong)."""
    entries = data.get("annotations") if isinstance(data, dict) else data
    if not isinstance(entries, list):
        return "coco17"
    first = next((e for e in entries if isinstance(e, dict) and isinstance(e.get("keypoints"), list)), None)
    return "coco17" if first is None else LAYOUT_OF_LENGTH.get(len(first["keypoints"]), "coco17")


def _annotation_images(images, path):
    """From an annotation file's ``images`` list: ``({id: index}, (width, height) | None)``.

    Checked: ``images`` is a list of objects whose ``id`` is an integer or a string;
    ``width`` / ``height``, where given, are positive integers. The size is returned when every
    image has the same one."""
    if not isinstance(images, list):
        raise _ferr(path, f"must be a list, got {_type_name(images)}", field="images")
    order, sizes = {}, set()
    for k, img in enumerate(images):
        if not isinstance(img, dict):
            raise _ferr(path, f"must be an object, got {_type_name(img)}", field=f"images[{k}]")
        if "id" in img:
            i = img["id"]
            if isinstance(i, bool) or not isinstance(i, (int, str)):
                raise _ferr(
                    path, f"must be an integer or a string, got {_type_name(i)}",
                    field=f"images[{k}].id",
                )
            order[i] = k
        w, h = img.get("width"), img.get("height")
        if w is not None and h is not None:
            sizes.add(
                tuple(
                    _number(v, path, f"images[{k}].{key}", integer=True, positive=True,
                            maximum=MAX_IMAGE_SIDE)
                    for key, v in (("width", w), ("height", h))
                )
            )
        else:
            sizes.add(None)
    size = sizes.pop() if len(sizes) == 1 else None
    return order, size


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
    layout: str | None = None,
) -> Keypoints2D:
    """Read COCO keypoints: a results list or an annotation file.

    * Results (what ``COCO.loadRes`` / COCO keypoint evaluation read): a JSON list of
      ``{"image_id": int, "category_id": 1, "keypoints": [x, y, v] * 17, "score": float}``;
      ``v`` is the keypoint confidence. Several entries per image are several people
      (:func:`select_person`, score = ``score``). AlphaPose writes the same list with 26
      keypoints (Halpe-26, ``halpe26``) and image ids that are frame files (``"12.jpg"``).
    * Annotations (``person_keypoints_*.json``): a dict with ``images`` and ``annotations``;
      ``v`` is the visibility flag (0 not labelled, 1 labelled but occluded, 2 visible): v > 0
      gives confidence 1. The frame order is the ``images`` order unless ``frame_of`` is given.

    ``layout`` (``coco17``, ``halpe26``, or any layout of jmocap with that many joints): by
    default the one whose joint count the first entry's keypoints have (78 values: Halpe-26;
    otherwise COCO-17, whose 51 values are then checked on every entry).

    Frames: by default the image id *is* the frame number (ids are integers, or numbered frame
    files such as ``"12.jpg"``; the clip spans the
    smallest to the largest id present, gaps become missing frames); ``frame_of`` (a mapping or
    a function image_id -> frame number) overrides this. ``category_id`` other than 1 (person)
    is skipped. No fps, image size or camera is stored (COCO image entries' ``width``/``height``
    are used when present and all equal).

    Values must have their JSON types: ``image_id``, ``category_id``, ``track_id`` integers,
    ``score`` and the keypoints numbers (``null`` keypoint values are missing joints), else a
    :class:`FormatError` names the file, the frame and the field.
    """
    path = Path(path)
    data = _load_json(path)
    if layout is None:
        layout = _layout_of(data)
    J = get_layout(layout).num_joints
    image_size = None
    if isinstance(data, dict) and "annotations" in data:
        entries = data["annotations"]
        kind = "coco_annotations"
        order, image_size = _annotation_images(data.get("images", []), path)
        if frame_of is None and order:
            frame_of = order
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
        category = e.get("category_id", 1)
        if _number(category, path, f"[{k}].category_id", f, integer=True) != 1:
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
            score = _number(score, path, f"[{k}].score", f, finite=False)
        kp = clean_keypoints(kp)
        track = e.get("track_id")
        if track is not None:
            track = _number(track, path, f"[{k}].track_id", f, integer=True)
        cands.append(
            Candidate(
                kp,
                score if np.isfinite(score) else 0.0,
                track if track is not None and track >= 0 else None,
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
    """Write a coco17 (or halpe26, AlphaPose's) clip as a COCO keypoint results list
    (image_id = first_image_id + frame).

    ``keypoints`` is ``[x, y, confidence] * J`` (missing joints 0, 0, 0) and ``score`` the mean
    confidence of the visible joints; frames with no visible joint are left out, as a detector
    with no detection would.
    """
    if clip.layout not in LAYOUT_OF_LENGTH.values():
        raise ValueError(f"COCO results need a coco17 or halpe26 clip, got layout {clip.layout!r}")
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


__all__ = ["read_coco_json", "write_coco_results"]
