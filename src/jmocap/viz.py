"""Visualisation of a reconstruction: offscreen MuJoCo video and force plots.

* :func:`render` writes an MP4 or GIF of a motion: the humanoid rendered offscreen by
  ``mujoco.Renderer`` from the model's ``front`` and ``side`` cameras (side by side), one
  ground reaction force arrow per foot, in red the foot segments whose contact probability
  exceeds 0.5 and, given 2D keypoints and the input camera, a third panel rendered from the
  input camera's exact viewpoint with the 2D keypoints drawn over it (a reconstruction that
  explains its input puts the humanoid under the detections). :func:`render_frames` yields
  the same frames as arrays.
* :func:`plot_forces` writes a PNG of the vertical GRF per foot and joint torques over time,
  after paper 000 (Shimada et al. 2021), Fig. 4 (vertical GRF, knee and ankle torques, the
  residual root force in body weights).
* :func:`render_result` does both for a result ``.npz`` (the ``jmocap render`` command).
* :func:`overlay_frames` / :func:`render_overlay` draw a motion over the input video's own
  frames from the input camera, with the 2D keypoints (the ``jmocap video`` command).

Headless OpenGL: MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` once, when ``mujoco`` is
imported (GLFW when unset, which needs a display and, failing, can leave the process unable to
render). This module sets ``MUJOCO_GL=egl`` if it is unset and ``mujoco`` is not imported yet;
as ``import jmocap`` has usually imported it already, :func:`open_renderer` also installs the
EGL (then OSMesa) context class for the renderer it creates, unless ``MUJOCO_GL`` names another
backend (the user's choice, e.g. ``glfw`` on a desktop). It raises :class:`RenderError` naming
the system packages to install when nothing works. (The in-process fall-back to OSMesa is best
effort; on a machine without EGL set ``MUJOCO_GL=osmesa``.)

The plotting and video packages (matplotlib, imageio, imageio-ffmpeg) are the ``viz`` extra,
not core dependencies: they are imported where they are used, and a missing one raises an
``ImportError`` saying ``pip install 'jmocap[viz]'`` (:func:`missing_viz_packages` checks
without importing).
"""

from __future__ import annotations

import os
import sys

if "mujoco" not in sys.modules:  # MuJoCo reads MUJOCO_GL once, at import
    os.environ.setdefault("MUJOCO_GL", "egl")

import copy  # noqa: E402
import importlib  # noqa: E402
import importlib.util  # noqa: E402
import math  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Iterator, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from jmocap.constants import NUM_CONTACTS  # noqa: E402
from jmocap.export import check_q  # noqa: E402
from jmocap.io import atomic_path  # noqa: E402
from jmocap.layouts import Layout, get_layout  # noqa: E402
from jmocap.model import Model  # noqa: E402
from jmocap.results import load_result  # noqa: E402

__all__ = [
    "RenderError",
    "open_renderer",
    "overlay_frames",
    "plot_forces",
    "render",
    "render_frames",
    "render_overlay",
    "render_result",
]

DEFAULT_SIZE = (320, 240)  # per view (width, height)
FORCE_SCALE_M_PER_BW = 0.5  # arrow length of a force of one body weight
ARROW_RGBA = np.array([0.1, 0.85, 0.1, 1.0], np.float32)  # green: unlike skin, floor, red feet
SCENE_RGBA = np.array([0.35, 0.45, 0.85, 1.0], np.float32)  # blue-grey: a scene's boxes (steps, ramps)
CONTACT_RGBA = np.array([0.9, 0.05, 0.05, 1.0], np.float32)
KEYPOINT_RGB = (0, 230, 255)
BONE_RGB = (255, 255, 255)
_HEADLESS = ("egl", "osmesa")
_SYSTEM_PACKAGES = "EGL: libegl1 + libgl1-mesa-dri (Mesa); OSMesa: libosmesa6 (Debian/Ubuntu names)"


class RenderError(RuntimeError):
    """No OpenGL context could be created for offscreen rendering."""


# ======================================================================================
# the optional packages of the `viz` extra
# ======================================================================================

VIZ_PACKAGES = ("matplotlib", "imageio", "imageio_ffmpeg")  # import names
VIZ_INSTALL = "pip install 'jmocap[viz]'"


def missing_viz_packages() -> list[str]:
    """The packages of the ``viz`` extra that are not installed (import names), without importing them."""
    return [name for name in VIZ_PACKAGES if importlib.util.find_spec(name) is None]


