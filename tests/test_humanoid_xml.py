"""Checks of the character src/jmocap/assets/mjcf/humanoid.xml against MuJoCo C (the reference).

Uses only mujoco + numpy (and jmocap.layouts for the keypoint site names).  Tolerances:
1e-9 for quantities that are sums of a few decimal numbers in float64 (mass, sole
heights), 1e-6 where the XML rounds to 6 digits (inertias written with 6 significant
figures, COMs with 1e-6 m).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
XML = ROOT / "src" / "jmocap" / "assets" / "mjcf" / "humanoid.xml"
GENERATOR = ROOT / "models" / "mjcf" / "make_humanoid.py"

try:
    from jmocap import layouts
except ImportError:  # not installed: use the source tree
    sys.path.insert(0, str(ROOT / "src"))
    from jmocap import layouts

# SMPL joint names and parents (SMPL's kintree), in SMPL's own order.
SMPL_PARENTS = {
    "pelvis": None,
    "left_hip": "pelvis",
    "right_hip": "pelvis",
    "spine1": "pelvis",
    "left_knee": "left_hip",
    "right_knee": "right_hip",
    "spine2": "spine1",
    "left_ankle": "left_knee",
    "right_ankle": "right_knee",
    "spine3": "spine2",
    "left_foot": "left_ankle",
    "right_foot": "right_ankle",
    "neck": "spine3",
    "left_collar": "spine3",
    "right_collar": "spine3",
    "head": "neck",
    "left_shoulder": "left_collar",
    "right_shoulder": "right_collar",
    "left_elbow": "left_shoulder",
    "right_elbow": "right_shoulder",
    "left_wrist": "left_elbow",
    "right_wrist": "right_elbow",
    "left_hand": "left_wrist",
    "right_hand": "right_wrist",
}

# Hinges per body, as specified for the character (41 in all).
HINGES = {
    "spine1": 3, "spine2": 0, "spine3": 3, "neck": 3, "head": 0,
    "left_hip": 3, "left_knee": 1, "left_ankle": 3, "left_foot": 1,
    "left_collar": 2, "left_shoulder": 3, "left_elbow": 1, "left_wrist": 2, "left_hand": 0,
}

MIRROR = np.array([1.0, -1.0, 1.0])
TOTAL_MASS = 73.0


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(XML))


@pytest.fixture()
def stand(model):
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, model.key("stand").id)
    mujoco.mj_forward(model, d)
    return d


def body_names(m):
    return [m.body(i).name for i in range(m.nbody)]


def hinge_ids(m):
    return [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]


def mirror_name(name: str) -> str:
    if "left_" in name:
        return name.replace("left_", "right_")
    if "right_" in name:
        return name.replace("right_", "left_")
    return name


def pose(m, d, **angles):
    """Set hinge angles (by joint name) on top of `stand` and run forward kinematics."""
    mujoco.mj_resetDataKeyframe(m, d, m.key("stand").id)
    for name, value in angles.items():
        d.qpos[m.joint(name).qposadr[0]] = value
    mujoco.mj_forward(m, d)
    return d


# ---- structure --------------------------------------------------------------------------


def test_generated_xml_is_up_to_date():
    spec = importlib.util.spec_from_file_location("make_humanoid", GENERATOR)
    gen = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = gen  # dataclasses resolve annotations through sys.modules
    try:
        spec.loader.exec_module(gen)
    finally:
        sys.modules.pop(spec.name, None)
    assert gen.generate() == XML.read_text(), "re-run models/mjcf/make_humanoid.py"


def test_compiles_with_smpl_bodies(model):
    assert model.nbody == 25  # world + 24 SMPL joints
    names = body_names(model)
    assert names[0] == "world"
    assert sorted(names[1:]) == sorted(SMPL_PARENTS)
    for name, parent in SMPL_PARENTS.items():
        pid = model.body(name).parentid[0]
        assert model.body(pid).name == (parent or "world"), name


def test_dimensions(model):
    """nq / nv / joint counts as MuJoCo compiles them, against the per-body hinge specification
    (HINGES, left side and midline; the right side mirrors the left)."""
    n_hinges = sum(n * (2 if body.startswith("left_") else 1) for body, n in HINGES.items())
    assert model.nq == 7 + n_hinges and model.nv == 6 + n_hinges
    assert model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    assert model.joint(0).name == "root" and model.body(model.jnt_bodyid[0]).name == "pelvis"
    assert len(hinge_ids(model)) == n_hinges == model.njnt - 1
    assert model.nu == 0  # torques are the controller's, not actuators'
    for body, n in HINGES.items():
        for b in {body, mirror_name(body)}:
            assert model.body(b).jntnum[0] == n, b


def test_hinges_named_and_anchored(model):
    counts = dict.fromkeys(SMPL_PARENTS, 0)
    axes = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}
    for j in hinge_ids(model):
        body = model.body(model.jnt_bodyid[j]).name
        name = model.joint(j).name
        assert name.startswith(body + "_") and name[-1] in axes, name
        np.testing.assert_array_equal(model.jnt_axis[j], axes[name[-1]])
        np.testing.assert_array_equal(model.jnt_pos[j], 0.0)  # anchored at the body origin
        counts[body] += 1
    for body, n in HINGES.items():
        assert counts[body] == n, body
        assert counts[mirror_name(body)] == n, body
    assert model.joint("left_knee_y") and model.joint("left_foot_y")
    # body frames aligned with the world at rest, inertia diagonal in those axes
    np.testing.assert_array_equal(model.body_quat[1:], np.tile([1.0, 0, 0, 0], (24, 1)))
    np.testing.assert_array_equal(model.body_iquat[1:], np.tile([1.0, 0, 0, 0], (24, 1)))


def test_armature_on_the_hinges_only_and_no_passive_forces(model):
    """What MuJoCo compiles from the hinge default class: the armature is added to the diagonal
    of the joint-space inertia at every hinge DoF and nowhere else (the root freejoint ignores
    defaults), the same on every hinge; no damping, springs or other passive forces."""
    rng = np.random.default_rng(1)
    bare = mujoco.MjModel.from_xml_path(str(XML))
    bare.dof_armature[:] = 0.0
    d, d0 = mujoco.MjData(model), mujoco.MjData(bare)
    for data, m in ((d, model), (d0, bare)):
        mujoco.mj_resetDataKeyframe(m, data, m.key("stand").id)
        data.qpos[7:] = rng.uniform(-0.3, 0.3, model.nq - 7) if m is model else d.qpos[7:]
        data.qvel[:] = rng.normal(size=model.nv) if m is model else d.qvel
        mujoco.mj_forward(m, data)
    M, M0 = np.zeros((2, model.nv, model.nv))
    mujoco.mj_fullM(model, d, M)
    mujoco.mj_fullM(bare, d0, M0)
    added = M - M0
    np.testing.assert_allclose(added, np.diag(np.diag(added)), atol=1e-15)
    arm = np.diag(added)
    np.testing.assert_array_equal(arm[:6], 0.0)
    assert np.all(arm[6:] > 0) and np.ptp(arm[6:]) < 1e-15
    # no passive force at a random velocity
    np.testing.assert_array_equal(d.qfrc_passive, 0.0)


def test_option(model):
    """The conventions of docs/DESIGN: z up, gravity -9.81 z (the body weight mass * 9.81 the
    code divides forces by), and the 100 Hz step the dynamic cycle integrates with."""
    assert model.opt.timestep == 0.01
    np.testing.assert_array_equal(model.opt.gravity, [0, 0, -9.81])


def test_friction_model_is_the_one_named_in_constants(model):
    """One friction model (jmocap.constants): every collision geom's sliding friction is
    FRICTION_MU and the cone is MuJoCo's pyramidal one, which the estimators linearise alike."""
    from jmocap.constants import FRICTION_CONE, FRICTION_MU

    assert FRICTION_CONE == "pyramidal"
    assert model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    np.testing.assert_allclose(model.geom_friction[colliding, 0], FRICTION_MU)


