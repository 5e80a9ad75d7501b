"""End-to-end tests of the synthetic clip generator (``jmocap.data.synthetic``), the clip
archive and ``jmocap data synth``; the package's layout (public API, no import cycles).

The character and its leg IK, the rotation helpers, cameras and 2D keypoints, and the physics
variant have their own files (``tests/test_synthetic_*.py``).

References are independent of the code under test: MuJoCo C (``mj_kinematics``, joint ranges
read from ``MjModel.jnt_range``), hand-made trajectories for the contact rule,
``numpy.polyfit`` for the flight parabola, the import statements of the package's sources.

Tolerances: planted feet < 1 mm (the generator's leg IK converges to 1e-7 m; 1 mm is what the
task asks); floor >= -1e-6 m (IK tolerance); flight curvature within 5 % of -g/2 (exact by
construction, the 5 % is the task's bound).
"""

from __future__ import annotations

import ast
import json
import re
import tarfile
import zipfile
from pathlib import Path

import mujoco
import numpy as np
import pytest

from jmocap.cli import main
from jmocap.data import synthetic as S
from jmocap.data.archive import MANIFEST, Archive, ArchiveError, ArchiveWriter, iter_clips
from jmocap.data.clip import load_clip
from jmocap.data.synthetic.curves import _runs
from jmocap.layouts import CONTACT_SITES, get_layout

FAST = dict(frames=45, max_attempts=12)


@pytest.fixture(scope="module")
def walk_clip():
    return S.generate_clip(11, 0, S.SynthConfig(kinds=("walk",), **FAST))


@pytest.fixture(scope="module")
def mixed_clips():
    cfg = S.SynthConfig(kinds=("dance", "squat", "kick", "lunge", "stand"), **FAST)
    return [S.generate_clip(5, i, cfg) for i in range(3)]


@pytest.fixture(scope="module")
def jump_clip():
    # long enough to contain a whole flight
    return S.generate_clip(2, 0, S.SynthConfig(kinds=("jump",), frames=150))


@pytest.fixture(scope="module")
def extended_clips():
    """One clip of each everyday kind of the extended generator (kinematic variant)."""
    return [S.generate_clip(3, 0, S.SynthConfig.extended_generator(kinds=(k,), frames=150))
            for k in ("bend", "crouch", "reach")]


def _model_for(clip):
    return S.character(round(clip.height_m, 2))


def _sites(mj, q, names):
    """World positions (T, n, 3) of named sites by MuJoCo C kinematics."""
    d = mujoco.MjData(mj)
    ids = [mj.site(n).id for n in names]
    out = np.zeros((len(q), len(ids), 3))
    for t, qt in enumerate(q):
        d.qpos[:] = qt
        mujoco.mj_kinematics(mj, d)
        out[t] = d.site_xpos[ids]
    return out


def _planted_runs(clip):
    return {k: [tuple(r) for r in v] for k, v in clip.meta["planned_contacts"].items()}


# --- determinism --------------------------------------------------------------------------


def test_same_seed_same_arrays():
    cfg = S.SynthConfig(frames=30, kinds=("walk", "dance"))
    a = S.generate_clip(7, 3, cfg)
    b = S.generate_clip(7, 3, cfg)
    for key in ("keypoints", "gt_q", "gt_qd", "gt_keypoints3d", "gt_contacts", "intrinsics", "extrinsics"):
        x, y = getattr(a, key), getattr(b, key)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes(), key
    assert a.meta == b.meta
    c = S.generate_clip(8, 3, cfg)
    assert c.gt_q.shape != a.gt_q.shape or not np.array_equal(c.gt_q, a.gt_q)


# --- kinematic cleanliness ---------------------------------------------------------------


