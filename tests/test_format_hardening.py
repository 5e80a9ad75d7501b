"""Hostile and clumsy input to the file-format readers (issue 16).

* VideoPose3D ``.npz`` files are pickles: real code-running payloads (``os.system``,
  ``builtins.exec`` via ``__reduce__``) are refused and never run, while files written by numpy
  1.x (``tests/assets/videopose3d_numpy1_p*.npz``, made by ``assets/make_videopose3d_numpy1.py``)
  and 2.x at pickle protocols 2 to 5 still load, checked against ``np.load(allow_pickle=True)``;
* VideoPose3D sequence names are unique per file and safe as file names;
* JSON readers: size, nesting, huge numbers and values of the wrong JSON type are
  ``FormatError``s naming the file, the frame and the field;
* frame numbering and counts within ``jmocap.data.limits``;
* ``.npz`` / ``.npy`` input: declared sizes checked before reading, no silent conversion of
  strings / booleans / objects to numbers in clips.
"""

from __future__ import annotations

import ast
import builtins
import io
import json
import os
import pickle
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npformat

from jmocap.data import limits
from jmocap.data.clip import Clip, ClipFormatError, FormatError, clip_to_arrays, load_clip
from jmocap.data.formats import (
    iter_videopose3d,
    load_npz_pickled,
    read_amass_joints,
    read_camera_json,
    read_clip,
    read_coco_json,
    read_keypoint_array,
    read_keypoints,
    read_mmpose_json,
    read_openpose_folder,
    read_videopose3d,
    safe_name,
    write_videopose3d,
)
from jmocap.data.formats.keypoints import Keypoints2D
from jmocap.data.limits import LimitError, Limits
from jmocap.results import load_result

ASSETS = Path(__file__).parent / "assets"
SRC = Path(__file__).parents[1] / "src" / "jmocap"


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


class RunsShell:
    """Unpickling this runs ``os.system(command)`` (pickled as ``posix.system``)."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


class RunsExec:
    """Unpickling this runs ``builtins.exec(source)``."""

    def __init__(self, source):
        self.source = source

    def __reduce__(self):
        return (builtins.exec, (self.source,))


def _npy_pickled(value, protocol: int) -> bytes:
    """A 0-d object array holding ``value``, as ``np.save`` writes it (a format 1.0 header, then
    ``pickle.dump`` of the array) but at the given pickle protocol."""
    b = io.BytesIO()
    npformat.write_array_header_1_0(b, {"descr": "|O", "fortran_order": False, "shape": ()})
    pickle.dump(np.array(value, dtype=object), b, protocol=protocol)
    return b.getvalue()


def _write_npz(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name + ".npy", data)
    return path


def _npy_bytes(a: np.ndarray) -> bytes:
    b = io.BytesIO()
    np.save(b, a, allow_pickle=False)
    return b.getvalue()


def _lying_npy(shape, descr="<f8") -> bytes:
    """A .npy header declaring ``shape`` followed by only 16 bytes of data."""
    b = io.BytesIO()
    npformat.write_array_header_1_0(b, {"descr": descr, "fortran_order": False, "shape": shape})
    return b.getvalue() + b"\0" * 16


def _reference(path: Path, field: str):
    """What numpy itself unpickles (the independent reference for files that are safe)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # numpy.core names under numpy 2
        with np.load(path, allow_pickle=True) as npz:
            return npz[field].item()


def _kp(T=4, J=17, seed=0):
    return np.random.default_rng(seed).uniform(10, 600, (T, J, 2)).astype(np.float32)


def _good_clip(T=5) -> Clip:
    kp = np.concatenate([_kp(T), np.ones((T, 17, 1), np.float32)], axis=-1)
    return Clip(
        name="c",
        layout="h36m17",
        fps=30.0,
        keypoints=kp,
        intrinsics=[1000.0, 1000.0, 320.0, 240.0],
        image_size=[640, 480],
        gt_contacts=np.zeros((T, 4), np.float32),
        height_m=1.8,
        mass_kg=70.0,
    )


def _match(*parts: str) -> str:
    """A regex matching the given literal parts in order."""
    return ".*".join(re.escape(p) for p in parts)


# --------------------------------------------------------------------------------------------
# 1. no unpickling of input
# --------------------------------------------------------------------------------------------


def test_the_payloads_are_live(tmp_path):
    """The payloads used below really run code under numpy's own loader (so refusing them is
    what protects us), on a marker of their own."""
    for n, payload in enumerate(
        [RunsShell(f"touch {tmp_path / 'live0'}"), RunsExec(f"open({str(tmp_path / 'live1')!r}, 'w').close()")]
    ):
        path = _write_npz(tmp_path / f"live{n}.npz", {"positions_2d": _npy_pickled({"S1": payload}, 3)})
        _reference(path, "positions_2d")
        assert (tmp_path / f"live{n}").exists()


