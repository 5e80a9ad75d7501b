"""jmocap.export.gltf: GLB round trip against MuJoCo C, structure, forces, bad input.

Reference: MuJoCo C ``mj_kinematics`` (``xpos``, ``xmat``, ``site_xpos``). The GLB is read
back with pygltflib (JSON) and this file's own code: the accessors are decoded with numpy
from the binary chunk, the animations evaluated at the frame times and the node hierarchy
composed as 4x4 ``T R S`` matrices, the glTF 2.0 rules, knowing nothing of the writer. World
points map back by the *documented* axes only: ``(X, Y, Z)_gltf = (y, z, x)_jmocap``.
Tolerance 1e-4 m (the issue's); float32 storage gives about 1e-6 m.

Structure: :func:`check_glb` is a pure-Python validator of the container and the document
(lengths, alignment, index ranges, accessor bounds, key times, unit quaternions, winding);
a test corrupts files to show it fails. The Khronos glTF validator (npm ``gltf-validator``)
runs too where it is installed: ``JMOCAP_GLTF_VALIDATOR`` names a node runner script (called
as ``node SCRIPT FILE.glb``, printing the validator's JSON report) or a folder holding
``node_modules/gltf-validator`` (``npm install gltf-validator`` in it); ``/tmp/gltfval`` and
``~/.cache/jmocap/gltf-validator`` are looked at as well. Otherwise that one test is skipped.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import mujoco
import numpy as np
import pygltflib
import pytest

from jmocap.model import character
from jmocap.results import result_model

C = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # documented: gltf = C @ jmocap
TOL = 1e-4
FPS = 30.0
CONTACT_NAMES = ("left_heel", "left_toe", "right_heel", "right_toe")

gltf = pytest.importorskip("jmocap.export.gltf")
write_glb = gltf.write_glb


# ======================================================================================
# inputs
# ======================================================================================


def make_result(model, T: int = 36, seed: int = 0, name: str = "walk", height_m=None, mass_kg=None) -> dict:
    """A short motion: a moving, turning, tilting root and hinges swinging inside their ranges."""
    rng = np.random.default_rng(seed)
    mj = model.mj
    t = np.arange(T) / FPS
    q = np.tile(np.asarray(mj.qpos0, np.float64), (T, 1))
    q[:, 0] = 0.3 + 1.2 * t
    q[:, 1] = -0.2 + 0.4 * np.sin(2 * t)
    q[:, 2] = 0.9 + 0.05 * np.sin(5 * t)
    yaw, pitch, roll = 2.5 * t + seed, 0.2 * np.sin(3 * t), 0.15 * np.cos(4 * t)
    for k in range(T):  # root quaternion: yaw about z, pitch about y, roll about x (intrinsic)
        qq = np.zeros(4)
        mujoco.mju_euler2Quat(qq, np.array([roll[k], pitch[k], yaw[k]]), "XYZ")
        q[k, 3:7] = qq
    for j in range(mj.njnt):
        if int(mj.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_HINGE):
            continue
        a = int(mj.jnt_qposadr[j])
        lo, hi = mj.jnt_range[j] if mj.jnt_limited[j] else (-np.pi, np.pi)
        mid, amp = 0.5 * (lo + hi), 0.45 * (hi - lo)
        q[:, a] = mid + amp * np.sin(2 * np.pi * rng.uniform(0.5, 2.0) * t + rng.uniform(0, 2 * np.pi))
    grf = rng.normal(scale=60.0, size=(T, 4, 3))
    grf[..., 2] = np.abs(grf[..., 2]) * 4 + 20.0  # vertical parts positive
    grf[: T // 3, 1] = 0.0  # the left toe off the ground for a while: no arrow
    prob = (np.sin(np.arange(T)[:, None] * 0.7 + np.arange(4)) > 0).astype(np.float32) * 0.8 + 0.1
    return {
        "name": name,
        "q": q.astype(np.float32),
        "fps": FPS,
        "grf": grf.astype(np.float32),
        "contact_prob": prob,
        "forces_estimated": True,
        "height_m": height_m,
        "mass_kg": mass_kg,
        "assumed": [],
    }


@pytest.fixture(scope="module")
def model():
    return character()


def mujoco_frames(model, q):
    """(T, nbody, 3) xpos, (T, nbody, 3, 3) xmat, (T, nsite, 3) site_xpos: MuJoCo C."""
    d = mujoco.MjData(model.mj)
    xpos, xmat, sites = [], [], []
    for qt in np.asarray(q, np.float64):
        d.qpos[:] = qt
        mujoco.mj_kinematics(model.mj, d)
        xpos.append(d.xpos.copy())
        xmat.append(d.xmat.reshape(-1, 3, 3).copy())
        sites.append(d.site_xpos.copy())
    return np.stack(xpos), np.stack(xmat), np.stack(sites)


# ======================================================================================
# an independent GLB reader
# ======================================================================================

COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def split_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk) of a GLB, checking the container (glTF 2.0, section 4.4)."""
    assert len(data) >= 20, "GLB shorter than its header"
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF", f"bad magic {magic!r}"
    assert version == 2, f"GLB version {version}"
    assert length == len(data), f"header length {length} != file size {len(data)}"
    assert length % 4 == 0, "file length not 4-byte aligned"
    chunks = []
    at = 12
    while at < length:
        assert at + 8 <= length, "truncated chunk header"
        n, kind = struct.unpack_from("<I4s", data, at)
        assert n % 4 == 0, f"chunk {kind!r} length {n} not a multiple of 4"
        assert at + 8 + n <= length, f"chunk {kind!r} runs past the end of the file"
        chunks.append((kind, data[at + 8 : at + 8 + n]))
        at += 8 + n
    assert at == length, "chunks do not end at the file's end"
    assert chunks and chunks[0][0] == b"JSON", "first chunk is not JSON"
    assert len(chunks) == 2 and chunks[1][0] == b"BIN\0", "expected one BIN chunk after the JSON"
    doc = json.loads(chunks[0][1].decode("utf-8"))
    return doc, chunks[1][1]