# ---- mass properties --------------------------------------------------------------------


def test_inertia_positive_and_triangle(model):
    for b in range(1, model.nbody):
        i = model.body_inertia[b]
        assert np.all(i > 0), model.body(b).name
        for k in range(3):
            assert i[k] <= i[(k + 1) % 3] + i[(k + 2) % 3], (model.body(b).name, i)


# de Leva (1996) Table 4, male: mass %, COM % from the first landmark, radii % (about the
# world x, y, z axes at rest, already permuted for the segment's orientation), and this
# model's segment (bodies, first landmark, second landmark in world coordinates at rest).
DE_LEVA = {
    "head+neck": (6.94, 50.02, (30.3, 31.5, 26.1), ("neck", "head"), (0, 0, 1.75), (0, 0, 1.51)),
    "upper trunk": (15.96, 29.99, (71.6, 45.4, 65.9), ("spine3", "left_collar", "right_collar"),
                    (0, 0, 1.44), (0, 0, 1.273)),
    "middle trunk": (16.33, 45.02, (48.2, 38.3, 46.8), ("spine1", "spine2"), (0, 0, 1.273), (0, 0, 1.062)),
    "lower trunk": (11.17, 61.15, (61.5, 55.1, 58.7), ("pelvis",), (0, 0, 1.062), (0, 0, 0.92)),
    "thigh": (14.16, 40.95, (32.9, 32.9, 14.9), ("left_hip",), (0, 0.085, 0.92), (0, 0.085, 0.50)),
    "shank": (4.33, 44.59, (25.5, 24.9, 10.3), ("left_knee",), (0, 0.085, 0.50), (0, 0.085, 0.07)),
    # foot: long axis x (heel to toe tip), sagittal radius about z
    "foot": (1.37, 44.15, (12.4, 24.5, 25.7), ("left_ankle", "left_foot"),
             (-0.05, 0.085, 0.025), (0.21, 0.085, 0.025)),
    # upper arm abducted: long axis y, transverse radius about z
    "upper arm": (2.71, 57.72, (28.5, 15.8, 26.9), ("left_shoulder",), (0, 0.18, 1.42), (0, 0.463, 1.42)),
    # forearm and hand palms down: sagittal radius about z, transverse about x
    "forearm": (1.62, 45.74, (26.5, 12.1, 27.6), ("left_elbow",), (0, 0.463, 1.42), (0, 0.733, 1.42)),
    "hand": (0.61, 36.24, (23.5, 18.4, 28.8), ("left_wrist", "left_hand"), (0, 0.733, 1.42), (0, 0.922, 1.42)),
}


