"""The evaluation harness and ``jmocap eval`` end to end on a tiny synthetic archive (2 short
physics clips, random-init parameters): files written, ground truth scoring exactly, methods
as config changes, aggregation, failures recorded, reproducibility."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

from jmocap import evaluate as E
from jmocap import methods
from jmocap import metrics as M
from jmocap.cli import main
from jmocap.data.archive import ArchiveWriter
from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.methods import PhysCapConfig


@pytest.fixture(scope="module")
def clips():
    cfg = SynthConfig(frames=10, physics=True, kinds=("walk", "jump"))
    return [generate_clip(3, i, cfg) for i in range(2)]


@pytest.fixture(scope="module")
def archive(tmp_path_factory, clips):
    root = tmp_path_factory.mktemp("heldout")
    with ArchiveWriter(root, {"test": True}) as w:
        for c in clips:
            w.add(c)
    return root


def test_pip_and_trajopt_take_only_the_learned_stage_from_the_weights_config(tmp_path):
    """The shipped weights' config is physcap's cycle (iterations 6, its contact threshold and
    mu): pip and trajopt take its learned-stage fields (layout, canonicalise, nets) and keep
    their own physics defaults (until stop 40 pip ran physcap's 6 steps per frame instead of
    its 2); a method's own config, and overrides given by the user, apply whole."""
    import shutil

    from jmocap import weights as W
    from jmocap.methods.pip import PIPConfig
    from jmocap.methods.trajopt import TrajOptConfig
    from jmocap.nets import NetConfig

    base = PhysCapConfig(iterations=6, contact_threshold=0.7, mu=0.6, canonicalise=False,
                         nets=NetConfig(window=7))
    for name, default in (("pip", PIPConfig()), ("pip_tpnet", None), ("trajopt", TrajOptConfig())):
        cfg = E.method_config(base, name)
        assert (cfg.canonicalise, cfg.nets) == (False, NetConfig(window=7)), name
        assert cfg.contact_threshold != 0.7 and cfg.mu != 0.6, name
        if default is not None:
            assert (cfg.contact_threshold, cfg.mu) == (default.contact_threshold, default.mu)
    assert E.method_config(base, "pip").iterations == PIPConfig().iterations == 2
    assert E.method_config(base, "physcap").iterations == 6  # physcap takes every field
    own = E.method_config(PIPConfig(iterations=3, mu=0.5), "pip", own=True)
    assert (own.iterations, own.mu) == (3, 0.5)
    # load_run_params: the shipped config, a config.json beside a params file, and --config
    assert W.load_run_params(None, method="pip")[1].iterations == 2
    assert W.load_run_params(None, '{"iterations": 4}', method="pip")[1].iterations == 4
    params = tmp_path / "run" / "params.msgpack"
    params.parent.mkdir()
    shutil.copy(W.DEFAULT_PARAMS, params)
    (params.parent / "config.json").write_text(json.dumps(
        {"cycle": {**W.default_config_fields(), "iterations": 5, "canonicalise": True}}))
    cfg = W.load_run_params(str(params), method="pip")[1]
    assert cfg.iterations == 2 and cfg.canonicalise
    assert W.load_run_params(str(params), method="physcap")[1].iterations == 5
    assert W.load_run_params(str(params), '{"mu": 0.7}', method="pip")[1].mu == 0.7


def test_method_configs_keep_the_trained_fields_and_change_only_their_switch():
    """Every eval name resolves through the methods registry; a method's config keeps the fields
    the weights were trained with, and each ablation differs from the full pipeline in exactly
    the one switch it names."""
    base = PhysCapConfig(use_dynet=False, iterations=3, mu=0.6)  # e.g. a trained config
    full = E.method_config(base, "physionical")
    assert (full.iterations, full.mu, full.use_dynet) == (3, 0.6, True)
    assert E.method_config(base, "physcap") == base  # the weights' own config, unchanged
    kin = E.method_config(base, "kinematic")
    assert isinstance(kin, methods.KinematicConfig) and (kin.layout, kin.nets) == (base.layout, base.nets)
    names = {f.name for f in dataclasses.fields(PhysCapConfig)}
    switches = {}
    for name in E.method_names():
        cfg = E.method_config(base, name)
        if name == E.GROUND_TRUTH:
            assert cfg is None
            continue
        method, _ = methods.resolve(name)
        assert isinstance(cfg, method.config_type)
        if method.name == "physcap" and name not in ("physcap", "physionical"):
            changed = {f for f in names if getattr(cfg, f) != getattr(full, f)}
            assert len(changed) == 1, (name, changed)
            switches[name] = changed.pop()
    assert switches == {"fixed_gains": "use_dynet", "no_grfnet": "use_grfnet",
                        "no_hard_constraint": "hard_constraint", "no_canonicalisation": "canonicalise"}
    with pytest.raises(ValueError, match="unknown method 'bogus'"):
        E.method_config(base, "bogus")


