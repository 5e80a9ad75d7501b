"""Batch reconstruction (jmocap.batch, jmocap.pipeline, ``jmocap reconstruct``), end to end on
tiny archives.

The reference for chunking is the whole-clip method, ``methods.get_method("physcap").reconstruct``: a clip
reconstructed in chunks of 8 frames (state carried, 2W - 1 frames of keypoint history) must
equal it to float32 rounding. Other checks: mixed input formats in one folder (jmocap clips,
an OpenPose folder with its camera sidecar, broken files), the manifest and summary, finite
outputs for clips with undetected frames, NaN outputs reported as failures, resume, zip input,
a SIGKILLed run that loses nothing and resumes, and two (forced host) devices.

Parameters are freshly initialised and the networks small (iterations=2) to keep compilation
short; ``root_residual_limit=None`` makes the untrained cycle a stable PD tracker (with the
limit, untrained networks let the body fall and the simulation is chaotic, so two equal
computations in float32 drift apart and no tight comparison is possible). A persistent XLA
cache shared with the subprocesses makes them skip recompiling the same programs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import jax
import numpy as np
import pytest

from jmocap import methods
from jmocap import physics as P
from jmocap.batch import BatchOptions, adapt_layout
from jmocap.batch import reconstruct_archive as _reconstruct_archive
from jmocap.camera import default_extrinsics
from jmocap.constants import DEFAULT_HEIGHT_M
from jmocap.data.clip import FormatError, clip_to_arrays, save_clip
from jmocap.data.formats import write_openpose_folder, write_videopose3d
from jmocap.data.sources import open_sources, scan_folder
from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.inputs import ClipInputs
from jmocap.methods.physcap import PhysCapConfig, init_params, reconstruct
from jmocap.methods.stages import target_pose
from jmocap.model import load_model
from jmocap.nets import NetConfig
from jmocap.pipeline import chunk_frames, chunk_plan
from jmocap.results import MOTION_FIELDS, RESULT_FORMAT, assumed_fields, check_finite, load_result
from jmocap.weights import check_params, load_run_params, params_sha256


def history_length(config) -> int:
    return methods.get_method("physcap").history(config)


def config_json(config) -> str:
    return json.dumps(methods.config_dict(config), sort_keys=True)


SMALL = PhysCapConfig(
    iterations=2,
    root_residual_limit=None,
    nets=NetConfig(tp_width=16, dyn_width=32, grf_width=32, tp_blocks=2),
)
OPTS = BatchOptions(chunk=8, bucket=8, batch=2)  # every call: 2 clips x (19 + 8) frames
ROOT = Path(__file__).resolve().parents[1]


def reconstruct_archive(*args, **kwargs):
    """The archive engine with the small ``physcap`` config these tests compile (the engine is
    method-agnostic; ``physcap`` with small nets compiles fastest)."""
    return _reconstruct_archive(*args, **{"method": "physcap", **kwargs})


# ---------------------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def params(xla_cache):
    # the unsafe_rbg key compiles in a third of threefry's time (the init is RNG-bound)
    key = jax.random.key(0, impl="unsafe_rbg")
    return jax.jit(lambda k: init_params(k, load_model(with_mjx=False), SMALL))(key)


def synth(index: int, frames: int, **changes):
    clip = generate_clip(7, index, SynthConfig(frames=frames))
    return clip.replace(name=f"c{index}", **changes) if changes else clip.replace(name=f"c{index}")


@pytest.fixture(scope="module")
def clips():
    c = {
        "short": synth(0, 6),
        "medium": synth(1, 12),
        "long": synth(2, 20),  # 3 chunks of 8
        "bare": synth(3, 7, extrinsics=None, height_m=None),  # default camera, default height
    }
    kp = synth(4, 10).keypoints.copy()
    kp[3:6] = 0.0  # three frames with nothing detected
    c["undetected_frames"] = synth(4, 10, keypoints=kp)
    c["openpose"] = synth(5, 8)
    return c


@pytest.fixture(scope="module")
def input_folder(tmp_path_factory, clips):
    """Good clips of several formats plus broken ones, loose in a folder (no manifest)."""
    root = tmp_path_factory.mktemp("input")
    for name in ("short", "medium", "long", "bare", "undetected_frames"):
        save_clip(root / f"{name}.npz", clips[name])
    write_openpose_folder(clips["openpose"], root / "takes" / "op_walk")  # + takes/op_walk.camera.json
    (root / "broken.npz").write_bytes(b"not a zip file, just garbage " * 20)
    np.save(root / "wrong_shape.npy", np.zeros((5, 7, 3)))
    nothing = clips["short"].replace(keypoints=np.zeros_like(clips["short"].keypoints))
    save_clip(root / "nothing_detected.npz", nothing)
    arrays = clip_to_arrays(clips["short"])
    arrays["keypoints"] = arrays["keypoints"].copy()
    arrays["keypoints"][2, 5, 0] = np.nan
    np.savez(root / "nan_keypoints.npz", **arrays)
    (root / "notes.txt").write_text("not a clip")
    return root


GOOD = {"short", "medium", "long", "bare", "undetected_frames", "takes/op_walk"}
BAD = {"broken", "wrong_shape", "nothing_detected", "nan_keypoints"}


def read_manifest(out: Path) -> dict[str, dict]:
    entries = {}
    for line in (out / "manifest.jsonl").read_text().splitlines():
        try:
            e = json.loads(line)
        except json.JSONDecodeError:  # a line cut by SIGKILL
            continue
        entries[e["name"]] = e
    return entries


@pytest.fixture(scope="module")
def first_run(xla_cache, params, input_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    t = time.perf_counter()
    summary = reconstruct_archive(input_folder, out, params, SMALL, OPTS)
    return out, summary, time.perf_counter() - t


# ---------------------------------------------------------------------------------------
# the functional core
# ---------------------------------------------------------------------------------------


def test_chunk_plan_and_frames():
    assert chunk_plan(20, 8, 8) == (8, 8, 8)
    assert chunk_plan(16, 8, 4) == (8, 8)
    assert chunk_plan(300, 256, 64) == (256, 64)
    assert chunk_plan(5, 256, 64) == (64,)
    assert chunk_plan(250, 256, 64) == (256,)
    idx, real = chunk_frames(20, 16, 8, 3)
    np.testing.assert_array_equal(idx, [13, 14, 15, 16, 17, 18, 19, 19, 19, 19, 19])
    np.testing.assert_array_equal(real, [True] * 7 + [False] * 4)
    idx, real = chunk_frames(20, 0, 4, 3)
    np.testing.assert_array_equal(idx, [0, 0, 0, 0, 1, 2, 3])
    assert not real[:3].any() and real[3:].all()
    # a lookahead reads frames after the chunk: real inside the clip, the last frame repeated after it
    idx, real = chunk_frames(20, 8, 4, 2, lookahead=3)
    np.testing.assert_array_equal(idx, [6, 7, 8, 9, 10, 11, 12, 13, 14])
    assert real.all()
    idx, real = chunk_frames(20, 16, 4, 1, lookahead=2)
    np.testing.assert_array_equal(idx, [15, 16, 17, 18, 19, 19, 19])
    np.testing.assert_array_equal(real, [True] * 5 + [False] * 2)


@pytest.mark.slow  # 15 s of compilation; test_chunked_equals_unchunked fails too if the history is short
def test_tpnet_receptive_field_is_the_history(params):
    """Frame t of TPNet's target depends on keypoints t - 2(W - 1) .. t (C_T windows C_P's
    outputs), so a chunk needs 2(W - 1) frames of history (+1 for the kinematic velocity)."""
    W = SMALL.nets.window
    assert history_length(SMALL) == 2 * W - 1
    model = load_model(with_mjx=False)
    base = ClipInputs.from_clip(synth(6, 2 * W + 2))
    kp = np.asarray(base.keypoints).copy()
    kp[0, 2:8, :2] += 40.0  # move the arms in frame 0 (a translation of all joints would leave K_rr)
    f = jax.jit(lambda x: target_pose(params, model, x, SMALL).q_hat)
    a, b = np.asarray(f(base)), np.asarray(f(base.replace(keypoints=kp)))
    t = 2 * (W - 1)
    assert np.abs(a[t] - b[t]).max() > 1e-6  # frame 2(W-1) still sees frame 0
    np.testing.assert_array_equal(a[t + 1 :], b[t + 1 :])  # later frames do not


def test_check_finite_names_field_and_frame():
    res = {k: np.zeros((5, 3), np.float32) for k in MOTION_FIELDS}
    check_finite(res, "clip.npz")
    res["tau"][3, 1] = np.nan
    with pytest.raises(ValueError, match=r"clip.npz: frame 3: field 'tau'"):
        check_finite(res, "clip.npz")


def test_config_overrides_and_params_check(tmp_path, params):
    from jmocap.weights import save_params

    path = tmp_path / "params.msgpack"
    save_params(path, params)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(dataclasses.asdict(SMALL)))
    p, c = load_run_params(path, str(cfg), method="physcap")
    assert c == SMALL and params_sha256(p) == params_sha256(params)
    _, c2 = load_run_params(path, '{"cycle": {"iterations": 3, "nets": {"tp_width": 16}}}', method="physcap")
    assert c2.iterations == 3 and c2.nets.tp_width == 16 and c2.nets.dyn_width == NetConfig().dyn_width
    with pytest.raises(ValueError, match="unknown config fields"):
        load_run_params(path, '{"iteration": 3}', method="physcap")
    check_params(p, c, "physcap")
    with pytest.raises(ValueError, match=r"do not fit the config: \[.dynet.\]"):
        check_params(p, c2, "physcap")


def test_scan_folder_names_and_skips(input_folder, tmp_path):
    sources = {s.name: s for s in scan_folder(input_folder)}
    assert set(sources) == GOOD | BAD  # no sidecar, no notes.txt
    assert sources["takes/op_walk"].where.endswith("takes/op_walk")
    inner = tmp_path / "in"
    shutil.copytree(input_folder, inner)
    (inner / "out").mkdir()
    (inner / "out" / "short.npz").write_bytes(b"a result")
    assert {s.name for s in scan_folder(inner, exclude=inner / "out")} == GOOD | BAD


def test_videopose3d_files_expand_and_layouts_are_converted(tmp_path):
    """A VideoPose3D file is one clip per (subject, action, camera); its h36m17 keypoints are
    converted to the BODY_25 the parameters read, with a warning saying what is missing."""
    rng = np.random.default_rng(0)
    seqs = {"S1": {"Walking": [rng.uniform(100, 900, (12, 17, 2)) for _ in range(2)]}}
    write_videopose3d(tmp_path / "data_2d_h36m_test.npz", seqs)
    sources = scan_folder(tmp_path)
    assert [s.name for s in sources] == ["data_2d_h36m_test/S1_Walking_0", "data_2d_h36m_test/S1_Walking_1"]
    clip = sources[1].load()
    assert clip.layout == "h36m17" and clip.num_frames == 12 and clip.fps == 50.0  # Human3.6M camera
    conv, warnings = adapt_layout(clip, SMALL)
    assert conv.layout == "body25" and conv.keypoints.shape == (12, 25, 3)
    assert conv.meta["layout_conversion"]["from"] == "h36m17"
    assert len(warnings) == 1 and "from h36m17 to body25" in warnings[0] and "absent: REye" in warnings[0]
    np.testing.assert_array_equal(conv.keypoints[:, 8], clip.keypoints[:, 0])  # MidHip <- Hip
    assert not conv.keypoints[:, 19:, 2].any()  # no feet
    assert adapt_layout(conv, SMALL) == (conv, [])


def test_image_size_is_assumed_only_when_missing(tmp_path, clips):
    folder = tmp_path / "cam_less"
    write_openpose_folder(clips["openpose"], folder, write_camera=False)
    with open_sources(folder) as sources:
        with pytest.raises(FormatError, match="no image size"):
            sources[0].load()
    with open_sources(folder, image_size=(640, 480)) as sources:
        clip = sources[0].load()
    np.testing.assert_array_equal(clip.image_size, [640, 480])
    assert "image_size" in assumed_fields(clip) and "intrinsics" in assumed_fields(clip)
    write_openpose_folder(clips["openpose"], folder)  # now with its sidecar: that wins
    with open_sources(folder, image_size=(640, 480)) as sources:
        np.testing.assert_array_equal(sources[0].load().image_size, clips["openpose"].image_size)


# ---------------------------------------------------------------------------------------
# an archive run
# ---------------------------------------------------------------------------------------


def test_run_completes_with_the_right_manifest(first_run, input_folder):
    out, summary, seconds = first_run
    m = read_manifest(out)
    assert set(m) == GOOD | BAD
    assert {n for n, e in m.items() if e["status"] == "ok"} == GOOD
    assert summary["ok"] == len(GOOD) and summary["failed"] == len(BAD) and summary["pending"] == 0
    assert summary["run"]["frames"] == sum(m[n]["frames"] for n in GOOD) == summary["frames"]
    assert json.loads((out / "summary.json").read_text()) == summary
    assert m["long"]["chunks"] == 3 and m["short"]["chunks"] == 1
    for n in GOOD:
        e = m[n]
        data = (out / e["file"]).read_bytes()
        assert len(data) == e["bytes"] and hashlib.sha256(data).hexdigest() == e["sha256"]
        assert e["seconds"] >= 0
    # failures name the file and what is wrong with it, and nothing is written for them
    err = {n: m[n]["error"] for n in BAD}
    assert "broken.npz" in err["broken"] and "not a readable .npz" in err["broken"]
    assert "wrong_shape.npy" in err["wrong_shape"] and "(5, 7, 3)" in err["wrong_shape"]
    assert "nothing_detected.npz" in err["nothing_detected"] and "field 'keypoints'" in err["nothing_detected"]
    assert "nan_keypoints.npz" in err["nan_keypoints"] and "frame 2" in err["nan_keypoints"]
    assert not any((out / f"{n}.npz").exists() for n in BAD)
    assert not list(out.rglob("*.tmp"))


def test_results_follow_the_schema(first_run, clips, params):
    out, _, _ = first_run
    model = load_model(with_mjx=False)
    names = {"short": "short", "long": "long", "bare": "bare", "takes/op_walk": "openpose",
             "undetected_frames": "undetected_frames", "medium": "medium"}
    for name, key in names.items():
        clip = clips[key]
        r = np.load(out / f"{name}.npz")
        T = clip.num_frames
        assert str(r["format"]) == RESULT_FORMAT and str(r["layout"]) == "body25"
        assert r["q"].shape == (T, model.nq) and r["target_q"].shape == (T, model.nq)
        assert r["qd"].shape == r["tau"].shape == (T, model.nv)
        assert r["grf"].shape == (T, 4, 3) and r["contact_prob"].shape == (T, 4)
        assert r["keypoints3d"].shape == (T, 25, 3)
        for k in MOTION_FIELDS:
            assert r[k].dtype == np.float32 and np.isfinite(r[k]).all(), (name, k)
        np.testing.assert_allclose(r["keypoints2d"], clip.keypoints, atol=1e-4)  # OpenPose JSON: 1e-4 px
        np.testing.assert_allclose(r["intrinsics"], clip.intrinsics)
        np.testing.assert_array_equal(r["image_size"], clip.image_size)
        source = str(r["extrinsics_source"])
        if clip.extrinsics is not None:
            assert source == "input"
            np.testing.assert_allclose(r["extrinsics"], clip.extrinsics, atol=1e-6)
        elif source == "default":  # the floor estimate of the untrained TPNet was not usable
            np.testing.assert_allclose(r["extrinsics"], default_extrinsics(), atol=1e-6)
        else:  # estimated (jmocap.methods.floor): a camera above the floor
            assert source == "estimated"
            R, t = r["extrinsics"][:3, :3], r["extrinsics"][:3, 3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
            assert (-R.T @ t)[2] > 0
        want_h = DEFAULT_HEIGHT_M if clip.height_m is None else clip.height_m  # (OpenPose: from its sidecar)
        assert float(r["height_m"]) == pytest.approx(want_h)
        assert float(r["fps"]) == clip.fps
        assert str(r["config"]) == config_json(SMALL)
        assert str(r["params_sha256"]) == params_sha256(params)
        assert len(str(r["model_sha256"])) == 64 and str(r["version"])
    bare = np.load(out / "bare.npz")
    assumed = json.loads(str(bare["assumed"]))
    assert "height_m" in assumed
    assert ("extrinsics" in assumed) == (str(bare["extrinsics_source"]) == "default")
    # where each height came from (jmocap.subject): the clips' own (OpenPose: its sidecar's);
    # 'bare' has none, and no camera placement to estimate one from
    m = read_manifest(out)
    for name in names:
        want = "nominal" if name == "bare" else "input"
        assert str(np.load(out / f"{name}.npz")["height_source"]) == want == m[name]["height_source"], name
    assert "extrinsics" in m["bare"]["height_estimate"]["reason"]
    res = load_result(out / "long.npz")  # the project's reader of result files
    assert res["q"].shape == (20, model.nq) and res["layout"] == "body25"
    assert res["method"] == "physcap" and res["forces_estimated"] is True
    assert res["mass_kg"] == pytest.approx(load_model(height_m=clips["long"].height_m,
                                                      mass_kg=clips["long"].mass_kg).total_mass)


def test_height_and_mass_options_set_every_clip(xla_cache, params, clips, tmp_path):
    """--height-m / --mass-kg: every clip's subject, over its own; recorded in the result, the
    manifest and archive.json (a resume with other values is refused)."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    save_clip(src / "short.npz", clips["short"])
    assert clips["short"].height_m != 1.6
    summary = reconstruct_archive(src, out, params, SMALL, dataclasses.replace(OPTS, height_m=1.6, mass_kg=60.0))
    assert summary["ok"] == 1
    res = load_result(out / "short.npz")
    assert res["height_m"] == 1.6 and res["mass_kg"] == pytest.approx(60.0) and res["height_source"] == "argument"
    assert read_manifest(out)["short"]["height_source"] == "argument"
    settings = json.loads((out / "archive.json").read_text())
    assert settings["height_m"] == 1.6 and settings["mass_kg"] == 60.0
    with pytest.raises(ValueError, match="different settings"):
        reconstruct_archive(src, out, params, SMALL, OPTS)


