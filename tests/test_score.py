"""Scoring against ground truth with any subset of named joints: the per-joint masks of
jmocap.metrics (against the same metric on an explicitly selected subset, and hand-computed
means), the ground-truth joint files (npz, JSON, y-up, offsets), and ``jmocap score``."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jmocap import metrics as M
from jmocap.cli import main
from jmocap.data.clip import FormatError
from jmocap.layouts import get_layout
from jmocap.results import load_result, write_result
from jmocap.score import load_ground_truth, score_result

DEMO = Path(__file__).resolve().parents[1] / "src/jmocap/assets/demo/ground_truth/demo_walk.npz"


def _pose_pair(T=12, J=10, seed=0):
    rng = np.random.default_rng(seed)
    gt = rng.normal(size=(T, J, 3)) * 0.3 + [0.0, 0.0, 1.0]
    pred = gt + rng.normal(size=(T, J, 3)) * 0.03
    return pred.astype(np.float32), gt.astype(np.float32)


def test_per_joint_mask_of_a_fixed_subset_is_the_subset():
    pred, gt = _pose_pair()
    keep = np.array([0, 2, 3, 5, 7, 8])
    mask = np.zeros(gt.shape[:2], bool)
    mask[:, keep] = True
    gt_nan = gt.copy()
    gt_nan[:, ~np.isin(np.arange(gt.shape[1]), keep)] = np.nan  # what is masked may be anything
    gz = np.nan_to_num(gt_nan)
    P, S = pred[:, keep], gt[:, keep]
    root_sub = (1,)  # joint 2 of the full set is joint 1 of the subset
    np.testing.assert_allclose(M.mpjpe(pred, gz, mask, root=(2,)), M.mpjpe(P, S, root=root_sub), rtol=1e-5)
    np.testing.assert_allclose(M.pa_mpjpe(pred, gz, mask), M.pa_mpjpe(P, S), rtol=1e-4)
    np.testing.assert_allclose(M.mpjpe(pred, gz, mask, align="none"), M.mpjpe(P, S, align="none"), rtol=1e-5)
    np.testing.assert_allclose(M.root_translation_error(pred, gz, mask, root=(2, 5)),
                               M.root_translation_error(P, S, root=(1, 3)), rtol=1e-5)
    np.testing.assert_allclose(M.acceleration_error(pred, gz, 30.0, mask), M.acceleration_error(P, S, 30.0),
                               rtol=1e-5)
    for a, b in zip(M.smoothness_error(pred, gz, mask), M.smoothness_error(P, S), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5)


def test_per_joint_mask_hand_computed():
    """Missing joints in some frames: the mean runs over the (frame, joint) pairs present; a
    root-aligned frame counts only where its root is present; a second difference only where
    its three frames have the joint."""
    pred, gt = _pose_pair(T=8, J=4, seed=2)
    mask = np.ones((8, 4), bool)
    mask[2, 1] = mask[5, 3] = mask[6, 0] = False
    err = np.linalg.norm(pred.astype(float) - gt, axis=-1) * 1000
    np.testing.assert_allclose(M.mpjpe(pred, gt, mask, align="none"), err[mask].mean(), rtol=1e-5)
    rel = np.linalg.norm((pred - pred[:, :1]) - (gt - gt[:, :1]), axis=-1) * 1000
    m_root = mask & mask[:, :1]  # frame 6 has no root: it does not count
    np.testing.assert_allclose(M.mpjpe(pred, gt, mask, root=(0,)), rel[m_root].mean(), rtol=1e-5)
    acc = np.linalg.norm((pred[2:] - 2 * pred[1:-1] + pred[:-2]) - (gt[2:] - 2 * gt[1:-1] + gt[:-2]),
                         axis=-1) * 900.0
    m_acc = mask[2:] & mask[1:-1] & mask[:-2]
    np.testing.assert_allclose(M.acceleration_error(pred, gt, 30.0, mask), acc[m_acc].mean(), rtol=1e-4)


def test_weighted_procrustes_fits_the_present_joints():
    """A similarity transform of the present joints, with the absent ones garbage, is undone
    exactly: PA-MPJPE 0 on the present joints."""
    rng = np.random.default_rng(4)
    gt = rng.normal(size=(3, 9, 3))
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    pred = 1.3 * gt @ R.T + [0.2, -0.1, 0.5]
    mask = np.ones((3, 9), bool)
    mask[:, [1, 4]] = False
    pred[:, [1, 4]] = 50.0  # far-off joints that must not pull the fit
    assert float(M.pa_mpjpe(jnp.asarray(pred), jnp.asarray(gt), mask)) < 1e-2


def _result_file(path: Path, frames=30) -> dict:
    with np.load(DEMO) as z:
        arrays = {
            "format": np.array("jmocap-result-1"), "name": np.array(path.stem), "method": np.array("pip"),
            "q": z["gt_q"][:frames].astype(np.float32), "fps": np.array(float(z["fps"])),
            "height_m": np.array(float(z["height_m"])), "mass_kg": np.array(float(z["mass_kg"])),
            "keypoints3d": z["gt_keypoints3d"][:frames].astype(np.float32), "layout": np.array("body25"),
            "forces_estimated": np.array(False), "assumed": np.array("[]"),
        }
        gt = z["gt_keypoints3d"][:frames].astype(np.float64)
    write_result(path, arrays)
    return {"gt": gt, "fps": float(arrays["fps"])}


def test_score_a_subset_ground_truth_in_a_y_up_world(tmp_path):
    """16 named joints of the truth, given in a y-up world with the floor at 0.9 and starting at
    result frame 4, a marker lost for a while, and the result 2 cm off in x: scores as expected."""
    info = _result_file(tmp_path / "walk.npz")
    r = load_result(tmp_path / "walk.npz")
    names = list(get_layout("body25").joints)
    use = [n for n in names if n not in ("Nose", "REye", "LEye", "REar", "LEar", "LSmallToe", "RSmallToe",
                                          "LHeel", "RHeel")][:16]
    idx = [names.index(n) for n in use]
    true = info["gt"][4:, idx] - [0.02, 0.0, 0.0]  # the result is 2 cm off along x
    true[5:9, 3] = np.nan  # a lost marker
    y_up = (true + [0.0, 0.0, 0.9]) @ np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]).T  # (x, z, -y)
    gt_file = tmp_path / "gt" / "walk.json"
    gt_file.parent.mkdir()
    gt_file.write_text(json.dumps({"format": "jmocap-gt-joints-1", "joint_names": use, "fps": info["fps"],
                                   "world_up": "y", "floor_height": 0.9, "frame_offset": 4,
                                   "joints3d": [[[None if np.isnan(v) else float(v) for v in p] for p in f]
                                                for f in y_up]}))
    gt = load_ground_truth(gt_file)
    np.testing.assert_allclose(gt["joints3d"], true, atol=1e-9)
    s = score_result(r, gt)
    assert s["joints"] == 16 and s["frames"] == 26
    assert s["mpjpe_abs_mm"] == pytest.approx(20.0, abs=0.05)
    assert s["root_err_mm"] == pytest.approx(20.0, abs=0.05)
    assert s["mpjpe_mm"] < 0.05 and s["pa_mpjpe_mm"] < 0.05 and s["accel_err_m_s2"] < 1e-3
    # the command: a folder of results, a folder of truths; a result without truth is reported
    _result_file(tmp_path / "other.npz")
    out = tmp_path / "scores"
    assert main(["score", str(tmp_path), str(tmp_path / "gt"), "--out", str(out)]) == 1
    rows = json.loads((out / "scores.json").read_text())
    assert set(rows) == {"walk"} and rows["walk"]["mpjpe_abs_mm"] == pytest.approx(20.0, abs=0.05)
    assert "| walk |" in (out / "scores.md").read_text()


def test_a_clip_with_3d_ground_truth_scores_its_own_result(tmp_path):
    _result_file(tmp_path / "demo_walk.npz", frames=120)
    s = score_result(load_result(tmp_path / "demo_walk.npz"), load_ground_truth(DEMO))
    assert s["mpjpe_abs_mm"] < 1e-3 and s["joints"] == 25
    # the result's feet (the simulated ground truth's): on the floor, never 3 cm under it
    assert s["pnp_pct"] > 90 and s["penetrate_pct"] == 0


@pytest.mark.parametrize("data, words", [
    ({"joint_names": ["RKnee"], "joints3d": [[[0, 0, 1]]] * 5, "fps": 30, "up": "y"}, "field 'up': unknown key"),
    ({"joint_names": ["RKnee"], "fps": 30}, "field 'joints3d': missing"),
    ({"joint_names": ["RKnee", "LKnee"], "joints3d": [[[0, 0, 1]]] * 5, "fps": 30}, "field 'joints3d' must be"),
    ({"joint_names": ["RKnee"], "joints3d": [[[0, 0, 1]]] * 5, "fps": 0}, "field 'fps'"),
    ({"joint_names": ["RKnee"], "joints3d": [[[0, 0, 1]]] * 5, "fps": 30, "world_up": "x"}, "world_up"),
])
def test_bad_ground_truth_files_name_the_field(tmp_path, data, words):
    p = tmp_path / "gt.json"
    p.write_text(json.dumps(data))
    with pytest.raises(FormatError, match=words):
        load_ground_truth(p)


def test_joints_the_layout_does_not_have_and_other_fps_are_errors(tmp_path):
    _result_file(tmp_path / "walk.npz")
    r = load_result(tmp_path / "walk.npz")
    gt = {"names": ["RKnee", "Pelvis"], "joints3d": np.zeros((30, 2, 3)), "fps": 30.0, "frame_offset": 0}
    with pytest.raises(ValueError, match="'Pelvis'"):
        score_result(r, gt)
    gt = {"names": ["RKnee"], "joints3d": np.zeros((30, 1, 3)), "fps": 25.0, "frame_offset": 0}
    with pytest.raises(ValueError, match="no resampling"):
        score_result(r, gt)


def test_eval_reads_a_clip_whose_ground_truth_lacks_joints(tmp_path):
    """A clip's gt_keypoints3d may hold NaN (x, y, z) for joints the ground truth does not have:
    the clip loads, and jmocap eval's metrics (evaluate_motion) run on the joints it has; a
    partly NaN point or inf is still an error."""
    from jmocap.data.clip import ClipFormatError, load_clip, save_clip

    clip = load_clip(DEMO)
    kg = np.array(clip.gt_keypoints3d, np.float32)
    lack = [0, 15, 16, 17, 18]  # no face joints in this "motion capture"
    kg[:, lack] = np.nan
    kg[10:14, 4] = np.nan  # a wrist lost for a while
    partial = clip.replace(gt_keypoints3d=kg)
    save_clip(tmp_path / "c.npz", partial)
    back = load_clip(tmp_path / "c.npz")
    assert np.isnan(back.gt_keypoints3d[:, lack]).all()
    rng = np.random.default_rng(0)
    pred = (clip.gt_keypoints3d + rng.normal(size=kg.shape) * 0.02).astype(np.float32)
    got = M.evaluate_motion(back, keypoints3d=pred)
    present = np.isfinite(kg).all(-1)
    err = np.linalg.norm(pred - np.nan_to_num(kg), axis=-1)[present].mean() * 1000
    assert got["mpjpe_abs_mm"] == pytest.approx(err, rel=1e-4)
    keep = [j for j in range(kg.shape[1]) if j not in lack and j != 4]
    ref = M.pa_mpjpe(pred[:, keep], clip.gt_keypoints3d[:, keep])
    assert got["pa_mpjpe_mm"] == pytest.approx(float(ref), rel=0.05)  # the wrist's 4 frames aside
    bad = kg.copy()
    bad[3, 7, 0] = np.nan  # half a point
    with pytest.raises(ClipFormatError, match="gt_keypoints3d"):
        clip.replace(gt_keypoints3d=bad)  # validated on construction
    bad = kg.copy()
    bad[3, 7] = np.inf
    with pytest.raises(ClipFormatError, match="gt_keypoints3d"):
        clip.replace(gt_keypoints3d=bad)


def test_force_plates_and_contacts_score_the_forces_and_feet(tmp_path):
    """Ground truth with per-foot force-plate forces and contact labels (the demo clip's own):
    the ground-truth motion and forces as the result score a net GRF error of ~0 and a per-foot
    correlation of 1; its foot skate and floating equal jmocap eval's for the same motion; forces
    1.1x too large are a 10 %-of-the-mean-force error; a result without forces gets no force scores."""
    from jmocap.data.clip import load_clip

    clip = load_clip(DEMO)
    arrays = {
        "format": np.array("jmocap-result-1"), "name": np.array("demo_walk"), "method": np.array("pip"),
        "q": clip.gt_q.astype(np.float32), "fps": np.array(clip.fps), "height_m": np.array(clip.height_m),
        "mass_kg": np.array(clip.mass_kg), "keypoints3d": clip.gt_keypoints3d.astype(np.float32),
        "layout": np.array("body25"), "forces_estimated": np.array(True), "assumed": np.array("[]"),
        "grf": clip.gt_grf.astype(np.float32), "tau": clip.gt_tau.astype(np.float32),
    }
    write_result(tmp_path / "r.npz", arrays)
    gt = load_ground_truth(DEMO)
    s = score_result(load_result(tmp_path / "r.npz"), gt)
    assert s["grf_err_pct_bw"] < 0.01 and s["foot_grf_corr"] == pytest.approx(1.0, abs=1e-5)
    ref = M.evaluate_motion(clip, q=clip.gt_q)
    assert s["skate_pct"] == pytest.approx(ref["skate_pct"], abs=1e-3)
    assert s["float_pct"] == pytest.approx(ref["float_pct"], abs=1e-3)
    write_result(tmp_path / "big.npz", dict(arrays, grf=(1.1 * clip.gt_grf).astype(np.float32)))
    s = score_result(load_result(tmp_path / "big.npz"), gt)
    w = clip.mass_kg * 9.81
    want = 10.0 * np.mean(np.linalg.norm(clip.gt_grf.sum(1), axis=-1)) / w
    assert s["grf_err_pct_bw"] == pytest.approx(want, rel=2e-3)
    write_result(tmp_path / "kin.npz", {k: v for k, v in arrays.items() if k not in ("grf", "tau")}
                 | {"forces_estimated": np.array(False)})
    s = score_result(load_result(tmp_path / "kin.npz"), gt)
    assert "grf_err_pct_bw" not in s and "skate_pct" in s
    # a result whose input has a terrain: a platform 30 cm above the floor under the whole walk
    # (reaching below the floor, so depths inside it are to its top: the motion's feet, at the
    # floor, are 30 cm inside it), and a box far away (which changes nothing)
    base = score_result(load_result(tmp_path / "r.npz"), gt)
    for box, sunk in (({"center": [0.0, 0.0, -0.1], "half_size": [50.0, 50.0, 0.4]}, True),
                      ({"center": [80.0, 0.0, 0.5], "half_size": [1.0, 1.0, 0.5]}, False)):
        scene = np.array(json.dumps({"format": "jmocap-scene-1", "boxes": [box]}))
        write_result(tmp_path / "scene.npz", dict(arrays, scene=scene))
        s = score_result(load_result(tmp_path / "scene.npz"), gt)
        if sunk:
            assert s["pnp_pct"] == 0.0 and s["penetrate_pct"] > 95.0 and s["float_pct"] == 0.0
        else:
            assert {k: s[k] for k in ("pnp_pct", "penetrate_pct", "float_pct")} == \
                {k: base[k] for k in ("pnp_pct", "penetrate_pct", "float_pct")}