def test_aggregate_means_over_clips_that_have_the_metric_and_max_for_max_grf():
    per_clip = {"m": {"a": {"mpjpe_mm": 10.0, "grf_max_pct_bw": 150.0},
                      "b": {"mpjpe_mm": 20.0, "grf_max_pct_bw": 300.0, "grf_ballistic_pct_bw": 4.0}}}
    summary, counts = E.aggregate(per_clip)
    assert summary["m"] == {"mpjpe_mm": 15.0, "grf_max_pct_bw": 300.0, "grf_ballistic_pct_bw": 4.0}
    assert counts["m"] == {"mpjpe_mm": 2, "grf_max_pct_bw": 2, "grf_ballistic_pct_bw": 1}


def test_jmocap_eval_end_to_end(archive, tmp_path):
    out = tmp_path / "eval"
    rc = main(["eval", str(archive), "--random-init", "--methods", "kinematic", "ground_truth",
               "--out", str(out), "--quiet", "--batch-size", "2"])
    assert rc == 0
    md, table, js = out / "metrics.md", out / "metrics.csv", out / "metrics.json"
    assert md.is_file() and table.is_file() and js.is_file()
    result = json.loads(js.read_text())
    assert result["methods"] == ["kinematic", "ground_truth"]
    assert len(result["clips"]) == 2 and not result["failures"]
    gt = result["summary"]["ground_truth"]
    # the ground truth through the metrics: exact where it must be
    for key in ("mpjpe_mm", "mpjpe_abs_mm", "root_err_mm", "e_smooth_mm", "reproj_input_px",
                "reproj_side_px", "grf_err_pct_bw", "torque_err_nm_kg"):
        assert gt[key] == pytest.approx(0.0, abs=1e-2), key
    assert gt["pa_mpjpe_mm"] == pytest.approx(0.0, abs=0.05)
    assert gt["pck150_pct"] == 100.0 and gt["contact_f1_pct"] == 100.0
    assert gt["auc_pct"] == pytest.approx(100 * 30 / 31, abs=1e-3)  # PCK at 0 mm is 0
    assert 50.0 < gt["grf_mean_pct_bw"] < 150.0  # a subject carries its own weight
    assert all(np.isfinite(v) for m in result["summary"].values() for v in m.values())
    # kinematic: no force estimates, so no residual/torque/GRF errors; implied GRF statistics
    kin = result["summary"]["kinematic"]
    assert "root_residual_pct_bw" not in kin and "grf_err_pct_bw" not in kin and "grf_mean_pct_bw" in kin
    # every metric of the ground-truth row is in the CSV and the markdown table
    rows = {r["method"]: r for r in csv.DictReader(table.open())}
    assert float(rows["ground_truth"]["mpjpe_mm"]) == pytest.approx(gt["mpjpe_mm"])
    assert rows["kinematic"]["root_residual_pct_bw"] == ""
    text = md.read_text()
    assert "| metric | unit |" in text and "`ground_truth`" in text
    for key in gt:
        assert M.METRICS[key].label in text
    # reproducible: the same seed gives the same numbers
    out2 = tmp_path / "again"
    assert main(["eval", str(archive), "--random-init", "--methods", "kinematic", "--out", str(out2),
                 "--quiet", "--batch-size", "2"]) == 0
    again = json.loads((out2 / "metrics.json").read_text())
    assert again["summary"]["kinematic"] == result["summary"]["kinematic"]