def test_planted_feet_do_not_move(walk_clip, mixed_clips, extended_clips):
    for clip in [walk_clip, *mixed_clips, *extended_clips]:
        mj = _model_for(clip).mj
        pos = _sites(mj, clip.gt_q.astype(np.float64), CONTACT_SITES)
        n_runs = 0
        for i, name in enumerate(CONTACT_SITES):
            for a, b in _planted_runs(clip)[name]:
                drift = np.max(np.linalg.norm(pos[a:b, i] - pos[a, i], axis=-1))
                assert drift < 1e-3, (clip.name, name, a, b, drift)
                assert np.all(np.abs(pos[a:b, i, 2]) < 1e-4)  # and they are on the floor
                n_runs += 1
        assert n_runs > 0


def test_contact_labels_follow_rempe_rule(walk_clip, mixed_clips, extended_clips):
    for clip in [walk_clip, *mixed_clips, *extended_clips]:
        mj = _model_for(clip).mj
        pos = _sites(mj, clip.gt_q.astype(np.float64), CONTACT_SITES)
        c = clip.gt_contacts.astype(bool)
        step = np.linalg.norm(np.diff(pos, axis=0), axis=-1)
        # labelled in contact => moved < 2 cm since the previous frame and < 5 cm high
        assert np.all(step[c[1:]] < 0.02)
        assert np.all(pos[..., 2][c] < 0.05)
        # and the converse (the rule is an equivalence)
        expect = (step < 0.02) & (pos[1:, :, 2] < 0.05)
        assert np.array_equal(c[1:], expect)
        assert np.array_equal(c[0], (step[0] < 0.02) & (pos[0, :, 2] < 0.05))


def test_contact_rule_hand_computed():
    p = np.zeros((4, 4, 3))
    p[:, 0, 2] = [0.0, 0.0, 0.0, 0.0]  # still on the floor: contact throughout
    p[:, 1, 0] = [0.0, 0.03, 0.06, 0.07]  # sliding 3 cm/frame, then 1 cm
    p[:, 2, 2] = [0.06, 0.06, 0.06, 0.06]  # still but 6 cm high
    p[:, 3, 2] = [0.0, 0.01, 0.049, 0.2]  # lifting
    c = S.contact_labels(p)
    assert c[:, 0].tolist() == [1, 1, 1, 1]
    assert c[:, 1].tolist() == [0, 0, 0, 1]  # frame 0 takes frame 1's displacement
    assert c[:, 2].tolist() == [0, 0, 0, 0]
    assert c[:, 3].tolist() == [1, 1, 0, 0]


def test_no_floor_penetration_and_limits(walk_clip, mixed_clips, jump_clip, extended_clips):
    for clip in [walk_clip, *mixed_clips, jump_clip, *extended_clips]:
        mj = _model_for(clip).mj
        names = [mj.site(i).name for i in range(mj.nsite)
                 if mj.site(i).name.startswith(("kp_", "contact_"))]
        pos = _sites(mj, clip.gt_q.astype(np.float64), names)
        assert pos[..., 2].min() >= -1e-6, clip.name
        q = clip.gt_q.astype(np.float64)
        for j in range(mj.njnt):
            if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and mj.jnt_limited[j]:
                a = mj.jnt_qposadr[j]
                lo, hi = mj.jnt_range[j]
                # float32 storage: 1e-6 rad
                assert q[:, a].min() >= lo - 1e-6 and q[:, a].max() <= hi + 1e-6, mj.joint(j).name


