"""Tests of jmocap.data.clip and the jmocap.data.formats package (one section per module).

Input files are written by hand here, following each format's own specification (OpenPose
``doc/02_output.md``, the COCO results format, MMPose's inferencer output, VideoPose3D's
``prepare_data_*`` scripts), then read back; joint orders are checked by name through
``jmocap.layouts``. Values are exact (float32 round trips through JSON/npz are lossless), so
comparisons are exact or at float32 resolution.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from jmocap.data import (
    Clip,
    ClipFormatError,
    FormatError,
    clean_keypoints,
    iter_videopose3d,
    load_clip,
    read_amass_joints,
    read_clip,
    read_coco_json,
    read_keypoint_array,
    read_keypoints,
    read_mmpose_json,
    read_openpose_folder,
    read_videopose3d,
    save_clip,
    write_coco_results,
    write_mmpose_json,
    write_openpose_folder,
    write_videopose3d,
)
from jmocap.data.formats import H36M_CAMERAS, sidecar_path
from jmocap.layouts import get_layout

BODY25 = get_layout("body25")
COCO17 = get_layout("coco17")
H36M17 = get_layout("h36m17")


def _random_kp(rng, T, J, w=1920, h=1080, missing=0.1):
    kp = np.zeros((T, J, 3), np.float32)
    kp[..., 0] = rng.uniform(1, w, (T, J))
    kp[..., 1] = rng.uniform(1, h, (T, J))
    kp[..., 2] = rng.uniform(0.05, 1.0, (T, J))
    miss = rng.uniform(size=(T, J)) < missing
    kp[miss] = 0.0
    return kp


def _clip(rng, layout="body25", T=12, **kw):
    J = get_layout(layout).num_joints
    return Clip(
        name="walk",
        layout=layout,
        fps=30.0,
        keypoints=_random_kp(rng, T, J),
        intrinsics=np.array([1000.0, 1010.0, 955.0, 541.0]),
        image_size=np.array([1920, 1080]),
        **kw,
    )


# --------------------------------------------------------------------------------------------
# jmocap clip .npz
# --------------------------------------------------------------------------------------------


def _with_gt(rng, T=12, nq=10):
    E = np.eye(4)
    E[:3, 3] = [0.1, 1.2, 4.0]
    return dict(
        extrinsics=E,
        gt_q=rng.normal(size=(T, nq)).astype(np.float32),
        gt_qd=rng.normal(size=(T, nq - 1)),
        gt_keypoints3d=rng.normal(size=(T, 25, 3)),
        gt_contacts=(rng.uniform(size=(T, 4)) > 0.5).astype(np.float32),
        gt_tau=rng.normal(size=(T, nq - 1)),
        gt_grf=rng.normal(size=(T, 4, 3)),
        height_m=1.75,
        mass_kg=70.0,
        meta={"motion": "walk", "seed": 3, "generator": "test"},
    )


def test_clip_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    clip = _clip(rng, **_with_gt(rng))
    path = save_clip(tmp_path / "sub" / "walk.npz", clip)
    assert sorted(os.listdir(tmp_path / "sub")) == ["walk.npz"]  # no temp file left behind
    back = load_clip(path)
    for key in (
        "keypoints",
        "intrinsics",
        "image_size",
        "extrinsics",
        "gt_q",
        "gt_qd",
        "gt_keypoints3d",
        "gt_contacts",
        "gt_tau",
        "gt_grf",
    ):
        np.testing.assert_array_equal(getattr(back, key), getattr(clip, key), err_msg=key)
    assert back.keypoints.dtype == np.float32 and back.gt_qd.dtype == np.float32
    assert back.intrinsics.dtype == np.float64
    assert (back.name, back.layout, back.fps, back.height_m, back.mass_kg) == (
        "walk",
        "body25",
        30.0,
        1.75,
        70.0,
    )
    assert back.meta == {"motion": "walk", "seed": 3, "generator": "test"}
    # the schema of the file itself
    with np.load(path, allow_pickle=False) as npz:
        assert str(npz["format"]) == "jmocap-clip-1"
        assert json.loads(str(npz["meta"]))["seed"] == 3
    cam = back.camera
    np.testing.assert_allclose(np.asarray(cam.intrinsics), clip.intrinsics, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(cam.extrinsics), clip.extrinsics, atol=1e-6)


def test_clip_minimal_and_missing_joints_zeroed(tmp_path):
    rng = np.random.default_rng(1)
    kp = _random_kp(rng, 5, 17)
    kp[2, 3] = [123.0, 45.0, 0.0]  # missing joint with garbage coordinates
    clip = Clip("c", "coco17", 25, kp, [1000, 1000, 320, 240], [640, 480])
    np.testing.assert_array_equal(clip.keypoints[2, 3], [0.0, 0.0, 0.0])
    back = load_clip(save_clip(tmp_path / "c.npz", clip))
    assert back.extrinsics is None and back.gt_q is None and back.meta == {}
    np.testing.assert_allclose(np.asarray(back.camera.extrinsics), np.eye(4))


def _save_raw(path, **arrays):
    np.savez_compressed(path, **arrays)
    return path


def _raw_clip_arrays(rng, T=6):
    return {
        "format": np.array("jmocap-clip-1"),
        "name": np.array("x"),
        "layout": np.array("h36m17"),
        "fps": np.array(50.0),
        "meta": np.array("{}"),
        "keypoints": _random_kp(rng, T, 17),
        "intrinsics": np.array([1145.0, 1144.0, 512.0, 515.0]),
        "image_size": np.array([1000, 1002]),
    }


@pytest.mark.parametrize(
    "change, expect",
    [
        (lambda a: a.update(layout=np.array("mpii16")), ["field 'layout'", "mpii16"]),
        (lambda a: a.update(keypoints=a["keypoints"][:, :16]), ["field 'keypoints'", "(T, 17, 3)"]),
        (
            lambda a: a["keypoints"].__setitem__((3, 5, 0), np.nan),
            ["field 'keypoints'", "non-finite", "frame 3"],
        ),
        (
            lambda a: a["keypoints"].__setitem__((4, 1, 2), 1.2),
            ["field 'keypoints'", "confidence", "frame 4"],
        ),
        (lambda a: a.update(keypoints=a["keypoints"][:0]), ["field 'keypoints'", "T = 0"]),
        (lambda a: a.update(gt_q=np.zeros((5, 10), np.float32)), ["field 'gt_q'", "5 frames", "6"]),
        (lambda a: a.update(gt_q=np.zeros((6, 10)), gt_qd=np.zeros((6, 8))), ["nq = 10", "nv = 8"]),
        (lambda a: a.update(gt_contacts=np.full((6, 4), 0.5)), ["field 'gt_contacts'", "frame 0"]),
        (lambda a: a.update(gt_grf=np.zeros((6, 4, 2))), ["field 'gt_grf'"]),
        (lambda a: a.update(intrinsics=np.array([0.0, 1.0, 2.0, 3.0])), ["field 'intrinsics'"]),
        (lambda a: a.update(extrinsics=np.ones((4, 4))), ["field 'extrinsics'"]),
        (lambda a: a.update(format=np.array("other-1")), ["field 'format'"]),
        (lambda a: a.pop("fps"), ["missing field 'fps'"]),
        (lambda a: a.update(meta=np.array("{not json")), ["field 'meta'"]),
    ],
)
def test_load_clip_errors_name_file_field_frame(tmp_path, change, expect):
    arrays = _raw_clip_arrays(np.random.default_rng(2))
    change(arrays)
    path = _save_raw(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ClipFormatError) as e:
        load_clip(path)
    msg = str(e.value)
    assert str(path) in msg
    for s in expect:
        assert s in msg, (s, msg)
    assert isinstance(e.value, ValueError) and isinstance(e.value, FormatError)


def test_load_clip_corrupted_file(tmp_path):
    path = tmp_path / "broken.npz"
    path.write_bytes(b"PK\x03\x04 this is not a zip")
    with pytest.raises(ClipFormatError, match="broken.npz"):
        load_clip(path)


def test_clip_construction_validates():
    rng = np.random.default_rng(3)
    with pytest.raises(ClipFormatError, match="clip 'walk'.*field 'fps'"):
        _clip(rng).replace(fps=-1.0)
    with pytest.raises(ClipFormatError, match="gt_tau"):
        _clip(rng, gt_q=np.zeros((12, 10)), gt_tau=np.zeros((11, 9)))


def test_clip_slice():
    rng = np.random.default_rng(4)
    clip = _clip(rng, **_with_gt(rng))
    part = clip.slice(2, 7)
    assert part.num_frames == 5 and part.gt_grf.shape == (5, 4, 3)
    np.testing.assert_array_equal(part.keypoints, clip.keypoints[2:7])


# --------------------------------------------------------------------------------------------
# missing-joint rules (formats/common.py)
# --------------------------------------------------------------------------------------------


def test_clean_keypoints_rules():
    kp = np.array(
        [
            [10.0, 20.0, 0.9],  # fine
            [0.0, 0.0, 0.0],  # OpenPose "not detected"
            [15.0, 25.0, 0.0],  # position but zero confidence
            [np.nan, 5.0, 0.8],  # NaN coordinate
            [0.0, 0.0, 0.7],  # exact origin: treated as missing
            [30.0, 40.0, 1.02],  # heatmap max slightly above 1: clipped
            [30.0, 40.0, np.nan],
            [30.0, 40.0, -0.5],
        ]
    )
    out = clean_keypoints(kp)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[0], [10, 20, 0.9], rtol=1e-6)
    for i in (1, 2, 3, 4, 6, 7):
        np.testing.assert_array_equal(out[i], 0.0)
    np.testing.assert_array_equal(out[5], [30, 40, 1.0])
    out2 = clean_keypoints(np.array([[1.0, 2.0], [np.nan, np.nan]]))
    np.testing.assert_array_equal(out2, [[1, 2, 1], [0, 0, 0]])


# --------------------------------------------------------------------------------------------
# OpenPose (formats/openpose.py; person tracking: formats/person.py)
# --------------------------------------------------------------------------------------------


def _op_person(kp25, person_id=-1):
    """One person as OpenPose 1.3 writes it (doc/02_output.md)."""
    return {
        "person_id": [person_id],
        "pose_keypoints_2d": [float(v) for v in np.asarray(kp25).reshape(-1)],
        "face_keypoints_2d": [],
        "hand_left_keypoints_2d": [],
        "hand_right_keypoints_2d": [],
        "pose_keypoints_3d": [],
        "face_keypoints_3d": [],
        "hand_left_keypoints_3d": [],
        "hand_right_keypoints_3d": [],
    }


def _op_write(folder: Path, frame: int, people, name="video"):
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / f"{name}_{frame:012d}_keypoints.json"
    p.write_text(json.dumps({"version": 1.3, "people": people}))
    return p


def _body(x0, y0, conf=0.9):
    """A crude standing BODY_25 skeleton around (x0, y0) with all joints visible."""
    kp = np.zeros((25, 3))
    rng = np.random.default_rng(int(x0 * 7 + y0))
    kp[:, 0] = x0 + rng.uniform(-40, 40, 25)
    kp[:, 1] = y0 + np.linspace(-150, 150, 25)
    kp[:, 2] = conf
    return kp


def test_openpose_read_order_gaps_missing(tmp_path):
    folder = tmp_path / "op"
    frames = {}
    for f in (5, 2, 0, 1, 3):  # written out of order; frame 4 absent -> missing frame
        kp = _body(500 + 10 * f, 400)
        kp[BODY25.index("LHeel")] = [111.0 + f, 222.0, 0.5]
        kp[BODY25.index("REar")] = [0.0, 0.0, 0.0]  # not detected
        frames[f] = kp
        _op_write(folder, f, [_op_person(kp)] if f != 3 else [])  # frame 3: nobody
    k2d = read_openpose_folder(folder)
    assert k2d.layout == "body25" and k2d.name == "video"
    np.testing.assert_array_equal(k2d.frame_ids, [0, 1, 2, 3, 4, 5])
    kp = k2d.keypoints
    assert kp.shape == (6, 25, 3)
    for f in (0, 1, 2, 5):
        np.testing.assert_allclose(kp[f, BODY25.index("LHeel")], [111.0 + f, 222.0, 0.5])
        np.testing.assert_array_equal(kp[f, BODY25.index("REar")], 0.0)
        np.testing.assert_allclose(kp[f, BODY25.index("Nose")], frames[f][0], rtol=1e-6)
    np.testing.assert_array_equal(kp[3], 0.0)
    np.testing.assert_array_equal(kp[4], 0.0)


def test_openpose_numeric_frame_sort(tmp_path):
    folder = tmp_path / "op"
    for f in (10, 9, 2):
        p = folder / f"clip_{f}_keypoints.json"
        folder.mkdir(exist_ok=True)
        p.write_text(json.dumps({"version": 1.3, "people": [_op_person(_body(100 * f, 300))]}))
    k2d = read_openpose_folder(folder)
    assert k2d.frame_ids[0] == 2 and k2d.num_frames == 9
    assert k2d.keypoints[0, 0, 0] == pytest.approx(_body(200, 300)[0, 0])
    assert k2d.keypoints[-1, 0, 0] == pytest.approx(_body(1000, 300)[0, 0])


def test_openpose_multi_person_tracking(tmp_path):
    """A subject walking right; a bystander with higher confidence appears from frame 3."""
    folder = tmp_path / "op"
    for f in range(8):
        subject = _body(400 + 8 * f, 500, conf=0.6)
        people = [_op_person(subject)]
        if f >= 3:
            people.insert(0, _op_person(_body(1400, 450, conf=0.95)))
        _op_write(folder, f, people)
    tracked = read_openpose_folder(folder).keypoints
    best = read_openpose_folder(folder, person="best").keypoints
    for f in range(8):
        np.testing.assert_allclose(tracked[f, :, 0], _body(400 + 8 * f, 500)[:, 0], rtol=1e-6)
    np.testing.assert_allclose(best[5, :, 0], _body(1400, 450)[:, 0], rtol=1e-6)


def test_openpose_tracking_by_person_id(tmp_path):
    folder = tmp_path / "op"
    # two people crossing: positions alone would swap them, person_id keeps them apart
    for f in range(4):
        a = _body(600 + 40 * f, 500, conf=0.7)
        b = _body(720 - 40 * f, 500, conf=0.8)
        _op_write(folder, f, [_op_person(b, person_id=2), _op_person(a, person_id=1)])
    kp = read_openpose_folder(folder).keypoints  # frame 0 picks the higher score: b
    for f in range(4):
        np.testing.assert_allclose(kp[f, :, 0], _body(720 - 40 * f, 500)[:, 0], rtol=1e-6)


def test_openpose_corrupted_files(tmp_path):
    folder = tmp_path / "op"
    _op_write(folder, 0, [_op_person(_body(500, 400))])
    bad = _op_write(folder, 1, [])
    bad.write_text('{"version": 1.3, "people": [')  # truncated
    with pytest.raises(FormatError) as e:
        read_openpose_folder(folder)
    assert bad.name in str(e.value) and "frame 1" in str(e.value)
    bad.write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": [1.0] * 74}]}))
    with pytest.raises(FormatError) as e:
        read_openpose_folder(folder)
    msg = str(e.value)
    assert (
        bad.name in msg
        and "frame 1" in msg
        and "people[0].pose_keypoints_2d" in msg
        and "74" in msg
    )
    bad.write_text(json.dumps({"version": 1.3}))
    with pytest.raises(FormatError, match="frame 1.*'people'"):
        read_openpose_folder(folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match="no OpenPose"):
        read_openpose_folder(tmp_path / "empty")


def test_openpose_writer_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    clip = _clip(rng, T=7)
    kp = clip.keypoints.copy()
    kp[4] = 0.0  # an empty frame
    clip = clip.replace(keypoints=kp)
    folder = write_openpose_folder(clip, tmp_path / "walk")
    files = sorted(os.listdir(folder))
    assert files == [f"walk_{f:012d}_keypoints.json" for f in range(7)]
    data = json.loads((folder / files[0]).read_text())
    assert data["version"] == 1.3
    (person,) = data["people"]
    assert len(person["pose_keypoints_2d"]) == 75
    for key in ("face_keypoints_2d", "hand_left_keypoints_2d", "hand_right_keypoints_2d"):
        assert person[key] == []
    assert json.loads((folder / files[4]).read_text())["people"] == []
    assert sidecar_path(folder).name == "walk.camera.json" and sidecar_path(folder).exists()
    back = read_clip(folder)  # picks up the sidecar camera and fps
    np.testing.assert_array_equal(back.keypoints, clip.keypoints)
    np.testing.assert_array_equal(back.intrinsics, clip.intrinsics)
    np.testing.assert_array_equal(back.image_size, clip.image_size)
    assert back.fps == clip.fps and back.layout == "body25"
    with pytest.raises(ValueError, match="body25"):
        write_openpose_folder(_clip(rng, layout="coco17"), tmp_path / "x")


# --------------------------------------------------------------------------------------------
# COCO (formats/coco.py)
# --------------------------------------------------------------------------------------------


def _coco_kp(x0, y0, v=0.8):
    kp = np.zeros((17, 3))
    kp[:, 0] = x0 + np.arange(17)
    kp[:, 1] = y0 + 10 * np.arange(17)
    kp[:, 2] = v
    return kp


def test_coco_results(tmp_path):
    res = []
    for image_id in (12, 10, 11, 14):  # out of order; 13 has no detection
        kp = _coco_kp(100 + image_id, 200)
        kp[COCO17.index("left_ankle")] = [0, 0, 0]
        res.append(
            {
                "image_id": image_id,
                "category_id": 1,
                "keypoints": kp.reshape(-1).tolist(),
                "score": 0.7,
            }
        )
    # a second, weaker person in image 10 far away
    res.append(
        {
            "image_id": 10,
            "category_id": 1,
            "keypoints": _coco_kp(900, 100, 0.3).reshape(-1).tolist(),
            "score": 0.2,
        }
    )
    path = tmp_path / "res.json"
    path.write_text(json.dumps(res))
    k2d = read_coco_json(path)
    assert k2d.layout == "coco17"
    np.testing.assert_array_equal(k2d.frame_ids, [10, 11, 12, 13, 14])
    kp = k2d.keypoints
    np.testing.assert_allclose(kp[0, COCO17.index("right_wrist")], [110 + 10, 300, 0.8], rtol=1e-6)
    np.testing.assert_array_equal(kp[0, COCO17.index("left_ankle")], 0.0)
    np.testing.assert_array_equal(kp[3], 0.0)
    # explicit mapping image_id -> frame
    k2 = read_coco_json(path, frame_of={10: 0, 11: 1, 12: 2, 14: 3})
    np.testing.assert_array_equal(k2.frame_ids, [0, 1, 2, 3])
    np.testing.assert_allclose(k2.keypoints[3, 0, 0], 114)
    with pytest.raises(FormatError, match="image_id 14"):
        read_coco_json(path, frame_of={10: 0, 11: 1, 12: 2})


def test_coco_annotations(tmp_path):
    kp = _coco_kp(50, 60)
    kp[:, 2] = 2
    kp[3, 2] = 1  # labelled, occluded -> confidence 1
    kp[4] = [0, 0, 0]  # not labelled
    data = {
        "images": [
            {"id": 7, "file_name": "b.jpg", "width": 640, "height": 480},
            {"id": 3, "file_name": "a.jpg", "width": 640, "height": 480},
        ],
        "annotations": [
            {
                "id": 1,
                "image_id": 3,
                "category_id": 1,
                "keypoints": kp.reshape(-1).tolist(),
                "num_keypoints": 16,
            }
        ],
        "categories": [{"id": 1, "name": "person"}],
    }
    path = tmp_path / "ann.json"
    path.write_text(json.dumps(data))
    k2d = read_coco_json(path)
    assert k2d.image_size == (640, 480)
    np.testing.assert_array_equal(k2d.frame_ids, [1])  # image 3 is the second image
    assert k2d.keypoints[0, 3, 2] == 1.0 and k2d.keypoints[0, 4, 2] == 0.0


def test_coco_writer_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(6)
    clip = _clip(rng, layout="coco17", T=5)
    path = write_coco_results(clip, tmp_path / "r.json")
    entries = json.loads(path.read_text())
    assert entries[0]["category_id"] == 1 and len(entries[0]["keypoints"]) == 51
    back = read_clip(path, image_size=(1920, 1080), intrinsics=clip.intrinsics, fps=30)
    np.testing.assert_array_equal(back.keypoints, clip.keypoints)
    bad = tmp_path / "bad.json"
    bad.write_text(
        json.dumps([{"image_id": 4, "category_id": 1, "keypoints": [1.0] * 50, "score": 1}])
    )
    with pytest.raises(FormatError) as e:
        read_coco_json(bad)
    assert "bad.json" in str(e.value) and "frame 4" in str(e.value) and "keypoints" in str(e.value)


# --------------------------------------------------------------------------------------------
# MMPose (formats/mmpose.py)
# --------------------------------------------------------------------------------------------


def _mm_inst(kp17, bbox_score=0.9):
    kp17 = np.asarray(kp17)
    return {
        "keypoints": kp17[:, :2].tolist(),
        "keypoint_scores": kp17[:, 2].tolist(),
        "bbox": [[0.0, 0.0, 10.0, 10.0]],
        "bbox_score": bbox_score,
    }


def test_mmpose_video_and_demo_formats(tmp_path):
    frames = []
    for f in range(4):
        insts = [_mm_inst(_coco_kp(100 + 5 * f, 100))]
        if f == 2:
            insts = []
        frames.append({"frame_id": f, "instances": insts})
    frames[1]["instances"][0]["keypoint_scores"][COCO17.index("nose")] = 0.0
    p = tmp_path / "video.json"
    p.write_text(json.dumps(frames))
    k2d = read_keypoints(p)
    assert k2d.layout == "coco17" and k2d.num_frames == 4
    np.testing.assert_allclose(
        k2d.keypoints[3, COCO17.index("left_eye")], [100 + 15 + 1, 110, 0.8], rtol=1e-6
    )
    np.testing.assert_array_equal(k2d.keypoints[1, COCO17.index("nose")], 0.0)
    np.testing.assert_array_equal(k2d.keypoints[2], 0.0)
    demo = tmp_path / "demo.json"
    demo.write_text(json.dumps({"meta_info": {"dataset_name": "coco"}, "instance_info": frames}))
    np.testing.assert_array_equal(read_mmpose_json(demo).keypoints, k2d.keypoints)
    single = tmp_path / "img.json"
    single.write_text(json.dumps([_mm_inst(_coco_kp(1, 2), 0.3), _mm_inst(_coco_kp(300, 2), 0.9)]))
    one = read_keypoints(single)
    assert one.num_frames == 1 and one.keypoints[0, 0, 0] == 300


def test_mmpose_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(7)
    clip = _clip(rng, layout="h36m17", T=6)
    path = write_mmpose_json(clip, tmp_path / "pred.json")
    back = read_mmpose_json(path, layout="h36m17")
    np.testing.assert_array_equal(back.keypoints, clip.keypoints)
    bad = [
        {"frame_id": 0, "instances": [_mm_inst(_coco_kp(1, 1))]},
        {
            "frame_id": 1,
            "instances": [{"keypoints": [[1.0, 2.0]] * 16, "keypoint_scores": [1.0] * 16}],
        },
    ]
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(bad))
    with pytest.raises(FormatError) as e:
        read_mmpose_json(p)
    assert (
        "bad.json" in str(e.value)
        and "frame 1" in str(e.value)
        and "instances[0].keypoints" in str(e.value)
    )


# --------------------------------------------------------------------------------------------
# VideoPose3D, plain arrays, AMASS (formats/videopose3d.py, arrays.py, amass.py)
# --------------------------------------------------------------------------------------------


def _vp3d_file(path, rng):
    """Mimics VideoPose3D's prepare_data_h36m.py: savez_compressed of two pickled dicts."""
    positions = {
        "S9": {
            "Walking 1": [rng.uniform(0, 1000, (20, 17, 2)).astype(np.float32) for _ in range(4)],
            "Sitting": [rng.uniform(0, 1000, (10, 17, 2)).astype(np.float32) for _ in range(4)],
        },
        "S11": {
            "Walking": [rng.uniform(0, 1000, (15, 17, 2)).astype(np.float32) for _ in range(4)]
        },
    }
    metadata = {
        "num_joints": 17,
        "keypoints_symmetry": [[4, 5, 6, 11, 12, 13], [1, 2, 3, 14, 15, 16]],
        "layout_name": "h36m",
    }
    np.savez_compressed(path, positions_2d=positions, metadata=metadata)
    return positions