def _payload(kind: str, marker: Path):
    if kind == "system":
        return RunsShell(f"touch {marker}"), "posix.system" if os.name == "posix" else "system"
    return RunsExec(f"open({str(marker)!r}, 'w').close()"), "builtins.exec"


def _ok_positions():
    return {"S1": {"Walking": [_kp()]}}


@pytest.mark.parametrize("kind", ["system", "exec"])
@pytest.mark.parametrize("where", ["positions_2d", "metadata", "nested"])
@pytest.mark.parametrize("protocol", [2, 3, 5])
def test_videopose3d_refuses_code_in_pickles(tmp_path, kind, where, protocol):
    marker = tmp_path / "marker"
    evil, name = _payload(kind, marker)
    positions: object = _ok_positions()
    metadata: object = {"layout_name": "h36m", "num_joints": 17}
    if where == "positions_2d":
        positions = {"S1": {"Walking": [evil]}}
    elif where == "metadata":
        metadata = {"layout_name": "h36m", "x": evil}
    else:  # deep inside a list inside the dict
        positions = {"S1": {"Walking": [_kp(), [1, {"a": [evil]}]]}}
    path = _write_npz(
        tmp_path / "data_2d_h36m_evil.npz",
        {"positions_2d": _npy_pickled(positions, protocol), "metadata": _npy_pickled(metadata, protocol)},
    )
    field = "metadata" if where == "metadata" else "positions_2d"
    for read in (read_videopose3d, lambda p: list(iter_videopose3d(p)), read_keypoints, read_clip):
        with pytest.raises(FormatError, match=_match(str(path), f"field '{field}'", f"refuses to unpickle '{name}'")):
            read(path)
    assert not marker.exists()