def _import_viz(module: str, what: str):
    """Import ``module`` (of a ``viz`` extra package) for ``what``, or say how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(
            f"{what} needs {e.name or module}, which is not installed; video and plots are the "
            f"optional viz extra: {VIZ_INSTALL}"
        ) from e


def _require_viz(what: str) -> None:
    missing = missing_viz_packages()
    if missing:
        raise ImportError(
            f"{what} needs {', '.join(missing)}, not installed; video and plots are the optional "
            f"viz extra: {VIZ_INSTALL}"
        )


# ======================================================================================
# headless renderer
# ======================================================================================


def _gl_context_class(backend: str):
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:  # pragma: no cover
        raise ValueError(backend)
    return GLContext


def open_renderer(mj: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """A ``mujoco.Renderer`` on a headless OpenGL context (EGL, then OSMesa); see the module doc.

    The offscreen framebuffer is enlarged (on a copy of ``mj``) when the image needs it.
    """
    if width > mj.vis.global_.offwidth or height > mj.vis.global_.offheight:
        mj = copy.copy(mj)
        mj.vis.global_.offwidth = max(width, mj.vis.global_.offwidth)
        mj.vis.global_.offheight = max(height, mj.vis.global_.offheight)
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    # the module whose `gl_context.GLContext` the Renderer instantiates (mujoco 3.x and 4.x)
    gl = getattr(sys.modules.get(mujoco.Renderer.__module__), "gl_context", None)
    if (requested and requested not in _HEADLESS) or gl is None:
        try:
            return mujoco.Renderer(mj, height, width)
        except Exception as e:
            raise RenderError(
                f"cannot create a MuJoCo renderer with MUJOCO_GL={requested or '(unset)'}: "
                f"{type(e).__name__}: {e}. Unset MUJOCO_GL or set it to egl or osmesa "
                f"for headless rendering ({_SYSTEM_PACKAGES})."
            ) from e
    first = requested or "egl"
    errors = []
    for backend in (first, *(b for b in _HEADLESS if b != first)):
        try:
            cls = _gl_context_class(backend)
        except Exception as e:  # the backend's library is missing (ImportError, OSError, ...)
            errors.append(f"{backend}: {type(e).__name__}: {e}")
            continue
        saved = gl.GLContext
        gl.GLContext = cls
        try:
            return mujoco.Renderer(mj, height, width)
        except Exception as e:
            errors.append(f"{backend}: {type(e).__name__}: {e}")
        finally:
            gl.GLContext = saved
    raise RenderError(
        "no headless OpenGL backend works for offscreen rendering ("
        + "; ".join(errors)
        + f"). Install the system libraries ({_SYSTEM_PACKAGES})."
    )


# ======================================================================================
# scene decorations
# ======================================================================================


def _add_geom(scene: mujoco.MjvScene) -> mujoco.MjvGeom | None:
    if scene.ngeom >= scene.maxgeom:
        return None
    g = scene.geoms[scene.ngeom]
    scene.ngeom += 1
    return g


def _add_arrow(scene, start: np.ndarray, end: np.ndarray, width: float, rgba) -> None:
    g = _add_geom(scene)
    if g is None:
        return
    mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.eye(3).ravel(), rgba)
    mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_ARROW, width, start, end)
    # MuJoCo's renderers (classic and Filament) draw an arrow of length size[2] / 2 (shaft to
    # size[2] / 3, head to size[2] / 2): make the drawn arrow end at `end`.
    g.size[2] = 2.0 * float(np.linalg.norm(end - start))


def _foot_forces(points: np.ndarray, forces: np.ndarray):
    """Per foot (heel + toe contact points, jmocap's contact order): the resultant force and
    its point of application on the heel-toe segment, weighted by the points' vertical forces
    (the centre of pressure of two parallel forces; their magnitudes if not both pushing up)."""
    out = []
    for heel, toe in ((0, 1), (2, 3)):
        f = forces[heel] + forces[toe]
        w = np.maximum(forces[[heel, toe], 2], 0.0)
        if w.sum() <= 1e-9:
            w = np.linalg.norm(forces[[heel, toe]], axis=1)
        w = w / w.sum() if w.sum() > 1e-9 else np.array([0.5, 0.5])
        out.append((w[0] * points[heel] + w[1] * points[toe], f))
    return out


def _pinhole_fit(image_size, W: int, H: int):
    """Uniform scale k and offset (ox, oy) placing the input image centred in a W x H panel."""
    Wi, Hi = float(image_size[0]), float(image_size[1])
    k = min(W / Wi, H / Hi)
    return k, (W - k * Wi) / 2.0, (H - k * Hi) / 2.0


def _set_pinhole(scene: mujoco.MjvScene, intrinsics, image_size, extrinsics, W: int, H: int) -> None:
    """Make the scene's OpenGL camera the OpenCV pinhole camera (letterboxed into W x H).

    ``extrinsics`` is world->camera ``[R t]`` (OpenCV axes: x right, y down, z forward). The
    OpenGL frustum at the near plane n spans, for panel pixel x, the ray direction
    ``((x - ox)/k - cx)/fx``; MuJoCo derives left/right from ``frustum_center`` and the panel's
    aspect, which matches exactly when fx = fy (otherwise the vertical scale wins).
    """
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    k, ox, oy = _pinhole_fit(image_size, W, H)
    R = np.asarray(extrinsics, np.float64)[:3, :3]
    t = np.asarray(extrinsics, np.float64)[:3, 3]
    n, far = 0.05, 100.0
    left = n * (-ox / k - cx) / fx
    right = n * ((W - ox) / k - cx) / fx
    top = n * (cy + oy / k) / fy
    bottom = -n * ((H - oy) / k - cy) / fy
    for cam in scene.camera:
        cam.pos[:] = -R.T @ t
        cam.forward[:] = R[2]
        cam.up[:] = -R[1]
        cam.frustum_center = 0.5 * (left + right)
        cam.frustum_width = 0.5 * (right - left)
        cam.frustum_bottom = bottom
        cam.frustum_top = top
        cam.frustum_near = n
        cam.frustum_far = far
        cam.orthographic = 0


def _layout_bones(model: Model, layout: Layout) -> list[tuple[int, int]]:
    """Skeleton edges between a layout's joints, derived from the model: a minimum spanning
    tree with edge weight (bodies between the two sites in the kinematic tree, rest-pose
    distance), which joins each joint to its anatomical neighbour (hip-knee, ankle-heel, ...)."""
    mj = model.mj
    ids = [mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, s) for s in layout.sites]
    if min(ids) < 0:
        return []
    d = mujoco.MjData(mj)
    mujoco.mj_kinematics(mj, d)
    body = [int(mj.site_bodyid[s]) for s in ids]
    parent = mj.body_parentid

    def chain(b):
        out = [b]
        while b > 0:
            b = int(parent[b])
            out.append(b)
        return out

    def hops(a, b):
        ca, cb = chain(a), chain(b)
        common = next(x for x in ca if x in cb)
        return ca.index(common) + cb.index(common)

    J = len(ids)
    edges = sorted(
        (hops(body[i], body[j]), float(np.linalg.norm(d.site_xpos[ids[i]] - d.site_xpos[ids[j]])), i, j)
        for i in range(J)
        for j in range(i + 1, J)
    )
    root = list(range(J))

    def find(i):
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    bones = []
    for _, _, i, j in edges:  # Kruskal
        ri, rj = find(i), find(j)
        if ri != rj:
            root[ri] = rj
            bones.append((i, j))
    return bones


def _gl_project(scene: mujoco.MjvScene, points: np.ndarray, W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """Panel pixels (N, 2) and depths (N,) of world points, as ``mjr_render`` projects them.

    MuJoCo renders a mono image from the average of the scene's two eye cameras (they sit
    +-ipd/2 apart even in mono), through a frustum with the camera's bottom/top at the near
    plane and a horizontal extent set by the panel's aspect around ``frustum_center``.
    """
    cam = mujoco.mjv_averageCamera(scene.camera[0], scene.camera[1])
    pos = np.asarray(cam.pos, np.float64)
    fwd = np.asarray(cam.forward, np.float64)
    up = np.asarray(cam.up, np.float64)
    rel = np.asarray(points, np.float64) - pos
    z = rel @ fwd
    x, y = rel @ np.cross(fwd, up), rel @ up
    half_h = 0.5 * (cam.frustum_top - cam.frustum_bottom)
    half_w = half_h * W / H
    if not cam.orthographic:
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = cam.frustum_near * x / z, cam.frustum_near * y / z
    u = (1.0 + (x - cam.frustum_center) / half_w) * W / 2
    v = (1.0 - (y - 0.5 * (cam.frustum_top + cam.frustum_bottom)) / half_h) * H / 2
    return np.stack([u, v], -1), z


def _draw_overlay(
    img: np.ndarray, points: np.ndarray | None, bones, labels: Sequence[str], arrows=(), frame=None
) -> np.ndarray:
    """Draw onto an image: force arrows ((2, 2) panel pixels, base and tip) as translucent
    outlines over everything (so that the parts hidden in a leg show), the input image's
    bounds ``frame`` (x0, y0, x1, y1), 2D keypoints (J, 3: panel x, y, confidence) with their
    bones, and text labels."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(img)
    H = img.shape[0]
    if len(arrows):
        layer = Image.new("RGBA", im.size, (0, 0, 0, 0))
        ghost = ImageDraw.Draw(layer)
        colour = tuple(int(255 * c) for c in ARROW_RGBA[:3]) + (150,)
        lw = max(1, round(H / 120))
        for base, tip in arrows:
            d = tip - base
            n = float(np.hypot(*d))
            if not np.isfinite(n) or n < 1.0:
                continue
            e, side = d / n, np.array([-d[1], d[0]]) / n
            head = min(0.35 * n, max(3.0, H / 40))
            neck = tip - head * e
            ghost.line([tuple(base), tuple(neck)], fill=colour, width=lw)
            ghost.polygon([tuple(tip), tuple(neck + 0.5 * head * side), tuple(neck - 0.5 * head * side)], fill=colour)
        im = Image.alpha_composite(im.convert("RGBA"), layer).convert("RGB")
    draw = ImageDraw.Draw(im)
    if frame is not None:
        draw.rectangle(frame, outline=(110, 110, 110))
    if points is not None:
        ok = (points[:, 2] > 0) & np.isfinite(points).all(1)
        lw = max(1, round(H / 200))
        for i, j in bones:
            if ok[i] and ok[j]:
                draw.line([tuple(points[i, :2]), tuple(points[j, :2])], fill=BONE_RGB, width=lw)
        r = max(1.5, H / 120)
        for x, y, _ in points[ok]:
            draw.ellipse([x - r, y - r, x + r, y + r], fill=KEYPOINT_RGB)
    for n, text in enumerate(labels):
        draw.text((4, 2 + 11 * n), text, fill=(255, 255, 255))
    return np.asarray(im)


