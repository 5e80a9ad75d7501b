"""jmocap.viz: offscreen videos (GIF/MP4), force arrows, contact marks, the input-camera view,
force plots and the ``jmocap render`` command.

Rendering needs a headless OpenGL (EGL or OSMesa: system packages libegl1 + libgl1-mesa-dri,
or libosmesa6); without one these tests skip, saying so. Videos are read back with imageio /
imageio-ffmpeg's own readers. The input-camera view is checked against
``jmocap.camera.project``: a force arrow's tip must land where the projection says (3 px at
320x240, with the input image letterboxed into the panel; the tolerance covers
rasterisation of the arrow's pointed head), and so is the projection that places the force
outlines drawn over the image.
"""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

import jmocap
from jmocap import cli, viz
from jmocap.camera import Camera, project
from jmocap.layouts import get_layout

W, H = 64, 48  # tiny views


@pytest.fixture(scope="module")
def model():
    return jmocap.load_model(with_mjx=False)


@pytest.fixture(scope="module")
def gl(model):
    """Skips a rendering test when no headless OpenGL works (the plots need none)."""
    try:
        viz.open_renderer(model.mj, 16, 16).close()
    except viz.RenderError as e:
        pytest.skip(f"no headless OpenGL (install libegl1 + libgl1-mesa-dri or libosmesa6): {e}")


def model_keypoints(model, q, layout):
    """(T, J, 3) world keypoints of a layout, from MuJoCo C's site positions."""
    import mujoco

    d = mujoco.MjData(model.mj)
    ids = list(model.site_ids(get_layout(layout).sites))
    out = []
    for qt in q:
        d.qpos[:] = qt
        mujoco.mj_kinematics(model.mj, d)
        out.append(d.site_xpos[ids].copy())
    return np.stack(out)


def squat(model, T=5):
    """A short motion: knees and hips flexing, feet on the floor."""
    q = np.tile(model.keyframe("stand"), (T, 1))
    s = np.linspace(0.0, 1.0, T)
    for side in ("left", "right"):
        q[:, model.mj.joint(f"{side}_hip_y").qposadr[0]] = -0.6 * s
        q[:, model.mj.joint(f"{side}_knee_y").qposadr[0]] = 1.2 * s
        q[:, model.mj.joint(f"{side}_ankle_y").qposadr[0]] = -0.3 * s
    return q


def standing_grf(model, T):
    """Half the body weight on each foot, split evenly between heel and toe."""
    grf = np.zeros((T, 4, 3))
    grf[..., 2] = model.total_mass * 9.81 / 4
    return grf


def test_gif_and_mp4_frames_and_size(gl, model, tmp_path):
    q = squat(model)
    gif = viz.render(tmp_path / "a.gif", model, q, 30.0, size=(W, H))
    frames = iio.imread(gif, index=None)
    assert frames.shape[:3] == (5, H, 2 * W)  # front | side
    assert frames[..., :3].std() > 10  # not a blank image
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).max() > 50  # the motion moves

    import imageio_ffmpeg

    mp4 = viz.render(tmp_path / "a.mp4", model, q, 30.0, size=(W, H), views=("front",))
    reader = imageio_ffmpeg.read_frames(str(mp4))
    meta = next(reader)
    video = [np.frombuffer(f, np.uint8).reshape(H, W, 3) for f in reader]
    assert meta["size"] == (W, H) and meta["fps"] == pytest.approx(30.0)
    assert len(video) == 5
    assert np.std(video[2]) > 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif", "a.mp4"]  # no temp files


