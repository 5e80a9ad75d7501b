"""Moving cameras (issue 20, items 1 and 2): the clip's per-frame camera track, the sidecar's
per-frame forms, and the synthetic moving cameras. References: OpenCV's ``projectPoints`` and
``Rodrigues`` per frame, numpy's matrix inverse, and the ground truth's own 3D joints."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jmocap.data.clip import Clip, ClipFormatError, load_clip, save_clip
from jmocap.data.formats import FormatError, read_camera_json, read_clip, write_camera_json
from jmocap.data.formats.camera_file import Y_UP_TO_Z_UP
from jmocap.data.synthetic import (
    MOVING_KINDS,
    CameraConfig,
    SynthConfig,
    clean_keypoints2d,
    generate_clip,
    look_at_extrinsics,
    project_points,
    sample_moving_camera,
)

T = 24
FPS = 30.0
INTR = np.array([1000.0, 990.0, 640.0, 360.0])
SIZE = {"width": 1280, "height": 720, "fx": 1000.0, "fy": 990.0, "cx": 640.0, "cy": 360.0}


def _track(T=T):
    """A camera circling the origin at 4 m, 1.5 m up, turning 0.6 rad over the clip, rolled a little."""
    out = []
    for i, a in enumerate(np.linspace(0.0, 0.6, T)):
        E = look_at_extrinsics([4 * np.cos(a), 4 * np.sin(a), 1.5], [0.1 * i / T, 0.0, 1.0])
        r = 0.05 * np.sin(i / 3)
        Rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
        E[:3] = Rz @ E[:3]
        out.append(E)
    return np.stack(out)


def _clip(track=None, **kw):
    return Clip(name="cam", layout="body25", fps=FPS, keypoints=np.zeros((T, 25, 3), np.float32), intrinsics=INTR,
                image_size=[1280, 720], camera_track=_track() if track is None else track, **kw)


def _points(rng, T=T, n=7):
    return rng.normal([0.0, 0.0, 1.0], 0.4, size=(T, n, 3))


def test_track_is_stored_sliced_and_its_first_frame_is_the_static_camera(tmp_path):
    track = _track()
    clip = _clip()
    assert clip.moving_camera
    np.testing.assert_array_equal(clip.extrinsics, track[0])
    np.testing.assert_array_equal(clip.world_to_camera(), track)
    back = load_clip(save_clip(tmp_path / "c.npz", clip))
    np.testing.assert_array_equal(back.camera_track, track)
    part = clip.slice(5, 12)
    np.testing.assert_array_equal(part.camera_track, track[5:12])
    np.testing.assert_array_equal(part.extrinsics, track[5])
    static = clip.replace(camera_track=None)
    assert not static.moving_camera
    np.testing.assert_array_equal(static.world_to_camera(), np.broadcast_to(track[0], (T, 4, 4)))


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.__setitem__((7, slice(0, 3), slice(0, 3)), 1.1 * t[7, :3, :3]), "is not a rigid transform .* at frame 7"),
    (lambda t: t.__setitem__((9, 0, 0), np.nan), "has non-finite values, first at frame 9"),
    (lambda t: t.__setitem__((slice(12, None), slice(0, 3), 3), t[12:, :3, 3] + 3.0),
     "moves at .* m/s between frames 11 and 12 .* a discontinuity"),
    (lambda t: t.__setitem__((slice(15, None), slice(0, 3)),
                             np.einsum("ij,tjk->tik", np.diag([1.0, -1.0, -1.0]), t[15:, :3])),
     "turns at .* deg/s between frames 14 and 15"),
])
def test_track_errors_name_the_field_and_frame(edit, message):
    track = _track()
    edit(track)
    with pytest.raises(ClipFormatError, match="field 'camera_track' " + message):
        _clip(track)


def test_track_shape_and_first_frame_must_agree_with_the_clip():
    with pytest.raises(ClipFormatError, match=r"'camera_track' must have shape \(24, 4, 4\)"):
        _clip(_track(T + 1))
    with pytest.raises(ClipFormatError, match="'extrinsics' differs from the first frame"):
        _clip(extrinsics=_track()[3])
    np.testing.assert_array_equal(_clip(extrinsics=_track()[0]).extrinsics, _track()[0])


def _forms(track):
    """The sidecar's extrinsics forms, per frame, written from the track by hand."""
    R, t = track[:, :3, :3], track[:, :3, 3]
    Rc = np.swapaxes(R, 1, 2)
    centre = -np.einsum("tij,tj->ti", Rc, t)
    cv2 = pytest.importorskip("cv2")
    rvec = np.stack([cv2.Rodrigues(r)[0][:, 0] for r in R])
    return {
        "extrinsics": {"extrinsics": track.tolist()},
        "R/t": {"R": R.tolist(), "t": t.tolist()},
        "rvec/tvec": {"rvec": rvec.tolist(), "tvec": t.tolist()},
        "cam_to_world": {"cam_to_world": np.linalg.inv(track).tolist()},
        "camera pose": {"camera_position": centre.tolist(), "camera_rotation": Rc.tolist()},
    }