def test_chunked_equals_unchunked(first_run, clips, params):
    """The 20-frame clip, reconstructed in chunks of 8, equals the physcap method's reconstruct on
    the whole clip (float32: rounding differences, relative to each field's magnitude)."""
    out, _, _ = first_run
    clip = clips["long"]
    r = np.load(out / "long.npz")
    model = load_model(height_m=clip.height_m, mass_kg=clip.mass_kg)  # the clip's subject, exactly
    ref = jax.jit(reconstruct)(params, model, ClipInputs.from_clip(clip), SMALL)
    kp3d = jax.vmap(lambda q: P.keypoints(model, q, "body25"))(ref.q)
    want = dict(q=ref.q, qd=ref.qd, tau=ref.tau, grf=ref.grf, contact_prob=ref.contact_prob,
                target_q=ref.target_q, keypoints3d=kp3d)
    for k in MOTION_FIELDS:
        w = np.asarray(want[k])
        scale = float(np.abs(w).max()) + 1e-3
        np.testing.assert_allclose(r[k], w, rtol=0, atol=1e-4 * scale, err_msg=k)


def test_resume_skips_finished_clips_and_redoes_missing_ones(first_run, params, input_folder):
    out, _, _ = first_run
    before = read_manifest(out)
    mtimes = {n: (out / before[n]["file"]).stat().st_mtime_ns for n in GOOD}
    s = reconstruct_archive(input_folder, out, params, SMALL, OPTS)
    assert s["run"]["ok"] == 0 and s["run"]["skipped"] == len(GOOD)
    assert s["run"]["failed"] == len(BAD)  # failed clips are retried (and fail again)
    assert all((out / before[n]["file"]).stat().st_mtime_ns == mtimes[n] for n in GOOD)
    (out / "medium.npz").unlink()  # a lost result is recomputed, bit for bit
    s = reconstruct_archive(input_folder, out, params, SMALL, OPTS)
    assert s["run"]["ok"] == 1 and s["ok"] == len(GOOD)
    assert read_manifest(out)["medium"]["sha256"] == before["medium"]["sha256"]
    with pytest.raises(ValueError, match="different settings"):  # never mix two configurations
        reconstruct_archive(input_folder, out, params, SMALL.replace(iterations=3), OPTS)