def test_grf_arrows_and_contact_marks_change_pixels(gl, model):
    q = model.keyframe("stand")[None]
    plain = next(viz.render_frames(model, q, size=(320, 240)))
    grf = standing_grf(model, 1)
    arrows = next(viz.render_frames(model, q, grf=grf, size=(320, 240)))
    changed = np.abs(arrows.astype(int) - plain.astype(int)).sum(-1) > 60
    assert changed.sum() > 150, f"GRF arrows drew (almost) nothing ({changed.sum()} px)"
    r, g, b = (arrows[changed][:, i].astype(int) for i in range(3))
    assert np.median(g - r) > 40 and np.median(g - b) > 40, "changed pixels are not the (green) arrows"

    contacts = np.array([[1.0, 1.0, 0.0, 0.2]])
    marked = next(viz.render_frames(model, q, contacts=contacts, size=(320, 240)))

    def red(img):
        img = img.astype(int)
        return int(((img[..., 0] > 120) & (img[..., 1] < 60) & (img[..., 2] < 60)).sum())

    assert red(plain) == 0 and red(marked) > 20, "contact feet are not marked red"


@pytest.mark.parametrize("view", ["camera", "front", "side"])
def test_arrow_and_projection_match_the_rendered_image(gl, model, view):
    """A 3D arrow of 0.5 m beside the body: the tip of what MuJoCo renders is where
    ``jmocap.camera.project`` puts it in the input-camera view (1920x1080 letterboxed into
    320x240, 30 px bars), and where ``viz._gl_project`` (which places the force outlines and
    keypoints' counterparts) puts it in every view."""
    import mujoco

    W_, H_ = 320, 240
    cam = Camera.look_at([2.5, -2.0, 1.2], [0.0, 0.0, 0.8], width=1920, height=1080, fx=1400.0, dtype=np.float64)
    d = mujoco.MjData(model.mj)
    d.qpos[:] = model.keyframe("stand")
    mujoco.mj_forward(model.mj, d)
    base, tip = np.array([0.25, -0.45, 0.0]), np.array([0.25, -0.45, 0.5])
    renderer = viz.open_renderer(model.mj, H_, W_)
    try:
        images = []
        for with_arrow in (False, True):
            if view == "camera":
                renderer.update_scene(d, camera=mujoco.MjvCamera())
                viz._set_pinhole(renderer.scene, cam.intrinsics, cam.image_size, cam.extrinsics, W_, H_)
            else:
                renderer.update_scene(d, camera=view)
            # as render_frames' default: no shadows (an extra geom moves the shadow map)
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            if with_arrow:
                viz._add_arrow(renderer.scene, base, tip, 0.02, viz.ARROW_RGBA)
            images.append(renderer.render().astype(int))
        uv_gl, _ = viz._gl_project(renderer.scene, tip[None], W_, H_)
    finally:
        renderer.close()
    ys, xs = np.nonzero(np.abs(images[1] - images[0]).sum(-1) > 60)
    assert len(ys) > 30
    top_row, top_col = ys.min(), xs[ys < ys.min() + 4].mean()
    u, v = uv_gl[0]
    assert abs(top_row - v) < 3.0 and abs(top_col - u) < 3.0, (top_row, top_col, u, v)
    if view == "camera":
        k, oy = W_ / 1920, (H_ - 1080 * W_ / 1920) / 2
        u, v = np.asarray(project(cam, tip)) * k + np.array([0.0, oy])
        assert abs(top_row - v) < 3.0 and abs(top_col - u) < 3.0, (top_row, top_col, u, v)
        np.testing.assert_allclose(uv_gl[0], [u, v], atol=1e-3)