@pytest.mark.parametrize("form", ["extrinsics", "R/t", "rvec/tvec", "cam_to_world", "camera pose"])
def test_sidecar_per_frame_forms_project_like_opencv(tmp_path, form):
    cv2 = pytest.importorskip("cv2")
    track = _track()
    p = tmp_path / "c.camera.json"
    p.write_text(json.dumps({**SIZE, **_forms(track)[form]}))
    side = read_camera_json(p)
    assert side["camera_track"].shape == (T, 4, 4) and "per frame" in side["convention"]
    np.testing.assert_array_equal(side["extrinsics"], side["camera_track"][0])
    X = _points(np.random.default_rng(0))
    uv, _ = project_points(side["intrinsics"], side["camera_track"], X)
    K = np.array([[INTR[0], 0, INTR[2]], [0, INTR[1], INTR[3]], [0, 0, 1]])
    for i in (0, 11, T - 1):
        rvec, _ = cv2.Rodrigues(track[i, :3, :3])
        ref, _ = cv2.projectPoints(X[i], rvec, track[i, :3, 3], K, np.zeros(5))
        np.testing.assert_allclose(uv[i], ref[:, 0], atol=1e-7)


def test_sidecar_track_in_a_y_up_world(tmp_path):
    """A y-up world's track sees jmocap's points where the file's world has them."""
    track = _track()
    p = tmp_path / "c.camera.json"
    p.write_text(json.dumps({**SIZE, "extrinsics": track.tolist(), "world_up": "y", "floor_height": 0.2}))
    side = read_camera_json(p)
    X = _points(np.random.default_rng(1))  # jmocap's z-up world
    X_file = X @ Y_UP_TO_Z_UP + np.array([0.0, 0.2, 0.0])  # the file's: A^T X + floor along y
    np.testing.assert_allclose(project_points(INTR, side["camera_track"], X)[0], project_points(INTR, track, X_file)[0],
                               atol=1e-8)


@pytest.mark.parametrize("data, field, message", [
    ({"R": _track()[:, :3, :3].tolist(), "t": _track()[0, :3, 3].tolist()}, "R",
     "gives one camera in 't' but one per frame in 'R'"),
    ({"R": _track()[:, :3, :3].tolist(), "t": _track()[:-1, :3, 3].tolist()}, "R", "the camera track's keys have different numbers of frames"),
    ({"camera_position": np.zeros((T, 3)).tolist(), "camera_rotation": (1.5 * _track()[:, :3, :3]).tolist()},
     "camera_rotation", "must be a rotation matrix"),
    ({"extrinsics": np.broadcast_to(np.diag([1.0, 1.0, 1.0, 2.0]), (T, 4, 4)).tolist()}, "extrinsics",
     "must be a rigid transform"),
])
def test_sidecar_track_errors_name_file_field_and_frame(tmp_path, data, field, message):
    p = tmp_path / "c.camera.json"
    p.write_text(json.dumps({**SIZE, **data}))
    with pytest.raises(FormatError, match=f"c.camera.json: .*field '{field}': {message}"):
        read_camera_json(p)


