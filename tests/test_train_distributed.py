"""Tests of jmocap.train across processes: two JAX processes on this machine (jax.distributed,
gloo CPU collectives, one CPU device each) train the run a single process trains, to float32
rounding, and hold identical parameters; a checkpoint (orbax, ``out/checkpoint/``) written by two
processes resumes in one and one written by one process resumes in two (through ``jmocap
train``'s flags); a batch the devices cannot share is refused; a checkpoint of the format before
orbax (``out/checkpoint.msgpack``) still resumes.

The tiny networks, clips and stages of tests/test_train.py; the first stage's batch of 4 windows
gives each process 2 rows, the second stage's batch of 2 one row. Every subprocess is killed
after TIMEOUT s (or as soon as another process of its run failed), so a hang cannot stall the
suite. The two-process tests are marked slow (`make test-slow`): about a minute each on 2 cores.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization

from jmocap.cli import main as cli_main
from jmocap.data.clip import save_clip
from jmocap.data.synthetic import SynthConfig, generate_clip
from jmocap.methods import PhysCapConfig
from jmocap.nets import NetConfig
from jmocap.train import (
    Checkpoints,
    StageConfig,
    TrainConfig,
    TrainingSet,
    initialize_distributed,
    train,
)
from jmocap.weights import load_params
from test_train import _Interrupted, _StopAfter  # an interruption mid-stage

TESTS = Path(__file__).resolve().parent
WORKER = TESTS / "distributed_worker.py"
TIMEOUT = 300  # s for one multi-process run, compiling included (30-60 s warm on 2 cores)

SMALL = PhysCapConfig(iterations=2, nets=NetConfig(tp_width=8, dyn_width=16, grf_width=16, tp_blocks=1))
STAGES = (
    StageConfig("tpnet", 3, 1e-3, 4, 4),
    StageConfig("grfnet", 2, 1e-3, 2, 3, cycle={"use_dynet": False}),
)
# Two processes sum a batch's per-window losses and gradients in another order than one process
# (each device its own rows, then an all-reduce), so the float32 results differ in the last bits:
# the first step's loss is the same, its gradient norm differs by 2e-7 (relative). Adam divides
# each gradient component by its own running RMS, which magnifies the rounding of components that
# are near-cancelling sums: measured (jax 0.10.2, CPU), 0.15 % of the parameters differ by more
# than 1e-6 after the 5 steps, none by more than 7.1e-6. Hence: all parameters within ATOL (7x
# that), and all but 1 % within 1e-6. A real difference in what is trained (other windows, half
# a batch's gradient, other dropout keys) moves nearly every parameter by about one Adam step,
# lr = 1e-3. The stiff simulation of the second stage carries the parameters' differences into its
# losses (measured 8e-5 relative at most).
ATOL = 5e-5
ROUNDING = 1e-6
LOSS_RTOL = 1e-3


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dist_clips")
    for i in range(2):
        save_clip(folder / f"c{i}.npz", generate_clip(7, i, SynthConfig(frames=12)))
    return folder


def _config(archive, out, stages=STAGES) -> TrainConfig:
    return TrainConfig(data=(str(archive),), out=str(out), seed=3, stages=stages, cycle=SMALL,
                       log_every=1, checkpoint_every=1)


def _write_config(config: TrainConfig, path: Path) -> Path:
    path.write_text(json.dumps(config.to_json()))
    return path


def _log(out) -> list[dict]:
    return [json.loads(line) for line in (Path(out) / "log.jsonl").read_text().splitlines()]


def _leaves(tree) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def _result(path: Path) -> list[np.ndarray]:
    with np.load(path) as z:
        return [z[f"leaf_{i}"] for i in range(len(z.files))]


def _assert_close(got, want) -> None:
    """Parameters equal to float32 rounding (see ATOL)."""
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=ATOL)
    diff = np.concatenate([np.abs(a - b).ravel() for a, b in zip(got, want, strict=True)])
    assert np.mean(diff > ROUNDING) < 0.01, f"{np.mean(diff > ROUNDING):.1%} of the parameters differ by > {ROUNDING}"


@pytest.fixture(scope="module")
def reference(xla_cache, archive, tmp_path_factory):
    """The single-process, uninterrupted run: (its output folder, its final parameters)."""
    out = tmp_path_factory.mktemp("one")
    config = _config(archive, out)
    return out, _leaves(train(config, progress=False, data=TrainingSet.load(config.data, config)))


def _restore(out: Path) -> dict:
    checkpoints = Checkpoints(out)
    try:
        return checkpoints.restore()
    finally:
        checkpoints.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run_processes(commands: list[list[str]], logs: Path, xla_cache: str, devices: int = 1) -> list[int]:
    """Run the processes of one run side by side, each seeing ``devices`` CPU devices; their
    exit statuses. All are killed when one fails or after TIMEOUT s."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
               JAX_COMPILATION_CACHE_DIR=xla_cache, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.2")
    files = [open(logs / f"process{i}.log", "w") for i in range(len(commands))]
    procs = [subprocess.Popen(c, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=TESTS.parent)
             for c, f in zip(commands, files, strict=True)]
    deadline = time.monotonic() + TIMEOUT
    try:
        while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
            if any(p.returncode not in (None, 0, 3) for p in procs):
                break  # one failed: the others would wait for it until their own timeouts
            time.sleep(0.2)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
        for f in files:
            f.close()
    return [p.returncode for p in procs]