def read_accessor(doc: dict, blob: bytes, i: int) -> np.ndarray:
    acc = doc["accessors"][i]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(COMPONENT[acc["componentType"]])
    n = NCOMP[acc["type"]]
    elem = dtype.itemsize * n
    stride = view.get("byteStride", elem)
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    rows = [np.frombuffer(blob, dtype, n, start + k * stride) for k in range(acc["count"])] if stride != elem else None
    a = np.stack(rows) if rows is not None else np.frombuffer(blob, dtype, acc["count"] * n, start).reshape(-1, n)
    return a[:, 0] if acc["type"] == "SCALAR" else a


def check_glb(data: bytes) -> dict:
    """A structural validation of a GLB that raises AssertionError on the first problem."""
    doc, blob = split_glb(data)
    assert doc["asset"]["version"] == "2.0"
    buffers = doc["buffers"]
    assert len(buffers) == 1 and "uri" not in buffers[0], "a GLB's one buffer is its BIN chunk"
    assert buffers[0]["byteLength"] <= len(blob) < buffers[0]["byteLength"] + 4, "buffer / BIN chunk length"
    ranges = {k: len(doc.get(k, [])) for k in ("accessors", "bufferViews", "nodes", "meshes", "materials")}

    def index(kind: str, i) -> None:
        assert isinstance(i, int) and 0 <= i < ranges[kind], f"{kind} index {i} out of range ({ranges[kind]})"

    for v, view in enumerate(doc["bufferViews"]):
        assert view["buffer"] == 0
        off = view.get("byteOffset", 0)
        assert off % 4 == 0, f"bufferView {v} offset {off} not 4-byte aligned"
        assert off + view["byteLength"] <= buffers[0]["byteLength"], f"bufferView {v} runs past its buffer"
    for i, acc in enumerate(doc["accessors"]):
        index("bufferViews", acc["bufferView"])
        view = doc["bufferViews"][acc["bufferView"]]
        size = np.dtype(COMPONENT[acc["componentType"]]).itemsize
        elem = size * NCOMP[acc["type"]]
        stride = view.get("byteStride", elem)
        off = acc.get("byteOffset", 0)
        assert off % size == 0, f"accessor {i} offset not aligned to its component"
        assert acc["count"] >= 1
        assert off + (acc["count"] - 1) * stride + elem <= view["byteLength"], f"accessor {i} runs past its view"
        a = read_accessor(doc, blob, i)
        if a.dtype.kind == "f":
            assert np.isfinite(a).all(), f"accessor {i} has non-finite values"
        if "min" in acc or "max" in acc:
            flat = a.reshape(len(a), -1)
            np.testing.assert_array_equal(np.asarray(acc["min"], a.dtype), flat.min(0), f"accessor {i} min")
            np.testing.assert_array_equal(np.asarray(acc["max"], a.dtype), flat.max(0), f"accessor {i} max")
    for s in doc["scenes"]:
        for n in s["nodes"]:
            index("nodes", n)
    parent = {}
    for n, node in enumerate(doc["nodes"]):
        for c in node.get("children", []):
            index("nodes", c)
            assert c not in parent, f"node {c} has two parents"
            parent[c] = n
        if "mesh" in node:
            index("meshes", node["mesh"])
        if "rotation" in node:
            assert abs(np.linalg.norm(node["rotation"]) - 1) < 1e-6, f"node {n} rotation not unit"
        assert "matrix" not in node or not any(k in node for k in ("translation", "rotation", "scale"))
    roots = set(range(len(doc["nodes"]))) - set(parent)
    assert roots == set(doc["scenes"][doc.get("scene", 0)]["nodes"]), "scene roots != parentless nodes"
    for n in parent:  # no cycles
        seen, k = set(), n
        while k in parent:
            assert k not in seen, f"node cycle at {k}"
            seen.add(k)
            k = parent[k]
    for m, mesh in enumerate(doc["meshes"]):
        for prim in mesh["primitives"]:
            assert prim.get("mode", 4) == 4
            index("materials", prim["material"])
            pos_i, nrm_i, idx_i = prim["attributes"]["POSITION"], prim["attributes"]["NORMAL"], prim["indices"]
            for i in (pos_i, nrm_i, idx_i):
                index("accessors", i)
            pos_acc = doc["accessors"][pos_i]
            assert "min" in pos_acc and "max" in pos_acc, f"mesh {m}: POSITION without min/max"
            assert doc["bufferViews"][doc["accessors"][idx_i]["bufferView"]].get("target") == 34963
            P, N = read_accessor(doc, blob, pos_i).astype(float), read_accessor(doc, blob, nrm_i).astype(float)
            idx = read_accessor(doc, blob, idx_i)
            assert len(P) == len(N)
            assert idx.max() < len(P) and len(idx) % 3 == 0, f"mesh {m}: indices out of range"
            np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-5, err_msg=f"mesh {m} normals")
            tri = idx.reshape(-1, 3)
            face = np.cross(P[tri[:, 1]] - P[tri[:, 0]], P[tri[:, 2]] - P[tri[:, 0]])
            area = np.linalg.norm(face, axis=1)
            assert (area > 0).all(), f"mesh {m}: degenerate triangles"
            # counter-clockwise seen from outside: the face normal agrees with the vertex normals
            agree = np.einsum("ij,ij->i", face / area[:, None], N[tri].sum(1))
            assert (agree > 0).all(), f"mesh {m}: {int((agree <= 0).sum())} triangles wound against their normals"
    for a, anim in enumerate(doc.get("animations", [])):
        assert anim["channels"]
        targets = set()
        for ch in anim["channels"]:
            assert 0 <= ch["sampler"] < len(anim["samplers"])
            index("nodes", ch["target"]["node"])
            key = (ch["target"]["node"], ch["target"]["path"])
            assert key not in targets, f"animation {a}: two channels for {key}"
            targets.add(key)
            s = anim["samplers"][ch["sampler"]]
            index("accessors", s["input"])
            index("accessors", s["output"])
            inp = doc["accessors"][s["input"]]
            assert inp["componentType"] == 5126 and inp["type"] == "SCALAR"
            assert "min" in inp and "max" in inp, f"animation {a}: input accessor without min/max"
            t = read_accessor(doc, blob, s["input"])
            assert t[0] >= 0 and (np.diff(t) > 0).all(), f"animation {a}: key times not strictly increasing"
            out = doc["accessors"][s["output"]]
            assert out["count"] == inp["count"], f"animation {a}: output count != input count"
            path = ch["target"]["path"]
            assert out["type"] == {"translation": "VEC3", "scale": "VEC3", "rotation": "VEC4"}[path]
            if path == "rotation":
                qs = read_accessor(doc, blob, s["output"]).astype(float)
                np.testing.assert_allclose(np.linalg.norm(qs, axis=1), 1.0, atol=1e-6, err_msg="quaternions")
    return doc