def test_videopose3d(tmp_path):
    rng = np.random.default_rng(8)
    path = tmp_path / "data_2d_h36m_gt.npz"
    pos = _vp3d_file(path, rng)
    k2d = read_videopose3d(path, "S9", "Walking 1", 2)
    assert k2d.layout == "h36m17" and k2d.num_frames == 20 and k2d.fps == 50.0
    np.testing.assert_allclose(k2d.keypoints[..., :2], pos["S9"]["Walking 1"][2])
    np.testing.assert_array_equal(k2d.keypoints[..., 2], 1.0)
    assert k2d.image_size == (1000, 1000) and k2d.intrinsics[0] == H36M_CAMERAS[2][1][0]
    # the file's symmetry metadata agrees with our layout's left/right pairs
    assert sorted(H36M17.flip_pairs) == sorted(
        zip([4, 5, 6, 11, 12, 13], [1, 2, 3, 14, 15, 16], strict=True)
    )
    assert H36M17.joints[3] == "RFoot" and H36M17.joints[10] == "Head"
    all_seqs = list(iter_videopose3d(path))
    assert len(all_seqs) == 12
    assert {(s.meta["subject"], s.meta["action"], s.meta["camera"]) for s in all_seqs} >= {
        ("S11", "Walking", 3)
    }
    clip = read_clip(path, subject="S11", action="Walking", camera=0)
    assert clip.image_size.tolist() == [1000, 1002] and clip.fps == 50.0
    with pytest.raises(FormatError, match="subject"):
        read_videopose3d(path)
    with pytest.raises(FormatError, match="no action 'Running'"):
        read_videopose3d(path, "S9", "Running", 0)