def test_zip_input_gives_the_same_results(first_run, params, input_folder, tmp_path):
    out, _, _ = first_run
    zpath = tmp_path / "clips.zip"
    with zipfile.ZipFile(zpath, "w") as z:
        for p in sorted(input_folder.rglob("*")):
            if p.is_file():
                z.write(p, p.relative_to(input_folder).as_posix())
    s = reconstruct_archive(zpath, tmp_path / "out", params, SMALL, OPTS)
    assert s["ok"] == len(GOOD) and s["failed"] == len(BAD)
    m = read_manifest(tmp_path / "out")
    assert m["broken"]["error"].startswith(f"{zpath}:broken.npz")  # named inside the zip
    for n in GOOD:
        a, b = np.load(out / f"{n}.npz"), np.load(tmp_path / "out" / f"{n}.npz")
        for k in MOTION_FIELDS:
            np.testing.assert_array_equal(a[k], b[k])


def test_non_finite_reconstruction_is_a_failure(first_run, params, clips, tmp_path):
    """NaN parameters (traced: the first run's compiled program) make every output NaN."""
    src = tmp_path / "in"
    src.mkdir()
    save_clip(src / "a.npz", clips["short"])
    bad = jax.tree.map(lambda x: x, params)
    bad["tpnet"]["params"]["c_trans"]["Dense_0"]["bias"] = np.full_like(
        np.asarray(bad["tpnet"]["params"]["c_trans"]["Dense_0"]["bias"]), np.nan
    )
    s = reconstruct_archive(src, tmp_path / "out", bad, SMALL, OPTS)
    assert s["ok"] == 0 and s["failed"] == 1
    err = read_manifest(tmp_path / "out")["a"]["error"]
    assert "a.npz: frame 0: field 'q'" in err and "not finite" in err
    assert not (tmp_path / "out" / "a.npz").exists()