# ======================================================================================
# evaluation of a glTF animation (glTF 2.0 section 3.11) and the node hierarchy
# ======================================================================================


def quat_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def sample(times, values, t, interpolation, rotation):
    k = int(np.searchsorted(times, t, side="right")) - 1
    if k < 0:
        return values[0]
    if k >= len(times) - 1 or interpolation == "STEP":
        return values[min(k, len(times) - 1)]
    u = (t - times[k]) / (times[k + 1] - times[k])
    a, b = values[k].astype(float), values[k + 1].astype(float)
    if not rotation:
        return (1 - u) * a + u * b
    d = np.dot(a, b)
    if d < 0:
        b, d = -b, -d
    if d > 0.9995:
        r = (1 - u) * a + u * b
    else:
        th = np.arccos(d)
        r = (np.sin((1 - u) * th) * a + np.sin(u * th) * b) / np.sin(th)
    return r / np.linalg.norm(r)


def key_time(k: int, fps: float = FPS) -> float:
    """Frame ``k``'s key time as stored (float32 seconds, glTF's only float type)."""
    return float(np.float32(k / fps))


class Scene:
    """A GLB read back: documents, accessors, evaluated world transforms."""

    def __init__(self, data: bytes):
        self.gltf = pygltflib.GLTF2.load_from_bytes(data)
        self.doc = json.loads(self.gltf.gltf_to_json())
        self.blob = self.gltf.binary_blob()
        self.names = [n.get("name") for n in self.doc["nodes"]]
        self.parent = {c: i for i, n in enumerate(self.doc["nodes"]) for c in n.get("children", [])}

    def node(self, name: str) -> int:
        return self.names.index(name)

    def animation(self, name: str) -> dict:
        return next(a for a in self.doc["animations"] if a["name"] == name)

    def trs(self, anim: dict, t: float) -> list[dict]:
        """Every node's translation / rotation / scale at time ``t`` of ``anim``."""
        out = [
            {
                "translation": np.asarray(n.get("translation", [0, 0, 0]), float),
                "rotation": np.asarray(n.get("rotation", [0, 0, 0, 1]), float),
                "scale": np.asarray(n.get("scale", [1, 1, 1]), float),
            }
            for n in self.doc["nodes"]
        ]
        for ch in anim["channels"]:
            s = anim["samplers"][ch["sampler"]]
            times = read_accessor(self.doc, self.blob, s["input"]).astype(float)
            values = read_accessor(self.doc, self.blob, s["output"])
            path = ch["target"]["path"]
            out[ch["target"]["node"]][path] = sample(times, values, t, s.get("interpolation", "LINEAR"),
                                                     path == "rotation")
        return out

    def world(self, anim: dict, t: float) -> np.ndarray:
        """(nodes, 4, 4) world matrices at time ``t``: ``world = world_parent @ T @ R @ S``."""
        trs = self.trs(anim, t)
        M = np.zeros((len(trs), 4, 4))
        done = [False] * len(trs)

        def solve(i):
            if done[i]:
                return M[i]
            L = np.eye(4)
            L[:3, :3] = quat_matrix(trs[i]["rotation"]) * trs[i]["scale"][None, :]
            L[:3, 3] = trs[i]["translation"]
            M[i] = solve(self.parent[i]) @ L if i in self.parent else L
            done[i] = True
            return M[i]

        for i in range(len(trs)):
            solve(i)
        return M