def test_clip_without_ground_truth_is_recorded_and_skipped(clips):
    bare = clips[0].replace(name="bare", gt_q=None, gt_qd=None, gt_keypoints3d=None)
    res = E.evaluate("memory", None, config=E.EvalConfig(methods=("ground_truth",), progress=False),
                     clips=[bare, clips[1]])
    assert res.clips == [clips[1].name]
    assert res.failures == [{"method": "*", "clip": "bare", "error": "no ground truth (gt_q, gt_keypoints3d)"}]
    assert res.summary["ground_truth"]["mpjpe_mm"] == pytest.approx(0.0, abs=1e-2)


def test_a_methods_per_clip_report_is_kept_beside_the_metrics_and_not_summarised(clips):
    """``Motion.diagnostics`` (e.g. ``pip``'s tracking failures) reach ``per_clip`` as
    ``diag_<name>``; the summary averages metrics only."""
    c = clips[1]
    batch = E._prepare([c], c.num_frames, 1)
    pred = {**E._ground_truth_pred(batch.gt[0]), "diagnostics": {"resets": np.float32(2.0)}}
    r = E._evaluate_clip(c, pred, batch.gt[0], c.num_frames, E.subject_model(c).total_mass)
    assert r["diag_resets"] == 2.0 and r["mpjpe_mm"] == pytest.approx(0.0, abs=1e-2)
    summary, _ = E.aggregate({"m": {c.name: r}})
    assert "diag_resets" not in summary["m"] and "mpjpe_mm" in summary["m"]


def test_evaluate_motion_of_the_ground_truth(clips):
    c = clips[1]
    r = M.evaluate_motion(c, q=c.gt_q, grf=c.gt_grf, tau=c.gt_tau, contact_prob=c.gt_contacts,
                          model=E.subject_model(c))
    assert r["mpjpe_mm"] == pytest.approx(0.0, abs=1e-2)
    assert r["grf_err_pct_bw"] == pytest.approx(0.0, abs=1e-3)
    assert r["contact_acc_pct"] == 100.0
    with pytest.raises(ValueError, match="q has 5 frames"):
        M.evaluate_motion(c, q=c.gt_q[:5])


def test_evaluate_motion_of_a_known_perturbation(clips):
    """The ground truth moved 30 mm along x and 40 mm along y (hand-worked: every joint and the
    root 50 mm off, the pose itself unchanged) and its forces scaled by 1.1 (an error of 10 % of
    the true force)."""
    c = clips[1]
    q = np.array(c.gt_q)
    q[:, 0] += 0.03
    q[:, 1] += 0.04
    r = M.evaluate_motion(c, q=q, grf=1.1 * c.gt_grf, model=E.subject_model(c))
    assert r["mpjpe_abs_mm"] == pytest.approx(50.0, abs=0.05)
    assert r["root_err_mm"] == pytest.approx(50.0, abs=0.05)
    assert r["mpjpe_mm"] == pytest.approx(0.0, abs=1e-2) and r["pa_mpjpe_mm"] == pytest.approx(0.0, abs=0.05)
    exact = M.evaluate_motion(c, q=c.gt_q, grf=c.gt_grf, model=E.subject_model(c))
    assert r["grf_err_pct_bw"] == pytest.approx(0.1 * exact["grf_mean_pct_bw"], rel=1e-3)


def test_cli_rejects_bad_arguments(archive, tmp_path, capsys):
    assert main(["eval", str(archive), "--random-init", "--methods", "bogus", "--out", str(tmp_path)]) == 1
    assert "unknown method 'bogus'" in capsys.readouterr().err
    assert main(["eval", str(archive), "--params", str(tmp_path / "none.msgpack"), "--out", str(tmp_path)]) == 1
    assert "none.msgpack" in capsys.readouterr().err


@pytest.mark.slow
def test_physionical_and_ablations_run_end_to_end(archive, tmp_path):
    """The dynamic cycle methods compile and produce finite metrics (slow: one compile each)."""
    params = E.random_params(0)
    res = E.evaluate(archive, params, config=E.EvalConfig(
        methods=("physionical", "no_grfnet"), progress=False), keep_motions=("synth_000000",))
    assert not res.failures
    for m in ("physionical", "no_grfnet"):
        assert "root_residual_pct_bw" in res.summary[m] and "mpjpe_mm" in res.summary[m]
        assert res.motions[m]["synth_000000"]["grf"].shape == (10, 4, 3)
    assert res.summary["no_grfnet"]["grf_mean_pct_bw"] == 0.0