def test_sidecar_frame_of_a_bad_rotation_is_named(tmp_path):
    track = _track()
    track[5, :3, :3] *= 1.2
    p = tmp_path / "c.camera.json"
    p.write_text(json.dumps({**SIZE, "extrinsics": track.tolist()}))
    with pytest.raises(FormatError, match="c.camera.json: frame 5: field 'extrinsics': must be a rigid transform"):
        read_camera_json(p)


def test_read_clip_takes_the_sidecar_track(tmp_path):
    clip = _clip()
    static = clip.replace(camera_track=None, extrinsics=None)
    path = save_clip(tmp_path / "walk.npz", static)
    write_camera_json(tmp_path / "walk.camera.json", clip)  # the track, written per frame
    got = read_clip(path)
    np.testing.assert_allclose(got.camera_track, clip.camera_track, atol=1e-12)
    np.testing.assert_allclose(got.extrinsics, clip.camera_track[0], atol=1e-12)
    # an explicit static camera replaces the track
    assert read_clip(path, extrinsics=np.eye(4)).camera_track is None
    # a track of another length is refused, naming the sidecar
    short = save_clip(tmp_path / "short.npz", static.slice(0, T - 2))
    write_camera_json(tmp_path / "short.camera.json", clip)
    with pytest.raises(FormatError, match=f"short.camera.json: field 'extrinsics': the camera track has {T} frames "
                                          f"but the clip has {T - 2}"):
        read_clip(short)


@pytest.mark.parametrize("kind", MOVING_KINDS)
def test_synthetic_moving_camera_sees_the_subject_from_its_track(kind):
    clip = generate_clip(11, 2, SynthConfig(frames=90, moving_camera=(kind,)))
    assert clip.moving_camera and clip.meta["camera"]["kind"] == kind
    track = clip.camera_track
    # the clean 2D keypoints are every frame's own projection (OpenCV as the reference)
    cv2 = pytest.importorskip("cv2")
    uv = clean_keypoints2d(clip)
    fx, fy, cx, cy = clip.intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    for i in (0, 45, 89):
        rvec, _ = cv2.Rodrigues(track[i, :3, :3])
        ref, _ = cv2.projectPoints(clip.gt_keypoints3d[i].astype(np.float64), rvec, track[i, :3, 3], K, np.zeros(5))
        np.testing.assert_allclose(uv[i], ref[:, 0], atol=1e-6)
    # the noisy keypoints are near them where confident; the subject stays in the image
    seen = clip.keypoints[..., 2] > 0.5
    assert np.median(np.linalg.norm(clip.keypoints[..., :2] - uv, axis=-1)[seen]) < 15.0
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < clip.image_size[0]) & (uv[..., 1] >= 0) & (uv[..., 1] < clip.image_size[1])
    assert inside.mean() >= 0.9
    # the camera really moves: its centre (pan: only its view direction)
    centre = -np.einsum("tji,tj->ti", track[:, :3, :3], track[:, :3, 3])
    travel = np.linalg.norm(centre[-1] - centre[0])
    turn = np.degrees(np.arccos(np.clip(track[0, 2, :3] @ track[-1, 2, :3], -1, 1)))
    if kind == "pan":
        assert travel < 1e-9 and turn > 0.5
    else:
        assert np.linalg.norm(np.diff(centre, axis=0), axis=-1).sum() > 0.3


def test_synthetic_moving_camera_is_deterministic_and_static_is_unchanged():
    cfg = SynthConfig(frames=60, moving_camera=("handheld", "orbit"))
    a, b = generate_clip(3, 1, cfg), generate_clip(3, 1, cfg)
    np.testing.assert_array_equal(a.camera_track, b.camera_track)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    # the motion does not depend on the camera; a static draw has no track
    s = generate_clip(3, 1, SynthConfig(frames=60))
    np.testing.assert_array_equal(a.gt_q, s.gt_q)
    assert s.camera_track is None and not s.moving_camera
    with pytest.raises(ValueError, match="unknown camera kind"):
        SynthConfig(moving_camera=("steadicam",))


