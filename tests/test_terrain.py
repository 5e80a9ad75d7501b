"""Synthetic terrain clips (issue 21, item 1): walks up and down steps, stairs and blocks.

References: the scene's signed distance (``jmocap.scene.sdf``, tested against MuJoCo's own
geometry distance in test_scene.py) for "no body point inside the terrain", MuJoCo C kinematics
(``site_trajectories``) for the body, and the boxes' own tops for the heights the feet stand
at. The physics variant on terrain (Newton's law, labels, CoP on the surface) is tested with the
other simulated clips in test_synthetic_physics.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import x64
from jmocap import cli
from jmocap.data import synthetic as S
from jmocap.data.archive import iter_clips
from jmocap.data.synthetic.terrain import TERRAIN_KINDS, place_terrain
from jmocap.scene import boxes, height_above, sdf


def _motion(kind: str, tries: int = 12):
    """The first terrain motion of kind ``kind`` that its footsteps allow (seeded draws)."""
    for i in range(tries):
        rng = np.random.default_rng([7, i])
        try:
            return S.generate_motion(1.75, rng, 7.0, 30.0, ("walk",), terrain=kind)
        except S.GenerationError:
            continue
    raise AssertionError(f"no {kind} motion in {tries} draws")


@pytest.fixture(scope="module", params=TERRAIN_KINDS)
def motion(request):
    return request.param, _motion(request.param)


def test_feet_stand_on_the_terrain_and_nothing_enters_it(motion):
    """Every planted contact site is on a surface (the floor or a box top, 0.1 mm), some of them
    on a box; no body point (keypoint and contact sites) is inside the floor or a box."""
    kind, m = motion
    ch = m.character
    sites = S.site_trajectories(ch, m.q, ch.check_sites)
    contact = sites[:, -4:]
    tops = np.array([c[2] + h[2] for c, h, _ in boxes(m.scene)])
    planted_h = height_above(m.scene, contact)[m.planted]
    z = contact[..., 2][m.planted]
    # a planted site is at the plan's sole height above its surface (the same as on flat floor)
    flat = S.generate_motion(1.75, np.random.default_rng([7, 0]), 4.0, 30.0, ("walk",))
    flat_h = S.site_trajectories(flat.character, flat.q, flat.character.contact_sites)[..., 2][flat.planted]
    assert np.ptp(planted_h) < 0.03 and abs(np.median(planted_h) - np.median(flat_h)) < 1e-3
    on_box = np.min(np.abs((z - planted_h)[:, None] - tops[None]), axis=1) < 1e-6
    assert on_box.any() and (~on_box).any()  # every terrain kind has footsteps on the floor and on a box
    with x64():
        d = np.asarray(jax.jit(sdf)(jax.tree.map(jnp.asarray, m.scene), jnp.asarray(sites)))
    assert d.min() > -1e-6, d.min()


def test_the_body_rises_and_falls_with_the_terrain(motion):
    """The pelvis ends higher than it starts by the terrain's height change under the feet
    (within 3 cm: the standing poses of the two ends differ a little)."""
    kind, m = motion
    ch = m.character
    contact = S.site_trajectories(ch, m.q, ch.contact_sites)
    ground = contact[..., 2] - height_above(m.scene, contact)  # the surface under each site
    change = ground[-1].mean() - ground[0].mean()
    rise = m.q[-10:, 2].mean() - m.q[:10, 2].mean()
    assert abs(rise - change) < 0.03, (kind, rise, change)
    expect = {"step_up": 1, "stairs_up": 1, "step_down": -1, "stairs_down": -1, "block": 0}[kind]
    assert np.sign(round(change, 3)) == expect


def test_a_footstep_that_the_boxes_cannot_separate_is_refused():
    """Two footsteps at one place on different levels cannot be made: the plan is refused."""
    ch = S.character(1.75)
    plan = S.Plan(ch, np.random.default_rng(0), {"z_rest_drop": 0.0, "alpha": 0.3})
    G = np.array([0.0, 0.1, 0.0])
    plan.start([G, G + [0.0, -0.2, 0.0]], 0.0, 0.3)
    for k in range(4):  # stepping on the spot
        plan.step(k % 2, plan.stance(k % 2).G, 1.0 + k, 1.4 + k)
    with pytest.raises(S.GenerationError, match="would cover a footstep"):
        place_terrain(plan, np.random.default_rng([0, 1]), "step_up")


def test_terrain_clips_are_deterministic_and_carry_their_scene(tmp_path):
    """``jmocap data synth --terrain`` writes clips with their scene; the same seed gives the
    same clip; the labels' heights are above the terrain (some contacts on a box)."""
    out = tmp_path / "terrain"
    rc = cli.main(["data", "synth", "--out", str(out), "--clips", "2", "--seed", "3", "--frames-per-clip", "90",
                   "--terrain", "step_up,stairs_down", "--quiet"])
    assert rc == 0
    clips = list(iter_clips(out))
    assert len(clips) == 2
    cfg = S.SynthConfig(frames=90, terrain=("step_up", "stairs_down"))
    for c in clips:
        assert c.scene is not None and c.meta["terrain"] in ("step_up", "stairs_down")
        again = S.generate_clip(3, c.meta["index"], cfg)
        np.testing.assert_array_equal(np.asarray(again.scene.centers), np.asarray(c.scene.centers, np.float64))
        np.testing.assert_allclose(again.gt_q, c.gt_q, atol=1e-6)
    for c in clips:  # the geometric labels measure heights above the terrain: some contacts are on a box
        ch = S.character(round(c.height_m, 2))
        pts = S.site_trajectories(ch, c.gt_q.astype(np.float64), ch.contact_sites)[c.gt_contacts > 0]
        assert len(pts) and np.all(height_above(c.scene, pts) < 0.05 + 1e-5)
        assert np.any(pts[:, 2] > 0.05)


def test_terrain_options_are_checked():
    with pytest.raises(ValueError, match="unknown terrain"):
        S.SynthConfig(terrain=("ramp",))
    with pytest.raises(ValueError, match="QP tracker"):
        S.SynthConfig(terrain=("step_up",), physics=True, physics_cfg=S.PhysicsConfig(controller="sampling"))
    assert cli.build_parser().parse_args(["data", "synth", "--out", "x", "--clips", "1", "--terrain"]).terrain == TERRAIN_KINDS