def test_videopose3d_custom_writer(tmp_path):
    rng = np.random.default_rng(9)
    a = rng.uniform(0, 600, (9, 17, 2)).astype(np.float32)
    path = write_videopose3d(
        tmp_path / "data_2d_custom_x.npz",
        {"clip.mp4": {"custom": [a]}},
        layout="coco17",
        video_metadata={"clip.mp4": {"w": 640, "h": 480}},
    )
    with np.load(path, allow_pickle=True) as npz:
        meta = npz["metadata"].item()
    assert meta["layout_name"] == "coco" and meta["keypoints_symmetry"][0][:2] == [1, 3]
    k2d = read_videopose3d(path)
    assert k2d.layout == "coco17" and k2d.image_size == (640, 480) and k2d.intrinsics is None
    np.testing.assert_allclose(k2d.keypoints[..., :2], a)


def test_keypoint_arrays(tmp_path):
    rng = np.random.default_rng(10)
    a = rng.uniform(1, 1000, (8, 17, 2))
    a[3, 5] = np.nan
    a[4, 6] = 0.0
    np.save(tmp_path / "kp.npy", a)
    k2d = read_keypoint_array(tmp_path / "kp.npy")
    assert k2d.layout == "h36m17"
    np.testing.assert_array_equal(k2d.keypoints[3, 5], 0.0)
    np.testing.assert_array_equal(k2d.keypoints[4, 6], 0.0)
    assert k2d.keypoints[0, 0, 2] == 1.0
    b = np.concatenate([a, rng.uniform(0, 1, (8, 17, 1))], -1)
    np.savez(
        tmp_path / "kp3.npz",
        keypoints=b,
        other=np.zeros(3),
        fps=np.array(25.0),
        image_size=np.array([1000, 1000]),
    )
    clip = read_clip(tmp_path / "kp3.npz")
    assert clip.fps == 25.0 and clip.meta.get("assumed") == ["intrinsics"]
    np.testing.assert_allclose(clip.intrinsics, [1000, 1000, 500, 500])
    np.testing.assert_allclose(clip.keypoints[0, :, 2], b[0, :, 2].astype(np.float32))
    np.save(tmp_path / "bad.npy", np.zeros((8, 16, 2)))
    with pytest.raises(FormatError, match=r"bad.npy.*\(T, 17, 2\|3\)"):
        read_keypoint_array(tmp_path / "bad.npy")
    np.savez(tmp_path / "two.npz", a=a, b=a)
    with pytest.raises(FormatError, match="none of the keypoint names"):
        read_keypoint_array(tmp_path / "two.npz")