def test_de_leva_segments_cover_every_body_once(model):
    """Every body carries exactly one de Leva segment (the bilateral ones mirrored) and the
    segments' mass fractions sum to 100 %: with test_de_leva_segments_reproduced (each segment
    has TOTAL_MASS * its fraction), MuJoCo's compiled total mass is the subject's."""
    owner, total_pct = {}, 0.0
    for segment, (pct, _, _, bodies, _, _) in DE_LEVA.items():
        sides = [bodies]
        if all(b.startswith("left_") for b in bodies):
            sides.append(tuple(mirror_name(b) for b in bodies))
        for side in sides:
            total_pct += pct
            for b in side:
                assert b not in owner, (b, segment, owner.get(b))
                owner[b] = segment
    assert sorted(owner) == sorted(body_names(model)[1:])
    assert abs(total_pct - 100.0) < 1e-9
    assert abs(model.body_subtreemass[0] - TOTAL_MASS) < 1e-9
    assert np.all(model.body_mass[1:] > 0)


@pytest.mark.parametrize("segment", sorted(DE_LEVA))
def test_de_leva_segments_reproduced(model, stand, segment):
    """Bodies carrying one de Leva segment together have its mass, COM and central inertia."""
    pct, com_pct, radii, bodies, a, b = DE_LEVA[segment]
    a, b = np.array(a), np.array(b)
    ids = [model.body(n).id for n in bodies]
    masses = model.body_mass[ids]
    coms = stand.xipos[ids]
    mass = masses.sum()
    assert abs(mass - TOTAL_MASS * pct / 100) < 1e-9
    com = masses @ coms / mass
    expected_com = a + com_pct / 100 * (b - a)
    np.testing.assert_allclose(com, expected_com, atol=2e-6)
    length = np.linalg.norm(b - a)
    inertia = np.zeros((3, 3))
    for i, m_i, c_i in zip(ids, masses, coms, strict=True):
        dvec = c_i - com
        inertia += np.diag(model.body_inertia[i]) + m_i * (dvec @ dvec * np.eye(3) - np.outer(dvec, dvec))
    expected = np.diag([mass * (r / 100 * length) ** 2 for r in radii])
    np.testing.assert_allclose(inertia, expected, rtol=1e-5, atol=1e-9)