def test_extended_kinds_do_what_they_say(extended_clips):
    """Bend: a hand comes within 45 % of the subject's height of the floor and the trunk
    (mid-hip to neck) tilts > 45 degrees from vertical; crouch: the hips drop by > 12 % of the
    height; reach: a wrist goes above the head top or > 40 % of the height sideways from the
    mid-hip. Positions by MuJoCo C kinematics; the subject heights are the extended range's."""
    names = ["kp_mid_hip", "kp_neck", "kp_head_top", "kp_left_wrist", "kp_right_wrist"]
    for clip, kind in zip(extended_clips, ("bend", "crouch", "reach"), strict=True):
        assert clip.meta["kind"] == kind and 1.45 <= clip.height_m <= 2.0
        assert kind in [k for k, _, _ in clip.meta["kind_per_frame"]]
        p = _sites(_model_for(clip).mj, clip.gt_q.astype(np.float64), names)
        hip, neck, top, wr = p[:, 0], p[:, 1], p[:, 2], p[:, 3:5]
        h = clip.height_m
        if kind == "bend":
            trunk = neck - hip
            tilt = np.degrees(np.arccos(trunk[:, 2] / np.linalg.norm(trunk, axis=-1)))
            assert wr[..., 2].min() < 0.45 * h and tilt.max() > 45.0, (wr[..., 2].min(), tilt.max())
        elif kind == "crouch":
            assert hip[:, 2].max() - hip[:, 2].min() > 0.12 * h
        else:
            up = (wr[..., 2] - top[:, None, 2]).max()
            side = np.linalg.norm(wr[..., :2] - hip[:, None, :2], axis=-1).max()
            assert up > 0.0 or side > 0.4 * h, (up, side)


def test_classic_generator_draws_only_classic_kinds():
    """Without ``extended`` the generator is the classic one (the documented archives are
    regenerated bit for bit: only the classic kinds, no extended variation)."""
    cfg = S.SynthConfig(frames=30)
    kinds = {k for i in range(4) for k in S.generate_clip(9, i, cfg).meta["kinds"]}
    assert kinds <= set(S.CLASSIC_KINDS)
    assert set(S.EXTENDED_KINDS) - set(S.CLASSIC_KINDS) == {"bend", "crouch", "reach"}
    assert S.MOTION_KINDS[:8] == ("walk", "run", "jump", "squat", "lunge", "kick", "stand", "dance")


def test_keypoints3d_are_the_layout_sites(walk_clip):
    mj = _model_for(walk_clip).mj
    lay = get_layout(walk_clip.layout)
    pos = _sites(mj, walk_clip.gt_q.astype(np.float64), lay.sites)
    np.testing.assert_allclose(walk_clip.gt_keypoints3d, pos, atol=1e-5)


def test_velocities_match_finite_differences(walk_clip):
    mj = _model_for(walk_clip).mj
    q = walk_clip.gt_q.astype(np.float64)
    qd = walk_clip.gt_qd.astype(np.float64)
    fps = walk_clip.fps
    # integrating the central-difference velocity over two frames from t-1 lands on t+1
    for t in range(1, len(q) - 1, 7):
        x = q[t - 1].copy()
        mujoco.mj_integratePos(mj, x, qd[t], 2.0 / fps)
        np.testing.assert_allclose(x, q[t + 1], atol=2e-4)


# --- jumps --------------------------------------------------------------------------------


def test_jump_has_ballistic_flight(jump_clip):
    T = jump_clip.num_frames
    planted = np.zeros(T, bool)
    for runs in _planted_runs(jump_clip).values():
        for a, b in runs:
            planted[a:b] = True
    flight = ~planted
    assert jump_clip.meta["flight_frames"] == int(flight.sum()) > 0
    runs = _runs(flight)
    a, b = max(runs, key=lambda r: r[1] - r[0])
    assert b - a >= 5
    # no contact labels during the flight (the feet leave at once, faster than 2 cm/frame)
    assert not jump_clip.gt_contacts[a + 1 : b].any()
    t = np.arange(a, b) / jump_clip.fps
    z = jump_clip.gt_q[a:b, 2].astype(np.float64)
    coef = np.polyfit(t, z, 2)
    assert abs(coef[0] - (-9.81 / 2)) < 0.05 * 9.81 / 2
    # the horizontal root motion is close to uniform during the flight (COM is ballistic)
    xy = jump_clip.gt_q[a:b, :2].astype(np.float64)
    acc = np.diff(xy, 2, axis=0) * jump_clip.fps**2
    assert np.max(np.abs(acc)) < 3.0


# --- package layout -------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "jmocap" / "data" / "synthetic"