# ======================================================================================
# tests
# ======================================================================================


def assert_matches_mujoco(scene: Scene, model, result: dict, anim_name: str) -> None:
    anim = scene.animation(anim_name)
    xpos, xmat, _ = mujoco_frames(model, result["q"])
    names = model.topo.body_names
    ids = [scene.node(names[b]) for b in range(1, model.mj.nbody)]
    pos_err = rot_err = 0.0
    for k in range(len(result["q"])):
        M = scene.world(anim, key_time(k, result["fps"]))
        got_p = M[ids, :3, 3]
        got_R = M[ids, :3, :3]
        pos_err = max(pos_err, np.abs(got_p - xpos[k, 1:] @ C.T).max())
        rot_err = max(rot_err, np.abs(got_R - C @ xmat[k, 1:]).max())
    assert pos_err < TOL, f"{anim_name}: max body position error {pos_err:.3g} m"
    assert rot_err < TOL, f"{anim_name}: max body orientation error {rot_err:.3g}"


@pytest.mark.parametrize("height_m,mass_kg", [(None, None), (1.6, 58.0)])
def test_round_trip_matches_mujoco(model, height_m, mass_kg, tmp_path):
    result = make_result(model, height_m=height_m, mass_kg=mass_kg)
    char = result_model(result)
    path = write_glb(result, tmp_path / "out" / "walk.glb")
    data = path.read_bytes()
    check_glb(data)
    scene = Scene(data)
    assert [a["name"] for a in scene.doc["animations"]] == ["walk"]
    names = char.topo.body_names
    for b in range(1, char.mj.nbody):  # one node per body, children by the body tree
        i = scene.node(names[b])
        p = int(char.mj.body_parentid[b])
        if p == 0:
            assert i not in scene.parent
        else:
            assert scene.names[scene.parent[i]] == names[p]
            # local translation: the character's own body_pos (a scaled model: its own lengths)
            np.testing.assert_allclose(scene.doc["nodes"][i]["translation"], char.mj.body_pos[b], atol=1e-7)
        assert "mesh" in scene.doc["nodes"][i], f"body {names[b]} has no mesh"
    assert_matches_mujoco(scene, char, result, "walk")
    # a key-time slerp lands between the frames: the midpoint is a valid pose near both
    M = scene.world(scene.animation("walk"), 0.5 / FPS)
    assert np.isfinite(M).all()


