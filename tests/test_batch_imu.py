"""``jmocap reconstruct`` on an archive of six-IMU clips (jmocap.batch_imu): results equal the
functional API's (jmocap.methods.pip_imu), a broken clip is recorded as failed while the others
finish, a re-run resumes, and a 2D method is refused."""

from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest

from jmocap import physics as P
from jmocap.batch_imu import is_imu_archive
from jmocap.cli import main
from jmocap.data.archive import Archive
from jmocap.methods import pip_imu as PI
from jmocap.model import character
from jmocap.results import load_result


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    root = tmp_path_factory.mktemp("imu") / "archive"
    assert main(["data", "synth", "--imu", "--physics", "--out", str(root), "--clips", "3", "--frames-per-clip", "30",
                 "--seed", "21", "--quiet"]) == 0
    return root


def test_reconstruct_an_imu_archive(archive, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(archive, src)
    assert is_imu_archive(src) and not is_imu_archive(tmp_path)
    with Archive(src) as a:
        names = a.names()
        good = a.load(names[0])
    (src / f"{names[2]}.npz").write_bytes(b"not a zip")  # a broken clip
    out = tmp_path / "out"
    assert main(["reconstruct", str(src), str(out), "--bvh", "--quiet"]) == 1  # one clip failed
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    status = {e["name"]: e["status"] for e in lines}
    assert status == {names[0]: "ok", names[1]: "ok", names[2]: "failed"}
    assert all((out / e["bvh"]).is_file() for e in lines if e["status"] == "ok")
    failed = next(e for e in lines if e["status"] == "failed")
    assert names[2] in failed["error"]
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["ok"], summary["failed"], summary["method"]) == (2, 1, "pip_imu")

    # the result is the functional API's motion of the same clip, with its BODY_25 joints
    r = load_result(out / f"{names[0]}.npz")
    assert r["method"] == "pip_imu" and r["layout"] == "body25" and r["forces_estimated"] is True
    model = character(good.height_m, good.mass_kg)
    params, net = PI.load_params()
    m = jax.jit(PI.reconstruct)(params, model, PI.IMUInputs.from_clip(good, model, 64), PI.PIPIMUConfig(net=net))
    T = good.num_frames
    assert r["q"].shape == (T, model.nq) and r["grf"].shape == (T, 4, 3)
    np.testing.assert_allclose(r["q"], np.asarray(m.q[:T]), atol=1e-5)
    np.testing.assert_allclose(r["grf"], np.asarray(m.grf[:T]), atol=1e-3)
    kp = jax.vmap(lambda q: P.keypoints(model, q, "body25"))(m.q[:T])
    np.testing.assert_allclose(r["keypoints3d"], np.asarray(kp), atol=1e-5)

    # a re-run skips the finished clips and retries the failed one
    capsys.readouterr()
    assert main(["reconstruct", str(src), str(out), "--bvh", "--quiet"]) == 1
    assert "2 already done" in capsys.readouterr().out


def test_a_2d_method_or_option_is_refused(archive, tmp_path, capsys):
    assert main(["reconstruct", str(archive), str(tmp_path / "out"), "--method", "kinematic", "--quiet"]) == 2
    assert "IMU clips" in capsys.readouterr().err
    assert main(["reconstruct", str(archive), str(tmp_path / "out"), "--mass-kg", "70", "--quiet"]) == 2
    assert "--mass-kg" in capsys.readouterr().err


def test_eval_on_an_imu_archive(archive, tmp_path):
    """``jmocap eval`` on IMU clips: the ground truth scores zero pose error against itself, the
    method's rows are finite, unknown methods are refused."""
    out = tmp_path / "eval"
    assert main(["eval", str(archive), "--out", str(out), "--methods", "pip_imu", "ground_truth",
                 "--max-clips", "2", "--quiet"]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    assert set(doc["means"]) == {"pip_imu", "ground_truth"} and len(doc["clips"]) == 2
    gt, est = doc["means"]["ground_truth"], doc["means"]["pip_imu"]
    for k in ("sip_deg", "ang_deg", "mpjpe_mm", "mesh_mm", "grf_err_pct_bw"):
        assert gt[k] == pytest.approx(0.0, abs=1e-3), k
        assert np.isfinite(est[k]) and est[k] > 0, k
    assert est["pnp_pct"] == pytest.approx(100.0) and 0 <= est["contact_f1_pct"] <= 100
    assert "| **pip** |" in (out / "metrics.md").read_text()
    assert main(["eval", str(archive), "--out", str(out), "--methods", "trajopt", "--quiet"]) == 2


def test_eval_on_an_imu_archive_reports_progress(archive, tmp_path, capsys):
    """Without --quiet, ``jmocap eval`` on IMU clips reports each clip's pip row on stderr (its
    progress callback once crashed on a keyword argument)."""
    assert main(["eval", str(archive), "--out", str(tmp_path / "eval"), "--methods", "pip_imu",
                 "--max-clips", "1"]) == 0
    assert ": pip MPJPE " in capsys.readouterr().err