def test_bvh_per_clip(first_run, params, clips, tmp_path):
    export = pytest.importorskip("jmocap.export")
    src = tmp_path / "in"
    src.mkdir()
    save_clip(src / "a.npz", clips["long"])
    out = tmp_path / "out"
    s = reconstruct_archive(src, out, params, SMALL, dataclasses.replace(OPTS, bvh=True))
    assert s["ok"] == 1 and read_manifest(out)["a"]["bvh"] == "a.bvh"
    bvh = export.read_bvh(out / "a.bvh")
    assert bvh.frames.shape[0] == 20 and bvh.frame_time == pytest.approx(1 / clips["long"].fps)
    (out / "a.bvh").unlink()  # a result without its BVH is not done when --bvh is asked for
    s = reconstruct_archive(src, out, params, SMALL, dataclasses.replace(OPTS, bvh=True))
    assert s["run"]["ok"] == 1 and (out / "a.bvh").is_file()
    assert reconstruct_archive(src, out, params, SMALL, OPTS)["run"]["skipped"] == 1


# ---------------------------------------------------------------------------------------
# the command line in subprocesses: SIGKILL + resume, two devices
# ---------------------------------------------------------------------------------------


def cli(tmp_path, params, *extra, cache, env=None):
    from jmocap.weights import save_params

    p = tmp_path / "params.msgpack"
    if not p.exists():
        save_params(p, params)
        (tmp_path / "cfg.json").write_text(json.dumps(dataclasses.asdict(SMALL)))
    cmd = [sys.executable, "-m", "jmocap.cli", "reconstruct", "--method", "physcap", *map(str, extra), "--params", str(p),
           "--config", str(tmp_path / "cfg.json"), "--chunk", "8", "--bucket", "8", "--quiet",
           "--cache-dir", cache]
    return cmd, {**os.environ, "PYTHONPATH": str(ROOT / "src"), **(env or {})}


