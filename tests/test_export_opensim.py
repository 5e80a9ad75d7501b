"""OpenSim export (jmocap.export.opensim): every file read back with OpenSim's own classes
(the ``opensim`` wheel) and compared with MuJoCo C, plus hand-worked frames."""

from __future__ import annotations

import math
import re

import mujoco
import numpy as np
import pytest

osim = pytest.importorskip("opensim")

from jmocap.data.clip import FormatError  # noqa: E402
from jmocap.export.opensim import (  # noqa: E402
    AXES,
    coordinates_table,
    foot_bodies,
    write_opensim,
)
from jmocap.layouts import get_layout  # noqa: E402
from jmocap.model import character, from_mjmodel  # noqa: E402

T = 6
FPS = 30.0


def _random_q(mj: mujoco.MjModel, rng: np.random.Generator, T: int) -> np.ndarray:
    """Hinges uniform within their ranges, an arbitrary root pose."""
    q = np.tile(np.asarray(mj.qpos0, np.float64), (T, 1))
    for j in range(mj.njnt):
        if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            lo, hi = mj.jnt_range[j] if mj.jnt_limited[j] else (-2.0, 2.0)
            q[:, mj.jnt_qposadr[j]] = rng.uniform(lo, hi, T)
        elif mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            a = mj.jnt_qposadr[j]
            q[:, a : a + 3] = rng.normal(0, 1, (T, 3)) + [0, 0, 1]
            quat = rng.normal(size=(T, 4))
            q[:, a + 3 : a + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return q


def _kinematics(mj, q):
    d = mujoco.MjData(mj)
    out = []
    for t in range(q.shape[0]):
        d.qpos[:] = q[t]
        mujoco.mj_kinematics(mj, d)
        out.append({k: np.array(getattr(d, k)) for k in ("xpos", "xmat", "xipos", "ximat", "site_xpos", "geom_xpos",
                                                          "geom_xmat")})
    return out


def _vec(v) -> np.ndarray:
    return np.array([v.get(i) for i in range(3)])


def _mat(R) -> np.ndarray:
    return np.array([[R.get(i, j) for j in range(3)] for i in range(3)])


def _pose_errors(model_path, mot_path, mj, q):
    """Set the OpenSim model to every row of the coordinates .mot; the largest differences from
    MuJoCo C (body origins, orientations, centres of mass, inertias in ground), and the model and
    state (at the last frame)."""
    om = osim.Model(str(model_path))
    state = om.initSystem()
    table = osim.TimeSeriesTable(str(mot_path))
    labels = list(table.getColumnLabels())
    coords = om.getCoordinateSet()
    assert sorted(labels) == sorted(coords.get(i).getName() for i in range(coords.getSize()))
    times = np.asarray(table.getIndependentColumn())
    np.testing.assert_allclose(times, np.arange(q.shape[0]) / FPS, atol=1e-9)
    kin = _kinematics(mj, q)
    err = dict(pos=0.0, rot=0.0, com=0.0, inertia=0.0)
    for t in range(q.shape[0]):
        row = table.getRowAtIndex(t)
        for i, label in enumerate(labels):
            c = coords.get(label)
            v = row[i]
            c.setValue(state, v if c.getMotionType() == osim.Coordinate.Translational else math.radians(v), False)
        om.realizePosition(state)
        k = kin[t]
        for b in range(1, mj.nbody):
            body = om.getBodySet().get(mj.body(b).name)
            R = _mat(body.getTransformInGround(state).R())
            err["pos"] = max(err["pos"], np.abs(_vec(body.getPositionInGround(state)) - AXES @ k["xpos"][b]).max())
            err["rot"] = max(err["rot"], np.abs(R - AXES @ k["xmat"][b].reshape(3, 3)).max())
            com = _vec(body.findStationLocationInGround(state, body.getMassCenter()))
            err["com"] = max(err["com"], np.abs(com - AXES @ k["xipos"][b]).max())
            inertia = body.getInertia()
            m, p = _vec(inertia.getMoments()), _vec(inertia.getProducts())
            I_body = np.array([[m[0], p[0], p[1]], [p[0], m[1], p[2]], [p[1], p[2], m[2]]])
            Ri = k["ximat"][b].reshape(3, 3)
            I_mj = AXES @ Ri @ np.diag(mj.body_inertia[b]) @ Ri.T @ AXES.T
            err["inertia"] = max(err["inertia"], np.abs(R @ I_body @ R.T - I_mj).max())
    return err, om, state


@pytest.fixture(scope="module")
def human(tmp_path_factory):
    model = character()
    mj = model.mj
    rng = np.random.default_rng(7)
    q = _random_q(mj, rng, T)
    layout = get_layout("body25")
    sites = [mj.site(s).id for s in layout.sites]
    kp = np.stack([k["site_xpos"][sites] for k in _kinematics(mj, q)])
    kp[1, 3] = np.nan  # a missing keypoint
    grf = np.zeros((T, 4, 3))
    grf[..., 2] = rng.uniform(20, 400, (T, 4))
    grf[..., :2] = rng.normal(0, 30, (T, 4, 2))
    # frame 0, worked by hand in test_grf_hand_worked_frame
    grf[0] = [[10.0, 0.0, 300.0], [0.0, 5.0, 100.0], [0.0, 0.0, 0.0], [0.0, -2.0, 0.5]]
    result = dict(q=q.astype(np.float32).astype(np.float64), fps=FPS, keypoints3d=kp, layout="body25", grf=grf,
                  forces_estimated=True, name="walk 1", height_m=None, mass_kg=None, assumed=[])
    out = tmp_path_factory.mktemp("opensim")
    paths = write_opensim(result, out)
    return dict(model=model, result=result, paths=paths, out=out)


def test_files_and_names(human):
    paths = human["paths"]
    assert set(paths) == {"model", "coordinates", "markers", "grf", "external_loads"}
    assert {p.name for p in paths.values()} == {"walk_1.osim", "walk_1_coordinates.mot", "walk_1_markers.trc",
                                                "walk_1_grf.mot", "walk_1_grf.xml"}
    assert sorted(p.name for p in human["out"].iterdir()) == sorted(p.name for p in paths.values())  # no temporaries
    head = paths["coordinates"].read_text().splitlines()[:7]
    assert head[1:6] == ["version=1", f"nRows={T}", f"nColumns={1 + 6 + 41}", "inDegrees=yes", "endheader"]
    mj = human["model"].mj
    hinges = [mj.joint(j).name for j in range(mj.njnt) if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    root = [f"pelvis_{s}" for s in ("tilt", "list", "rotation", "tx", "ty", "tz")]
    assert head[6].split("\t") == ["time", *root, *hinges]


def test_osim_model_reproduces_mujoco(human):
    """(a) OpenSim's model at the .mot's coordinates puts every body where MuJoCo C does."""
    model = human["model"]
    err, om, state = _pose_errors(human["paths"]["model"], human["paths"]["coordinates"], model.mj,
                                  human["result"]["q"])
    assert err["pos"] < 1e-4 and err["com"] < 1e-4, err
    assert err["rot"] < 1e-5 and err["inertia"] < 1e-6, err
    assert om.getTotalMass(state) == pytest.approx(float(np.sum(model.mj.body_mass)), rel=1e-9)
    assert om.getNumBodies() == model.mj.nbody - 1
    g = _vec(om.getGravity())
    np.testing.assert_allclose(g, [0.0, -9.81, 0.0], atol=1e-12)
    # display geometry: every geom's shape (a capsule's cylinder and caps) where MuJoCo C puts it
    mj = model.mj
    k = _kinematics(mj, human["result"]["q"][-1:])[0]
    shapes = 0
    for comp in om.getComponentsList():
        kind = comp.getConcreteClassName()
        if kind not in ("Sphere", "Cylinder", "Brick", "Ellipsoid"):
            continue
        shapes += 1
        frame = osim.PhysicalFrame.safeDownCast(comp.getOwner())
        body, g, end = re.fullmatch(r"(.+)_geom(\d+)(_a|_b)?", frame.getName()).groups()
        g = [i for i in range(mj.ngeom) if mj.geom_bodyid[i] == mj.body(body).id][int(g)]
        R_mj = k["geom_xmat"][g].reshape(3, 3)
        center = k["geom_xpos"][g] + {None: 0.0, "_a": 1.0, "_b": -1.0}[end] * mj.geom_size[g][1] * R_mj[:, 2]
        np.testing.assert_allclose(_vec(frame.getPositionInGround(state)), AXES @ center, atol=1e-9)
        if kind == "Cylinder":  # OpenSim's cylinder axis (y) is MuJoCo's (z)
            R = _mat(frame.getTransformInGround(state).R())
            np.testing.assert_allclose(R[:, 1], AXES @ R_mj[:, 2], atol=1e-9)
    capsules = int(np.sum(mj.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE))
    assert shapes == 3 * capsules + int(np.sum(mj.geom_bodyid > 0)) - capsules
    # the model's markers sit at the layout's sites: at the last frame they are the keypoints
    kp = AXES @ human["result"]["keypoints3d"][-1].T
    names = get_layout("body25").joints
    markers = om.getMarkerSet()
    assert markers.getSize() == len(names)
    for i, n in enumerate(names):
        np.testing.assert_allclose(_vec(markers.get(n).getLocationInGround(state)), kp[:, i], atol=1e-6)


def test_coordinate_ranges(human):
    om = osim.Model(str(human["paths"]["model"]))
    mj = human["model"].mj
    knee = om.getCoordinateSet().get("left_knee_y")
    j = mj.joint("left_knee_y").id
    assert (knee.getRangeMin(), knee.getRangeMax()) == pytest.approx(tuple(mj.jnt_range[j]))
    assert not knee.getDefaultClamped()


def test_trc_reads_back(human):
    """(b) OpenSim's TRC reader returns keypoints3d in OpenSim axes; NaN stays missing."""
    path = human["paths"]["markers"]
    table = osim.TimeSeriesTableVec3(str(path))
    kp = human["result"]["keypoints3d"] @ AXES.T
    assert list(table.getColumnLabels()) == list(get_layout("body25").joints)
    assert table.getNumRows() == T
    assert table.getTableMetaDataAsString("Units") == "m"
    assert float(table.getTableMetaDataAsString("DataRate")) == FPS
    np.testing.assert_allclose(np.asarray(table.getIndependentColumn()), np.arange(T) / FPS, atol=1e-9)
    got = np.array([[_vec(table.getRowAtIndex(t)[j]) for j in range(kp.shape[1])] for t in range(T)])
    np.testing.assert_allclose(got, kp, atol=1e-5)  # NaN == NaN here
    assert np.isnan(got[1, 3]).all()
    markers = osim.TRCFileAdapter().read(str(path))["markers"]  # the adapter the GUI uses
    assert markers.getNumRows() == T


def test_grf_hand_worked_frame(human):
    """(c) Columns and frame 0 worked by hand: left foot in contact (heel 10, 0, 300 N and
    toe 0, 5, 100 N, jmocap axes), right foot below the contact threshold."""
    table = osim.TimeSeriesTable(str(human["paths"]["grf"]))
    labels = list(table.getColumnLabels())
    expect = []
    for s in ("l", "r"):
        expect += [f"ground_force_{s}_v{a}" for a in "xyz"] + [f"ground_force_{s}_p{a}" for a in "xyz"]
    expect += [f"ground_torque_{s}_{a}" for s in ("l", "r") for a in "xyz"]
    assert labels == expect
    row = dict(zip(labels, [table.getRowAtIndex(0)[i] for i in range(len(labels))], strict=True))
    mj = human["model"].mj
    site = _kinematics(mj, human["result"]["q"][:1])[0]["site_xpos"]
    lh, lt, rh, rt = (AXES @ site[mj.site(n).id] for n in ("contact_left_heel", "contact_left_toe",
                                                              "contact_right_heel", "contact_right_toe"))
    # left: F = heel + toe = (10, 0, 300) + (0, 5, 100) jmocap = (10, 400, -5) OpenSim
    assert [row["ground_force_l_vx"], row["ground_force_l_vy"], row["ground_force_l_vz"]] == pytest.approx(
        [10.0, 400.0, -5.0], abs=1e-9)
    # CoP = (300 heel + 100 toe) / 400 on the floor
    cop = 0.75 * lh + 0.25 * lt
    assert [row["ground_force_l_px"], row["ground_force_l_py"], row["ground_force_l_pz"]] == pytest.approx(
        [cop[0], 0.0, cop[2]], abs=1e-9)
    # free moment: heel - cop = 0.25 d, toe - cop = -0.75 d (d = heel - toe); (a x f)_Y = a_Z f_X - a_X f_Z
    # with f_heel = (10, 300, 0), f_toe = (0, 100, -5): 0.25 (10 d_Z) - 0.75 (5 d_X) = 2.5 d_Z - 3.75 d_X
    d = lh - lt
    assert row["ground_torque_l_y"] == pytest.approx(2.5 * d[2] - 3.75 * d[0], abs=1e-9)
    assert row["ground_torque_l_x"] == 0.0 and row["ground_torque_l_z"] == 0.0
    # right: 0.5 N vertical is no contact: the CoP is the sites' mean on the floor; the toe's force
    # (0, -2, 0.5) jmocap = (0, 0.5, 2) OpenSim at toe - mean = -d/2: moment_Y = -(-d_X / 2) 2 = d_X
    d = rh - rt
    mean = (rh + rt) / 2
    assert [row["ground_force_r_vx"], row["ground_force_r_vy"], row["ground_force_r_vz"]] == pytest.approx(
        [0.0, 0.5, 2.0], abs=1e-9)
    assert [row["ground_force_r_px"], row["ground_force_r_py"], row["ground_force_r_pz"]] == pytest.approx(
        [mean[0], 0.0, mean[2]], abs=1e-9)
    assert row["ground_torque_r_y"] == pytest.approx(d[0], abs=1e-9)
    # every frame: the force columns are the summed site forces
    grf = human["result"]["grf"] @ AXES.T
    for t in range(T):
        r = [table.getRowAtIndex(t)[i] for i in range(len(labels))]
        np.testing.assert_allclose(r[0:3], grf[t, 0] + grf[t, 1], atol=1e-6)
        np.testing.assert_allclose(r[6:9], grf[t, 2] + grf[t, 3], atol=1e-6)


def test_external_loads(human):
    """(d) OpenSim loads the ExternalLoads, applies two forces to the feet and evaluates them
    from the .mot."""
    om = osim.Model(str(human["paths"]["model"]))
    loads = osim.ExternalLoads(str(human["paths"]["external_loads"]), True)
    assert loads.getSize() == 2
    assert loads.getDataFileName() == human["paths"]["grf"].name
    bodies = [loads.get(i).getAppliedToBodyName() for i in range(2)]
    mj = human["model"].mj
    assert bodies == ["left_ankle", "right_ankle"]
    assert [mj.body(b).name for b in foot_bodies(human["model"])] == bodies
    om.addModelComponent(loads)
    om.initSystem()
    table = osim.TimeSeriesTable(str(human["paths"]["grf"]))
    labels = list(table.getColumnLabels())
    t = 2
    row = dict(zip(labels, [table.getRowAtIndex(t)[i] for i in range(len(labels))], strict=True))
    for i, s in enumerate(("l", "r")):
        ef = loads.get(i)
        np.testing.assert_allclose(_vec(ef.getForceAtTime(t / FPS)), [row[f"ground_force_{s}_v{a}"] for a in "xyz"],
                                   atol=1e-6)
        np.testing.assert_allclose(_vec(ef.getPointAtTime(t / FPS)), [row[f"ground_force_{s}_p{a}"] for a in "xyz"],
                                   atol=1e-6)
        np.testing.assert_allclose(_vec(ef.getTorqueAtTime(t / FPS)), [row[f"ground_torque_{s}_{a}"] for a in "xyz"],
                                   atol=1e-6)


def test_root_coordinates_hand_worked():
    """Yaw about jmocap's z is pelvis_rotation (about OpenSim's Y), unwrapped past 180 degrees
    (300 then 0 = 360: continuous);
    a pitch about jmocap's -y is pelvis_tilt (about OpenSim's Z); translation (x, z, -y)."""
    model = character()
    q = np.tile(model.mj.qpos0, (5, 1))
    for t, yaw in enumerate((0.0, 100.0, 200.0, 300.0)):
        h = math.radians(yaw) / 2
        q[t, 3:7] = [math.cos(h), 0.0, 0.0, math.sin(h)]
    h = math.radians(20.0) / 2
    q[4, 3:7] = [math.cos(h), 0.0, -math.sin(h), 0.0]
    q[:, 0:3] = [1.0, 2.0, 0.9]
    knee = model.mj.jnt_qposadr[model.mj.joint("left_knee_y").id]
    q[:, knee] = 0.5
    names, values = coordinates_table(dict(q=q, fps=FPS), model)
    col = {n: values[:, i] for i, n in enumerate(names)}
    np.testing.assert_allclose(col["pelvis_rotation"], [0.0, 100.0, 200.0, 300.0, 360.0], atol=1e-9)
    np.testing.assert_allclose(col["pelvis_tilt"], [0.0, 0.0, 0.0, 0.0, 20.0], atol=1e-9)
    np.testing.assert_allclose(col["pelvis_list"], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.stack([col["pelvis_tx"], col["pelvis_ty"], col["pelvis_tz"]], 1),
                               [[1.0, 0.9, -2.0]] * 5, atol=1e-12)
    np.testing.assert_allclose(col["left_knee_y"], math.degrees(0.5), atol=1e-9)


TINY = """
<mujoco>
  <worldbody>
    <body name="root" pos="0 0 1" quat="0.9 0.1 0.2 0.3">
      <freejoint name="free"/>
      <inertial pos="0.01 0.02 0.03" quat="0.8 0.3 -0.2 0.1" mass="5" diaginertia="0.1 0.2 0.3"/>
      <body name="a" pos="0.1 0.2 -0.3" quat="0.7 0.2 -0.5 0.1">
        <joint name="a1" type="hinge" axis="1 1 0" pos="0.05 0 0.02" ref="17"/>
        <joint name="a2" type="hinge" axis="0 0.3 1" pos="0.05 0 0.02"/>
        <inertial pos="0 0 -0.1" quat="0.5 0.5 0.5 -0.5" mass="2" diaginertia="0.01 0.02 0.03"/>
        <body name="b" pos="0 0 -0.4" euler="20 -30 45">
          <inertial pos="0 0.1 -0.1" mass="1" diaginertia="0.01 0.02 0.01"/>
        </body>
        <body name="c" pos="0.1 0 -0.2">
          <joint name="c1" type="hinge" axis="0.2 -1 0.4" range="-60 60" limited="true"/>
          <inertial pos="0 0 -0.1" mass="1" diaginertia="0.01 0.01 0.01"/>
        </body>
      </body>
    </body>
    <body name="post" pos="1 -0.5 0.2" euler="10 0 30">
      <inertial pos="0 0 0.1" mass="1" diaginertia="0.01 0.01 0.01"/>
      <body name="flap" pos="0 0.1 0.3" quat="0.9 0 0.3 0.1">
        <joint name="f1" type="hinge" axis="0 1 0.2" pos="0 0 -0.05"/>
        <inertial pos="0.1 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>
      </body>
    </body>
    <body name="swing" pos="-1 0.5 1.5" quat="0.8 0.2 0.1 -0.3">
      <joint name="s1" type="hinge" axis="1 0 0.3" pos="0.1 0 0"/>
      <inertial pos="0 0 -0.3" mass="1" diaginertia="0.01 0.01 0.01"/>
    </body>
  </worldbody>
</mujoco>"""


def test_general_mjcf_round_trip(tmp_path):
    """Rotated bodies and inertial frames, joint anchors, non-orthogonal hinge axes, a hinge
    reference angle, a rotated weld, and bodies welded or hinged to the world: OpenSim
    reproduces MuJoCo C."""
    mj = mujoco.MjModel.from_xml_string(TINY)
    model = from_mjmodel(mj, with_mjx=False)
    q = _random_q(mj, np.random.default_rng(3), T)
    paths = write_opensim(dict(q=q, fps=FPS, name="tiny"), tmp_path, model=model)
    assert set(paths) == {"model", "coordinates"}
    err, om, state = _pose_errors(paths["model"], paths["coordinates"], mj, q)
    assert max(err.values()) < 1e-8, err
    assert om.getTotalMass(state) == pytest.approx(12.0)
    assert om.getCoordinateSet().get("a1").getDefaultValue() == pytest.approx(math.radians(17))


def test_unsupported_joint(tmp_path):
    xml = TINY.replace('<joint name="c1" type="hinge"', '<joint name="c1" type="slide"')
    mj = mujoco.MjModel.from_xml_string(xml)
    model = from_mjmodel(mj, with_mjx=False)
    with pytest.raises(ValueError, match="'c1' is a slide joint"):
        write_opensim(dict(q=np.tile(mj.qpos0, (2, 1)), fps=FPS), tmp_path, model=model)
    assert not list(tmp_path.iterdir())


def test_no_forces_writes_no_grf(human, tmp_path):
    """(e) A result without force estimates (the kinematic method) writes no GRF files."""
    for extra in ({"forces_estimated": False}, {"grf": None}):
        result = {**human["result"], **extra}
        out = tmp_path / str(len(extra) + len(list(tmp_path.iterdir())))
        paths = write_opensim(result, out, name="k")
        assert set(paths) == {"model", "coordinates", "markers"}
        assert sorted(p.name for p in out.iterdir()) == ["k.osim", "k_coordinates.mot", "k_markers.trc"]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda r: r["q"].__setitem__((2, 9), np.nan), "'q'"),
        (lambda r: r.__setitem__("q", r["q"][:, :-1]), "'q'"),
        (lambda r: r.__setitem__("q", r["q"][:0]), "'q'"),
        (lambda r: r["q"].__setitem__((1, slice(3, 7)), 0.0), "'q'"),
        (lambda r: r.__setitem__("fps", 0.0), "'fps'"),
        (lambda r: r.__setitem__("fps", "thirty"), "'fps'"),
        (lambda r: r.__setitem__("grf", r["grf"][:, :3]), "'grf'"),
        (lambda r: r["grf"].__setitem__((0, 0, 0), np.inf), "'grf'"),
        (lambda r: r.__setitem__("keypoints3d", r["keypoints3d"][:-1]), "'keypoints3d'"),
        (lambda r: r.__setitem__("layout", "coco17"), "'layout'"),
        (lambda r: r.__setitem__("layout", "nonsense"), "'layout'"),
    ],
)
def test_bad_input_names_the_field(human, tmp_path, change, field):
    result = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in human["result"].items()}
    change(result)
    with pytest.raises(FormatError, match=field):
        write_opensim(result, tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_inverse_kinematics_tracks_the_trc(human, tmp_path):
    """OpenSim's InverseKinematicsTool runs on the exported model and markers (same names,
    same units and axes) and fits them to within a few millimetres."""
    om = osim.Model(str(human["paths"]["model"]))
    om.initSystem()
    ik = osim.InverseKinematicsTool()
    ik.setModel(om)
    ik.set_marker_file(str(human["paths"]["markers"]))
    ik.setStartTime(0.0)
    ik.setEndTime((T - 1) / FPS)
    ik.set_output_motion_file(str(tmp_path / "ik.mot"))
    ik.set_results_directory(str(tmp_path))  # its marker-error report goes here, not to the cwd
    assert ik.run()
    state = om.initSystem()
    solved = osim.TimeSeriesTable(str(tmp_path / "ik.mot"))
    labels = list(solved.getColumnLabels())
    kp = human["result"]["keypoints3d"] @ AXES.T
    names = get_layout("body25").joints
    worst = 0.0
    for t in range(T):
        row = solved.getRowAtIndex(t)
        for i, label in enumerate(labels):
            c = om.getCoordinateSet().get(label)
            v = row[i]
            c.setValue(state, v if c.getMotionType() == osim.Coordinate.Translational else math.radians(v), False)
        om.realizePosition(state)
        for j, n in enumerate(names):
            if np.isfinite(kp[t, j]).all():
                worst = max(worst, np.linalg.norm(_vec(om.getMarkerSet().get(n).getLocationInGround(state)) - kp[t, j]))
    assert worst < 5e-3