def test_sample_moving_camera_keeps_joints_ahead_of_the_camera():
    rng = np.random.default_rng(5)
    # a subject walking 3 m along x
    base = np.stack([np.linspace(0, 3, 60), np.zeros(60), np.ones(60)], -1)
    points = base[:, None] + rng.normal(0, 0.3, (1, 15, 3)) * np.array([0.3, 0.3, 1.0])
    for kind in MOVING_KINDS:
        K, size, track, info = sample_moving_camera(rng, points, 30.0, kind, CameraConfig())
        _, z = project_points(K, track, points)
        assert z.min() >= CameraConfig().min_depth_m and info["kind"] == kind
        _clip_ok = Clip(name="x", layout="body25", fps=30.0, keypoints=np.zeros((60, 25, 3), np.float32),
                        intrinsics=K, image_size=size, camera_track=track)  # continuous, rigid
        assert _clip_ok.moving_camera


# ---------------------------------------------------------------------------------------
# the methods' inputs, the metrics, the harness and the batch engine
# ---------------------------------------------------------------------------------------


def test_clip_inputs_carry_every_frames_camera_padded_with_the_last():
    from jmocap.inputs import ClipInputs

    clip = _clip()
    inp = ClipInputs.from_clip(clip, T + 8)
    assert inp.camera_track.shape == (T + 8, 4, 4)
    np.testing.assert_allclose(inp.camera_track[:T], clip.camera_track, atol=1e-6)
    np.testing.assert_allclose(inp.camera_track[T:], np.broadcast_to(clip.camera_track[-1], (8, 4, 4)), atol=1e-6)
    np.testing.assert_allclose(inp.world_to_camera(), inp.camera_track)
    static = ClipInputs.from_clip(clip.replace(camera_track=None), T + 8)
    np.testing.assert_allclose(static.camera_track, np.broadcast_to(clip.extrinsics, (T + 8, 4, 4)), atol=1e-6)
    bare = static.with_static_camera(np.eye(4, dtype=np.float32))
    assert bare.camera_track is None
    np.testing.assert_array_equal(np.asarray(bare.world_to_camera()), np.broadcast_to(np.eye(4), (T + 8, 4, 4)))


def test_camera_frame_metrics_by_hand():
    """A camera sliding along x (no rotation) at 0.1 m per frame over a still body: scored as
    if the first frame's camera had stayed, the body's camera-frame root is off by the slide
    (mean over frames of 0.1 t m) while its root-aligned pose is exact; scored with the track,
    nothing is off. The world-frame metrics do not see the camera."""
    from jmocap.camera import Camera

    n = 10
    rng = np.random.default_rng(0)
    body = rng.normal(0.0, 0.3, (1, 25, 3)) + np.array([0.0, 0.0, 1.0])
    kp = np.repeat(body, n, 0)
    track = np.repeat(look_at_extrinsics([0.0, -4.0, 1.0], [0.0, 0.0, 1.0])[None], n, 0)
    # the camera's centre moves by +0.1 t along x: x_cam = R (X - c_t), so t_t = t_0 - R c_t
    track[:, :3, 3] -= 0.1 * np.arange(n)[:, None] * track[0, :3, 0][None]
    cam = Camera(INTR.astype(np.float32), np.array([1280.0, 720.0], np.float32), track.astype(np.float32))
    first = cam.replace(extrinsics=cam.extrinsics[0])
    pred, gt = {"keypoints3d": kp}, {"keypoints3d": kp}
    root = (8,)  # BODY_25's mid hip
    with_track = M_eval(pred, gt, cam, None, root)
    assert with_track["mpjpe_cam_mm"] == pytest.approx(0.0, abs=1e-3)
    assert with_track["root_err_cam_mm"] == pytest.approx(0.0, abs=1e-3)
    static = M_eval(pred, gt, cam, first, root)
    assert static["root_err_cam_mm"] == pytest.approx(1000.0 * 0.1 * np.arange(n).mean(), rel=1e-4)
    assert static["mpjpe_cam_mm"] == pytest.approx(0.0, abs=1e-3)
    # 0.1 m per frame at 30 fps is a constant velocity: no acceleration error
    assert static["accel_err_cam_m_s2"] == pytest.approx(0.0, abs=1e-2)
    assert static["root_err_mm"] == with_track["root_err_mm"] == pytest.approx(0.0, abs=1e-3)
    # a static camera has no camera-frame metrics
    assert "mpjpe_cam_mm" not in M_eval(pred, gt, first, None, root)


