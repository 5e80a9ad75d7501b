"""``jmocap video`` on videos the test renders itself, where the truth is known.

The shipped demo walk (``assets/demo/ground_truth/demo_walk.npz``: the character's ``gt_q``) is
rendered by MuJoCo from a camera 3.6 m away (the person about half the frame's height) into an
MP4; BlazePose, the tracker and the flip repair run on it, and the BODY_25 keypoints are
compared with the character's own keypoint sites (``jmocap.model.site_trajectory`` of the
layout's sites) projected through the same camera. Then the whole command: video -> keypoint
clip + camera sidecar -> reconstruction -> overlay MP4; two people side by side (two tracks,
``--person`` picks one); and bad input.

Needs the video extra (LiteRT, OpenCV, imageio-ffmpeg: skipped, saying so, without it; the
suite's ``test`` extra installs it) and a headless OpenGL for the renders.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import jmocap
from jmocap import cli, viz
from jmocap.camera import Camera, project
from jmocap.layouts import BODY25
from jmocap.model import character, site_trajectory
from jmocap.video import missing_video_packages

pytestmark = pytest.mark.skipif(
    bool(missing_video_packages()),
    reason=f"the video extra is not installed ({', '.join(missing_video_packages())}): pip install 'jmocap[video]'",
)

DEMO = jmocap.__path__[0] + "/assets/demo/ground_truth/demo_walk.npz"
W, H, FPS = 640, 480, 30.0
FRAMES = 40
# accuracy on the rendered walk (pixels; the person is ~240 px tall): per joint group, the median
# and the 90th percentile of the distance to the true projected site
GROUPS = {"shoulders": ("LShoulder", "RShoulder"), "elbows": ("LElbow", "RElbow"), "hips": ("LHip", "RHip"),
          "knees": ("LKnee", "RKnee"), "ankles": ("LAnkle", "RAnkle")}
MEDIAN_PX, P90_PX = 8.0, 15.0


@pytest.fixture(scope="module")
def demo():
    d = np.load(DEMO)
    return {"q": d["gt_q"].astype(np.float64), "height": float(d["height_m"])}


def walk_camera(q, width=W, height=H, side=1.0):
    """A camera 3.6 m from the middle of the walk, level with the hips, a little ahead of it."""
    mid = q[:, :3].mean(0)
    eye = np.array([mid[0] + 0.5 * side, mid[1] - 3.4 * side, 1.0])
    return Camera.look_at(eye, np.array([mid[0], mid[1], 0.9]), fx=520.0, width=width, height=height,
                          dtype=np.float64)


def render_video(path, model, q, camera, size):
    try:
        return viz.render(path, model, q, FPS, camera=camera, views=("camera",), size=size)
    except viz.RenderError as e:
        pytest.skip(f"no headless OpenGL (install libegl1 + libgl1-mesa-dri or libosmesa6): {e}")


@pytest.fixture(scope="module")
def walk(demo, tmp_path_factory):
    """The rendered walk: its MP4, camera, character and the true 2D BODY_25 keypoints."""
    q = demo["q"][:FRAMES]
    model = character(demo["height"])
    cam = walk_camera(q)
    path = render_video(tmp_path_factory.mktemp("walk") / "walk.mp4", model, q, cam, (W, H))
    sites = site_trajectory(model.mj, q, model.site_ids(BODY25.sites))
    truth = np.asarray(project(cam, sites))
    return {"path": path, "camera": cam, "model": model, "q": q, "truth": truth}


def swapped_frames(kp, truth):
    """Frames whose left/right limbs are closer to the truth swapped than as labelled."""
    J = BODY25.joints
    pairs = [(J.index("L" + n), J.index("R" + n)) for n in ("Shoulder", "Elbow", "Wrist", "Hip", "Knee", "Ankle")]
    d = sum(np.linalg.norm(kp[:, a, :2] - truth[:, a], axis=-1) + np.linalg.norm(kp[:, b, :2] - truth[:, b], axis=-1)
            for a, b in pairs)
    x = sum(np.linalg.norm(kp[:, a, :2] - truth[:, b], axis=-1) + np.linalg.norm(kp[:, b, :2] - truth[:, a], axis=-1)
            for a, b in pairs)
    return np.nonzero(x < d)[0]


def test_detected_keypoints_match_the_rendered_truth(walk, tmp_path):
    from jmocap.data.clip import load_clip
    from jmocap.video.extract import VideoOptions, extract_clips

    s = extract_clips(walk["path"], tmp_path, VideoOptions())
    assert s["frames"] == FRAMES and s["fps"] == FPS and s["fps_source"] == "video" and s["size"] == [W, H]
    assert len(s["tracks"]) == 1 and s["tracks"][0]["frames_with_pose"] == FRAMES
    clip = load_clip(s["clips"][0])
    assert clip.layout == "body25" and clip.num_frames == FRAMES and clip.meta["first_frame"] == 0
    assert clip.meta["assumed"] == ["intrinsics"]  # no camera file: f = 1000 px, centred
    np.testing.assert_allclose(clip.intrinsics, [1000.0, 1000.0, W / 2, H / 2])
    kp, truth = clip.keypoints, walk["truth"]
    report = {}
    for group, names in GROUPS.items():
        ids = [BODY25.index(n) for n in names]
        assert (kp[:, ids, 2] > 0.05).mean() > 0.95, group  # detected (the far side's with less confidence)
        err = np.linalg.norm(kp[:, ids, :2] - truth[:, ids], axis=-1)
        report[group] = (float(np.median(err)), float(np.percentile(err, 90)))
    print("median / p90 px:", {g: f"{m:.1f} / {p:.1f}" for g, (m, p) in report.items()})
    for group, (med, p90) in report.items():
        assert med < MEDIAN_PX and p90 < P90_PX, (group, med, p90)
    swapped = swapped_frames(kp, truth)
    assert len(swapped) <= 0.1 * FRAMES, swapped
    assert not clip.keypoints[:, [BODY25.index("LSmallToe"), BODY25.index("RSmallToe")]].any()
    raw = np.load(s["clips"][0])["blazepose_landmarks"]
    assert raw.shape == (FRAMES, 33, 5)
    np.testing.assert_allclose(raw[:, 23, :2], kp[:, BODY25.index("LHip"), :2], atol=1e-3)


def test_the_flip_repair_is_what_keeps_left_and_right(walk, tmp_path):
    """Without the repair, the detector's own labels on this side-on walk: the repaired labels
    are right in at least as many frames, and the repair reports what it changed."""
    from jmocap.data.clip import load_clip
    from jmocap.video.extract import VideoOptions, extract_clips

    raw = extract_clips(walk["path"], tmp_path / "raw", VideoOptions(repair_flips=False))
    fixed = extract_clips(walk["path"], tmp_path / "fixed", VideoOptions())
    kp_raw, kp_fixed = (load_clip(s["clips"][0]).keypoints for s in (raw, fixed))
    bad_raw, bad_fixed = swapped_frames(kp_raw, walk["truth"]), swapped_frames(kp_fixed, walk["truth"])
    assert len(bad_fixed) <= len(bad_raw)
    changed = np.nonzero(np.abs(kp_raw[:, BODY25.index("LKnee")] - kp_fixed[:, BODY25.index("LKnee")]).max(-1) > 0)[0]
    assert len(changed) == fixed["tracks"][0]["flipped_frames"]
    assert raw["tracks"][0]["flipped_frames"] == 0


def test_video_command_end_to_end(walk, tmp_path, xla_cache, capsys):
    """video -> keypoint clip + camera sidecar -> result -> overlay MP4, through the command line."""
    import imageio.v3 as iio

    from jmocap.data.formats import read_camera_json, read_clip
    from jmocap.results import load_result

    cam = walk["camera"]
    fx, fy, cx, cy = (float(v) for v in cam.intrinsics)
    camfile = tmp_path / "cam.json"
    camfile.write_text(json.dumps({"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": W, "height": H,
                                   "extrinsics": np.asarray(cam.extrinsics).tolist()}))
    out = tmp_path / "out"
    argv = ["video", str(walk["path"]), str(out), "--camera", str(camfile), "--height", "1.8", "--method",
            "kinematic", "--host-devices", "1", "--quiet", "--cache-dir", xla_cache]
    rc = cli.main(argv)
    text = capsys.readouterr()
    assert rc == 0, text.err
    assert f"{FRAMES} frames" in text.out and "1 track(s), 1 person(s) reconstructed" in text.out
    clip_path = out / "keypoints" / "walk_p0.npz"
    clip = read_clip(clip_path)  # with its sidecar
    side = read_camera_json(out / "keypoints" / "walk_p0.camera.json")
    np.testing.assert_allclose(side["intrinsics"], [fx, fy, cx, cy])
    np.testing.assert_allclose(side["extrinsics"], np.asarray(cam.extrinsics), atol=1e-12)
    assert clip.height_m == 1.8 and "assumed" not in clip.meta and clip.num_frames == FRAMES
    r = load_result(out / "results" / "walk_p0.npz")
    assert r["q"].shape == (FRAMES, walk["model"].nq) and r["method"] == "kinematic"
    assert r["height_source"] == "input" and not {"intrinsics", "extrinsics"} & set(r["assumed"])
    # the reconstruction explains its input: its joints project onto the detected keypoints
    ok = clip.keypoints[..., 2] > 0.5
    reproj = np.asarray(project(cam, r["keypoints3d"]))
    assert np.median(np.linalg.norm(reproj - clip.keypoints[..., :2], axis=-1)[ok]) < 15.0
    overlay = out / "walk_p0_overlay.mp4"
    with warnings.catch_warnings():  # imageio starts ffmpeg by fork + exec (JAX warns on any fork)
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
        frames = iio.imread(overlay, index=None)
    assert frames.shape == (FRAMES, H, W, 3)
    summary = json.loads((out / "video.json").read_text())
    assert summary["overlays"] == [str(overlay)] and summary["tracks"][0]["clip"] == "walk_p0"
    # OUTPUT is not overwritten by accident
    rc = cli.main(argv)
    assert rc == 2 and "--overwrite" in capsys.readouterr().err


def test_overlay_draws_the_character_where_the_camera_sees_it(walk):
    """On black frames: the pelvis projects onto a drawn pixel, an empty corner stays black, and
    frames outside the motion's range pass through untouched (but for the label)."""
    q, cam, model = walk["q"][:3], walk["camera"], walk["model"]
    black = [np.zeros((H, W, 3), np.uint8) for _ in range(5)]
    out = list(viz.overlay_frames(model, q, iter(black), cam, first_frame=1, alpha=1.0))
    assert len(out) == 5
    pelvis = np.asarray(project(cam, site_trajectory(model.mj, q, model.site_ids(["kp_mid_hip"]))))[:, 0]
    for i in range(3):
        u, v = (int(c) for c in pelvis[i])
        assert out[i + 1][v - 2:v + 3, u - 2:u + 3].max() > 20  # drawn (the floor is not)
        assert not out[i + 1][H - 40:, W - 40:].any()  # the floor is hidden: a corner of it stays black
    for i in (0, 4):
        assert not out[i][40:].any()  # no character outside first_frame .. first_frame + T - 1


