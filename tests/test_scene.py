"""Scenes (issue 21, item 1): the signed distance against MuJoCo's own geometry distance
(``mj_geomDistance`` between the scene's geoms, added by ``add_to_spec``, and a small sphere
moved to each point), the document's validation, and padding for batches."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from conftest import x64
from jmocap import scene as SC

DOC = {"format": "jmocap-scene-1", "boxes": [
    {"center": [1.0, 0.5, 0.15], "half_size": [0.4, 0.3, 0.15], "yaw_deg": 25.0},  # a step
    {"center": [-1.2, 0.0, 0.25], "half_size": [1.0, 0.5, 0.05], "yaw_deg": -10.0, "pitch_deg": 12.0},  # a ramp
    {"center": [0.0, -1.5, 0.6], "half_size": [0.2, 0.2, 0.6], "rotation": np.eye(3).tolist()},  # a pillar
]}


def _mujoco_distance(scene: SC.Scene, points: np.ndarray, radius: float = 1e-3) -> np.ndarray:
    """Signed distance of each point to the nearest scene geom (floor plane included), from
    MuJoCo: a sphere of ``radius`` on a mocap body at the point, ``mj_geomDistance`` to every
    static geom, plus the radius."""
    spec = mujoco.MjSpec()
    floor = spec.worldbody.add_geom()
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [0, 0, 1]
    names = SC.add_to_spec(spec, scene)
    body = spec.worldbody.add_body()
    body.mocap = True
    ball = body.add_geom()
    ball.name = "probe"
    ball.type = mujoco.mjtGeom.mjGEOM_SPHERE
    ball.size = [radius, 0, 0]
    ball.contype, ball.conaffinity = 0, 0
    m = spec.compile()
    d = mujoco.MjData(m)
    probe = m.geom("probe").id
    targets = [0] + [m.geom(n).id for n in names]
    out = []
    for p in points:
        d.mocap_pos[0] = p
        mujoco.mj_kinematics(m, d)
        fromto = np.zeros(6)
        out.append(min(mujoco.mj_geomDistance(m, d, probe, g, 10.0, fromto) for g in targets) + radius)
    return np.asarray(out)


def test_sdf_matches_mujocos_geometry_distance():
    """Points around and inside every box (faces, edges, corners, the ramp's slope) and above
    the floor: the JAX distance equals MuJoCo's to 1e-6 m; padding boxes change nothing."""
    scene = SC.parse_scene(DOC)
    rng = np.random.default_rng(0)
    pts = [rng.uniform([-2.5, -2.2, -0.1], [2.0, 1.2, 1.4], size=(300, 3))]
    for c, h, R in zip(scene.centers, scene.half_sizes, scene.rotations, strict=True):  # near the surfaces
        local = rng.uniform(-1.3, 1.3, size=(200, 3)) * h
        pts.append(c + local @ R.T)
    pts = np.concatenate(pts)
    ref = _mujoco_distance(scene, pts)
    with x64():
        got = np.asarray(jax.jit(SC.sdf)(jax.tree.map(jnp.asarray, scene), jnp.asarray(pts)))
        padded = np.asarray(SC.sdf(jax.tree.map(jnp.asarray, SC.pad(scene, 8)), jnp.asarray(pts)))
    np.testing.assert_allclose(got, ref, atol=1e-6)
    np.testing.assert_array_equal(padded, got)
    assert (got < 0).sum() > 50 and (got > 0).sum() > 300  # both sides were tested


def test_surface_height_matches_mujocos_ray_cast():
    """The terrain height under points (the generator's and the labels' height) equals where a
    vertical ray cast down by MuJoCo (``mj_ray`` from 10 m up) first meets the scene, on the
    step, the ramp, the pillar, beside them and on the bare floor; padding changes nothing."""
    scene = SC.parse_scene(DOC)
    rng = np.random.default_rng(1)
    xy = rng.uniform([-2.5, -2.2], [2.0, 1.2], size=(400, 2))
    spec = mujoco.MjSpec()
    floor = spec.worldbody.add_geom()
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [0, 0, 1]
    SC.add_to_spec(spec, scene)
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    geomid = np.zeros(1, np.int32)
    ref = np.array([10.0 - mujoco.mj_ray(m, d, np.array([x, y, 10.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, geomid)
                    for x, y in xy])
    got = SC.surface_height(scene, xy)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    np.testing.assert_array_equal(SC.surface_height(SC.pad(scene, 6), xy), got)
    assert (got > 0.01).sum() > 40 and (got == 0).sum() > 100  # boxes and floor both hit
    assert np.unique(np.round(got[got > 0.01], 3)).size > 10  # the ramp's slope, not only flat tops


def test_sdf_gradient_is_the_unit_normal():
    """Off the surfaces the distance's gradient has length one (eikonal) and points along the
    step from the point to MuJoCo's nearest surface point (finite differences agree)."""
    scene = jax.tree.map(jnp.asarray, SC.parse_scene(DOC))
    with x64():
        p = jnp.asarray([[1.5, 1.1, 0.5], [1.0, 0.5, 0.25], [-1.2, 0.1, 0.6], [0.1, -1.45, 0.3]])
        g = jax.vmap(jax.grad(lambda x: SC.sdf(scene, x)))(p)
        np.testing.assert_allclose(np.linalg.norm(g, axis=-1), 1.0, atol=1e-9)
        eps = 1e-6
        fd = np.stack([(SC.sdf(scene, p + eps * e) - SC.sdf(scene, p - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
        np.testing.assert_allclose(g, fd, atol=1e-6)


def test_the_floor_alone_is_height():
    empty = SC.Scene.empty()
    p = np.array([[0.3, -2.0, 0.7], [5.0, 1.0, -0.2]])
    np.testing.assert_allclose(SC.sdf(empty, jnp.asarray(p)), p[:, 2], atol=1e-7)
    assert SC.parse_scene({"format": "jmocap-scene-1"}).num_boxes == 0


@pytest.mark.parametrize(("doc", "message"), [
    ([], "a scene is a JSON object"),
    ({"format": "other"}, "format 'other'"),
    ({"boxes": [{"center": [0, 0, 0]}]}, "box 0: missing 'half_size'"),
    ({"boxes": [{"center": [0, 0], "half_size": [1, 1, 1]}]}, r"box 0: 'center' must have shape \(3,\)"),
    ({"boxes": [{"center": [0, 0, 0], "half_size": [1, 0, 1]}]}, "box 0: every 'half_size' must be in"),
    ({"boxes": [{"center": [0, 0, "a"], "half_size": [1, 1, 1]}]}, "box 0: 'center' must be numbers"),
    ({"boxes": [{"center": [0, 0, float("nan")], "half_size": [1, 1, 1]}]}, "box 0: 'center' is not finite"),
    ({"boxes": [{"center": [0, 0, 0], "half_size": [1, 1, 1], "rotation": [[1, 0, 0], [0, 2, 0], [0, 0, 1]]}]},
     "box 0: 'rotation' is not a rotation matrix"),
    ({"boxes": [{"center": [0, 0, 0], "half_size": [1, 1, 1], "rotation": np.eye(3).tolist(), "yaw_deg": 3}]},
     "give 'rotation' or angles"),
    ({"boxes": [{"center": [0, 0, 0], "half_size": [1, 1, 1], "colour": "red"}]}, r"box 0: unknown keys \['colour'\]"),
    ("{not json", "not JSON"),
])
def test_bad_scenes_are_refused_with_the_box_and_key(doc, message):
    with pytest.raises(SC.SceneError, match=message):
        SC.parse_scene(doc, where="steps.json")


def test_document_round_trip():
    scene = SC.parse_scene(DOC)
    again = SC.parse_scene(SC.scene_document(SC.pad(scene, 5)))
    for a, b in zip(jax.tree.leaves(scene), jax.tree.leaves(again), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_foot_metrics_measure_against_the_scene():
    """Hand-worked: four foot points resting on a 30 cm step for 10 frames, labelled in
    contact. Against the floor they float on every frame; against the scene they touch it. The
    same points sunk 5 cm into the step penetrate only against the scene."""
    from jmocap import metrics as M

    step = SC.parse_scene({"boxes": [{"center": [0.0, 0.0, 0.15], "half_size": [0.5, 0.5, 0.15]}]})
    T = 10
    feet = np.tile(np.array([[-0.1, 0.1, 0.3], [0.1, 0.1, 0.3], [-0.1, -0.1, 0.3], [0.1, -0.1, 0.3]]), (T, 1, 1))
    contacts = np.ones((T, 4))
    on = M.evaluate_arrays({"feet": feet}, {"contacts": contacts}, fps=30.0, scene=step)
    flat = M.evaluate_arrays({"feet": feet}, {"contacts": contacts}, fps=30.0)
    assert (on["float_pct"], on["pnp_pct"], on["penetrate_pct"], on["mpe_mm"]) == (0.0, 100.0, 0.0, 0.0)
    assert flat["float_pct"] == 100.0 and abs(flat["mpe_mm"] - 300.0) < 1e-3
    sunk = feet - np.array([0.0, 0.0, 0.05])
    inside = M.evaluate_arrays({"feet": sunk}, {"contacts": contacts}, fps=30.0, scene=step)
    assert inside["pnp_pct"] == 0.0 and inside["penetrate_pct"] == 100.0 and abs(inside["mpe_mm"] - 50.0) < 1e-3
    assert M.evaluate_arrays({"feet": sunk}, {"contacts": contacts}, fps=30.0)["penetrate_pct"] == 0.0


def test_a_clip_keeps_its_scene_through_its_file(tmp_path):
    """``scene`` is saved in the clip's npz as its document and read back; a bad one is refused
    naming the file and the box."""
    from jmocap.data.clip import ClipFormatError, load_clip, save_clip
    from jmocap.data.synthetic import SynthConfig, generate_clip

    clip = generate_clip(3, 0, SynthConfig(frames=20)).replace(scene=DOC)
    assert isinstance(clip.scene, SC.Scene) and clip.scene.num_boxes == 3
    save_clip(tmp_path / "c.npz", clip)
    back = load_clip(tmp_path / "c.npz")
    for a, b in zip(jax.tree.leaves(clip.scene), jax.tree.leaves(back.scene), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert load_clip(tmp_path / "c.npz").slice(2, 10).scene.num_boxes == 3
    with pytest.raises(ClipFormatError, match="field 'scene': box 1: missing 'center'"):
        clip.replace(scene={"boxes": [DOC["boxes"][0], {"half_size": [1, 1, 1]}]})