def M_eval(pred, gt, camera, pred_camera, root):
    from jmocap import metrics as M

    return M.evaluate_arrays(pred, gt, fps=FPS, camera=camera, root=root, pred_camera=pred_camera)


@pytest.fixture(scope="module")
def shipped():
    from jmocap.weights import default_params

    return default_params("kinematic")


@pytest.fixture(scope="module")
def moving_clips():
    cfg = SynthConfig(frames=64, moving_camera=("handheld", "orbit"))
    return [generate_clip(21, i, cfg) for i in range(2)]


def test_eval_of_a_moving_camera_given_and_ignored(shipped, moving_clips):
    """TPNet's camera-frame output does not depend on the extrinsics: with the track given its
    world root error is its camera-frame one (one rigid motion per frame for both), and with the
    camera's motion ignored (``camera="static"``) the camera-frame metrics stay while the world
    ones grow by the camera's travel."""
    from jmocap.evaluate import EvalConfig, evaluate

    params, config = shipped
    res = {how: evaluate("moving", params, config, EvalConfig(("kinematic",), 2, progress=False, camera=how),
                         clips=moving_clips).summary["kinematic"] for how in ("given", "static")}
    g, s = res["given"], res["static"]
    assert g["root_err_mm"] == pytest.approx(g["root_err_cam_mm"], rel=1e-3)
    for key in ("mpjpe_cam_mm", "root_err_cam_mm", "accel_err_cam_m_s2", "pa_mpjpe_mm"):
        assert s[key] == pytest.approx(g[key], rel=1e-3, abs=1e-3), key
    assert s["root_err_mm"] > g["root_err_mm"] + 20.0


def test_batch_results_keep_the_track_and_chunks_see_their_own_cameras(shipped, moving_clips, tmp_path):
    """``jmocap reconstruct``'s engine on a moving-camera clip: the result stores the track, and
    a clip reconstructed in chunks (every chunk with its frames' cameras) equals one whole chunk."""
    from jmocap.batch import BatchOptions, reconstruct_archive
    from jmocap.results import load_result

    clip = moving_clips[0]
    src = tmp_path / "in"
    src.mkdir()
    save_clip(src / f"{clip.name}.npz", clip)
    params, config = shipped
    out = {}
    for chunk in (16, 64):
        reconstruct_archive(src, tmp_path / str(chunk), params, config, BatchOptions(batch=1, chunk=chunk, bucket=16),
                            method="kinematic")
        out[chunk] = load_result(tmp_path / str(chunk) / f"{clip.name}.npz")
    np.testing.assert_allclose(out[16]["camera_track"], clip.camera_track, atol=1e-12)
    np.testing.assert_allclose(out[16]["q"], out[64]["q"], atol=1e-4)
    # the root TPNet puts in front of each frame's camera: ahead of it, at a plausible depth
    depth = np.einsum("tj,tj->t", out[16]["q"][:, :3], clip.camera_track[:, 2, :3]) + clip.camera_track[:, 2, 3]
    assert (depth > 1.0).all()


def test_stabilised_windows_are_what_the_target_camera_sees():
    """Points on the plane at depth d in frame s's camera, lifted at d and projected through frame
    t's camera, land where camera t projects them (reference: the pinhole projection); a camera
    that only turns needs no depth at all."""
    from jmocap.methods.contact_estimation import stabilise_window

    rng = np.random.default_rng(3)
    track = _track(4)
    d = np.array([3.0, 3.5, 4.0, 4.5])
    fx, fy, cx, cy = INTR
    xy = np.stack([rng.uniform(200, 1000, (4, 13)), rng.uniform(100, 600, (4, 13))], -1)  # seen by camera s
    ray = np.stack([(xy[..., 0] - cx) / fx, (xy[..., 1] - cy) / fy, np.ones((4, 13))], -1) * d[:, None, None]
    Xw = np.einsum("sji,skj->ski", track[:, :3, :3], ray - track[:, None, :3, 3])  # the world points
    frames = np.array([[0, 1, 2, 3]] * 4)  # every target frame's window holds all four frames
    win = np.broadcast_to(xy, (4, 4, 13, 2))
    got = np.asarray(stabilise_window(win, frames, INTR, track, d))
    for t in range(4):
        ref, _ = project_points(INTR, track[t], Xw)  # (4 sources, 13, 2) seen by camera t
        np.testing.assert_allclose(got[t], ref, atol=1e-3)  # float32 pixels
    turning = track.copy()
    centre = -track[0, :3, :3].T @ track[0, :3, 3]
    turning[:, :3, 3] = -np.einsum("sij,j->si", turning[:, :3, :3], centre)  # every camera at the same centre
    a = np.asarray(stabilise_window(win, frames, INTR, turning, d))
    b = np.asarray(stabilise_window(win, frames, INTR, turning, 3.0 * d))
    np.testing.assert_allclose(a, b, atol=1e-3)


