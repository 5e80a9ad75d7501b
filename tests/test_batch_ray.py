# ruff: noqa: F811  (test_batch's fixtures, imported below, are the arguments of these tests)
"""The Ray engine (``jmocap reconstruct --engine ray``, :mod:`jmocap.batch_ray`) against the local
engine (:func:`jmocap.batch.reconstruct_archive`), the reference: the same result files, byte for
byte, the same failures with the same messages, and either engine resuming the other's run.

On a Ray cluster started on this machine (a head and a worker node, loopback only, one CPU each):
a worker actor SIGKILLed mid-run is restarted by Ray and the run still writes every clip; a
driver stopped by SIGTERM mid-run leaves only complete results, and the local engine finishes the
run. Ray's start-up and each actor's compilation take tens of seconds: every test here is slow
(``make test-slow``). The cluster fixture stops *every* Ray process on the machine when it ends
(``ray stop --force``): do not run it beside a Ray cluster of your own.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow
ray = pytest.importorskip("ray")  # the `ray` extra (in `test`): absent only outside the project's venv

from jmocap.batch_ray import RayOptions, reconstruct_archive_ray  # noqa: E402
from jmocap.data.clip import save_clip  # noqa: E402
from test_batch import (  # noqa: E402,F401  (fixtures: params, clips, input_folder, xla_cache via conftest)
    BAD,
    GOOD,
    OPTS,
    SMALL,
    cli,
    clips,
    input_folder,
    params,
    read_manifest,
    reconstruct_archive,
    synth,
)

# for the processes of the loopback cluster (``ray start``, the CLI's driver): Ray 2.5x starts a
# cluster with token authentication, and a process joining it must say so to send the token
# (~/.ray/auth_token, one file on this machine). This process's own local Ray (the first test)
# needs nothing: Ray reads the variable when it is imported, and its local instance agrees with it.
ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token"}
WORKER = "MapBatches(_Worker)"  # the process title of a reconstruction actor


def same_results(a: Path, b: Path) -> list[str]:
    """The names whose result files are byte-identical in both output folders (asserting the
    manifests agree on every clip's status and failure message)."""
    ma, mb = read_manifest(a), read_manifest(b)
    assert set(ma) == set(mb)
    same = []
    for name, e in ma.items():
        assert mb[name]["status"] == e["status"], name
        if e["status"] != "ok":
            assert mb[name]["error"] == e["error"]
            continue
        assert mb[name]["sha256"] == e["sha256"], name
        assert (b / mb[name]["file"]).read_bytes() == (a / e["file"]).read_bytes(), name
        same.append(name)
    return same


@pytest.fixture(scope="module")
def local_run(xla_cache, params, input_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    reconstruct_archive(input_folder, out, params, SMALL, OPTS)
    return out


def test_ray_writes_what_the_local_engine_writes_and_each_resumes_the_other(xla_cache, params, input_folder,
                                                                              local_run, tmp_path):
    # a local Ray instance started for the run; it reads, buckets and fails clips as the local engine
    ray_out = tmp_path / "ray"
    summary = reconstruct_archive_ray(input_folder, ray_out, params, SMALL, OPTS, RayOptions(workers=2),
                                      method="physcap")
    assert summary["engine"] == "ray" and not ray.is_initialized()  # its own instance, shut down
    assert summary["ok"] == len(GOOD) and summary["failed"] == len(BAD) and summary["pending"] == 0
    assert set(same_results(local_run, ray_out)) == GOOD
    assert json.loads((ray_out / "archive.json").read_text()) == json.loads((local_run / "archive.json").read_text())

    # Ray begins (3 clips), the local engine finishes; then the reverse
    for first, second in (("ray", "local"), ("local", "ray")):
        out = tmp_path / f"{first}_then_{second}"
        for engine, opts in ((first, dataclasses.replace(OPTS, max_clips=3)), (second, OPTS)):
            if engine == "ray":
                s = reconstruct_archive_ray(input_folder, out, params, SMALL, opts, RayOptions(workers=1),
                                            method="physcap")
            else:
                s = reconstruct_archive(input_folder, out, params, SMALL, opts)
        assert s["run"]["skipped"] > 0 and s["pending"] == 0
        assert set(same_results(local_run, out)) == GOOD


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A Ray head and a worker node on this machine (loopback, one CPU each); yields the address."""
    ray_bin = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"
    env = {**os.environ, **ENV}
    port = _free_port()
    address = f"127.0.0.1:{port}"
    temp = tmp_path_factory.mktemp("ray")
    common = ["--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--disable-usage-stats"]
    # the cluster's token (kept if there is one): what `ray start` and the driver read
    subprocess.run([ray_bin, "get-auth-token", "--generate"], env=env, check=True, capture_output=True, timeout=120)
    try:
        subprocess.run([ray_bin, "start", "--head", "--port", str(port), "--include-dashboard", "false",
                        "--temp-dir", str(temp), *common], env=env, check=True, capture_output=True, timeout=120)
        subprocess.run([ray_bin, "start", "--address", address, *common], env=env, check=True, capture_output=True,
                       timeout=120)
        yield address
    finally:
        subprocess.run([ray_bin, "stop", "--force"], env=env, capture_output=True, timeout=120)


def _worker_pids() -> list[int]:
    out = subprocess.run(["ps", "-eo", "pid,args"], capture_output=True, text=True).stdout
    return [int(line.split()[0]) for line in out.splitlines() if WORKER in line and "ps -eo" not in line]


def _wait_for_results(out: Path, proc: subprocess.Popen, n: int = 1, timeout: float = 300) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if (out / "manifest.jsonl").exists() and sum(e["status"] == "ok" for e in read_manifest(out).values()) >= n:
            return
        time.sleep(0.05)
    pytest.fail(f"no result within {timeout} s (exit {proc.poll()}): {proc.stderr.read().decode()[-2000:]}")


@pytest.fixture(scope="module")
def many(tmp_path_factory, xla_cache, params):
    """16 good clips and one broken file, with the local engine's results."""
    src, out = tmp_path_factory.mktemp("many_in"), tmp_path_factory.mktemp("many_local")
    for i in range(16):
        save_clip(src / f"k{i:02d}.npz", synth(40 + i, 6 + i % 3))
    (src / "broken.npz").write_bytes(b"not a zip file " * 10)
    reconstruct_archive(src, out, params, SMALL, OPTS)
    return src, out


def test_a_killed_worker_is_restarted_and_a_stopped_run_resumes_locally(cluster, many, params, xla_cache, tmp_path):
    src, reference = many
    out = tmp_path / "out"
    cmd, env = cli(tmp_path, params, src, out, "--batch", "2", "--engine", "ray", "--address", cluster,
                   "--workers", "2", cache=xla_cache, env=ENV)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _wait_for_results(out, proc)
        victims = _worker_pids()
        assert victims, "no reconstruction actor found to kill"
        os.kill(victims[0], signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, stderr.decode()[-3000:]  # 1: the broken file failed, every other clip ok
    assert "16/17 clips ok, 1 failed" in stdout.decode()
    assert len(same_results(reference, out)) == 16

    # the driver stopped by SIGTERM after its first results; the local engine finishes the run
    out2 = tmp_path / "out2"
    cmd, env = cli(tmp_path, params, src, out2, "--batch", "2", "--engine", "ray", "--address", cluster,
                   "--workers", "1", cache=xla_cache, env=ENV)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _wait_for_results(out2, proc)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    summary = json.loads((out2 / "summary.json").read_text())
    if proc.returncode == 143:  # stopped before the end (the usual case)
        assert summary["interrupted"] == "SIGTERM" and "run the same command again to resume" in stderr.decode()
    else:  # finished before the signal landed: nothing left to resume, still a valid run
        assert proc.returncode == 1, stderr.decode()[-3000:]
    cmd, env = cli(tmp_path, params, src, out2, "--batch", "2", "--host-devices", "1", cache=xla_cache)
    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 1, rerun.stderr[-3000:]
    assert "16/17 clips ok, 1 failed" in rerun.stdout
    assert len(same_results(reference, out2)) == 16
    assert np.isfinite(np.load(out2 / "k00.npz")["q"]).all()