# ======================================================================================
# rendering
# ======================================================================================


def _series(x, shape: tuple, name: str, where: str) -> np.ndarray | None:
    if x is None:
        return None
    a = np.asarray(x, np.float64)
    if a.shape != shape:
        raise ValueError(f"{where}: field {name!r} has shape {a.shape}, expected {shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"{where}: field {name!r}: frame {int(np.argwhere(bad)[0, 0])} has non-finite values")
    return a


def _size(size, where: str) -> tuple[int, int]:
    try:
        W, H = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: size must be (width, height), got {size!r}") from None
    if not (8 <= W <= 4096 and 8 <= H <= 4096):
        raise ValueError(f"{where}: size must be between 8x8 and 4096x4096 pixels per view, got {W}x{H}")
    return W, H


def render_frames(
    model: Model,
    q,
    *,
    grf=None,
    contacts=None,
    keypoints2d=None,
    camera=None,
    layout: str | Layout | None = None,
    views: Sequence[str] = ("front", "side"),
    size: tuple[int, int] = DEFAULT_SIZE,
    force_scale: float = FORCE_SCALE_M_PER_BW,
    quality: str = "fast",
    fps: float | None = None,
    scene=None,
) -> Iterator[np.ndarray]:
    """An iterator of RGB frames (H, W * number of views, 3) uint8, one per frame of ``q``.

    The arguments are checked before the iterator is returned (``ValueError``); the renderer
    is opened on the first frame and closed when the iterator is exhausted or closed.

    Args:
      model: the character (its ``mj`` model is rendered, as the MJCF draws it).
      q: (T, nq) configurations.
      grf: optional (T, 4, 3) world-frame contact forces at the four contact sites (left heel,
        left toe, right heel, right toe), drawn per foot: a green arrow of the foot's
        resultant force (heel + toe) from its centre of pressure between the two sites,
        ``force_scale`` metres per body weight (``model.total_mass * |g|``); forces under 1 %
        of body weight are not drawn. Each arrow is a 3D geom in the scene plus a translucent
        outline over the image, since the centre of pressure is often under the shank and the
        arrow inside the leg.
      contacts: optional (T, 4) contact probabilities; a contact with probability > 0.5 turns
        the foot segment carrying its site red (the hindfoot for a heel, the toes for a toe).
        The contact sites lie on the sole, inside the foot geoms, where a sphere marker would
        be hidden.
      keypoints2d: optional (T, J, 3) input keypoints (pixels, confidence; confidence 0 =
        missing), drawn over the ``camera`` view (added to ``views`` if absent). Needs
        ``camera``; ``layout`` (or J = 25, BODY_25) gives the bones, otherwise points only.
      camera: a :class:`jmocap.camera.Camera` (unbatched): the ``"camera"`` view renders from
        its exact pose and intrinsics, the input image letterboxed into the panel; a moving
        camera's extrinsics are (T, 4, 4), frame t rendered from camera t.
      views: model camera names (the humanoid has ``front`` and ``side``, tracking the centre
        of mass) and/or ``"camera"``, left to right.
      size: (width, height) of each view in pixels.
      quality: ``"fast"`` (default: no shadows, floor reflections or multisampling, about 5x
        faster with Mesa's software OpenGL) or ``"high"`` (the model's own visual settings).
      fps: only for the time label.
      scene: a :class:`jmocap.scene.Scene` (the clip's terrain): its boxes are drawn in every
        view (blue-grey).
    """
    where = "render"
    q = check_q(model, q, f"{where}: field 'q'")
    T = len(q)
    W, H = _size(size, where)
    if quality not in ("fast", "high"):
        raise ValueError(f"{where}: quality must be 'fast' or 'high', got {quality!r}")
    grf = _series(grf, (T, NUM_CONTACTS, 3), "grf", where)
    contacts = _series(contacts, (T, 4), "contacts", where)
    mj = model.mj
    views = list(views)
    kp = None
    if keypoints2d is not None:
        kp = np.asarray(keypoints2d, np.float64)
        if kp.ndim != 3 or kp.shape[0] != T or kp.shape[2] != 3:
            raise ValueError(f"{where}: field 'keypoints2d' has shape {kp.shape}, expected (T={T}, J, 3)")
        if camera is None:
            raise ValueError(f"{where}: keypoints2d need the camera (its image size and intrinsics place them)")
        if "camera" not in views:
            views.append("camera")
    if not views:
        raise ValueError(f"{where}: no views")
    cam_ids = {}
    for v in views:
        if v == "camera":
            if camera is None:
                raise ValueError(f"{where}: view 'camera' needs the camera argument")
            continue
        cid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_CAMERA, v)
        if cid < 0:
            names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(mj.ncam)]
            raise ValueError(f"{where}: unknown view {v!r}; the model's cameras: {names} (or 'camera')")
        cam_ids[v] = cid
    sites = np.asarray(model.topo.contact_sites, int)
    if (grf is not None or contacts is not None) and len(sites) != 4:
        raise ValueError(f"{where}: grf/contacts need the model's four contact sites")

    if camera is not None:
        intr = np.asarray(camera.intrinsics, np.float64)
        isize = np.asarray(camera.image_size, np.float64)
        extr = np.asarray(camera.extrinsics, np.float64)
        if intr.shape != (4,) or isize.shape != (2,) or extr.shape not in ((4, 4), (T, 4, 4)):
            raise ValueError(f"{where}: camera must be unbatched (its extrinsics one (4, 4) or one per frame, "
                             f"(T, 4, 4)), got intrinsics {intr.shape}, extrinsics {extr.shape}")
        k, ox, oy = _pinhole_fit(isize, W, H)
    bones: list[tuple[int, int]] = []
    if kp is not None:
        lay = get_layout(layout) if layout is not None else (get_layout("body25") if kp.shape[1] == 25 else None)
        if lay is not None:
            if lay.num_joints != kp.shape[1]:
                raise ValueError(f"{where}: keypoints2d have {kp.shape[1]} joints, layout {lay.name!r} has {lay.num_joints}")
            bones = _layout_bones(model, lay)

    if not (math.isfinite(force_scale) and force_scale > 0):
        raise ValueError(f"{where}: force_scale must be positive, got {force_scale}")
    weight = model.total_mass * float(np.linalg.norm(model.gravity))
    scale = float(force_scale) / weight
    arrow_w = 0.01 * float(mj.stat.extent)  # 20 mm for the humanoid (extent 2 m)
    # contact markers: the geoms of the body that carries each contact site (hindfoot, toes)
    contact_geoms = [np.nonzero(mj.geom_bodyid == mj.site_bodyid[s])[0] for s in sites]
    from jmocap.scene import boxes as scene_boxes

    boxes = [] if scene is None else scene_boxes(scene)  # the terrain, padding left out

    def frames() -> Iterator[np.ndarray]:
        mjr = copy.copy(mj)  # render settings go on a copy of the user's model
        if quality == "fast":
            mjr.vis.quality.offsamples = 0  # no multisampling
        renderer = open_renderer(mjr, H, W)
        d = mujoco.MjData(mjr)
        free_cam = mujoco.MjvCamera()
        try:
            for t in range(T):
                d.qpos[:] = q[t]
                mujoco.mj_kinematics(mjr, d)
                mujoco.mj_comPos(mjr, d)  # for cameras that track the centre of mass
                mujoco.mj_camlight(mjr, d)
                tinted = set()
                if contacts is not None:
                    for c in np.nonzero(contacts[t] > 0.5)[0]:
                        tinted.update(int(g) for g in contact_geoms[c])
                panels = []
                for v in views:
                    if v == "camera":
                        renderer.update_scene(d, camera=free_cam)
                        _set_pinhole(renderer.scene, intr, isize, extr[t] if extr.ndim == 3 else extr, W, H)
                    else:
                        renderer.update_scene(d, camera=cam_ids[v])
                    scene = renderer.scene
                    if quality == "fast":  # shadows and floor reflections cost ~5x on llvmpipe
                        scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
                        scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
                    if tinted:
                        for i in range(scene.ngeom):
                            g = scene.geoms[i]
                            if g.objtype == mujoco.mjtObj.mjOBJ_GEOM and g.objid in tinted:
                                g.rgba[:] = CONTACT_RGBA
                    for c, h, R in boxes:  # the terrain (a scene's boxes, jmocap.scene)
                        g = _add_geom(scene)
                        if g is not None:
                            mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_BOX, h, c, R.ravel(), SCENE_RGBA)
                    arrows = []
                    if grf is not None:
                        for start, force in _foot_forces(d.site_xpos[sites].astype(np.float64), grf[t]):
                            if np.linalg.norm(force) > 0.01 * weight:
                                end = start + scale * force
                                _add_arrow(scene, start, end, arrow_w, ARROW_RGBA)
                                uv, z = _gl_project(scene, np.stack([start, end]), W, H)
                                if (z > scene.camera[0].frustum_near).all():
                                    arrows.append(uv)
                    img = renderer.render()
                    points = frame = None
                    if v == "camera":
                        frame = (ox, oy, ox + k * isize[0] - 1, oy + k * isize[1] - 1)
                        if kp is not None:
                            points = kp[t].copy()
                            points[:, 0] = k * points[:, 0] + ox
                            points[:, 1] = k * points[:, 1] + oy
                    label = [v] + ([f"t {t / fps:.2f} s"] if fps and not panels else [])
                    panels.append(_draw_overlay(img, points, bones, label, arrows, frame))
                yield np.concatenate(panels, axis=1)
        finally:
            renderer.close()

    return frames()