def test_two_people_two_tracks_and_person_picks_one(demo, tmp_path):
    from jmocap.data.clip import load_clip
    from jmocap.video.extract import VideoOptions, extract_clips

    model = character(demo["height"])
    qa, qb = demo["q"][0:20], demo["q"][60:80]
    try:
        left = list(viz.render_frames(model, qa, camera=walk_camera(qa, 320, H), views=("camera",), size=(320, H)))
        right = list(viz.render_frames(model, qb, camera=walk_camera(qb, 320, H, side=-1.0), views=("camera",),
                                       size=(320, H)))
    except viz.RenderError as e:
        pytest.skip(f"no headless OpenGL: {e}")
    path = tmp_path / "two.mp4"
    viz._write_mp4(path, (np.concatenate([a, b], axis=1) for a, b in zip(left, right, strict=True)), FPS)
    s = extract_clips(path, tmp_path / "all", VideoOptions(person="all"))
    assert [(t["start"], t["end"], t["frames_with_pose"]) for t in s["tracks"]] == [(0, 19, 20), (0, 19, 20)]
    xs = [float(np.median(load_clip(c).keypoints[..., 0][load_clip(c).keypoints[..., 2] > 0])) for c in s["clips"]]
    assert xs[0] < 320 < xs[1]  # numbered left to right
    s1 = extract_clips(path, tmp_path / "one", VideoOptions(person="1"))
    assert [p.rsplit("/", 1)[-1] for p in s1["clips"]] == ["two_p1.npz"]
    assert [t.get("clip") for t in s1["tracks"]] == [None, "two_p1"]