def test_contact_estimate_of_a_static_camera_does_not_change_with_stabilisation():
    import jax

    from jmocap.inputs import ClipInputs
    from jmocap.methods import contact_estimation as CE

    clip = generate_clip(4, 0, SynthConfig(frames=40))
    inp = ClipInputs.from_clip(clip, 48)
    params = CE.default_contact_params()
    raw = np.asarray(jax.jit(CE.estimate_contacts)(params, inp))
    stab = np.asarray(jax.jit(CE.estimate_contacts)(params, inp, depth=np.full(48, 4.0, np.float32)))
    np.testing.assert_allclose(stab, raw, atol=1e-6)


def test_cli_data_synth_moving_camera(tmp_path, capsys):
    """``--moving-camera`` (the four kinds by default, or a list that may include ``static``) is
    recorded in the archive's settings; its clips carry their tracks; with ``--imu`` it is refused."""
    import json as _json

    from jmocap.cli import main
    from jmocap.data.archive import Archive

    out = tmp_path / "moving"
    assert main(["data", "synth", "--out", str(out), "--clips", "2", "--seed", "5", "--frames-per-clip", "20",
                 "--moving-camera", "pan,static", "--quiet"]) == 0  # seed 5: one of each
    assert _json.loads((out / "archive.json").read_text())["config"]["moving_camera"] == ["pan", "static"]
    kinds = []
    for name in ("synth_000000", "synth_000001"):
        clip = Archive(out).load(name)
        kinds.append(clip.meta["camera"].get("kind", "static"))
        assert clip.moving_camera == (kinds[-1] == "pan")
    lines = [_json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [x.get("camera", "static") for x in lines] == kinds
    capsys.readouterr()
    assert main(["data", "info", str(out)]) == 0
    assert kinds == ["pan", "static"]
    assert "cameras: pan 1, static 1" in capsys.readouterr().out
    default = tmp_path / "default"
    assert main(["data", "synth", "--out", str(default), "--clips", "1", "--seed", "4", "--frames-per-clip", "20",
                 "--moving-camera", "--quiet"]) == 0
    assert Archive(default).load("synth_000000").meta["camera"]["kind"] in MOVING_KINDS
    capsys.readouterr()
    assert main(["data", "synth", "--out", str(tmp_path / "imu"), "--clips", "1", "--imu", "--moving-camera"]) == 2
    assert "--moving-camera is for 2D keypoint clips" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["data", "synth", "--out", str(tmp_path / "x"), "--clips", "1", "--moving-camera", "steadicam"])


def test_reconstructability_checks_every_frames_camera():
    """A camera descending 0.12 m per frame from 1.5 m: the first frame under the floor (z < -0.1
    m: frame 14, at -0.18 m) is named."""
    from jmocap.data.validate import check_reconstructable

    track = _track()
    drop = 0.12 * np.arange(T)  # the centre c_t moves down by drop_t: t_t = -R c_t gains drop_t R e_z
    track[:, :3, 3] += drop[:, None] * track[:, :3, 2]
    z = np.array([(-E[:3, :3].T @ E[:3, 3])[2] for E in track])
    np.testing.assert_allclose(z, 1.5 - drop, atol=1e-9)
    with pytest.raises(FormatError, match="frame 14: field 'camera_track': the camera is .* below the floor"):
        check_reconstructable(_clip(track), "cam")
    with pytest.raises(FormatError, match="field 'keypoints'"):  # the level track passes: the next check speaks
        check_reconstructable(_clip(), "cam")