def test_amass_joints(tmp_path):
    rng = np.random.default_rng(11)
    J = rng.normal(size=(30, 24, 3))
    np.savez(
        tmp_path / "amass.npz", Jtr=J, mocap_framerate=np.array(120.0), poses=np.zeros((30, 156))
    )
    j3 = read_amass_joints(tmp_path / "amass.npz")
    assert j3.fps == 120.0 and j3.joints.shape == (30, 24, 3) and j3.joint_names[0] == "pelvis"
    assert j3.joint_names[7] == "left_ankle"
    np.testing.assert_array_equal(j3.joints, J)
    np.savez(tmp_path / "params.npz", poses=np.zeros((30, 156)), mocap_framerate=np.array(120.0))
    with pytest.raises(FormatError, match="'joints' or 'Jtr'"):
        read_amass_joints(tmp_path / "params.npz")


# --------------------------------------------------------------------------------------------
# read_clip dispatch (formats/__init__.py) and sidecars (formats/camera_file.py)
# --------------------------------------------------------------------------------------------


def test_read_clip_dispatch_and_sidecar(tmp_path):
    rng = np.random.default_rng(12)
    clip = _clip(rng, **_with_gt(rng))
    save_clip(tmp_path / "c.npz", clip)
    same = read_clip(tmp_path / "c.npz")
    np.testing.assert_array_equal(same.gt_q, clip.gt_q)
    # OpenPose folder without any camera information: a clear error asking for the image size
    folder = tmp_path / "vid"
    _op_write(folder, 0, [_op_person(_body(500, 400))])
    with pytest.raises(FormatError, match="image size"):
        read_clip(folder)
    # with a sidecar
    (tmp_path / "vid.camera.json").write_text(
        json.dumps(
            {
                "fx": 1200,
                "fy": 1200,
                "cx": 640,
                "cy": 360,
                "width": 1280,
                "height": 720,
                "fps": 60,
                "extrinsics": np.eye(4).tolist(),
            }
        )
    )
    c = read_clip(folder)
    assert c.fps == 60 and c.image_size.tolist() == [1280, 720] and c.intrinsics[0] == 1200
    assert c.meta["format"] == "openpose" and "assumed" not in c.meta
    # explicit arguments win over the sidecar
    c = read_clip(folder, fps=24, intrinsics=[900, 900, 640, 360])
    assert c.fps == 24 and c.intrinsics[0] == 900
    # sidecar problems name the file and field
    (tmp_path / "vid.camera.json").write_text(
        json.dumps({"fx": 1200, "fy": 1200, "cx": 640, "width": 1, "height": 1})
    )
    with pytest.raises(FormatError, match="vid.camera.json.*'cy'"):
        read_clip(folder)
    with pytest.raises(FormatError, match="unknown keypoint file type"):
        (tmp_path / "x.txt").write_text("hi")
        read_clip(tmp_path / "x.txt")