def _output(logs: Path, n: int) -> str:
    return "\n".join(f"--- process {i}:\n" + (logs / f"process{i}.log").read_text()[-4000:] for i in range(n))


def _workers(config_path: Path, results: Path, xla_cache: str, stop_after: int | None = None) -> list[int]:
    """A two-process run of the worker script; each process's parameters in results/process<i>.npz."""
    port = _free_port()
    extra = [] if stop_after is None else ["--stop-after", str(stop_after)]
    commands = [[sys.executable, str(WORKER), str(config_path), str(results / f"process{i}.npz"),
                 "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(i), *extra]
                for i in range(2)]
    return _run_processes(commands, results, xla_cache)


@pytest.mark.slow  # two processes: 45-65 s on 2 busy cores
def test_two_processes_train_what_one_process_trains(xla_cache, archive, reference, tmp_path):
    ref_out, ref_params = reference
    out = tmp_path / "two"
    codes = _workers(_write_config(_config(archive, out), tmp_path / "config.json"), tmp_path, xla_cache)
    assert codes == [0, 0], _output(tmp_path, 2)

    first, second = _result(tmp_path / "process0.npz"), _result(tmp_path / "process1.npz")
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)  # the replicated parameters: the same bits everywhere
    _assert_close(first, ref_params)
    for a, b in zip(_leaves(load_params(out / "params.msgpack")), first, strict=True):
        np.testing.assert_array_equal(a, b)  # written by process 0

    log, ref_log = _log(out), _log(ref_out)  # process 0's log alone, one line per step
    assert [(r["stage"], r["step"]) for r in log] == [(r["stage"], r["step"]) for r in ref_log]
    assert log[0]["loss"] == pytest.approx(ref_log[0]["loss"], rel=1e-6)  # the same windows and keys
    np.testing.assert_allclose([r["loss"] for r in log], [r["loss"] for r in ref_log], rtol=LOSS_RTOL)
    # orbax keeps the latest two of the five checkpoints (three steps, two steps)
    assert sorted(p.name for p in (out / "checkpoint").iterdir()) == ["3", "4"]


@pytest.mark.slow  # two processes: 45-65 s on 2 busy cores
def test_checkpoint_of_two_processes_resumes_in_one(xla_cache, archive, reference, tmp_path):
    ref_out, ref_params = reference
    out = tmp_path / "run"
    config = _config(archive, out)
    codes = _workers(_write_config(config, tmp_path / "config.json"), tmp_path, xla_cache, stop_after=2)
    assert codes == [3, 3], _output(tmp_path, 2)  # both interrupted after the 2nd step's checkpoint
    saved = _restore(out)
    assert (saved["stage"], saved["step"]) == (0, 2) and saved["opt_state"] is not None

    resumed = train(config, progress=False)
    _assert_close(_leaves(resumed), ref_params)
    assert [(r["stage"], r["step"]) for r in _log(out)] == [(r["stage"], r["step"]) for r in _log(ref_out)]