def test_bad_input_is_named_and_refused(tmp_path, capsys):
    missing = tmp_path / "nothere.mp4"
    assert cli.main(["video", str(missing), str(tmp_path / "o1"), "--quiet"]) == 2
    assert f"{missing}: no such video file" in capsys.readouterr().err
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    assert cli.main(["video", str(text), str(tmp_path / "o2"), "--quiet"]) == 2
    assert f"{text}: not a readable video file" in capsys.readouterr().err
    empty = tmp_path / "empty.mp4"
    viz._write_mp4(empty, (np.full((H, W, 3), 90, np.uint8) for _ in range(12)), FPS)
    assert cli.main(["video", str(empty), str(tmp_path / "o3"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{empty}: no person found in 12 frames" in err and "Traceback" not in err
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, "width": 1920, "height": 1080}))
    assert cli.main(["video", str(empty), str(tmp_path / "o4"), "--camera", str(cam), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{cam}: field 'width': the camera file is for 1920x1080 images" in err
    assert not (tmp_path / "o1").exists() or not any((tmp_path / "o1").iterdir())


def test_a_camera_track_file_gives_each_clip_its_frames_cameras(walk, tmp_path):
    """A camera file with one camera per video frame (here the true camera, turned a little more
    each frame about its own axis): the clip carries the track of its frames; a track of another
    length is refused, naming the camera file."""
    from jmocap.data.clip import load_clip
    from jmocap.video.extract import VideoError, VideoOptions, extract_clips

    cam = walk["camera"]
    fx, fy, cx, cy = (float(v) for v in cam.intrinsics)
    E = np.asarray(cam.extrinsics, np.float64)
    track = np.repeat(E[None], FRAMES, 0)
    for t in range(FRAMES):  # a slow roll, 0.2 degrees per frame
        r = np.radians(0.2 * t)
        track[t, :3] = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]]) @ E[:3]
    camfile = tmp_path / "cam.json"
    base = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": W, "height": H}
    camfile.write_text(json.dumps({**base, "extrinsics": track.tolist()}))
    s = extract_clips(walk["path"], tmp_path / "out", VideoOptions(camera=camfile))
    clip = load_clip(s["clips"][0])
    start = clip.meta["first_frame"]
    np.testing.assert_allclose(clip.camera_track, track[start:start + clip.num_frames], atol=1e-12)
    camfile.write_text(json.dumps({**base, "extrinsics": track[:-1].tolist()}))
    with pytest.raises(VideoError, match=f"cam.json: field 'extrinsics': the camera track has {FRAMES - 1} frames"):
        extract_clips(walk["path"], tmp_path / "short", VideoOptions(camera=camfile))