def test_package_re_exports_every_public_name_of_its_modules():
    """``jmocap.data.formats`` (the import path callers use) offers each module's public names."""
    import importlib
    import pkgutil

    import jmocap.data.formats as formats

    modules = [m.name for m in pkgutil.iter_modules(formats.__path__)]
    assert {"common", "keypoints", "openpose", "coco", "mmpose", "videopose3d"} <= set(modules)
    for m in modules:
        mod = importlib.import_module(f"jmocap.data.formats.{m}")
        assert mod.__doc__, m
        for name in mod.__all__:
            assert name in formats.__all__, f"{m}.{name} not in jmocap.data.formats.__all__"
            assert getattr(formats, name) is getattr(mod, name), f"{m}.{name}"


def test_alphapose_halpe26_results(tmp_path):
    """AlphaPose's output: a COCO results list with 26 keypoints (Halpe-26) and frame-file image
    ids ("12.jpg"); read as a halpe26 clip with frames 0..2, and written back as it was read."""
    from jmocap.layouts import get_layout

    H = get_layout("halpe26")
    rng = np.random.default_rng(3)
    res = []
    for t in (0, 2, 1):
        kp = np.concatenate([rng.uniform(100, 900, (26, 2)), rng.uniform(0.3, 1.0, (26, 1))], -1)
        res.append({"image_id": f"{t}.jpg", "category_id": 1, "keypoints": kp.reshape(-1).tolist(),
                    "score": 2.5, "box": [1, 2, 3, 4], "idx": [0.0]})
    path = tmp_path / "alphapose-results.json"
    path.write_text(json.dumps(res))
    k2d = read_coco_json(path)
    assert k2d.layout == "halpe26" and k2d.keypoints.shape == (3, 26, 3)
    np.testing.assert_array_equal(k2d.frame_ids, [0, 1, 2])
    np.testing.assert_allclose(k2d.keypoints[2, H.index("LHeel")], res[1]["keypoints"][3 * 24:3 * 25], rtol=1e-6)
    clip = read_clip(path, image_size=(1920, 1080), fps=30)
    assert clip.layout == "halpe26" and clip.to_layout("body25").meta["layout_conversion"]["not_used"] == ["Head"]
    back = read_coco_json(write_coco_results(clip, tmp_path / "again.json"))
    np.testing.assert_allclose(back.keypoints, clip.keypoints, rtol=1e-6)
    with pytest.raises(FormatError, match="image_id 'a.jpg' is not an integer"):
        (tmp_path / "named.json").write_text(json.dumps([{**res[0], "image_id": "a.jpg"}]))
        read_coco_json(tmp_path / "named.json")