# ---- joint limits -----------------------------------------------------------------------


def test_every_hinge_limited_with_zero_inside(model):
    for j in hinge_ids(model):
        lo, hi = model.jnt_range[j]
        assert model.jnt_limited[j], model.joint(j).name
        assert lo <= 0.0 <= hi and lo < hi, model.joint(j).name


# AAOS (1965) normal ranges of motion (degrees; as tabulated in Norkin & White, "Measurement of
# Joint Motion"), for movements that are a rotation about one hinge axis at the T-pose.  Each
# movement is identified by its effect, found by forward kinematics: a point (body origin or
# site) of the left side moving along a world axis (0 x forward, 1 y left, 2 z up) in the
# given direction; the right side is checked with the y direction mirrored.
AAOS_1965 = {
    "hip flexion": ("left_hip_y", "left_knee", 0, +1, 120),
    "hip extension": ("left_hip_y", "left_knee", 0, -1, 30),
    "hip abduction": ("left_hip_x", "left_knee", 1, +1, 45),
    "hip adduction": ("left_hip_x", "left_knee", 1, -1, 30),
    "hip internal rotation": ("left_hip_z", "left_foot", 1, -1, 45),  # toes turn in
    "hip external rotation": ("left_hip_z", "left_foot", 1, +1, 45),
    "knee flexion": ("left_knee_y", "left_ankle", 0, -1, 135),
    "knee extension": ("left_knee_y", "left_ankle", 0, +1, 0),
    "ankle dorsiflexion": ("left_ankle_y", "left_foot", 2, +1, 20),
    "ankle plantarflexion": ("left_ankle_y", "left_foot", 2, -1, 50),
    "ankle eversion": ("left_ankle_x", "kp_left_small_toe", 2, +1, 15),  # lateral edge up
    "ankle inversion": ("left_ankle_x", "kp_left_small_toe", 2, -1, 35),
    "elbow flexion": ("left_elbow_z", "left_wrist", 0, +1, 150),  # palms down: forearm forward
    "wrist flexion": ("left_wrist_x", "left_hand", 2, -1, 80),  # palms down: fingers down
    "wrist extension": ("left_wrist_x", "left_hand", 2, +1, 70),
    "wrist radial deviation": ("left_wrist_z", "left_hand", 0, +1, 20),  # thumb side: forward
    "wrist ulnar deviation": ("left_wrist_z", "left_hand", 0, -1, 30),
}
AAOS_TOL = np.radians(0.01)  # the XML writes radians with 4 decimals


def point_position(m, d, name):
    try:
        return d.site(name).xpos.copy()
    except KeyError:
        return d.body(name).xpos.copy()


@pytest.mark.parametrize("movement", sorted(AAOS_1965))
def test_ranges_are_aaos_normal_motion(model, movement):
    """The range limit on the side that produces the movement is the AAOS normal value, on both
    sides of the body; this checks the limits and their signs against anatomy, not the XML."""
    joint, point, axis, direction, degrees = AAOS_1965[movement]
    d = mujoco.MjData(model)
    for side in ("left", "right"):
        j = joint if side == "left" else mirror_name(joint)
        p = point if side == "left" else mirror_name(point)
        want = direction * (-1 if (side == "right" and axis == 1) else 1)
        rest = point_position(model, pose(model, d), p)
        moved = point_position(model, pose(model, d, **{j: 0.05}), p) - rest
        assert abs(moved[axis]) > 1e-3, (j, p)  # the probe moves along the axis
        lo, hi = model.joint(j).range
        limit = hi if np.sign(moved[axis]) == want else -lo
        assert abs(limit - np.radians(degrees)) <= AAOS_TOL, (side, movement, np.degrees(limit))