def test_keypoint_overlay_on_camera_view(gl, model, tmp_path):
    q = squat(model, 3)
    cam = Camera.look_at([3.0, -1.5, 1.4], [0.0, 0.0, 0.8], width=640, height=480, fx=800.0, dtype=np.float64)
    kp3 = model_keypoints(model, q, "body25")
    kp2 = np.concatenate([np.asarray(project(cam, kp3)), np.ones((3, 25, 1))], -1)
    kp2[:, 0] = 0.0  # a missing joint (confidence 0) is not drawn
    frames = list(viz.render_frames(model, q, keypoints2d=kp2, camera=cam, layout="body25", size=(W, H)))
    assert frames[0].shape == (H, 3 * W, 3)  # front | side | camera (added for the keypoints)
    cyan = (frames[1][..., 0] < 60) & (frames[1][..., 1] > 180) & (frames[1][..., 2] > 200)
    assert cyan[:, 2 * W :].sum() > 10 and cyan[:, : 2 * W].sum() == 0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(q="nan"), r"render: field 'q': frame 1: coordinate 9"),
        (dict(q="nq"), r"expected shape \(T, nq=48\)"),
        (dict(grf=np.zeros((5, 4))), r"field 'grf' has shape \(5, 4\), expected \(5, 4, 3\)"),
        (dict(views=("top",)), r"unknown view 'top'; the model's cameras: \['front', 'side'\]"),
        (dict(keypoints2d=np.zeros((5, 25, 3))), r"keypoints2d need the camera"),
        (dict(path="a.avi"), r"unsupported video format '.avi'"),
    ],
)
def test_render_rejects_bad_input(model, tmp_path, kwargs, match):
    q = squat(model)
    bad_q = kwargs.pop("q", None)
    if bad_q == "nan":
        q[1, 9] = np.nan
    elif bad_q == "nq":
        q = q[:, :47]
    path = tmp_path / kwargs.pop("path", "a.gif")
    with pytest.raises(ValueError, match=match):
        viz.render(path, model, q, 30.0, size=(W, H), **kwargs)
    assert not any(tmp_path.iterdir())


def test_plot_forces_writes_png(model, tmp_path):
    T = 60
    t = np.arange(T) / 30.0
    grf = np.zeros((T, 4, 3))
    grf[:, 0, 2] = 400 * np.clip(np.sin(2 * np.pi * t), 0, None)
    grf[:, 3, 2] = 400 * np.clip(-np.sin(2 * np.pi * t), 0, None)
    tau = np.random.default_rng(0).normal(size=(T, model.nv))
    png = viz.plot_forces(tmp_path / "plots" / "f.png", grf, 30.0, gt_grf=0.9 * grf, tau=tau, model=model)
    img = iio.imread(png)
    assert img.ndim == 3 and img.shape[0] > img.shape[1] > 400  # four stacked panels
    assert img[..., :3].std() > 5
    png2 = viz.plot_forces(tmp_path / "g.png", grf, 30.0)  # no model: newtons, GRF only
    assert iio.imread(png2).shape[0] < img.shape[0]
    with pytest.raises(ValueError, match="needs the model"):
        viz.plot_forces(tmp_path / "h.png", grf, 30.0, tau=tau)
    with pytest.raises(ValueError, match=r"model has no joint 'tail'"):
        viz.plot_forces(tmp_path / "h.png", grf, 30.0, tau=tau, model=model, joints=["tail"])
    assert not (tmp_path / "h.png").exists()


def test_cli_render(gl, model, tmp_path, capsys):
    q = squat(model)
    cam = Camera.look_at([3.0, -1.5, 1.4], [0.0, 0.0, 0.8], width=640, height=480, fx=800.0, dtype=np.float64)
    kp3 = model_keypoints(model, q, "body25")
    kp2 = np.concatenate([np.asarray(project(cam, kp3)), np.ones((5, 25, 1))], -1)
    np.savez(
        tmp_path / "clip.npz", q=q, qd=np.zeros((5, model.nv)), tau=np.zeros((5, model.nv)),
        grf=standing_grf(model, 5), contact_prob=np.ones((5, 4)), keypoints2d=kp2,
        fps=np.array(30.0), layout=np.array("body25"), intrinsics=np.asarray(cam.intrinsics),
        image_size=np.array([640, 480]), extrinsics=np.asarray(cam.extrinsics),
    )
    rc = cli.main(["render", str(tmp_path / "clip.npz"), "--out", str(tmp_path / "clip.gif"),
                   "--plots", str(tmp_path / "plots"), "--size", f"{W}x{H}", "--no-side"])
    assert rc == 0, capsys.readouterr().err
    assert iio.imread(tmp_path / "clip.gif", index=None).shape[:3] == (5, H, 2 * W)  # front | camera
    assert (tmp_path / "plots" / "clip_forces.png").is_file()
    assert cli.main(["render", str(tmp_path / "missing.npz")]) == 1
    assert "result file not found" in capsys.readouterr().err