def test_several_clips_share_one_skeleton(model, tmp_path):
    a = make_result(model, T=30, seed=1, name="walk")
    b = make_result(model, T=20, seed=2, name="walk")  # same name: made unique
    c = make_result(model, T=12, seed=3, name="jump")
    c["forces_estimated"] = False
    path = write_glb([a, b, c], tmp_path / "clips.glb")
    data = path.read_bytes()
    doc = check_glb(data)
    scene = Scene(data)
    assert [x["name"] for x in doc["animations"]] == ["walk", "walk_2", "jump"]
    assert sum(n == "pelvis" for n in scene.names) == 1
    for r, name in ((a, "walk"), (b, "walk_2"), (c, "jump")):
        assert_matches_mujoco(scene, model, r, name)
    # the clip without estimated forces keeps the arrows at scale 0
    anim = scene.animation("jump")
    for k in range(12):
        trs = scene.trs(anim, key_time(k))
        for site in CONTACT_NAMES:
            assert not trs[scene.node(f"grf_{site}")]["scale"].any()
    with pytest.raises(ValueError, match="another character"):
        write_glb([a, make_result(model, height_m=1.5, mass_kg=50.0)], tmp_path / "mixed.glb")


def test_forces_and_contacts(model, tmp_path):
    result = make_result(model)
    data = write_glb(result, tmp_path / "f.glb").read_bytes()
    check_glb(data)
    scene = Scene(data)
    anim = scene.animation("walk")
    weight = model.total_mass * 9.81
    _, _, site_xpos = mujoco_frames(model, result["q"])
    roots = set(scene.doc["scenes"][0]["nodes"])
    for k in (0, 5, 17, 35):
        trs = scene.trs(anim, key_time(k))
        for c, (site, sid) in enumerate(zip(CONTACT_NAMES, model.topo.contact_sites, strict=True)):
            arrow = scene.node(f"grf_{site}")
            assert arrow in roots  # world frame
            tr = trs[arrow]
            np.testing.assert_allclose(tr["translation"], C @ site_xpos[k, sid], atol=TOL)
            f = C @ result["grf"][k, c].astype(float)
            # the arrow is unit length along +Y, scaled (1, |F| / weight, 1): its tip is F / weight
            tip = quat_matrix(tr["rotation"]) @ (tr["scale"] * [0, 1, 0])
            np.testing.assert_allclose(tip * weight, f, atol=1e-3 * np.linalg.norm(f) + 1e-6)
            if not f.any():
                assert not tr["scale"].any(), "zero force: the arrow vanishes"
            else:
                assert tr["scale"][0] == 1 and tr["scale"][2] == 1
            marker = scene.node(f"contact_{site}")
            assert marker in roots
            np.testing.assert_allclose(trs[marker]["translation"], C @ site_xpos[k, sid], atol=TOL)
            on = float(result["contact_prob"][k, c] > 0.5)
            np.testing.assert_array_equal(trs[marker]["scale"], [on, on, on])
    # markers switch: STEP samplers; the arrow mesh is unit length along +Y
    for ch in anim["channels"]:
        s = anim["samplers"][ch["sampler"]]
        is_marker = scene.names[ch["target"]["node"]].startswith("contact_") and ch["target"]["path"] == "scale"
        assert s.get("interpolation", "LINEAR") == ("STEP" if is_marker else "LINEAR")
    mesh = scene.doc["meshes"][scene.doc["nodes"][scene.node("grf_left_heel")]["mesh"]]
    pos = scene.doc["accessors"][mesh["primitives"][0]["attributes"]["POSITION"]]
    assert pos["min"][1] == pytest.approx(0.0, abs=1e-7) and pos["max"][1] == pytest.approx(1.0, abs=1e-7)
    # without estimated forces, or with forces=False / contacts=False: no such nodes
    kin = dict(result, forces_estimated=False)
    for r, kw, absent in ((kin, {}, "grf_"), (result, {"forces": False}, "grf_"),
                          (result, {"contacts": False}, "contact_"), (dict(result, grf=None), {}, "grf_")):
        names = Scene(write_glb(r, tmp_path / "n.glb", **kw).read_bytes()).names
        assert not any(n.startswith(absent) for n in names), (kw, absent)
        assert "pelvis" in names