def test_ranges_mirror(model):
    for j in hinge_ids(model):
        name = model.joint(j).name
        if not name.startswith("left_"):
            continue
        lo, hi = model.jnt_range[j]
        rlo, rhi = model.joint(mirror_name(name)).range
        if name.endswith("_y"):
            assert (rlo, rhi) == (lo, hi), name
        else:  # the mirror image of a rotation about x or z by a is one by -a
            assert (rlo, rhi) == (-hi, -lo), name


# ---- standing pose ----------------------------------------------------------------------


def test_stand_keyframe_is_rest_pose(model):
    key = model.key("stand")
    np.testing.assert_array_equal(key.qpos[3:7], [1, 0, 0, 0])
    np.testing.assert_array_equal(key.qpos[7:], 0.0)
    np.testing.assert_array_equal(key.qpos, model.qpos0)


def test_contact_sites_on_the_floor(model, stand):
    assert layouts.CONTACT_SITES == (
        "contact_left_heel", "contact_left_toe", "contact_right_heel", "contact_right_toe")
    for name in layouts.CONTACT_SITES:
        assert abs(stand.site(name).xpos[2]) < 1e-9, name
    assert model.body(model.site("contact_left_heel").bodyid[0]).name == "left_ankle"
    assert model.body(model.site("contact_left_toe").bodyid[0]).name == "left_foot"
    assert model.body(model.site("contact_right_heel").bodyid[0]).name == "right_ankle"
    assert model.body(model.site("contact_right_toe").bodyid[0]).name == "right_foot"
    # heel behind the ankle, toe ahead of the ball of the foot
    assert stand.site("contact_left_heel").xpos[0] < stand.body("left_ankle").xpos[0]
    assert stand.site("contact_left_toe").xpos[0] > stand.body("left_foot").xpos[0]


def geom_lowest_z(m, d, g):
    t = m.geom_type[g]
    pos, mat, size = d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3), m.geom_size[g]
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        return pos[2] - np.abs(mat[2]) @ size
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return pos[2] - abs(mat[2, 2]) * size[1] - size[0]
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return pos[2] - size[0]
    raise AssertionError(f"unexpected geom type {t}")


def test_no_geom_below_floor(model, stand):
    floor = model.geom("floor").id
    assert model.geom_type[floor] == mujoco.mjtGeom.mjGEOM_PLANE
    assert model.geom_bodyid[floor] == 0 and stand.geom_xpos[floor][2] == 0.0
    lowest = {}
    for g in range(model.ngeom):
        if g == floor:
            continue
        z = geom_lowest_z(model, stand, g)
        # cross-check against MuJoCo's own (local) bounding box
        aabb = model.geom_aabb[g]
        mat = stand.geom_xmat[g].reshape(3, 3)
        z_aabb = (stand.geom_xpos[g] + mat @ aabb[:3])[2] - np.abs(mat[2]) @ aabb[3:]
        assert abs(z - z_aabb) < 1e-9
        assert z >= -1e-9, model.geom(g).name
        lowest[model.body(model.geom_bodyid[g]).name] = z
    # the feet boxes stand exactly on the floor
    for body in ("left_ankle", "left_foot", "right_ankle", "right_foot"):
        assert abs(lowest[body]) < 1e-9, body
        assert model.geom_type[model.body(body).geomadr[0]] == mujoco.mjtGeom.mjGEOM_BOX


def test_collisions_only_with_floor(model):
    floor = model.geom("floor").id
    for g in range(model.ngeom):
        for h in range(g + 1, model.ngeom):
            collide = (model.geom_contype[g] & model.geom_conaffinity[h]) or (
                model.geom_contype[h] & model.geom_conaffinity[g])
            assert bool(collide) == (floor in (g, h)), (model.geom(g).name, model.geom(h).name)