@pytest.mark.slow  # two processes: 45-65 s on 2 busy cores
def test_checkpoint_of_one_process_resumes_in_two_through_the_cli(xla_cache, archive, reference, tmp_path):
    _, ref_params = reference
    out = tmp_path / "run"
    config = _config(archive, out)
    with pytest.raises(_Interrupted):  # the first stage and one step of the second
        train(config, progress=False, data=_StopAfter(TrainingSet.load(config.data, config), 4))
    config_path = _write_config(config, tmp_path / "config.json")
    port = _free_port()
    commands = [[sys.executable, "-m", "jmocap.cli", "train", "--config", str(config_path), "--quiet",
                 "--cache-dir", xla_cache, "--coordinator", f"localhost:{port}", "--num-processes", "2",
                 "--process-id", str(i)] for i in range(2)]
    codes = _run_processes(commands, tmp_path, xla_cache)
    assert codes == [0, 0], _output(tmp_path, 2)
    assert "on 2 process(es), 2 device(s)" in (tmp_path / "process0.log").read_text()
    _assert_close(_leaves(load_params(out / "params.msgpack")), ref_params)


def test_a_batch_the_devices_cannot_share_is_refused(xla_cache, archive, tmp_path):
    """One process with two CPU devices: a stage's batch of 3 cannot be split over them."""
    stages = (StageConfig("tpnet", 2, 1e-3, 4, 4), StageConfig("grfnet", 2, 1e-3, 3, 3))
    out = tmp_path / "out"
    config_path = _write_config(_config(archive, out, stages), tmp_path / "config.json")
    codes = _run_processes([[sys.executable, "-m", "jmocap.cli", "train", "--config", str(config_path), "--quiet"]],
                           tmp_path, xla_cache, devices=2)
    text = (tmp_path / "process0.log").read_text()
    assert codes == [2], text
    assert "stage 'grfnet': batch 3 is not divisible by the 2 devices" in text
    assert not out.exists()  # refused before anything was written


def test_distributed_flags_are_given_together(tmp_path, capsys):
    with pytest.raises(ValueError, match="together"):
        initialize_distributed("localhost:1234", 2, None)
    assert cli_main(["train", "--config", str(tmp_path / "c.json"), "--num-processes", "2"]) == 2
    assert "--coordinator, --num-processes and --process-id together" in capsys.readouterr().err


def test_a_checkpoint_msgpack_of_before_orbax_still_resumes(xla_cache, archive, reference, tmp_path):
    """A run interrupted mid-stage by the code before orbax left ``out/checkpoint.msgpack``
    (written here the way that code wrote it, from the state an interrupted run holds); with no
    ``out/checkpoint/`` it is resumed from, to the uninterrupted run's parameters."""
    _, ref_params = reference
    out = tmp_path / "run"
    config = _config(archive, out)
    with pytest.raises(_Interrupted):
        train(config, progress=False, data=_StopAfter(TrainingSet.load(config.data, config), 2))
    s = _restore(out)
    shutil.rmtree(out / "checkpoint")
    payload = {  # the fields and encodings of the former jmocap.train._save_checkpoint
        "rng": json.dumps(s["rng"]), "val": json.dumps(s["val"]), "stage": s["stage"], "step": s["step"],
        "params": s["params"], "opt_state": s["opt_state"], "key": np.asarray(s["key"]),
    }
    (out / "checkpoint.msgpack").write_bytes(serialization.msgpack_serialize(payload))

    resumed = train(config, progress=False)
    _assert_close(_leaves(resumed), ref_params)
    assert sorted(p.name for p in (out / "checkpoint").iterdir()) == ["1", "2"]  # orbax from then on