def test_structure_checker_catches_corruption(model, tmp_path):
    data = write_glb(make_result(model, T=8), tmp_path / "s.glb").read_bytes()
    doc, blob = split_glb(data)
    check_glb(data)

    def glb(d: dict, b: bytes = blob, fix_length=True) -> bytes:
        j = json.dumps(d).encode()
        j += b" " * (-len(j) % 4)
        out = struct.pack("<I4s", len(j), b"JSON") + j + struct.pack("<I4s", len(b), b"BIN\0") + b
        return struct.pack("<4sII", b"glTF", 2, 12 + len(out) + (0 if fix_length else 4)) + out

    check_glb(glb(doc))  # re-encoding alone is fine
    bad = []
    d = json.loads(json.dumps(doc))
    d["accessors"][0]["count"] += 10**6
    bad.append(("runs past", glb(d)))
    d = json.loads(json.dumps(doc))
    d["accessors"][0]["max"][0] += 1.0
    bad.append(("max", glb(d)))
    d = json.loads(json.dumps(doc))
    d["nodes"][0]["children"].append(len(d["nodes"]))
    bad.append(("out of range", glb(d)))
    d = json.loads(json.dumps(doc))
    t_acc = d["animations"][0]["samplers"][0]["input"]
    b2 = bytearray(blob)
    off = d["bufferViews"][d["accessors"][t_acc]["bufferView"]]["byteOffset"]
    b2[off + 4 : off + 8] = struct.pack("<f", 10.0)  # the second key time jumps ahead
    bad.append(("min|max|increasing", glb(d, bytes(b2))))
    d = json.loads(json.dumps(doc))
    prim = d["meshes"][0]["primitives"][0]
    idx = d["accessors"][prim["indices"]]
    b3 = bytearray(blob)
    off = d["bufferViews"][idx["bufferView"]]["byteOffset"]
    b3[off : off + 4] = b3[off + 2 : off + 4] + b3[off : off + 2]  # flip a triangle
    bad.append(("wound against", glb(d, bytes(b3))))
    bad.append(("header length", glb(doc, fix_length=False)))
    bad.append(("BIN chunk", glb(doc, blob[:-4])))
    for what, corrupt in bad:
        with pytest.raises(AssertionError, match=what):
            check_glb(corrupt)