def render(
    path: str | os.PathLike,
    model: Model,
    q,
    fps: float,
    *,
    grf=None,
    contacts=None,
    keypoints2d=None,
    camera=None,
    layout: str | Layout | None = None,
    views: Sequence[str] = ("front", "side"),
    size: tuple[int, int] = DEFAULT_SIZE,
    force_scale: float = FORCE_SCALE_M_PER_BW,
    quality: str = "fast",
    scene=None,
) -> Path:
    """Render a motion to ``path``: MP4 (H.264, imageio-ffmpeg's ffmpeg) or GIF, by extension.

    Every frame is rendered (``fps`` is the playback rate). Arguments as
    :func:`render_frames`. MP4 streams frames to ffmpeg; a GIF holds them all in memory
    (about 0.25 MB per 640x240 frame), so prefer MP4 for long clips. Written atomically (temp file in the same folder, then
    ``os.replace``). Returns the path.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".mp4", ".gif"):
        raise ValueError(f"render({path}): unsupported video format {path.suffix!r}; use .mp4 or .gif")
    fps = float(fps)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"render({path}): fps must be positive, got {fps}")
    frames = render_frames(
        model, q, grf=grf, contacts=contacts, keypoints2d=keypoints2d, camera=camera, layout=layout,
        views=views, size=size, force_scale=force_scale, quality=quality, fps=fps, scene=scene,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        if ext == ".gif":
            iio = _import_viz("imageio.v3", "render(): GIF output")
            iio.imwrite(tmp, np.stack(list(frames)), extension=".gif", duration=1000.0 / fps, loop=0)
        else:
            _write_mp4(tmp, frames, fps)
    return path


def _write_mp4(path: Path, frames: Iterator[np.ndarray], fps: float) -> None:
    imageio_ffmpeg = _import_viz("imageio_ffmpeg", "render(): MP4 output")
    writer = None
    try:
        for frame in frames:
            # yuv420p needs even dimensions: pad by one black row/column if needed
            h, w = frame.shape[:2]
            if h % 2 or w % 2:
                frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)))
            if writer is None:
                writer = imageio_ffmpeg.write_frames(
                    str(path), (frame.shape[1], frame.shape[0]), fps=fps, codec="libx264",
                    pix_fmt_out="yuv420p", quality=8, macro_block_size=2, ffmpeg_log_level="error",
                )
                with warnings.catch_warnings():
                    # JAX warns on any fork; ffmpeg is exec'd straight away, which is safe
                    warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
                    writer.send(None)  # start ffmpeg
            writer.send(np.ascontiguousarray(frame))
    finally:
        if writer is not None:
            writer.close()


# ======================================================================================
# a motion drawn over the input video's frames (jmocap video)
# ======================================================================================

OVERLAY_ALPHA = 0.6  # opacity of the rendered humanoid over the input frame


def overlay_frames(
    model: Model,
    q,
    frames,
    camera,
    *,
    keypoints2d=None,
    first_frame: int = 0,
    layout: str | Layout | None = None,
    alpha: float = OVERLAY_ALPHA,
    quality: str = "fast",
    fps: float | None = None,
) -> Iterator[np.ndarray]:
    """The input frames with the motion rendered over them from the input camera.

    Args:
      model: the character the motion was reconstructed with.
      q: (T, nq) configurations for frames ``first_frame .. first_frame + T - 1`` of ``frames``;
        the other frames pass through with only the time label.
      frames: an iterable of (H, W, 3) uint8 RGB frames (consumed once: a video may be
        streamed), H and W the camera's image size.
      camera: the unbatched :class:`jmocap.camera.Camera` of the frames (its intrinsics, image
        size and extrinsics; a moving camera's extrinsics (T, 4, 4), one per frame of ``q``).
      keypoints2d: optional (T, J, 3) 2D keypoints of the same frames (pixels, confidence; 0 =
        missing), drawn with their bones (``layout``, or J = 25: BODY_25).
      alpha: opacity of the humanoid over the frame.

    The humanoid is rendered by MuJoCo offscreen through the exact pinhole camera (as the
    ``camera`` view of :func:`render_frames`), without the floor; a segmentation render of the
    same scene is the mask where it is blended over the frame. Yields (H, W, 3) uint8 frames.
    """
    where = "overlay_frames"
    q = check_q(model, q, f"{where}: field 'q'")
    T = len(q)
    if quality not in ("fast", "high"):
        raise ValueError(f"{where}: quality must be 'fast' or 'high', got {quality!r}")
    if not 0.0 <= float(alpha) <= 1.0:
        raise ValueError(f"{where}: alpha must be in [0, 1], got {alpha}")
    intr = np.asarray(camera.intrinsics, np.float64)
    isize = np.asarray(camera.image_size, np.float64)
    extr = np.asarray(camera.extrinsics, np.float64)
    if intr.shape != (4,) or isize.shape != (2,) or extr.shape not in ((4, 4), (T, 4, 4)):
        raise ValueError(f"{where}: camera must be unbatched (its extrinsics one (4, 4) or one per frame of q, "
                         f"(T, 4, 4)), got intrinsics {intr.shape}, extrinsics {extr.shape}")
    W, H = int(round(isize[0])), int(round(isize[1]))
    _size((W, H), where)
    kp = None
    bones: list[tuple[int, int]] = []
    if keypoints2d is not None:
        kp = np.asarray(keypoints2d, np.float64)
        if kp.ndim != 3 or kp.shape[0] != T or kp.shape[2] != 3:
            raise ValueError(f"{where}: field 'keypoints2d' has shape {kp.shape}, expected (T={T}, J, 3)")
        lay = get_layout(layout) if layout is not None else (get_layout("body25") if kp.shape[1] == 25 else None)
        if lay is not None:
            if lay.num_joints != kp.shape[1]:
                raise ValueError(f"{where}: keypoints2d have {kp.shape[1]} joints, layout {lay.name!r} has {lay.num_joints}")
            bones = _layout_bones(model, lay)
    mj = copy.copy(model.mj)  # render settings go on a copy of the user's model
    if quality == "fast":
        mj.vis.quality.offsamples = 0
    hidden = 5  # geom group of the floor (planes): not drawn
    planes = np.nonzero(mj.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)[0]
    mj.geom_group[planes] = hidden
    option = mujoco.MjvOption()
    option.geomgroup[hidden] = 0
    a = float(alpha)

    def gen() -> Iterator[np.ndarray]:
        renderer = None
        d = mujoco.MjData(mj)
        free_cam = mujoco.MjvCamera()
        try:
            for t, frame in enumerate(frames):
                img = np.asarray(frame)
                if img.shape != (H, W, 3):
                    raise ValueError(f"{where}: frame {t} has shape {img.shape}, expected ({H}, {W}, 3)")
                i = t - int(first_frame)
                points = None
                if 0 <= i < T:
                    if renderer is None:
                        renderer = open_renderer(mj, H, W)
                    d.qpos[:] = q[i]
                    mujoco.mj_kinematics(mj, d)
                    mujoco.mj_camlight(mj, d)
                    renderer.update_scene(d, camera=free_cam, scene_option=option)
                    _set_pinhole(renderer.scene, intr, isize, extr[i] if extr.ndim == 3 else extr, W, H)
                    if quality == "fast":
                        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
                        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
                    rgb = renderer.render()
                    renderer.enable_segmentation_rendering()
                    try:
                        seg = renderer.render()
                    finally:
                        renderer.disable_segmentation_rendering()
                    mask = (seg[..., 0] >= 0) & (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM))
                    w = (a * mask)[..., None]
                    img = (img * (1.0 - w) + rgb * w).round().astype(np.uint8)
                    if kp is not None:
                        points = kp[i]
                label = [f"frame {t}" + (f"  t {t / fps:.2f} s" if fps else "")]
                yield _draw_overlay(np.ascontiguousarray(img), points, bones, label)
        finally:
            if renderer is not None:
                renderer.close()

    return gen()


def render_overlay(path: str | os.PathLike, model: Model, q, frames, camera, fps: float, **kwargs) -> Path:
    """Write :func:`overlay_frames` (same arguments) as an MP4 at ``fps``, atomically, streaming
    the frames (memory: one frame). Returns the path."""
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"render_overlay({path}): the overlay is written as .mp4")
    fps = float(fps)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"render_overlay({path}): fps must be positive, got {fps}")
    it = overlay_frames(model, q, frames, camera, fps=fps, **kwargs)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        _write_mp4(tmp, it, fps)
    return path


# ======================================================================================
# force plots
# ======================================================================================

DEFAULT_TORQUE_JOINTS = ("left_knee_y", "right_knee_y", "left_ankle_y", "right_ankle_y")


def plot_forces(
    path: str | os.PathLike,
    grf,
    fps: float,
    *,
    gt_grf=None,
    tau=None,
    joints: Sequence[str] | None = None,
    model: Model | None = None,
) -> Path:
    """Plot forces over time to a PNG (matplotlib, Agg), after paper 000 Fig. 4.

    Panels: (a) vertical GRF per foot (heel + toe, contact order L heel, L toe, R heel, R toe),
    in body weights when ``model`` is given (newtons otherwise), ``gt_grf`` dashed; then, with
    ``tau`` (T, nv) and ``model``, one panel per joint kind (left and right together) of the
    hinge torques of ``joints`` (default knee and ankle flexion) in N m, and the magnitude of
    the residual root force ``|tau[:3]|`` in body weights. Written atomically. Returns the path.
    """
    FigureCanvasAgg = _import_viz("matplotlib.backends.backend_agg", "plot_forces()").FigureCanvasAgg
    Figure = _import_viz("matplotlib.figure", "plot_forces()").Figure
    path = Path(path)
    where = f"plot_forces({path})"
    fps = float(fps)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: fps must be positive, got {fps}")
    grf = np.asarray(grf, np.float64)
    if grf.ndim != 3 or grf.shape[1:] != (NUM_CONTACTS, 3):
        raise ValueError(f"{where}: field 'grf' has shape {grf.shape}, expected (T, {NUM_CONTACTS}, 3)")
    T = grf.shape[0]
    gt_grf = _series(gt_grf, (T, NUM_CONTACTS, 3), "gt_grf", where)
    time = np.arange(T) / fps
    weight = None if model is None else model.total_mass * float(np.linalg.norm(model.gravity))
    unit = "body weights" if weight else "N"
    norm = weight or 1.0

    torque_groups: dict[str, list[tuple[str, int]]] = {}
    if tau is not None:
        if model is None:
            raise ValueError(f"{where}: plotting tau needs the model (joint names and dof addresses)")
        tau = _series(tau, (T, model.nv), "tau", where)
        names = model.topo.joint_names
        if joints is None:
            joints = [j for j in DEFAULT_TORQUE_JOINTS if j in names]
        for j in joints:
            if j not in names:
                raise ValueError(f"{where}: model has no joint {j!r}")
            jid = names.index(j)
            if int(model.mj.jnt_type[jid]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
                raise ValueError(f"{where}: joint {j!r} is not a hinge or slide joint")
            kind = j.removeprefix("left_").removeprefix("right_")
            torque_groups.setdefault(kind, []).append((j, int(model.mj.jnt_dofadr[jid])))

    n_panels = 1 + len(torque_groups) + (1 if tau is not None and model.topo.free_dof else 0)
    fig = Figure(figsize=(8.0, 2.3 * n_panels), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(n_panels, 1, sharex=True, squeeze=False)[:, 0]
    colours = {"left": "tab:blue", "right": "tab:red"}

    ax = axes[0]
    for side, (heel, toe) in (("left", (0, 1)), ("right", (2, 3))):
        ax.plot(time, (grf[:, heel, 2] + grf[:, toe, 2]) / norm, color=colours[side], label=f"{side} foot")
        if gt_grf is not None:
            ax.plot(time, (gt_grf[:, heel, 2] + gt_grf[:, toe, 2]) / norm, "--", color=colours[side],
                    alpha=0.7, label=f"{side} foot (ground truth)")
    ax.set_ylabel(f"vertical GRF\n({unit})")
    ax.set_title("(a) vertical ground reaction force per foot (heel + toe)", fontsize=9, loc="left")
    ax.legend(fontsize=7, loc="best")
    panel = 1
    for kind, members in torque_groups.items():
        ax = axes[panel]
        for j, dof in members:
            side = "left" if j.startswith("left_") else "right" if j.startswith("right_") else None
            ax.plot(time, tau[:, dof], color=colours.get(side, "k"), label=j)
        ax.set_ylabel(f"{kind} torque\n(N m)")
        ax.set_title(f"({chr(ord('a') + panel)}) joint torque: {kind}", fontsize=9, loc="left")
        ax.legend(fontsize=7, loc="best")
        panel += 1
    if panel < n_panels:
        d0 = model.topo.free_dof[0]
        ax = axes[panel]
        ax.plot(time, np.linalg.norm(tau[:, d0 : d0 + 3], axis=1) / norm, color="k")
        ax.set_ylabel(f"|root force|\n({unit})")
        ax.set_title(f"({chr(ord('a') + panel)}) residual (virtual) root force", fontsize=9, loc="left")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.axhline(0.0, color="0.6", lw=0.6)
    axes[-1].set_xlabel("time (s)")

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


# ======================================================================================
# result files (the `jmocap render` command)
# ======================================================================================


def result_camera(result: dict):
    """The input :class:`jmocap.camera.Camera` of a :func:`jmocap.export.load_result` dict, or None."""
    if result.get("intrinsics") is None or result.get("image_size") is None:
        return None
    from jmocap.camera import Camera

    fx, fy, cx, cy = (float(v) for v in result["intrinsics"])
    w, h = (float(v) for v in result["image_size"])
    extrinsics = next((result[k] for k in ("camera_track", "camera_track_estimated", "extrinsics")
                       if result.get(k) is not None), None)
    return Camera.from_intrinsics(fx, fy, cx, cy, w, h, extrinsics=extrinsics, dtype=np.float64)


def render_result(
    result_path: str | os.PathLike,
    out: str | os.PathLike | None = None,
    *,
    plots: str | os.PathLike | None = None,
    size: tuple[int, int] = DEFAULT_SIZE,
    side: bool = True,
    quality: str = "fast",
    model: Model | None = None,
) -> list[Path]:
    """Render a result ``.npz``: a video (default: the result's path with ``.mp4``) and, with
    ``plots`` (a folder), ``<name>_forces.png``. The model defaults to jmocap's humanoid scaled
    to the result's ``height_m`` / ``mass_kg``. Returns the written paths."""
    import jmocap

    _require_viz("render_result() (jmocap render)")
    result_path = Path(result_path)
    r = load_result(result_path)
    if model is None:
        model = jmocap.load_model(height_m=r["height_m"], mass_kg=r.get("mass_kg"), with_mjx=False)
    if r["q"].shape[1] != model.nq:
        raise ValueError(f"{result_path}: field 'q' has nq = {r['q'].shape[1]}, the model has {model.nq}")
    camera = result_camera(r)
    out = Path(out) if out is not None else result_path.with_suffix(".mp4")
    written = [
        render(
            out, model, r["q"], r["fps"], grf=r["grf"], contacts=r["contact_prob"],
            keypoints2d=r["keypoints2d"] if camera is not None else None, camera=camera,
            layout=r["layout"], views=("front", "side") if side else ("front",), size=size,
            quality=quality, scene=r.get("scene"),
        )
    ]
    if plots is not None:
        if r["grf"] is None:
            raise ValueError(f"{result_path}: no forces to plot (its method, {r['method']!r}, estimates none)")
        written.append(
            plot_forces(
                Path(plots) / f"{result_path.stem}_forces.png", r["grf"], r["fps"],
                gt_grf=r.get("gt_grf"), tau=r["tau"], model=model,
            )
        )
    return written