def test_height(model, stand):
    assert abs(stand.site("kp_head_top").xpos[2] - 1.75) < 1e-6
    assert model.body(model.site("kp_head_top").bodyid[0]).name == "head"
    head_geom = model.body("head").geomadr[0]
    top = stand.geom_xpos[head_geom][2] + model.geom_size[head_geom][1] + model.geom_size[head_geom][0]
    assert abs(top - 1.75) < 1e-9


# ---- sites ------------------------------------------------------------------------------


def test_layout_sites_exist(model):
    sites = {model.site(i).name for i in range(model.nsite)}
    for layout in layouts.LAYOUTS.values():
        missing = {s for s in layout.sites if s} - sites  # "": a joint the character has no site for
        assert not missing, (layout.name, missing)
        assert layout.sited == all(layout.sites) and (layout.sited or layout.name == "blazepose33"), layout.name
    for name in layouts.all_keypoint_sites():
        assert model.site(name).group[0] == 3, name
    for name in layouts.CONTACT_SITES:
        assert model.site(name).group[0] == 4, name
    assert np.all(model.site_size[:, 0] <= 0.02)


SITE_BODIES = {
    "kp_nose": "head", "kp_left_eye": "head", "kp_left_ear": "head", "kp_head_top": "head",
    "kp_neck": "spine3", "kp_thorax": "spine3", "kp_spine": "spine1", "kp_mid_hip": "pelvis",
    "kp_left_shoulder": "left_shoulder", "kp_left_elbow": "left_elbow",
    "kp_left_wrist": "left_wrist", "kp_left_hip": "left_hip", "kp_left_knee": "left_knee",
    "kp_left_ankle": "left_ankle", "kp_left_heel": "left_ankle",
    "kp_left_big_toe": "left_foot", "kp_left_small_toe": "left_foot",
}


def test_sites_on_anatomical_bodies(model, stand):
    for site, body in SITE_BODIES.items():
        for s, b in ((site, body), (mirror_name(site), mirror_name(body))):
            assert model.body(model.site(s).bodyid[0]).name == b, s
    # joint keypoints sit at their joint centre (the body origin)
    for joint in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle"):
        np.testing.assert_array_equal(model.site(f"kp_left_{joint}").pos, 0.0)
    # OpenPose neck between the shoulders, mid-hip between the hips
    np.testing.assert_allclose(
        stand.site("kp_neck").xpos,
        (stand.site("kp_left_shoulder").xpos + stand.site("kp_right_shoulder").xpos) / 2, atol=1e-12)
    np.testing.assert_allclose(
        stand.site("kp_mid_hip").xpos,
        (stand.site("kp_left_hip").xpos + stand.site("kp_right_hip").xpos) / 2, atol=1e-12)
    # heel keypoint at the back of the heel, a bit above the sole; toes ahead of the ball
    heel = stand.site("kp_left_heel").xpos
    assert heel[0] < stand.site("contact_left_heel").xpos[0] and 0 < heel[2] < 0.05
    assert stand.site("kp_left_big_toe").xpos[0] > stand.site("kp_left_small_toe").xpos[0]
    assert stand.site("kp_left_big_toe").xpos[1] < stand.site("kp_left_small_toe").xpos[1]
    # face forward (+x)
    for s in ("kp_nose", "kp_left_eye"):
        assert stand.site(s).xpos[0] > 0.05


# ---- symmetry ---------------------------------------------------------------------------


def test_left_right_symmetry(model, stand):
    for b in range(1, model.nbody):
        name = model.body(b).name
        other = model.body(mirror_name(name)).id
        np.testing.assert_array_equal(stand.xpos[b], stand.xpos[other] * MIRROR, err_msg=name)
        np.testing.assert_array_equal(stand.xipos[b], stand.xipos[other] * MIRROR, err_msg=name)
        assert model.body_mass[b] == model.body_mass[other], name
        np.testing.assert_array_equal(model.body_inertia[b], model.body_inertia[other], err_msg=name)
    for s in range(model.nsite):
        name = model.site(s).name
        other = model.site(mirror_name(name)).id
        np.testing.assert_array_equal(stand.site_xpos[s], stand.site_xpos[other] * MIRROR, err_msg=name)
    for g in range(model.ngeom):
        name = model.geom(g).name
        other = model.geom(mirror_name(name)).id
        np.testing.assert_array_equal(stand.geom_xpos[g], stand.geom_xpos[other] * MIRROR, err_msg=name)
        np.testing.assert_array_equal(model.geom_size[g], model.geom_size[other], err_msg=name)