def find_validator() -> Path | None:
    """A node runner script for the Khronos glTF validator, or None (see the module docstring)."""
    if shutil.which("node") is None:
        return None
    candidates = [os.environ.get("JMOCAP_GLTF_VALIDATOR"), "/tmp/gltfval",
                  str(Path.home() / ".cache" / "jmocap" / "gltf-validator")]
    for c in candidates:
        if not c:
            continue
        p = Path(c)
        if p.is_file():
            return p
        for pkg in (p / "node_modules" / "gltf-validator", p):
            if (pkg / "package.json").is_file() and (pkg / "gltf_validator.dart.js").is_file():
                return pkg
    return None


def test_khronos_validator(model, tmp_path):
    found = find_validator()
    if found is None:
        pytest.skip("Khronos glTF validator not installed (set JMOCAP_GLTF_VALIDATOR; see the module docstring)")
    if found.is_file():
        script = found
    else:
        script = tmp_path / "validate.js"
        script.write_text(
            f"const fs = require('fs'); const v = require({json.dumps(str(found))});\n"
            "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])), {maxIssues: 0})\n"
            "  .then(r => console.log(JSON.stringify(r)))\n"
            "  .catch(e => { console.error(e); process.exit(2); });\n"
        )
    a, b = make_result(model, T=24, seed=4), make_result(model, T=10, seed=5, name="other")
    b["grf"] = None
    for name, arg in (("one", a), ("two", [a, b])):
        path = write_glb(arg, tmp_path / f"{name}.glb")
        run = subprocess.run(["node", str(script), str(path)], capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
        report = json.loads(run.stdout)
        issues = report["issues"]
        msgs = [f"{m['code']}: {m['message']} ({m.get('pointer', '')})" for m in issues["messages"]]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, msgs
        assert report["info"]["animationCount"] == (1 if name == "one" else 2)


def test_write_is_atomic(model, tmp_path):
    path = tmp_path / "x.glb"
    path.write_bytes(b"old")
    result = make_result(model, T=5)
    result["q"][2, 9] = np.nan
    with pytest.raises(ValueError):
        write_glb(result, path)
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.glb"]


def _bad(**changes):
    def make(model):
        r = make_result(model, T=6)
        for k, v in changes.items():
            r[k] = v(r) if callable(v) else v
        return r

    return make


def _nan_at(key, index):
    def f(r):
        a = np.array(r[key], np.float64)
        a[index] = np.nan
        return a

    return f


@pytest.mark.parametrize(
    "make,match",
    [
        (_bad(q=lambda r: r["q"][:, :-1]), r"field 'q': expected shape \(T, nq=48\)"),
        (_bad(q=lambda r: r["q"][:0]), r"field 'q': no frames"),
        (_bad(q=_nan_at("q", (3, 10))), r"field 'q': frame 3: coordinate 10"),
        (_bad(q=lambda r: np.zeros_like(r["q"])), r"field 'q': frame 0: root quaternion"),
        (_bad(q=lambda r: np.full(r["q"].shape, "a")), r"field 'q': expected numbers"),
        (_bad(q=None), r"missing field 'q'"),
        (_bad(fps=0.0), r"fps must be positive"),
        (_bad(fps=float("nan")), r"fps must be positive"),
        (_bad(fps="fast"), r"fps must be a number"),
        (_bad(fps=None), r"missing field 'fps'"),
        (_bad(grf=lambda r: r["grf"][:, :3]), r"field 'grf': expected shape \(6, 4, 3\)"),
        (_bad(grf=_nan_at("grf", (4, 0, 2))), r"field 'grf': frame 4 has a non-finite"),
        (_bad(contact_prob=lambda r: r["contact_prob"][:-1]), r"field 'contact_prob': expected shape \(6, 4\)"),
        (_bad(contact_prob=_nan_at("contact_prob", (1, 1))), r"field 'contact_prob': frame 1"),
    ],
)
def test_write_glb_rejects_bad_input(model, make, match, tmp_path):
    with pytest.raises(ValueError, match=match) as e:
        write_glb(make(model), tmp_path / "bad.glb")
    assert "result 0 (walk)" in str(e.value) or "missing field" in str(e.value)
    assert not (tmp_path / "bad.glb").exists()


def test_write_glb_rejects_bad_arguments(model, tmp_path):
    with pytest.raises(ValueError, match="no results"):
        write_glb([], tmp_path / "a.glb")
    with pytest.raises(ValueError, match="result 1 is a str"):
        write_glb([make_result(model, T=3), "walk.npz"], tmp_path / "a.glb")