def test_sigkill_loses_nothing_and_the_rerun_completes(xla_cache, first_run, params, tmp_path):
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    n = 24
    for i in range(n):
        save_clip(src / f"k{i:02d}.npz", synth(20 + i, 6 + i % 3))
    cmd, env = cli(tmp_path, params, src, out, "--batch", "2", "--host-devices", "1", cache=xla_cache)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None:
            if (out / "manifest.jsonl").exists() and any(
                e["status"] == "ok" for e in read_manifest(out).values()
            ):
                break
            time.sleep(0.005)
        assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()}"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    done = {k: e for k, e in read_manifest(out).items() if e["status"] == "ok"}
    assert 0 < len(done) < n
    for e in done.values():  # every recorded result is complete
        data = (out / e["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == e["sha256"]
        assert np.isfinite(np.load(out / e["file"])["q"]).all()
    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    after = read_manifest(out)
    assert len(after) == n and all(e["status"] == "ok" for e in after.values())
    assert all(after[k]["sha256"] == e["sha256"] for k, e in done.items())  # untouched
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ok"] == n and summary["run"]["skipped"] == len(done)
    assert f"{n}/{n} clips ok" in rerun.stdout


@pytest.mark.slow  # compiles the sharded program in a subprocess (30 s on 2 busy cores)
def test_two_devices_shard_the_batch(xla_cache, first_run, params, input_folder, tmp_path):
    """Two host devices (``--host-devices 2``), one clip each per call (kinematic mode, whose q
    is the target pose that the one-device run also returns)."""
    out1, _, _ = first_run
    out = tmp_path / "out"
    cmd, env = cli(tmp_path, params, input_folder, out, "--batch", "1", "--method", "kinematic",
                   "--host-devices", "2", cache=xla_cache)
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stderr  # the broken clips fail, as on one device
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["devices"]) == 2
    assert summary["ok"] == len(GOOD) and summary["failed"] == len(BAD)
    for n in GOOD:
        a, b = np.load(out / f"{n}.npz"), np.load(out1 / f"{n}.npz")
        np.testing.assert_allclose(a["q"], b["target_q"], rtol=0, atol=1e-4 * (np.abs(b["target_q"]).max() + 1))
        assert "tau" not in a.files and "grf" not in a.files  # not estimated: absent, not zeros
        assert str(a["method"]) == "kinematic" and not bool(a["forces_estimated"])


def test_openpose_folder_as_the_whole_input(xla_cache, first_run, params, clips, tmp_path):
    """An OpenPose --write_json folder given directly as INPUT is one clip."""
    folder = tmp_path / "video01"
    write_openpose_folder(clips["openpose"], folder)
    s = reconstruct_archive(folder, tmp_path / "out", params, SMALL, OPTS)
    assert s["ok"] == 1 and s["clips"] == 1
    r = np.load(tmp_path / "out" / "video01.npz")
    np.testing.assert_allclose(r["intrinsics"], clips["openpose"].intrinsics)  # from the sidecar
    shutil.rmtree(folder)


# ---------------------------------------------------------------------------------------
# hostile or clumsy input (issue 16): what the batch engine guarantees
# ---------------------------------------------------------------------------------------


def test_warnings_are_recorded_in_manifest_and_result(first_run):
    out, summary, _ = first_run
    m = read_manifest(out)
    w = m["undetected_frames"]["warnings"]
    assert any("frames 3-5" in x for x in w), w  # the three undetected frames, as a range
    if m["bare"]["extrinsics_source"] == "default":
        assert any("extrinsics" in x for x in m["bare"]["warnings"])  # the assumed camera
    res = load_result(out / m["undetected_frames"]["file"])
    assert res["warnings"] == w
    assert summary["warnings"] >= 2


def test_a_failing_batch_fails_only_its_culprit(params, input_folder, tmp_path, monkeypatch):
    """An error inside a batch (here: the engine refuses clip 'medium') is retried clip by clip:
    only the culprit fails, its batch-mates get their results."""
    from jmocap.pipeline import Reconstructor

    real = Reconstructor.run_group

    def run_group(self, clips):
        if any(c.name == "c1" for c in clips):  # 'medium' is synth(1, ...): name c1
            raise RuntimeError("the engine failed on c1")
        return real(self, clips)

    monkeypatch.setattr(Reconstructor, "run_group", run_group)
    s = reconstruct_archive(input_folder, tmp_path / "out", params, SMALL, BatchOptions(chunk=8, bucket=8, batch=8))
    m = read_manifest(tmp_path / "out")
    assert {n for n, e in m.items() if e["status"] == "ok"} == GOOD - {"medium"}
    assert "the engine failed on c1" in m["medium"]["error"] and "medium" in m["medium"]["error"]
    assert s["failed"] == len(BAD) + 1


def test_results_do_not_depend_on_batch_mates(params, clips, tmp_path):
    """With the default batching, a clip reconstructed alone gives the same bytes of motion as
    in a batch with other clips (one of them half undetected), so a resume, which regroups the
    clips it has left, is exact."""
    mixed, alone = tmp_path / "mixed", tmp_path / "alone"
    for d, names in ((mixed, ("long", "undetected_frames", "medium")), (alone, ("long",))):
        d.mkdir()
        for n in names:
            save_clip(d / f"{n}.npz", clips[n])
    for d in (mixed, alone):
        reconstruct_archive(d, tmp_path / f"out_{d.name}", params, SMALL, BatchOptions())
    a, b = load_result(tmp_path / "out_alone" / "long.npz"), load_result(tmp_path / "out_mixed" / "long.npz")
    for k in ("q", "qd", "tau", "grf", "contact_prob", "target_q", "keypoints3d"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_a_variant_names_itself_in_its_results(params, clips, tmp_path):
    """A run of a variant (``physionical``: ``physcap`` with other config fields) records the
    variant's name in its results and manifest, not its base method's. (The config here is the
    tests' ``SMALL``, so the compiled program is ``first_run``'s: only the naming is checked.)"""
    src = tmp_path / "in"
    src.mkdir()
    save_clip(src / "short.npz", clips["short"])
    out = tmp_path / "out"
    _reconstruct_archive(src, out, params, SMALL, OPTS, method="physionical")
    assert str(load_result(out / "short.npz")["method"]) == "physionical"
    assert json.loads((out / "archive.json").read_text())["method"] == "physionical"


def test_output_folder_problems_are_one_line_errors(params, input_folder, tmp_path):
    from jmocap.data.archive import ArchiveError

    (tmp_path / "file").write_text("x")
    with pytest.raises(ArchiveError, match="exists and is not a folder"):
        reconstruct_archive(input_folder, tmp_path / "file", params, SMALL, OPTS)
    out = tmp_path / "out"
    out.mkdir()
    stale = [out / ".jmocap-abc123.tmp", out / ".short.npz.k2j3.tmp", out / "sub" / ".jmocap-x.npz"]
    for p in stale:
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(b"left by a killed run")
    import fcntl

    with open(out / ".jmocap.lock", "a+b") as lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(ArchiveError, match="another jmocap run"):
            reconstruct_archive(input_folder, out, params, SMALL, OPTS)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.json").write_text('{"author": "me"}')
    with pytest.raises(ArchiveError, match="no clips found.*notes.json"):
        reconstruct_archive(empty, tmp_path / "out2", params, SMALL, OPTS)
    assert not (tmp_path / "out2").exists()  # nothing made for an input without clips
    old = os.umask(0o027)
    try:
        reconstruct_archive(input_folder, out, params, SMALL, OPTS)
    finally:
        os.umask(old)
    assert not any(p.exists() for p in stale)  # removed when the run started
    assert (out / "short.npz").stat().st_mode & 0o777 == 0o640  # 0o666 less the umask
    assert (out / "manifest.jsonl").is_file()


@pytest.mark.slow  # (the default suite: tests/test_fuzz.py's signal cases, smaller and faster)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_ends_the_run_with_a_summary(xla_cache, first_run, params, tmp_path, sig):
    """SIGTERM / SIGINT: the results computed so far are written, summary.json says the run was
    interrupted, the exit status is 128 + the signal, no traceback; the rerun completes."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    n = 24
    for i in range(n):
        save_clip(src / f"k{i:02d}.npz", synth(20 + i, 6 + i % 3))
    cmd, env = cli(tmp_path, params, src, out, "--batch", "2", "--host-devices", "1", cache=xla_cache)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None:
            if (out / "manifest.jsonl").exists() and any(e["status"] == "ok" for e in read_manifest(out).values()):
                break
            time.sleep(0.005)
        assert proc.poll() is None, f"the run ended before the signal: {proc.stderr.read()}"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and "interrupted" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] == sig.name and 0 < summary["ok"] < n
    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert json.loads((out / "summary.json").read_text())["interrupted"] is None


def test_tiled_vmap_equals_vmap_for_any_tile_and_groups():
    """jmocap.pipeline.tiled_vmap against jax.vmap: a pytree of arguments, tiles that do and do
    not divide a group (remainders), one and two groups, tile 0 and a tile larger than a group;
    a batch that the groups do not divide is refused."""
    import jax.numpy as jnp

    from jmocap.pipeline import tiled_vmap

    def f(a, b):
        return {"s": jnp.sin(a) * b["w"] + jnp.sum(b["v"]), "v": b["v"][::-1] * a}

    rng = np.random.default_rng(0)
    a = rng.normal(size=12).astype(np.float32)
    b = {"w": rng.normal(size=12).astype(np.float32), "v": rng.normal(size=(12, 3)).astype(np.float32)}
    want = jax.vmap(f)(a, b)
    for tile, groups in ((0, 1), (5, 1), (4, 1), (4, 2), (5, 2), (6, 2), (64, 2)):
        got = jax.jit(lambda x, y, t=tile, g=groups: tiled_vmap(f, (x, y), t, g))(a, b)
        for k in want:
            np.testing.assert_allclose(np.asarray(got[k]), np.asarray(want[k]), rtol=1e-6, atol=1e-6,
                                       err_msg=f"tile {tile}, groups {groups}, {k}")
    with pytest.raises(ValueError, match="cannot be split into 5 equal groups"):
        tiled_vmap(f, (a, b), 2, 5)
