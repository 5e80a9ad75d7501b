"""Tests of jmocap.train: the staged loop trains only its stage's networks, logs finite losses,
applies per-stage cycle overrides, and resumes after an interruption to exactly the result of an
uninterrupted run (checkpoints hold stage, step, parameters, optimiser state and key).

Tiny networks, two short synthetic clips and a few steps per stage, so that the test measures
the loop's bookkeeping, not learning. A persistent compilation cache shared by the module's
runs (conftest's ``xla_cache``) makes the second and third runs reuse the first one's compiled
steps.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from jmocap.data.clip import save_clip
from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.methods import PhysCapConfig
from jmocap.nets import NetConfig
from jmocap.train import StageConfig, TrainConfig, TrainingSet, train
from jmocap.weights import load_params

SMALL = PhysCapConfig(iterations=2, nets=NetConfig(tp_width=8, dyn_width=16, grf_width=16, tp_blocks=1))
STAGES = (
    StageConfig("tpnet", 3, 1e-3, 2, 4),
    StageConfig("grfnet", 2, 1e-3, 2, 3, cycle={"use_dynet": False}),
)


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("train_clips")
    for i in range(2):
        save_clip(folder / f"c{i}.npz", generate_clip(7, i, SynthConfig(frames=12)))
    return folder


def _config(archive, out, stages=STAGES):
    return TrainConfig(data=(str(archive),), out=str(out), seed=3, stages=stages, cycle=SMALL,
                       log_every=1, checkpoint_every=1)


class _Interrupted(Exception):
    pass


class _StopAfter:
    """A TrainingSet that raises after ``n`` samples (an interruption mid-stage)."""

    def __init__(self, data, n):
        self.data, self.n, self.models = data, n, data.models

    def sample(self, rng, batch, frames):
        if self.n == 0:
            raise _Interrupted
        self.n -= 1
        return self.data.sample(rng, batch, frames)


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def test_stages_log_resume_and_overrides(xla_cache, archive, tmp_path):
    config = _config(archive, tmp_path / "a")
    data = TrainingSet.load(config.data, config)
    full = train(config, progress=False, data=data)

    log = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["step"]) for r in log] == [("tpnet", 1), ("tpnet", 2), ("tpnet", 3),
                                                       ("grfnet", 1), ("grfnet", 2)]
    assert all(np.isfinite(r["loss"]) and np.isfinite(r["grad_norm"]) for r in log)
    saved = json.loads((tmp_path / "a" / "config.json").read_text())
    assert saved["stages"][1]["cycle"] == {"use_dynet": False}
    assert TrainConfig.from_json(saved).stages == STAGES

    # each stage trains its own networks only
    after_tp = load_params(tmp_path / "a" / "params_tpnet.msgpack")
    after_grf = load_params(tmp_path / "a" / "params_grfnet.msgpack")
    for a, b in zip(_leaves(after_tp["tpnet"]), _leaves(after_grf["tpnet"]), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(_leaves(after_tp["dynet"]), _leaves(after_grf["dynet"]), strict=True):
        np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(a, b) for a, b in
               zip(_leaves(after_tp["grfnet"]), _leaves(after_grf["grfnet"]), strict=True))

    # interrupted in the middle of the first stage, then resumed: the same parameters
    config_b = dataclasses.replace(config, out=str(tmp_path / "b"))
    with pytest.raises(_Interrupted):
        train(config_b, progress=False, data=_StopAfter(data, 2))
    ckpt = tmp_path / "b" / "checkpoint"
    assert ckpt.exists()
    resumed = train(config_b, progress=False, data=data)
    for a, b in zip(_leaves(full), _leaves(resumed), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    log_b = [json.loads(line) for line in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["step"]) for r in log_b] == [(r["stage"], r["step"]) for r in log]


def test_layout_mix_gives_other_layouts_joints(archive, tmp_path):
    """``layout_mix``: the shared windows look like a COCO-17 / Human3.6M-17 detector's output
    converted to BODY_25 (no feet; the neck as the shoulders' midpoint; for H36M no eyes or ears),
    the rest of the windows as they are; the ground truth is untouched."""
    from jmocap.layouts import BODY25

    feet = [BODY25.index(j) for j in ("LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")]
    face = [BODY25.index(j) for j in ("REye", "LEye", "REar", "LEar")]
    neck, ls, rs = BODY25.index("Neck"), BODY25.index("LShoulder"), BODY25.index("RShoulder")
    plain = TrainingSet.load((str(archive),), _config(archive, tmp_path))
    mixed = TrainingSet.load((str(archive),), dataclasses.replace(_config(archive, tmp_path),
                                                                    layout_mix={"coco17": 0.4, "h36m17": 0.3}))
    kinds = []
    for seed in range(40):
        _, a = plain.sample(np.random.default_rng(seed), 1, 4)
        _, b = mixed.sample(np.random.default_rng(seed), 1, 4)
        np.testing.assert_array_equal(a["gt_kp3d"], b["gt_kp3d"])
        kp, ref = b["keypoints"][0], a["keypoints"][0]
        if np.array_equal(kp, ref):
            kinds.append("body25")
            continue
        assert not kp[:, feet].any()
        both = (ref[:, ls, 2] > 0) & (ref[:, rs, 2] > 0)
        np.testing.assert_allclose(kp[both, neck, :2], (ref[both, ls, :2] + ref[both, rs, :2]) / 2, rtol=1e-6)
        kinds.append("h36m17" if not kp[:, face].any() else "coco17")
    assert {"body25", "coco17", "h36m17"} <= set(kinds)


def test_init_and_cosine_schedule(xla_cache, archive, tmp_path):
    """``init`` starts a run from another run's networks (a fine-tuning run), a mismatched file is
    refused with the network named; ``schedule="cosine"`` decays the stage's rate to 0 (optax's
    schedule: lr at step 0, lr/2 half way, 0 at the end)."""
    from jmocap.train import learning_rate

    first = _config(archive, tmp_path / "first", stages=STAGES[:1])
    data = TrainingSet.load(first.data, first)
    trained = train(first, progress=False, data=data)
    ft_stage = StageConfig("grfnet", 2, 1e-3, 2, 3, cycle={"use_dynet": False}, schedule="cosine")
    ft = dataclasses.replace(_config(archive, tmp_path / "ft", stages=(ft_stage,)),
                             init=str(tmp_path / "first" / "params.msgpack"))
    tuned = train(ft, progress=False, data=data)
    for a, b in zip(_leaves(trained["tpnet"]), _leaves(tuned["tpnet"]), strict=True):
        np.testing.assert_array_equal(a, b)  # started from the first run's TPNet, left frozen
    fresh = train(dataclasses.replace(ft, out=str(tmp_path / "fresh"), init=None), progress=False, data=data)
    assert any(not np.array_equal(a, b) for a, b in zip(_leaves(fresh["tpnet"]), _leaves(tuned["tpnet"]), strict=True))

    sched = learning_rate(StageConfig("tpnet", 100, 1e-3, 2, 4, schedule="cosine"))
    np.testing.assert_allclose([float(sched(0)), float(sched(50)), float(sched(100))], [1e-3, 5e-4, 0.0], atol=1e-9)
    with pytest.raises(ValueError, match="schedule"):
        learning_rate(StageConfig("tpnet", 100, 1e-3, 2, 4, schedule="step"))

    wide = dataclasses.replace(SMALL, nets=dataclasses.replace(SMALL.nets, tp_width=16))
    with pytest.raises(ValueError, match="tpnet"):
        train(dataclasses.replace(ft, out=str(tmp_path / "wide"), cycle=wide), progress=False,
              data=TrainingSet.load(first.data, dataclasses.replace(first, cycle=wide)))


def test_validation_best_parameters_and_early_stopping(xla_cache, archive, tmp_path):
    """``val_data``: TPNet's root-relative MPJPE on fixed windows is logged every ``val_every``
    steps of a TPNet stage (not of the others), equals the mean joint distance computed here in
    numpy from TPNet's output on the same windows, the best parameters are written, and with
    ``patience`` a stage that stops improving ends early (a zero learning rate: the check after
    the first step cannot improve on the one at the start) and the run goes on with the next stage."""
    from jmocap.methods.stages import target_pose
    from jmocap.train import _inputs, _validation_windows

    stages = (StageConfig("tpnet", 6, 0.0, 2, 4), StageConfig("grfnet", 2, 1e-3, 2, 3, cycle={"use_dynet": False}))
    config = dataclasses.replace(_config(archive, tmp_path / "v", stages=stages), val_data=(str(archive),),
                                 val_every=1, val_windows=4, patience=1)
    data = TrainingSet.load(config.data, config)
    params = train(config, progress=False, data=data)
    log = [json.loads(line) for line in (tmp_path / "v" / "log.jsonl").read_text().splitlines()]
    vals = [r for r in log if "val_mpjpe_mm" in r]
    assert [(r["stage"], r["step"]) for r in vals] == [("tpnet", 0), ("tpnet", 1)]  # the start, then step 1
    assert vals[0]["val_mpjpe_mm"] == vals[1]["val_mpjpe_mm"] == vals[1]["best_mm"]
    assert [r for r in log if r.get("early_stop")] == [{"stage": "tpnet", "step": 1, "early_stop": True, "best_step": 0}]
    assert [r["step"] for r in log if r["stage"] == "grfnet" and "loss" in r] == [1, 2]  # the next stage ran
    best = load_params(tmp_path / "v" / "params_best.msgpack")
    for a, b in zip(_leaves(best["tpnet"]), _leaves(params["tpnet"]), strict=True):
        np.testing.assert_array_equal(a, b)
    # the logged number, recomputed
    errs, frames = [], 0
    for model, d in _validation_windows(data, 4, 2, 4):
        for i in range(d["mask"].shape[0]):
            m = jax.tree.map(lambda x, i=i: x[i], model)
            di = {k: v[i] for k, v in d.items()}
            tp = target_pose(params, m, _inputs(di), SMALL, train=False)
            gt = (di["gt_kp3d"] - di["gt_q"][:, None, :3]) @ di["extrinsics"][:3, :3].T
            e = np.linalg.norm(np.asarray(tp.p_rr) - gt, axis=-1).mean(-1)
            errs.append(float(np.sum(e * di["mask"])))
            frames += int(di["mask"].sum())
    np.testing.assert_allclose(vals[0]["val_mpjpe_mm"], 1000 * sum(errs) / frames, rtol=1e-4)