def test_mirrored_poses_are_mirror_images(model):
    """A left pose (x, y, z angles) mirrors to the right pose (-x, y, -z)."""
    rng = np.random.default_rng(0)
    d1, d2 = mujoco.MjData(model), mujoco.MjData(model)
    angles = {}
    for j in hinge_ids(model):
        lo, hi = model.jnt_range[j]
        angles[model.joint(j).name] = rng.uniform(lo, hi)
    mirrored = {}
    for name, a in angles.items():
        sign = 1.0 if name.endswith("_y") else -1.0
        mirrored[mirror_name(name)] = sign * a
    pose(model, d1, **angles)
    pose(model, d2, **mirrored)
    for s in range(model.nsite):
        other = model.site(mirror_name(model.site(s).name)).id
        np.testing.assert_allclose(d1.site_xpos[s], d2.site_xpos[other] * MIRROR, atol=1e-12)


# ---- sign conventions documented in the XML ---------------------------------------------


def test_positive_directions(model):
    d = mujoco.MjData(model)
    pose(model, d)
    rest = {model.site(i).name: d.site_xpos[i].copy() for i in range(model.nsite)}

    def moved(site, **angles):
        return pose(model, d, **angles).site(site).xpos - rest[site]

    assert moved("kp_left_ankle", left_knee_y=1.0)[0] < -0.1  # knee flexion: shank backward
    assert moved("kp_left_knee", left_hip_y=-1.0)[0] > 0.1  # hip flexion is negative
    assert moved("kp_left_knee", left_hip_x=0.5)[1] > 0.05  # left hip +x: abduction
    assert moved("kp_left_big_toe", left_ankle_y=0.5)[2] < -0.02  # ankle +y: plantarflexion
    assert moved("kp_left_big_toe", left_foot_y=0.5)[2] < -0.01  # toes +y: flexion (down)
    assert moved("kp_left_big_toe", left_ankle_z=0.5)[1] > 0.05  # left ankle +z: toes outward
    assert moved("kp_left_small_toe", left_ankle_x=0.3)[2] > 0.005  # left ankle +x: eversion
    assert moved("kp_left_wrist", left_elbow_z=-1.0)[0] > 0.1  # elbow flexion: forearm forward
    assert moved("kp_right_wrist", right_elbow_z=1.0)[0] > 0.1
    assert moved("kp_nose", spine1_y=0.5)[0] > 0.1  # trunk flexion forward
    assert moved("kp_nose", spine3_x=0.3)[1] < -0.05  # +x: right lateral bending
    assert moved("kp_nose", neck_z=0.5)[1] > 0.03  # +z: turn to the left
    assert moved("kp_left_shoulder", left_collar_x=0.5)[2] > 0.05  # collar +x: elevation
    assert moved("kp_left_shoulder", left_collar_z=0.3)[0] < -0.02  # collar +z: retraction
    # arms down at the sides
    down = pose(model, d, left_shoulder_x=-np.pi / 2)
    np.testing.assert_allclose(
        down.site("kp_left_elbow").xpos - down.site("kp_left_shoulder").xpos, [0, 0, -0.283], atol=1e-12)
    assert moved("kp_left_elbow", left_shoulder_z=-1.0)[0] > 0.1  # -z: horizontal flexion
    # shoulder +y (internal rotation): with the elbow flexed forward, the forearm goes down
    assert moved("kp_left_wrist", left_elbow_z=-np.pi / 2, left_shoulder_y=0.5)[2] < -0.1


# ---- MuJoCo C simulation ----------------------------------------------------------------


def test_passive_simulation_stays_finite(model):
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, model.key("stand").id)
    for _ in range(100):
        mujoco.mj_step(model, d)
    assert np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))
    assert d.qpos[2] > 0.0  # the pelvis has not gone through the floor
    assert np.all(d.contact.dist > -0.05)