def _imported_synthetic_names():
    """(file, name) of every ``from jmocap.data.synthetic import name`` in the repository's
    Python sources and the Markdown docs."""
    out = []
    for folder in ("src", "tests", "experiments"):
        for path in (ROOT / folder).rglob("*.py"):
            text = path.read_text(encoding="utf-8")
            if "jmocap.data.synthetic" not in text:
                continue
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.ImportFrom) and node.module == "jmocap.data.synthetic":
                    out += [(path.name, a.name) for a in node.names]
    for path in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]:
        if path.exists():
            for m in re.finditer(r"from jmocap\.data\.synthetic import ([\w, ]+)", path.read_text()):
                out += [(path.name, n.strip()) for n in m.group(1).split(",") if n.strip()]
    return out


def test_every_imported_name_is_exported():
    names = _imported_synthetic_names()
    assert len({f for f, _ in names}) >= 5  # cli, tests, experiments, docs import from it
    for f, name in names:
        assert name in S.__all__ and hasattr(S, name), (f, name)
    for name in S.__all__:
        assert hasattr(S, name), name


def test_modules_have_docstrings_and_no_import_cycles():
    graph = {}
    for path in sorted(PACKAGE.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        assert ast.get_docstring(tree), f"{path.name} has no module docstring"
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{path.name}: relative import"
                mod = node.module or ""
                if path.stem != "__init__":
                    # a module importing the package root would run __init__ (a cycle)
                    assert mod != "jmocap.data.synthetic", f"{path.name} imports the package root"
                if mod.startswith("jmocap.data.synthetic."):
                    deps.add(mod.rsplit(".", 1)[1])
            elif isinstance(node, ast.Import):
                assert not any(a.name.startswith("jmocap.data.synthetic") for a in node.names)
        graph[path.stem] = deps
    graph.pop("__init__")
    assert set().union(*graph.values()) <= set(graph)
    # Kahn's algorithm: every module gets an order iff the graph has no cycle
    order, todo = [], dict(graph)
    while todo:
        ready = sorted(m for m, d in todo.items() if d <= set(order))
        assert ready, f"import cycle among {sorted(todo)}"
        order += ready
        for m in ready:
            del todo[m]


# --- archive --------------------------------------------------------------------------------


def _assert_same_clip(a, b):
    assert a.name == b.name and a.layout == b.layout and a.fps == b.fps
    for key in ("keypoints", "gt_q", "gt_qd", "gt_keypoints3d", "gt_contacts", "intrinsics",
                "image_size", "extrinsics"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert a.meta == b.meta


def test_archive_round_trip(tmp_path, mixed_clips):
    root = tmp_path / "arch"
    with ArchiveWriter(root, {"seed": 5}) as w:
        for i, c in enumerate(mixed_clips):
            w.add(c, index=i)
        w.add_failure("synth_000099", "no valid motion", index=99)
    lines = [json.loads(x) for x in (root / MANIFEST).read_text().splitlines()]
    assert [x["name"] for x in lines] == [c.name for c in mixed_clips] + ["synth_000099"]
    for x, c in zip(lines, mixed_clips, strict=False):
        assert x["status"] == "ok" and x["file"] == f"{c.name}.npz"
        assert x["frames"] == c.num_frames and x["fps"] == c.fps and x["layout"] == c.layout
        assert x["kind"] == c.meta["kind"] and x["height_m"] == c.height_m
        import hashlib

        assert x["sha256"] == hashlib.sha256((root / x["file"]).read_bytes()).hexdigest()
        _assert_same_clip(load_clip(root / x["file"]), c)
    assert lines[-1]["status"] == "failed" and lines[-1]["error"] == "no valid motion"
    a = Archive(root)
    assert len(a) == len(mixed_clips) and a.settings == {"seed": 5}
    for c, r in zip(mixed_clips, a, strict=True):
        _assert_same_clip(r, c)
    # zip and tar.gz of the folder read the same (with a top-level folder inside)
    with zipfile.ZipFile(tmp_path / "a.zip", "w") as z:
        for f in root.iterdir():
            z.write(f, arcname=f"arch/{f.name}")
    with tarfile.open(tmp_path / "a.tar.gz", "w:gz") as t:
        t.add(root, arcname="arch")
    for path in (tmp_path / "a.zip", tmp_path / "a.tar.gz"):
        got = list(iter_clips(path, verify=True))
        assert [c.name for c in got] == [c.name for c in mixed_clips]
        _assert_same_clip(got[0], mixed_clips[0])


def test_archive_files_are_deterministic(tmp_path, mixed_clips):
    for sub in ("a", "b"):
        with ArchiveWriter(tmp_path / sub) as w:
            w.add(mixed_clips[0])
    assert (tmp_path / "a" / "synth_000000.npz").read_bytes() == (tmp_path / "b" / "synth_000000.npz").read_bytes()


def test_archive_resume_after_interruption(tmp_path, mixed_clips):
    root = tmp_path / "arch"
    with ArchiveWriter(root, {"seed": 5}) as w:
        w.add(mixed_clips[0])
    # simulate a crash: a half-written manifest line and a stray temp file
    with open(root / MANIFEST, "a") as f:
        f.write('{"name": "synth_000001", "file": "synth_0')
    (root / ".synth_000001.npz.123.tmp").write_bytes(b"partial")
    a = Archive(root)  # the reader ignores the truncated line
    assert a.names() == [mixed_clips[0].name]
    with ArchiveWriter(root, {"seed": 5}) as w:
        assert w.has(mixed_clips[0].name, verify=True)
        assert not w.has(mixed_clips[1].name)
        w.add(mixed_clips[1])
    text = (root / MANIFEST).read_text()
    assert text.endswith("\n") and len(text.splitlines()) == 2
    assert Archive(root).names() == [c.name for c in mixed_clips[:2]]
    # a missing file makes has() false again (it will be rewritten)
    (root / f"{mixed_clips[1].name}.npz").unlink()
    with ArchiveWriter(root, {"seed": 5}) as w:
        assert not w.has(mixed_clips[1].name)
    with pytest.raises(ArchiveError, match="different settings"):
        ArchiveWriter(root, {"seed": 6})


def test_archive_errors(tmp_path):
    with pytest.raises(ArchiveError, match="no manifest"):
        Archive(tmp_path)
    (tmp_path / MANIFEST).write_text('{"name": "a", "status": "ok"}\nnot json\n{"name": "b", "status": "ok"}\n')
    with pytest.raises(ArchiveError, match="line 2"):
        Archive(tmp_path)


# --- CLI ------------------------------------------------------------------------------------


def test_cli_data_synth(tmp_path, capsys):
    out = tmp_path / "synth"
    argv = ["data", "synth", "--out", str(out), "--clips", "2", "--seed", "9", "--frames-per-clip",
            "30", "--kinds", "stand,dance", "--layout", "h36m17", "--quiet"]
    assert main(argv) == 0
    msg = capsys.readouterr().out
    assert "2 clips written" in msg and "frames/s" in msg
    lines = [json.loads(x) for x in (out / MANIFEST).read_text().splitlines()]
    assert [x["name"] for x in lines] == ["synth_000000", "synth_000001"]
    assert all(x["frames"] == 30 and x["layout"] == "h36m17" and x["seed"] == 9 for x in lines)
    clip = load_clip(out / lines[0]["file"])
    assert clip.keypoints.shape == (30, 17, 3)
    # resuming does nothing more; a bigger --clips adds only the new ones
    assert main(argv) == 0
    msg = capsys.readouterr().out
    assert "0 clips written" in msg and "2 already there" in msg
    argv3 = list(argv)
    argv3[argv3.index("2")] = "3"
    assert main(argv3) == 0
    assert len((out / MANIFEST).read_text().splitlines()) == 3
    # same seed elsewhere: byte-identical files
    out2 = tmp_path / "again"
    argv2 = list(argv)
    argv2[argv2.index(str(out))] = str(out2)
    assert main(argv2) == 0
    l2 = [json.loads(x) for x in (out2 / MANIFEST).read_text().splitlines()]
    assert [x["sha256"] for x in l2] == [x["sha256"] for x in lines]
    # info
    assert main(["data", "info", str(out)]) == 0
    assert "3 clips" in capsys.readouterr().out
    # changing settings on an existing archive is refused
    with pytest.raises(ArchiveError):
        main(argv[:-1] + ["--fps", "25", "--quiet"])
    # the extended generator is recorded in the archive's settings
    ext = tmp_path / "ext"
    assert main(["data", "synth", "--out", str(ext), "--clips", "1", "--seed", "9", "--frames-per-clip", "30",
                 "--kinds", "reach", "--extended", "--quiet"]) == 0
    cfg = json.loads((ext / "archive.json").read_text())["config"]
    assert cfg["extended"] is True and cfg["height_m"] == [1.45, 2.0]
    assert cfg["camera"]["focal_equiv_mm"] == [13.0, 120.0] and cfg["corruption"]["occlusion_prob"] > 0
    assert Archive(ext).ok[0]["kind"] == "reach"


def test_cli_data_info_root_residual_by_hand(tmp_path, capsys):
    """``jmocap data info`` on a physics archive: the share of frames with a root residual,
    frame-weighted, overall and per kind, from the manifest (hand-worked: 10 % of a 100-frame
    walk and none of a 300-frame run are 10 of 400 frames)."""
    out = tmp_path / "phys"
    out.mkdir()
    rows = [dict(name="a", file="a.npz", status="ok", kind="walk", frames=100, residual_frame_share=0.1,
                 residual_force_mean=0.02, residual_force_max=0.5),
            dict(name="b", file="b.npz", status="ok", kind="run", frames=300, residual_frame_share=0.0,
                 residual_force_mean=0.0, residual_force_max=0.0)]
    (out / MANIFEST).write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert main(["data", "info", str(out)]) == 0
    assert ("root residual: 2.5 % of frames (walk 10.0 %, run 0.0 %); 1 of 2 clips without; mean force 1.00 % BW"
            in capsys.readouterr().out)


def test_cli_data_synth_sampling_controller(tmp_path, capsys):
    """``--controller sampling`` is recorded in the archive's settings and in the clip's physics
    metadata, and its clip has no root residual; without ``--physics`` it is refused."""
    out = tmp_path / "samp"
    assert main(["data", "synth", "--out", str(out), "--clips", "1", "--seed", "4", "--frames-per-clip", "20",
                 "--kinds", "walk", "--physics", "--controller", "sampling", "--quiet"]) == 0
    cfg = json.loads((out / "archive.json").read_text())["config"]
    assert cfg["physics_cfg"]["controller"] == "sampling"
    clip = Archive(out).load("synth_000000")
    assert clip.meta["physics"]["controller"] == "sampling"
    assert clip.meta["physics"]["residual_frame_share"] == 0.0
    np.testing.assert_array_equal(clip.gt_residual, 0.0)
    capsys.readouterr()
    assert main(["data", "info", str(out)]) == 0
    assert "root residual: 0.0 % of frames (walk 0.0 %); 1 of 1 clips without" in capsys.readouterr().out
    assert main(["data", "synth", "--out", str(tmp_path / "x"), "--clips", "1", "--controller", "sampling",
                 "--quiet"]) == 2
    assert "--controller needs --physics" in capsys.readouterr().err


def test_cli_bad_arguments(capsys):
    with pytest.raises(SystemExit):
        main(["data", "synth", "--out", "x", "--clips", "1", "--frames-per-clip", "9:3"])
    with pytest.raises(SystemExit):
        main(["data", "synth", "--out", "x", "--clips", "1", "--kinds", "fly"])
    with pytest.raises(SystemExit):
        main([])