def test_videopose3d_refuses_non_plain_objects(tmp_path):
    """Classes numpy could rebuild but that are not plain data, arrays of objects inside the
    dict, a shape the data does not fill, and truncated pickles."""
    cases = {
        "masked array": ({"S1": {"W": [np.ma.masked_array([1.0])]}}, "refuses to unpickle 'numpy.ma.core"),
        "set": ({"S1": {"W": [{1, 2}]}}, "refuses to unpickle 'builtins.set'"),
        "complex": ({"S1": {"W": [1j]}}, "refuses to unpickle 'builtins.complex'"),
        "object array": ({"S1": {"W": [np.array([None, 1], dtype=object)]}}, "holds an array of Python objects"),
    }
    for label, (value, message) in cases.items():
        path = _write_npz(tmp_path / f"{label}.npz", {"positions_2d": _npy_pickled(value, 3)})
        with pytest.raises(FormatError, match=_match("field 'positions_2d'", message)):
            read_videopose3d(path)
    data = _npy_pickled(_ok_positions(), 3)
    path = _write_npz(tmp_path / "truncated.npz", {"positions_2d": data[: len(data) // 2]})
    with pytest.raises(FormatError, match="field 'positions_2d': not a readable pickled array"):
        read_videopose3d(path)


def test_videopose3d_refuses_arrays_larger_than_the_limit(tmp_path):
    """A pickled array's state may declare a shape far larger than its data; numpy would
    allocate it first. Also a plain member whose header declares too much."""
    small = pickle.dumps(np.array([None], dtype=object), protocol=2)
    huge = small.replace(b"K\x01\x85", b"J\x00\xca\x9a;\x85")  # shape (1,) -> (10**9,)
    assert huge != small
    header = io.BytesIO()
    npformat.write_array_header_1_0(header, {"descr": "|O", "fortran_order": False, "shape": (1,)})
    path = _write_npz(tmp_path / "huge.npz", {"positions_2d": header.getvalue() + huge})
    with pytest.raises(LimitError, match="field 'positions_2d'.*max_file_bytes"):
        read_videopose3d(path)
    path = _write_npz(
        tmp_path / "huge2.npz",
        {"positions_2d": _npy_pickled(_ok_positions(), 3), "metadata": _lying_npy((10**11,))},
    )
    with pytest.raises(LimitError, match="field 'metadata'.*max_file_bytes"):
        read_videopose3d(path)


def _check_same(got, ref):
    assert type(got) is type(ref) or isinstance(got, type(ref)), (type(got), type(ref))
    if isinstance(ref, dict):
        assert list(got) == list(ref)
        for k in ref:
            _check_same(got[k], ref[k])
    elif isinstance(ref, (list, tuple)):
        assert len(got) == len(ref)
        for a, b in zip(got, ref, strict=True):
            _check_same(a, b)
    elif isinstance(ref, np.ndarray):
        assert got.dtype == ref.dtype and got.shape == ref.shape
        np.testing.assert_array_equal(got, ref)
    else:
        assert got == ref and type(got) is type(ref)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_videopose3d_plain_files_load_at_every_protocol(tmp_path, protocol):
    """numpy 2 object arrays of dicts of float32 / float64 arrays, numpy scalars, strings and
    bytes, at pickle protocols 2-5, read exactly as numpy reads them."""
    positions = {
        "S9": {"Walking 1": [_kp(5, seed=c) for c in range(4)]},
        "S11": {"Sitting": [_kp(3).astype(np.float64), np.asfortranarray(_kp(2).astype(np.float64))]},
    }
    metadata = {
        "layout_name": "h36m",
        "num_joints": np.int64(17),
        "keypoints_symmetry": [[4, 5, 6, 11, 12, 13], [1, 2, 3, 14, 15, 16]],
        "extra": {"s": np.str_("x"), "f": np.float32(2.5), "b": b"raw", "e": b"", "t": (1, None, True)},
    }
    path = _write_npz(
        tmp_path / f"p{protocol}.npz",
        {"positions_2d": _npy_pickled(positions, protocol), "metadata": _npy_pickled(metadata, protocol)},
    )
    got = load_npz_pickled(path, ["positions_2d", "metadata"])
    for field in ("positions_2d", "metadata"):
        _check_same(got[field], _reference(path, field))
    k2d = read_videopose3d(path, "S11", "Sitting", 1)
    np.testing.assert_allclose(k2d.keypoints[..., :2], positions["S11"]["Sitting"][1])


def test_videopose3d_savez_and_writer_files_load(tmp_path):
    path = tmp_path / "savez.npz"
    positions = {"S1": {"Walk": [_kp(), _kp(seed=1).astype(np.float64)]}}
    np.savez_compressed(path, positions_2d=positions, metadata={"layout_name": "h36m", "num_joints": 17})
    _check_same(load_npz_pickled(path, ["positions_2d"])["positions_2d"], _reference(path, "positions_2d"))
    assert [s.name for s in iter_videopose3d(path)] == ["S1_Walk_0", "S1_Walk_1"]
    a = _kp(6)
    path = write_videopose3d(tmp_path / "w.npz", {"v.mp4": {"custom": [a]}}, layout="coco17",
                             video_metadata={"v.mp4": {"w": 640, "h": 480}})
    k2d = read_videopose3d(path)
    assert k2d.image_size == (640, 480) and k2d.layout == "coco17"
    np.testing.assert_allclose(k2d.keypoints[..., :2], a)


@pytest.mark.parametrize("protocol", [2, 3, 5])
def test_videopose3d_files_written_by_numpy1_load(protocol):
    """Files written by numpy 1.26 (``numpy.core.*`` names in the pickle)."""
    path = ASSETS / f"videopose3d_numpy1_p{protocol}.npz"
    assert b"numpy.core.multiarray" in zipfile.ZipFile(path).read("positions_2d.npy")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy.core deprecation: those modules are not imported
        got = load_npz_pickled(path, ["positions_2d", "metadata"])
    for field in ("positions_2d", "metadata"):
        _check_same(got[field], _reference(path, field))
    # and against the values the generator script documents
    seqs = {s.name: s for s in iter_videopose3d(path)}
    assert sorted(seqs) == ["S11_Sitting_0"] + [f"S9_Walking_1_{c}" for c in range(4)]
    n = 3 * 17 * 2
    np.testing.assert_array_equal(
        seqs["S9_Walking_1_2"].keypoints[..., :2], np.arange(n).reshape(3, 17, 2) + 1 + 2000
    )
    np.testing.assert_array_equal(
        seqs["S11_Sitting_0"].keypoints[..., :2], np.arange(2 * 17 * 2).reshape(2, 17, 2) + 0.5
    )


def test_no_reader_unpickles():
    """No ``allow_pickle`` other than a literal False, no ``pickle.load``/``loads`` and no
    ``pickle.Unpickler`` outside the restricted unpickler, anywhere in src."""
    found = []
    for py in SRC.rglob("*.py"):
        tree = ast.parse(py.read_text(), str(py))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                for kw in node.keywords:
                    if kw.arg == "allow_pickle" and not (
                        isinstance(kw.value, ast.Constant) and kw.value.value is False
                    ):
                        found.append(f"{py}:{node.lineno}: allow_pickle")
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in ("pickle", "_pickle", "cPickle", "dill", "joblib")
                and node.attr in ("load", "loads", "Unpickler")
                and py.name != "safe_pickle.py"
            ):
                found.append(f"{py}:{node.lineno}: pickle.{node.attr}")
    assert not found, found


# --------------------------------------------------------------------------------------------
# 2. unique, safe VideoPose3D sequence names
# --------------------------------------------------------------------------------------------


def test_videopose3d_names_are_unique_and_deterministic(tmp_path):
    positions = {
        "S1": {"Walk 1": [_kp()], "Walk_1": [_kp(seed=1)], "Walk/1": [_kp(seed=2)], "walk 1": [_kp(seed=3)]},
    }
    path = tmp_path / "d.npz"
    np.savez_compressed(path, positions_2d=positions)
    seqs = list(iter_videopose3d(path))
    names = [s.name for s in seqs]
    assert names == ["S1_Walk_1_0", "S1_Walk_1_0~2", "S1_Walk_1_0~3", "S1_walk_1_0~4"]
    assert len({n.casefold() for n in names}) == 4  # distinct on case-insensitive file systems too
    assert "renamed_from" not in seqs[0].meta
    assert [s.meta.get("renamed_from") for s in seqs[1:]] == ["S1_Walk_1_0", "S1_Walk_1_0", "S1_walk_1_0"]
    assert [s.meta["action"] for s in seqs] == list(positions["S1"])  # the original keys are kept
    np.testing.assert_allclose(seqs[1].keypoints[..., :2], positions["S1"]["Walk_1"][0])
    assert [s.name for s in iter_videopose3d(path)] == names  # deterministic
    assert read_videopose3d(path, "S1", "Walk/1", 0).name == "S1_Walk_1_0~3"  # same as iter


def test_videopose3d_names_are_safe_file_names(tmp_path):
    long_a, long_b = "x" * 300 + "a", "x" * 300 + "b"
    positions = {
        "../..": {"a\\b\x00c": [_kp()]},
        ".hidden": {"ok": [_kp()]},
        "S1": {long_a: [_kp()], long_b: [_kp()], "é" * 200: [_kp()]},
    }
    path = tmp_path / "d.npz"
    np.savez_compressed(path, positions_2d=positions)
    names = [s.name for s in iter_videopose3d(path)]
    assert len(set(names)) == len(names) == 5
    for n in names:
        assert not set(n) & {"/", "\\", "\x00"} and not n.startswith(".") and n not in ("", ".", "..")
        assert len(n.encode("utf-8")) <= 100
        (tmp_path / "out" / n).mkdir(parents=True)  # really usable as one component
    assert names[0] == "___.._a_b_c_0" and names[1] == "_hidden_ok_0"
    assert len(list((tmp_path / "out").iterdir())) == 5
    assert safe_name("a" * 150) != safe_name("a" * 151)  # cut names keep a hash of the whole


# --------------------------------------------------------------------------------------------
# 3. JSON readers
# --------------------------------------------------------------------------------------------


def _openpose(tmp_path, frames: dict[int, object], name="op") -> Path:
    d = tmp_path / name
    d.mkdir()
    for k, v in frames.items():
        (d / f"v_{k:012d}_keypoints.json").write_text(v if isinstance(v, str) else json.dumps(v))
    return d


GOOD25 = [float(i + 1) for i in range(75)]
GOOD17 = [float(i + 1) for i in range(51)]
MM17 = [[float(i + 1), float(i + 2)] for i in range(17)]


def test_json_size_depth_and_huge_numbers(tmp_path):
    d = _openpose(tmp_path, {0: {"people": [{"pose_keypoints_2d": GOOD25}]}})
    with limits.use(Limits(max_file_bytes=100)), pytest.raises(LimitError, match=_match("frame 0", "max_file_bytes")):
        read_openpose_folder(d)
    d = _openpose(tmp_path, {3: "[" * 100_000 + "]" * 100_000}, "deep")
    with pytest.raises(LimitError, match=_match("frame 3", "max_json_depth = 64", "--limit max_json_depth=")):
        read_openpose_folder(d)
    d = _openpose(tmp_path, {3: {"people": [], "x": json.loads("[" * 70 + "]" * 70)}}, "deep70")
    with pytest.raises(LimitError, match="JSON nests arrays / objects more than 64 deep"):
        read_openpose_folder(d)
    with limits.use(Limits(max_json_depth=100)):
        assert read_openpose_folder(d).num_frames == 1  # a raised limit lets it through
    d = _openpose(tmp_path, {0: '{"people": [], "n": ' + "7" * 5000 + "}"}, "digits")
    with pytest.raises(FormatError, match=_match("frame 0", "not readable JSON", "digits")):
        read_openpose_folder(d)
    p = tmp_path / "cam.camera.json"
    p.write_text('{"fx": 1000, "fy": 1000, "cx": 1, "cy": 1, "width": 9, "height": 9, "fps": 1e400}')
    with pytest.raises(FormatError, match=_match(str(p), "field 'fps'", "finite")):
        read_camera_json(p)


OPENPOSE_CASES = [
    ({"people": {"a": 1}}, "field 'people': must be a list"),
    ({"people": [{"pose_keypoints_2d": ["1"] * 75}]}, "field 'people[0].pose_keypoints_2d': must contain only numbers, found a string '1'"),
    ({"people": [{"pose_keypoints_2d": [True] * 75}]}, "field 'people[0].pose_keypoints_2d': must contain only numbers, found a boolean"),
    ({"people": [{"pose_keypoints_2d": GOOD25[:-1]}]}, "field 'people[0].pose_keypoints_2d': has 74 values"),
    ({"people": [{"pose_keypoints_2d": {"x": 1}}]}, "field 'people[0].pose_keypoints_2d': must be a list"),
    ({"version": "x", "people": []}, "field 'version': must be a number, got a string 'x'"),
    ({"people": [{"person_id": True, "pose_keypoints_2d": GOOD25}]}, "field 'people[0].person_id': must be a number, got a boolean"),
    ({"people": [{"person_id": ["2"], "pose_keypoints_2d": GOOD25}]}, "field 'people[0].person_id': must be a number"),
    ([1, 2], "field 'people': not an OpenPose keypoints file"),
]


@pytest.mark.parametrize("data, message", OPENPOSE_CASES)
def test_openpose_wrong_json_types(tmp_path, data, message):
    d = _openpose(tmp_path, {0: {"people": []}, 7: data})
    f = d / "v_000000000007_keypoints.json"
    with pytest.raises(FormatError, match="^" + _match(f"{f}: frame 7: ", message)):
        read_openpose_folder(d)


def test_openpose_good_values_still_read(tmp_path):
    """What the checks must let through: integer and null values, person_id lists, version."""
    values = [int(v) for v in GOOD25]
    values[3:6] = [None, None, None]
    d = _openpose(tmp_path, {0: {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": values}]}})
    k = read_openpose_folder(d)
    assert k.keypoints.dtype == np.float32 and k.keypoints[0, 1, 2] == 0 and k.keypoints[0, 0, 0] == 1


def _json_file(tmp_path, data, name="f.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(data))
    return p


COCO_CASES = [
    ([{"image_id": "1", "keypoints": GOOD17, "score": 1}], None, "field 'image_id': image_id '1' is not an integer"),
    ([{"image_id": 1.0, "keypoints": GOOD17, "score": 1}], None, "field 'image_id': image_id 1.0 is not an integer"),
    ([{"image_id": True, "keypoints": GOOD17, "score": 1}], None, "field 'image_id': image_id True is not an integer"),
    ([{"image_id": 3, "keypoints": GOOD17[:-1], "score": 1}], 3, "field '[0].keypoints': has 50 values, expected 51"),
    ([{"image_id": 3, "keypoints": ["1"] * 51, "score": 1}], 3, "field '[0].keypoints': must contain only numbers"),
    ([{"image_id": 3, "keypoints": GOOD17, "score": "0.9"}], 3, "field '[0].score': must be a number, got a string '0.9'"),
    ([{"image_id": 3, "keypoints": GOOD17, "score": True}], 3, "field '[0].score': must be a number, got a boolean"),
    ([{"image_id": 3, "keypoints": GOOD17, "category_id": "1"}], 3, "field '[0].category_id': must be a number"),
    ([{"image_id": 3, "keypoints": GOOD17, "track_id": False}], 3, "field '[0].track_id': must be a number"),
    ({"images": [{"id": [1]}], "annotations": []}, None, "field 'images[0].id': must be an integer or a string"),
    ({"images": [{"id": 1, "width": "640", "height": 480}], "annotations": []}, None, "field 'images[0].width': must be a number"),
    ({"images": {"a": 1}, "annotations": []}, None, "field 'images': must be a list"),
    ({"images": [{"id": 1}], "annotations": [{"image_id": [1], "keypoints": GOOD17}]}, None, "field 'image_id'"),
]


@pytest.mark.parametrize("data, frame, message", COCO_CASES)
def test_coco_wrong_json_types(tmp_path, data, frame, message):
    p = _json_file(tmp_path, data)
    where = f"{p}: frame {frame}: " if frame is not None else f"{p}: "
    with pytest.raises(FormatError, match="^" + _match(where, message)):
        read_coco_json(p)


MMPOSE_CASES = [
    ([{"frame_id": 0, "instances": [{"keypoints": [["1", "2"]] * 17}]}], 0, "field 'instances[0].keypoints': must contain only numbers, found a string"),
    ([{"frame_id": 0, "instances": [{"keypoints": [[True, False]] * 17}]}], 0, "field 'instances[0].keypoints': must contain only numbers, found a boolean"),
    ([{"frame_id": 0, "instances": [{"keypoints": [[1, 2]] * 16 + [[1]]}]}], 0, "field 'instances[0].keypoints': has rows of different lengths"),
    ([{"frame_id": 0, "instances": [{"keypoints": "x"}]}], 0, "field 'instances[0].keypoints': must be a (17, 2) list"),
    ([{"frame_id": 0, "instances": [{"keypoints": MM17, "keypoint_scores": ["1"] * 17}]}], 0, "field 'instances[0].keypoint_scores': must contain only numbers"),
    ([{"frame_id": 0, "instances": [{"keypoints": MM17, "bbox_score": "0.5"}]}], 0, "field 'instances[0].bbox_score': must be a number"),
    ([{"frame_id": 0, "instances": [{"keypoints": MM17, "track_id": "a"}]}], 0, "field 'instances[0].track_id': must be a number"),
    ([{"frame_id": True, "instances": []}], 0, "field 'frame_id': must be an integer, got a boolean"),
    ([{"frame_id": "3", "instances": []}], 0, "field 'frame_id': must be an integer, got a string"),
    ([{"frame_id": 0, "instances": {"a": 1}}], 0, "field 'instances': must be a list"),
]


@pytest.mark.parametrize("data, frame, message", MMPOSE_CASES)
def test_mmpose_wrong_json_types(tmp_path, data, frame, message):
    p = _json_file(tmp_path, data)
    with pytest.raises(FormatError, match="^" + _match(f"{p}: frame {frame}: ", message)):
        read_mmpose_json(p)


def test_mmpose_huge_numbers_are_missing_joints(tmp_path):
    """An integer too large for a float is an infinite coordinate: a missing joint, as NaN is."""
    p = tmp_path / "m.json"
    kps = json.dumps(MM17).replace("[1.0, 2.0]", "[" + "1" * 400 + ", 2]", 1)
    p.write_text('[{"frame_id": 0, "instances": [{"keypoints": ' + kps + "}]}]")
    k = read_mmpose_json(p)
    assert k.keypoints[0, 0].tolist() == [0, 0, 0] and k.keypoints[0, 1, 2] == 1


CAMERA = {"fx": 1000.0, "fy": 1000.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
ROT = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
CAMERA_CASES = [
    ({"fps": "30"}, "fps", "must be a number, got a string '30'"),
    ({"fps": True}, "fps", "must be a number, got a boolean"),
    ({"fps": 0}, "fps", "must be > 0"),
    ({"fx": "1000"}, "fx", "must be a number, got a string"),
    ({"cy": False}, "cy", "must be a number, got a boolean"),
    ({"fy": -5}, "fy", "must be > 0"),
    ({"width": 640.5}, "width", "must be an integer"),
    ({"width": 1e30}, "width", "must be at most 2147483647"),
    ({"height": True}, "height", "must be a number, got a boolean"),
    ({"intrinsics": [1, 2, 3]}, "intrinsics", "is not a camera sidecar key"),
    ({"image_size": [1e30, 5]}, "image_size", "is not a camera sidecar key"),
    ({"extrinsics": np.eye(3).tolist()}, "extrinsics", "must have shape (4, 4), got (3, 3)"),
    ({"extrinsics": (2 * np.eye(4)).tolist()}, "extrinsics", "must be a rigid transform"),
    ({"extrinsics": np.diag([1.0, 1, -1, 1]).tolist()}, "extrinsics", "must be a rigid transform"),
    ({"extrinsics": [["1", 0, 0, 0]] + np.eye(4)[1:].tolist()}, "extrinsics", "must contain only numbers"),
    ({"extrinsics": "eye"}, "extrinsics", "must be a list of lists"),
]


@pytest.mark.parametrize("change, field, message", CAMERA_CASES)
def test_camera_sidecar_wrong_json_types(tmp_path, change, field, message):
    p = _json_file(tmp_path, {**CAMERA, **change}, "c.camera.json")
    with pytest.raises(FormatError, match="^" + _match(f"{p}: field '{field}': {message}")):
        read_camera_json(p)


def test_camera_sidecar_good_values(tmp_path):
    p = _json_file(tmp_path, {**CAMERA, "width": 640.0, "fps": 25, "extrinsics": ROT.tolist()}, "c.camera.json")
    cam = read_camera_json(p)
    assert cam["image_size"] == (640, 480) and type(cam["image_size"][0]) is int and cam["fps"] == 25.0
    np.testing.assert_array_equal(cam["extrinsics"], ROT)


def test_to_clip_refuses_a_converted_image_size():
    k = Keypoints2D(keypoints=np.ones((2, 17, 3), np.float32), layout="h36m17", name="k",
                    frame_ids=np.arange(2), source="src.json")
    for size, message in ((("640", 480), "got a string"), ((True, 480), "got a boolean"),
                          ((640, 1e30), "at most"), ((640,), "must be (width, height)")):
        with pytest.raises(FormatError, match=_match("src.json", "field 'image_size'", message)):
            k.to_clip(image_size=size)
    with pytest.raises(FormatError, match=_match("src.json: field 'fps'", "must be a number")):
        k.to_clip(image_size=(640, 480), fps="30")
    assert k.to_clip(image_size=np.array([640, 480])).image_size.tolist() == [640, 480]


# --------------------------------------------------------------------------------------------
# 4. frame numbering and count
# --------------------------------------------------------------------------------------------


def test_frame_gaps_and_counts_are_limited(tmp_path):
    d = _openpose(tmp_path, {0: {"people": []}, 20_001: {"people": []}})
    with pytest.raises(LimitError, match=_match("frame 20001", "max_frame_gap = 10000")):
        read_openpose_folder(d)
    with limits.use(Limits(max_frame_gap=20_000)):
        assert read_openpose_folder(d).num_frames == 20_002
    d = _openpose(tmp_path, {i: {"people": []} for i in range(6)}, "six")
    with limits.use(Limits(max_frames=5)):
        with pytest.raises(LimitError, match="6 frames, over the limit max_frames = 5"):
            read_openpose_folder(d)
        p = _json_file(tmp_path, [{"image_id": i, "keypoints": GOOD17} for i in (0, 5)])
        with pytest.raises(LimitError, match="max_frames"):
            read_coco_json(p)
        np.save(tmp_path / "a.npy", _kp(6))
        with pytest.raises(LimitError, match="max_frames"):
            read_keypoint_array(tmp_path / "a.npy")
        np.savez_compressed(tmp_path / "vp.npz", positions_2d={"S1": {"W": [_kp(6)]}})
        with pytest.raises(LimitError, match="max_frames"):
            list(iter_videopose3d(tmp_path / "vp.npz"))
        with pytest.raises(LimitError, match=_match("clip 'c'", "max_frames")):
            _good_clip(6)
        _good_clip(5)


@pytest.mark.parametrize(
    "frames, message",
    [
        ([-1, 0], "frame -1: frame number -1 is negative"),
        ([1.5], "field 'frame_id': must be an integer"),
        ([2, 2], "frame 2: frame number 2 appears more than once"),
    ],
)
def test_bad_frame_numbers(tmp_path, frames, message):
    p = _json_file(tmp_path, [{"frame_id": f, "instances": []} for f in frames])
    with pytest.raises(FormatError, match=_match(str(p), message)):
        read_mmpose_json(p)


# --------------------------------------------------------------------------------------------
# 5. strict .npz / .npy reading
# --------------------------------------------------------------------------------------------


def _clip_file(tmp_path, name="c.npz", **changes) -> Path:
    arrays = clip_to_arrays(_good_clip())
    arrays.update(changes)
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("fps", np.array("30"), "field 'fps' must be a number"),
        ("fps", np.array(True), "field 'fps' must be a number"),
        ("height_m", np.array("1.8"), "field 'height_m' must be a number"),
        ("mass_kg", np.array(False), "field 'mass_kg' must be a number"),
        ("keypoints", np.full((5, 17, 3), "1"), "field 'keypoints' cannot be read as float32: it holds strings"),
        ("intrinsics", np.array([True, True, True, True]), "field 'intrinsics' cannot be read as float64: it holds booleans"),
        ("intrinsics", np.array([1000, 1000, 320, 240], np.complex128), "field 'intrinsics' cannot be read as float64: it holds complex"),
        ("image_size", np.array(["640", "480"]), "field 'image_size' cannot be read as float64: it holds strings"),
        ("image_size", np.array([1e30, 5.0]), "field 'image_size' must be positive integers up to"),
        ("extrinsics", np.eye(4, dtype=bool), "field 'extrinsics' cannot be read as float64: it holds booleans"),
        ("gt_contacts", np.zeros((5, 4), bool), "field 'gt_contacts' cannot be read as float32: it holds booleans"),
        ("gt_q", np.full((5, 7), "0"), "field 'gt_q' cannot be read as float32: it holds strings"),
    ],
)
def test_clip_files_refuse_converted_types(tmp_path, field, value, message):
    path = _clip_file(tmp_path, **{field: value})
    with pytest.raises(ClipFormatError, match="^" + _match(f"{path}: {message}")):
        load_clip(path)


def test_clip_objects_refuse_converted_types():
    clip = _good_clip()
    for change, message in (
        ({"fps": "30"}, "field 'fps' must be a number"),
        ({"fps": True}, "field 'fps' must be a number"),
        ({"mass_kg": "70"}, "field 'mass_kg' must be a number"),
        ({"intrinsics": [1000, 1000, "320", 240]}, "field 'intrinsics'"),
        ({"gt_contacts": np.ones((5, 4), bool)}, "field 'gt_contacts'"),
        ({"keypoints": clip.keypoints.astype(object)}, "field 'keypoints'"),
    ):
        with pytest.raises(ClipFormatError, match=re.escape(message)):
            clip.replace(**change)
    assert clip.replace(fps=np.float32(25), mass_kg=np.int64(60)).fps == 25.0


def test_clip_files_with_pickled_objects_are_not_unpickled(tmp_path):
    marker = tmp_path / "marker"
    path = _clip_file(tmp_path, image_size=np.array([RunsShell(f"touch {marker}"), 480], dtype=object))
    with pytest.raises(ClipFormatError, match=_match(str(path), "field 'image_size': holds Python objects")):
        load_clip(path)
    assert not marker.exists()


def test_clip_meta_json_is_bounded(tmp_path):
    deep = "[" * 100_000 + "]" * 100_000
    path = _clip_file(tmp_path, meta=np.array('{"x": ' + deep + "}"))
    with pytest.raises(LimitError, match=_match(str(path), "field 'meta'", "too deeply", "max_json_depth")):
        load_clip(path)
    path = _clip_file(tmp_path, "c2.npz", meta=np.array('{"x": ' + "[" * 70 + "]" * 70 + "}"))
    with pytest.raises(LimitError, match=_match(str(path), "field 'meta'", "max_json_depth")):
        load_clip(path)


def test_declared_array_sizes_are_checked_before_reading(tmp_path):
    """A member (or .npy) whose header declares 800 GB but holds 16 bytes: every reader says
    which limit, instead of numpy's MemoryError (or an allocation)."""
    lying = _lying_npy((10**11,))
    clip = tmp_path / "clip.npz"
    arrays = {k: _npy_bytes(v) for k, v in clip_to_arrays(_good_clip()).items()}
    _write_npz(clip, {**arrays, "gt_tau": lying})
    kp = _write_npz(tmp_path / "kp.npz", {"keypoints": _npy_bytes(_kp()), "fps": lying})
    amass = _write_npz(tmp_path / "amass.npz", {"joints": lying, "fps": _npy_bytes(np.array(30.0))})
    result = _write_npz(tmp_path / "result.npz", {"q": lying, "fps": _npy_bytes(np.array(30.0))})
    (tmp_path / "kp.npy").write_bytes(lying)
    for read, path in ((load_clip, clip), (read_keypoint_array, kp), (read_amass_joints, amass),
                       (load_result, result), (read_keypoint_array, tmp_path / "kp.npy")):
        with pytest.raises(LimitError, match=_match(str(path), "800000000000 bytes", "max_file_bytes")):
            read(path)
    with limits.use(Limits(max_file_bytes=1000)), pytest.raises(LimitError, match="max_file_bytes"):
        load_clip(_clip_file(tmp_path, "big.npz", gt_q=np.zeros((5, 100))))
    raw = _write_npz(tmp_path / "raw.npz", arrays)
    with zipfile.ZipFile(raw, "a") as z:
        z.writestr("notes", b"not an array")  # np.load would hand back these bytes
    with pytest.raises(ClipFormatError, match=_match(str(raw), "member 'notes' is not an array")):
        load_clip(raw)


def test_keypoint_array_extras_refuse_converted_types(tmp_path):
    for label, extra, message in (
        ("fps_str", {"fps": np.array("30")}, "field 'fps': has shape () (<U2), expected () numbers"),
        ("fps_vec", {"fps": np.array([30.0, 30.0])}, "field 'fps': has shape (2,)"),
        ("size_huge", {"image_size": np.array([1e30, 5.0])}, "field 'image_size': must be positive integers"),
        ("size_nan", {"image_size": np.array([np.nan, 5.0])}, "field 'image_size': has non-finite values"),
        ("intr_bool", {"intrinsics": np.ones(4, bool)}, "field 'intrinsics': has shape (4,) (bool)"),
    ):
        path = tmp_path / f"{label}.npz"
        np.savez(path, keypoints=_kp(), **extra)
        with pytest.raises(FormatError, match="^" + _match(f"{path}: {message}")):
            read_keypoint_array(path)
    path = tmp_path / "ok.npz"
    np.savez(path, keypoints=_kp(), fps=np.array(25), image_size=np.array([640.0, 480.0]))
    k = read_keypoint_array(path)
    assert k.fps == 25.0 and k.image_size == (640, 480)


def test_amass_and_results_refuse_wrong_types(tmp_path):
    path = tmp_path / "a.npz"
    np.savez(path, joints=np.zeros((3, 22, 3)), fps=np.array("60"))
    with pytest.raises(FormatError, match=_match(str(path), "field 'fps'", "expected a number")):
        read_amass_joints(path)
    for key, text, message in (
        ("assumed", '"fps"', "must be a JSON list of strings"),
        ("assumed", "[" * 100_000 + "]" * 100_000, "max_json_depth"),
        ("warnings", "[" * 70 + "]" * 70, "max_json_depth"),
        ("diagnostics", '{"x": true}', "not a JSON object of numbers"),
        ("diagnostics", '{"x": ' + "9" * 5000 + "}", "not readable JSON"),
    ):
        path = tmp_path / f"r_{key}.npz"
        np.savez(path, q=np.zeros((3, 8), np.float32), fps=np.array(30.0), **{key: np.array(text)})
        with pytest.raises(FormatError, match=_match(str(path), f"field '{key}'", message)):
            load_result(path)