def test_a_moving_camera_renders_each_frame_from_its_own_pose(gl, model):
    """The ``camera`` view of a camera track (T, 4, 4): frame t is the image of the static camera
    at track[t] (frame 1's camera moved a metre sideways changes frame 1 only)."""
    q = squat(model, 3)
    a = Camera.look_at([3.0, -1.5, 1.4], [0.0, 0.0, 0.8], width=640, height=480, fx=800.0, dtype=np.float64)
    b = Camera.look_at([3.0, -0.5, 1.4], [0.0, 0.0, 0.8], width=640, height=480, fx=800.0, dtype=np.float64)
    track = np.stack([np.asarray(a.extrinsics), np.asarray(b.extrinsics), np.asarray(a.extrinsics)])
    moving = a.replace(extrinsics=track)
    got = list(viz.render_frames(model, q, camera=moving, views=("camera",), size=(W, H)))
    still = list(viz.render_frames(model, q, camera=a, views=("camera",), size=(W, H)))
    moved = list(viz.render_frames(model, q, camera=b, views=("camera",), size=(W, H)))
    np.testing.assert_array_equal(got[0], still[0])
    np.testing.assert_array_equal(got[1], moved[1])
    np.testing.assert_array_equal(got[2], still[2])
    assert np.abs(got[1].astype(int) - still[1].astype(int)).sum() > 0


def test_the_overlay_of_a_moving_camera_draws_each_frame_from_its_own_pose(gl, model):
    """``overlay_frames`` with a camera track (one per frame of q): frame t drawn from camera t."""
    q = squat(model, 2)
    a = Camera.look_at([3.0, -1.5, 1.4], [0.0, 0.0, 0.8], width=W, height=H, fx=400.0, dtype=np.float64)
    b = Camera.look_at([3.0, -0.5, 1.4], [0.0, 0.0, 0.8], width=W, height=H, fx=400.0, dtype=np.float64)
    moving = a.replace(extrinsics=np.stack([np.asarray(a.extrinsics), np.asarray(b.extrinsics)]))
    blank = [np.zeros((H, W, 3), np.uint8)] * 2
    got = list(viz.overlay_frames(model, q, iter(blank), moving))
    np.testing.assert_array_equal(got[0], list(viz.overlay_frames(model, q, iter(blank), a))[0])
    np.testing.assert_array_equal(got[1], list(viz.overlay_frames(model, q, iter(blank), b))[1])


def test_a_scenes_boxes_are_drawn(gl, model):
    """A step beside the standing character (jmocap.scene): pixels around its projected top
    centre change to the scene's blue-grey in the front view; without it they do not."""
    from jmocap.scene import parse_scene

    q = model.keyframe("stand")[None]
    step = parse_scene({"boxes": [{"center": [0.0, 0.7, 0.15], "half_size": [0.25, 0.25, 0.15]}]})
    plain = next(viz.render_frames(model, q, size=(320, 240), views=("front",)))
    drawn = next(viz.render_frames(model, q, size=(320, 240), views=("front",), scene=step))
    changed = np.abs(drawn.astype(int) - plain.astype(int)).sum(-1) > 60
    assert changed.sum() > 200, f"the box drew (almost) nothing ({changed.sum()} px)"
    r, g, b = (drawn[changed][:, i].astype(int) for i in range(3))
    assert np.median(b - r) > 30, "changed pixels are not the (blue-grey) box"
