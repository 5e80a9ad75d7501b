"""The fuzz suite of ``jmocap reconstruct`` (issue 16): inputs that a hostile or clumsy user makes.

The cases come from ``tests/fuzz_inputs.py`` (deterministic; see its docstring for what each
expectation means). The invariants asserted for every run:

* no traceback anywhere: none on the CLI's stderr, no exception escaping ``jmocap.cli.main``;
* the documented exit status: 0 every clip ok, 1 some clips failed, 2 bad arguments or a
  structural input problem (with a one-line ``jmocap reconstruct: ...`` message), 130 SIGINT,
  143 SIGTERM;
* no clip fails because of another clip: every ``ok`` case of a mixed archive gets a result;
* every failure message is one line that names the file (its path below INPUT or the archive
  member) and a field (``field '...'``), a frame (``frame N``) or a limit (``max_...``), or
  says what is wrong with the file as a whole (``not valid JSON``, ``not a readable .npz file``), and no
  raw ``SomeError: ...``;
* nothing is written outside OUTPUT (the sandbox tree is compared before and after; TMPDIR is
  a sandbox folder that must be empty afterwards), and no code from the input runs (the pickle
  payloads' MARKER file never appears);
* summary.json is written whenever the run gets going (exit 0, 1, 130, 143).

Problems are collected over a whole run and reported grouped by cause, one line per case.

Default suite (about a minute on two cores): the generator's own checks, one CLI subprocess over
a mixed folder of ~60 per-clip cases (every format), and the most important archive-level cases
(most of them in this process through ``jmocap.cli.main``, the signals in subprocesses). The
full run (``make test-slow``, marker ``slow``): all ~380 per-clip cases in one folder, the same
cases packed as ``.zip`` / ``.tar`` / ``.tar.gz`` inputs and as jmocap clip archives, runs with
``coco17`` / ``h36m17`` parameters (random initialisation, small networks) for the clips of
those layouts, and every archive-level case.

Environment: ``JMOCAP_FUZZ_REPORT=DIR`` writes each run's grouped problems to ``DIR/<test>.json``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import pickle
import re
import signal
import stat
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import warnings
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

import fuzz_inputs as F

ROOT = Path(__file__).resolve().parents[1]
RUN_OPTS = ["--method", "kinematic", "--batch", "4", "--chunk", "32", "--bucket", "16", "--host-devices", "1",
            "--quiet"]
TIMEOUT_S = 600  # a subprocess run
INPROCESS_TIMEOUT_S = 120  # an in-process run (stopped by SIGALRM: a symlink loop must not hang the suite)
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


# =========================================================================================
# running the command
# =========================================================================================


@dataclass
class Run:
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    exception: str | None = None  # a traceback that escaped jmocap.cli.main (in-process runs)
    hung: bool = False  # stopped after TIMEOUT_S / INPROCESS_TIMEOUT_S


def _argv(inp: Path, out: Path, cache: str, extra=()) -> list[str]:
    return ["reconstruct", str(inp), str(out), *RUN_OPTS, "--cache-dir", cache, *map(str, extra)]


def _env(sandbox: Path, extra: dict | None = None) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "TMPDIR": str(sandbox / "tmp"),
           "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("XLA_FLAGS", None)
    return {**env, **(extra or {})}


def run_subprocess(sandbox: Path, inp: Path, out: Path, cache: str, extra=(), *, umask: int | None = None,
                   env: dict | None = None, timeout: float = TIMEOUT_S) -> Run:
    cmd = [sys.executable, "-m", "jmocap.cli", *_argv(inp, out, cache, extra)]
    t = time.perf_counter()
    pre = (lambda: os.umask(umask)) if umask is not None else None
    try:
        p = subprocess.run(cmd, env=_env(sandbox, env), capture_output=True, text=True, timeout=timeout,
                           preexec_fn=pre, errors="replace")
    except subprocess.TimeoutExpired as e:
        out = (e.stdout or b"").decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
        err = (e.stderr or b"").decode(errors="replace") if isinstance(e.stderr, bytes) else (e.stderr or "")
        return Run(None, out, err, time.perf_counter() - t, hung=True)
    return Run(p.returncode, p.stdout, p.stderr, time.perf_counter() - t)


class _Hang(BaseException):
    """Raised by SIGALRM in a run that takes too long (not an Exception: nothing swallows it)."""


def _alarm(signum, frame):
    raise _Hang


def run_inprocess(sandbox: Path, inp: Path, out: Path, cache: str, extra=(), *, umask: int | None = None) -> Run:
    """``jmocap.cli.main`` in this process (compiled programs stay in memory between runs).
    stdout/stderr are captured (thread tracebacks included: they print to ``sys.stderr``);
    TMPDIR is the sandbox's; warnings are shown, not raised (the suite's filter turns
    jmocap's RuntimeWarnings into errors, which a subprocess would not do)."""
    from jmocap import cli

    out_buf, err_buf = io.StringIO(), io.StringIO()
    old_tmp, old_mask = tempfile.tempdir, None
    tempfile.tempdir = str(sandbox / "tmp")
    old_handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    t = time.perf_counter()
    rc, exc, hung = None, None, False
    old_alarm = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(INPROCESS_TIMEOUT_S)
    try:
        if umask is not None:
            old_mask = os.umask(umask)
        with warnings.catch_warnings(), contextlib.redirect_stdout(out_buf), contextlib.redirect_stderr(err_buf):
            warnings.simplefilter("default")
            try:
                rc = cli.main(_argv(inp, out, cache, extra))
            except SystemExit as e:  # argparse
                rc = e.code if isinstance(e.code, int) else 2
            except _Hang:
                hung = True
            except BaseException:  # noqa: BLE001 - what must never happen
                exc = traceback.format_exc()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old_alarm)
        if old_mask is not None:
            os.umask(old_mask)
        tempfile.tempdir = old_tmp
        for s, h in old_handlers.items():
            if signal.getsignal(s) is not h:
                signal.signal(s, h)
    return Run(rc, out_buf.getvalue(), err_buf.getvalue(), time.perf_counter() - t, exc, hung)


# =========================================================================================
# what a run leaves behind
# =========================================================================================


def snapshot(root: Path, exclude: list[Path]) -> dict[str, tuple]:
    """Every entry under ``root`` but ``exclude`` (and what is under them): kind, size,
    mtime and mode (links: their target)."""
    ex = {os.path.abspath(e) for e in exclude} | {os.path.join(os.path.abspath(root), F.MARKER)}
    out: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        dirnames[:] = [n for n in dirnames if os.path.join(dirpath, n) not in ex]
        for n in dirnames + filenames:
            p = os.path.join(dirpath, n)
            if p in ex:
                continue
            try:
                st = os.lstat(p)
            except OSError:
                continue
            rel = os.path.relpath(p, root)
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir", stat.S_IMODE(st.st_mode))
            else:
                out[rel] = ("file", st.st_size, st.st_mtime_ns, stat.S_IMODE(st.st_mode))
    return out


def read_manifest(out: Path) -> tuple[dict[str, dict], list[str]]:
    """(latest entry per name, lines that are not JSON objects)."""
    entries, bad = {}, []
    path = out / "manifest.jsonl"
    if not path.is_file():
        return entries, bad
    for line in path.read_text(errors="replace").splitlines():
        if not line.strip():
            continue
        try:
            e = json.loads(line)
        except json.JSONDecodeError:
            bad.append(line[:200])
            continue
        if isinstance(e, dict) and "name" in e:
            entries[e["name"]] = e
        else:
            bad.append(line[:200])
    return entries, bad


def read_summary(out: Path) -> dict | None:
    try:
        return json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return None


def skipped_paths(summary: dict | None) -> list[str]:
    items = (summary or {}).get("skipped")
    out = []
    for s in items if isinstance(items, list) else []:
        out.append(str(s.get("path", s)) if isinstance(s, dict) else str(s))
    return out


# =========================================================================================
# problems, grouped by cause
# =========================================================================================


class Problems:
    def __init__(self, title: str):
        self.title = title
        self.groups: dict[str, list[str]] = {}

    def add(self, group: str, detail: str) -> None:
        self.groups.setdefault(group, []).append(_short(detail))

    def __bool__(self) -> bool:
        return bool(self.groups)

    def report(self) -> str:
        lines = [f"{self.title}: {sum(map(len, self.groups.values()))} problems in {len(self.groups)} groups"]
        for g, items in sorted(self.groups.items(), key=lambda kv: -len(kv[1])):
            lines.append(f"-- {g} ({len(items)})")
            lines += [f"   {i}" for i in items]
        return "\n".join(lines)

    def check(self, name: str) -> None:
        dest = os.environ.get("JMOCAP_FUZZ_REPORT")
        if dest:
            Path(dest).mkdir(parents=True, exist_ok=True)
            (Path(dest) / f"{re.sub(r'[^A-Za-z0-9_.-]+', '_', name)}.json").write_text(
                json.dumps({"title": self.title, "groups": self.groups}, indent=1))
        if self:
            pytest.fail(self.report(), pytrace=False)


def _short(text: str, n: int = 400) -> str:
    text = str(text).replace("\n", "\\n")
    return text if len(text) <= n else text[: n - 3] + "..."


def message_problems(msg: str, token: str) -> list[str]:
    """Why a failure message is not clean (empty: it is)."""
    out = []
    if not msg:
        return ["message: empty"]
    if token and token not in msg:
        out.append("message: does not name the file")
    if not re.search(F.DETAIL_RE, msg) and not re.search(F.FILE_LEVEL_RE, msg):
        out.append("message: names no field, frame or limit, nor a whole-file problem")
    if "\n" in msg.strip():
        out.append("message: more than one line")
    if re.search(F.UNCLEAN_RE, msg):
        out.append("message: raw exception text (SomeError: ... / traceback)")
    return out


def check_run_hygiene(problems: Problems, run: Run, sandbox: Path, before: dict, exclude: list[Path],
                      out: Path, *, summary_required: bool) -> None:
    """Hangs, tracebacks, MARKER, files outside OUTPUT, TMPDIR, summary.json."""
    if run.hung:
        problems.add("hang: the run was stopped after its time limit", f"{run.seconds:.0f} s")
    if run.exception:
        problems.add("exception escaped jmocap.cli.main", run.exception.strip().splitlines()[-1])
    if "Traceback (most recent call last)" in run.stderr:
        tb = run.stderr[run.stderr.index("Traceback (most recent call last)"):].splitlines()
        last = next((ln for ln in tb[1:] if ln and not ln.startswith(" ")), tb[-1])
        problems.add("traceback on stderr", last)
    marker = sandbox / F.MARKER  # (not in the snapshot: reported here)
    if marker.exists():
        problems.add("code from the input ran (MARKER written)", marker.read_text(errors="replace"))
    after = snapshot(sandbox, exclude)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    for k in changed[:20]:
        problems.add("file written, changed or removed outside OUTPUT", f"{k}: {before.get(k)} -> {after.get(k)}")
    tmp = sandbox / "tmp"
    left = sorted(p.relative_to(tmp).as_posix() for p in tmp.rglob("*")) if tmp.is_dir() else []
    if left:
        problems.add("left behind in TMPDIR", ", ".join(left[:10]))
    if summary_required and read_summary(out) is None:
        problems.add("summary.json", f"not written (exit {run.rc})")


@dataclass
class Expect:
    """What must happen to the clips of one case (or one clip archive member)."""

    key: str
    owns: object  # name -> bool
    expect: str
    layout: str
    mention: tuple[str, ...]
    token: str  # a failure message must contain this (the file)
    clips: int | None = 1
    distinct: bool = False  # ok clips of the case have different frame counts


def case_expects(chosen: list[F.Case], token_prefix: str = "") -> list[Expect]:
    return [Expect(c.id, c.owns, c.expect, c.layout, c.mention, token_prefix + c.id, c.clips, c.distinct)
            for c in chosen]


def check_clips(problems: Problems, expects: list[Expect], entries: dict[str, dict], out: Path,
                run_layout: str) -> None:
    """Per case: how many clips, ok or failed as expected, clean messages, finite results."""
    owned: set[str] = set()
    for e in expects:
        names = [n for n in entries if e.owns(n)]
        owned.update(names)
        lo = 0 if (e.clips is None and e.expect == "either") else (1 if e.clips is None else e.clips)
        hi = None if e.clips is None else e.clips
        if len(names) < lo or (hi is not None and len(names) > hi):
            problems.add("wrong number of clips for a case (missing from the manifest, merged or duplicated)",
                         f"{e.key}: expected {e.clips if e.clips is not None else '>= 1'}, got {names}")
        oks = [entries[n].get("frames") for n in names if entries[n].get("status") == "ok"]
        if e.distinct and len(oks) > 1 and len(set(oks)) < len(oks):
            problems.add("clips whose names collide were merged (the same sequence twice)",
                         f"{e.key}: frames {oks} for {names}")
        for n in names:
            entry = entries[n]
            other_layout = e.layout != run_layout
            if entry.get("status") == "ok":
                if e.expect == "fail":
                    problems.add("invalid input got a result (expected a failure)", f"{e.key}: {n}")
                if other_layout and (entry.get("layout_conversion") or {}).get("from") != e.layout:
                    problems.add("clip of another layout got a result without its conversion recorded",
                                 f"{e.key}: {n} ({e.layout}): {entry.get('layout_conversion')}")
                _check_result(problems, e.key, out, entry)
                continue
            err = str(entry.get("error") or "")
            if e.expect == "ok":
                problems.add("valid clip failed (no clip may fail for another's sake)", f"{e.key}: {err}")
            for why in message_problems(err, e.token):
                problems.add(why, f"{e.key}: {err}")
            if e.expect == "fail" and e.mention and not any(m in err for m in e.mention):
                problems.add("message: lacks the expected field / limit",
                             f"{e.key}: wants one of {list(e.mention)}: {err}")
    for n in sorted(set(entries) - owned):
        problems.add("manifest has a clip no case made", f"{n!r}: {entries[n].get('status')} {entries[n].get('error', '')}")


def _check_result(problems: Problems, key: str, out: Path, entry: dict) -> None:
    f = entry.get("file")
    path = out / f if isinstance(f, str) else None
    if path is None or not path.is_file():
        problems.add("result file missing for an ok clip", f"{key}: {f!r}")
        return
    try:
        with np.load(path, allow_pickle=False) as r:
            q = r["q"]
        if not np.isfinite(q).all():
            problems.add("result not finite", f"{key}: {f}")
    except Exception as e:  # noqa: BLE001
        problems.add("result file unreadable", f"{key}: {f}: {e}")


def check_summary_consistency(problems: Problems, out: Path, entries: dict[str, dict]) -> None:
    s = read_summary(out)
    if s is None:
        return
    ok = sum(1 for e in entries.values() if e.get("status") == "ok")
    if s.get("ok") != ok or s.get("failed") != len(entries) - ok:
        problems.add("summary.json disagrees with the manifest",
                     f"summary ok={s.get('ok')} failed={s.get('failed')}; manifest ok={ok} failed={len(entries) - ok}")


# =========================================================================================
# fixtures
# =========================================================================================


@dataclass
class Sandbox:
    root: Path
    inp: Path = field(init=False)
    out: Path = field(init=False)

    def __post_init__(self):
        self.inp = self.root / "in"
        self.out = self.root / "a" / "b" / "out"
        (self.root / "tmp").mkdir(parents=True, exist_ok=True)
        self.out.parent.mkdir(parents=True, exist_ok=True)  # (OUTPUT's own parents may be created)

    @property
    def marker(self) -> Path:
        return self.root / F.MARKER


def mixed_run(sandbox: Sandbox, expects: list[Expect], inp: Path, cache: str, *, title: str,
              extra=(), run_layout: str = "body25", want_rc: int = 1) -> Problems:
    """One CLI subprocess over ``inp``; every invariant of a mixed archive."""
    exclude = [sandbox.out, sandbox.root / "tmp"]
    before = snapshot(sandbox.root, exclude)
    run = run_subprocess(sandbox.root, inp, sandbox.out, cache, extra)
    problems = Problems(f"{title} (exit {run.rc}, {run.seconds:.1f} s)")
    if run.rc != want_rc:
        problems.add("exit code", f"expected {want_rc}, got {run.rc}: {run.stderr.strip().splitlines()[-3:]}")
    check_run_hygiene(problems, run, sandbox.root, before, exclude, sandbox.out, summary_required=True)
    entries, bad = read_manifest(sandbox.out)
    for line in bad:
        problems.add("manifest line that is not a JSON object", line)
    check_clips(problems, expects, entries, sandbox.out, run_layout)
    check_summary_consistency(problems, sandbox.out, entries)
    return problems


@pytest.fixture
def sandbox(tmp_path) -> Sandbox:
    return Sandbox(tmp_path)


@pytest.fixture(scope="module")
def layout_params(tmp_path_factory, xla_cache):
    """``--params`` / ``--config`` of kinematic parameters for coco17 and h36m17 clips (random
    initialisation, small networks: the fuzz runs check plumbing, not accuracy)."""
    import jax

    from jmocap.methods.kinematic import KinematicConfig, init_params
    from jmocap.model import load_model
    from jmocap.nets import NetConfig
    from jmocap.weights import save_params

    d = tmp_path_factory.mktemp("layout_params")
    out = {}
    model = load_model(with_mjx=False)
    for layout in ("coco17", "h36m17"):
        cfg = KinematicConfig(layout=layout, nets=NetConfig(tp_width=16, tp_blocks=1))
        key = jax.random.key(0, impl="unsafe_rbg")
        params = jax.jit(lambda k, cfg=cfg: init_params(k, model, cfg))(key)
        save_params(d / f"{layout}.msgpack", params)
        (d / f"{layout}.json").write_text(json.dumps({"layout": layout, "nets": {"tp_width": 16, "tp_blocks": 1}}))
        out[layout] = ["--params", str(d / f"{layout}.msgpack"), "--config", str(d / f"{layout}.json")]
    return out


# =========================================================================================
# the generator itself
# =========================================================================================


def test_generator_is_complete_and_deterministic(tmp_path):
    all_cases = F.cases()
    assert len(all_cases) + len(F.archive_cases()) >= 300
    by_format = {c.format for c in all_cases}
    assert by_format == {"clip", "openpose", "coco", "mmpose", "vp3d", "array"}
    for fmt in by_format:  # each format has valid and broken cases, and the fast subset covers it
        mine = [c for c in all_cases if c.format == fmt]
        assert {"ok", "fail"} <= {c.expect for c in mine}, fmt
        assert any(c.fast for c in mine), fmt
    assert 40 <= len(F.cases(fast=True)) <= 70
    for c in all_cases:
        assert c.expect in ("ok", "fail", "either") and c.layout in ("body25", "coco17", "h36m17"), c.id
    # deterministic: the fast subset twice gives the same bytes
    trees = []
    for k in range(2):
        root = tmp_path / f"t{k}"
        F.build_folder(root, F.cases(fast=True), tmp_path / F.MARKER)
        trees.append({p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()})
    assert trees[0].keys() == trees[1].keys()
    assert [k for k in trees[0] if trees[0][k] != trees[1][k]] == []
    assert not (tmp_path / F.MARKER).exists()  # building never unpickles


def test_payloads_are_live_and_bombs_are_real(tmp_path):
    """The MARKER assertions mean something only if the payloads do run when unpickled, and the
    bomb assertions only if the streams really expand past 1 GiB."""
    marker = tmp_path / F.MARKER
    pickle.loads(pickle.dumps(F.Payload(marker, "exec-ok")))
    pickle.loads(pickle.dumps(F.Payload(marker, "system-ok", "system")))
    assert marker.read_text().split() == ["exec-ok", "system-ok"]
    stream, crc, size = F.deflated_zeros()
    assert size > F.GIB and len(stream) < size / 500
    d = zlib.decompressobj(-15)
    head = d.decompress(stream[:4096], 1 << 20)
    assert head == bytes(len(head)) and len(head) == 1 << 20
    F.bomb_npz(tmp_path / "bomb.npz")
    with zipfile.ZipFile(tmp_path / "bomb.npz") as z:
        info = z.getinfo("keypoints.npy")
        assert info.file_size > F.GIB and info.compress_size < 2 << 20
        with z.open(info) as f:
            assert f.read(6) == b"\x93NUMPY"


# =========================================================================================
# default suite: one mixed archive, the important archive-level cases
# =========================================================================================


def test_fast_mixed_archive(sandbox, xla_cache):
    """~60 per-clip cases of every format in one folder, one CLI run: the valid ones (body25)
    get results whatever their neighbours are, the others fail alone with clean messages."""
    chosen = F.build_folder(sandbox.inp, F.cases(fast=True), sandbox.marker)
    problems = mixed_run(sandbox, case_expects(chosen), sandbox.inp, xla_cache,
                         title=f"fast mixed archive ({len(chosen)} cases)")
    problems.check("fast_mixed_archive")


def _archive_params():
    out = []
    for c in F.archive_cases():
        marks = [] if c.fast else [pytest.mark.slow]
        out.append(pytest.param(c, id=c.id, marks=marks))
    return out


def _symlinks_work(tmp: Path) -> bool:
    try:
        (tmp / ".probe_link").symlink_to(".")
        (tmp / ".probe_link").unlink()
        return True
    except OSError:
        return False


@pytest.mark.parametrize("case", _archive_params())
def test_archive_case(case: F.ArchiveCase, sandbox, xla_cache):
    if case.needs_non_root and IS_ROOT:
        pytest.skip("permission-based case: running as root")
    if case.needs_symlinks and not _symlinks_work(sandbox.root):
        pytest.skip("no symbolic links here")
    spec = case.build(sandbox.root)
    chmods = spec.extra.get("chmod", [])
    try:
        problems = (_signal_case if "signal" in spec.extra else _archive_run)(case, spec, sandbox, xla_cache)
    finally:
        for p, mode in chmods:
            with contextlib.suppress(OSError):
                p.chmod(mode)
    problems.check(f"archive_{case.id}")


class TmpWatch:
    """The most bytes TMPDIR held while a run was going (polled): a zip bomb must be refused
    before it is extracted."""

    def __init__(self, path: Path, interval: float = 0.02):
        self.path, self.interval, self.max_bytes = path, interval, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def _poll(self):
        while not self._stop.is_set():
            total = 0
            for dirpath, _, files in os.walk(self.path):
                for f in files:
                    with contextlib.suppress(OSError):
                        total += os.lstat(os.path.join(dirpath, f)).st_size
            self.max_bytes = max(self.max_bytes, total)
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def _exclude_for(spec: F.RunSpec, sandbox: Sandbox) -> list[Path]:
    ex = [sandbox.root / "tmp"]
    if not spec.output.is_file():
        ex.append(spec.output)
    return ex


def _archive_run(case: F.ArchiveCase, spec: F.RunSpec, sandbox: Sandbox, cache: str) -> Problems:
    exclude = _exclude_for(spec, sandbox)
    before = snapshot(sandbox.root, exclude)
    runner = run_inprocess if spec.inprocess else run_subprocess
    with TmpWatch(sandbox.root / "tmp") as watch:
        run = runner(sandbox.root, spec.input, spec.output, cache, spec.args, umask=spec.umask)
    problems = Problems(f"{case.id} (exit {run.rc}, {run.seconds:.1f} s)")
    limit = spec.extra.get("max_tmp_bytes")
    if limit is not None and watch.max_bytes > limit:
        problems.add("a bomb was extracted before it was refused",
                     f"TMPDIR held {watch.max_bytes / 2**20:.0f} MiB (limit of this check {limit / 2**20:.0f} MiB)")
    _check_archive_outcome(problems, case, spec, run, sandbox, before, exclude)
    if spec.extra.get("rerun") and run.rc in (0, 1):
        again = runner(sandbox.root, spec.input, spec.output, cache, spec.args, umask=spec.umask)
        if again.rc != run.rc:
            problems.add("exit code", f"re-run: expected {run.rc} again, got {again.rc}: {again.stderr[-300:]}")
        s = read_summary(spec.output) or {}
        if (s.get("run") or {}).get("ok", 0) != 0:
            problems.add("re-run redid finished clips (or read OUTPUT as input)", json.dumps(s.get("run")))
        entries, _ = read_manifest(spec.output)
        if set(entries) != set(spec.clips):
            problems.add("re-run: OUTPUT read as input", f"clips {sorted(entries)}")
    return problems


def _stderr_messages(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("jmocap reconstruct:")]


def _check_archive_outcome(problems: Problems, case: F.ArchiveCase, spec: F.RunSpec, run: Run,
                           sandbox: Sandbox, before: dict, exclude: list[Path]) -> None:
    out = spec.output
    refused = spec.extra.get("refused")
    if run.rc not in case.exit:
        tail = [ln for ln in run.stderr.strip().splitlines() if ln.strip()][-3:]
        problems.add("exit code", f"expected {sorted(case.exit)}, got {run.rc}: {tail}")
    check_run_hygiene(problems, run, sandbox.root, before, exclude, out,
                      summary_required=run.rc in (0, 1, 130, 143) and out.is_dir())
    if run.rc == 2:
        msgs = _stderr_messages(run.stderr)
        if len(msgs) != 1:
            problems.add("exit 2 without exactly one 'jmocap reconstruct: ...' line", _short(run.stderr, 600))
        elif case.message and not any(m in msgs[0] for m in case.message):
            problems.add("exit 2 message lacks what it is about", f"wants one of {list(case.message)}: {msgs[0]}")
        elif re.search(F.UNCLEAN_RE, msgs[0]):
            problems.add("message: raw exception text (SomeError: ... / traceback)", msgs[0])
        return
    if run.rc not in (0, 1) or not out.is_dir():
        return
    entries, bad = read_manifest(out)
    for line in bad:
        problems.add("manifest line that is not a JSON object", line)
    summary = read_summary(out)
    for name, want in spec.clips.items():
        e = entries.get(name)
        if e is None:
            problems.add("clip missing from the manifest", f"{name!r} (want {want})")
            continue
        status = e.get("status")
        err = str(e.get("error") or "")
        if want == "ok" and status != "ok":
            problems.add("valid clip failed (no clip may fail for another's sake)", f"{name}: {err}")
        if want == "fail" and status == "ok":
            problems.add("invalid input got a result (expected a failure)", name)
        if status != "ok":
            for why in message_problems(err, ""):
                problems.add(why, f"{name!r}: {err}")
            wants = spec.mention.get(name)
            if wants and not any(m in err for m in wants):
                problems.add("message: lacks the expected field / limit", f"{name!r}: wants {list(wants)}: {err}")
    for name in spec.absent:
        if name in entries:
            problems.add("a non-clip (or escaping path) is in the manifest", f"{name!r}: {entries[name]}")
    for name in spec.extra.get("outside_links", []):
        hits = [n for n in entries if n == name or n.startswith(name + "/")]
        for n in hits:
            if entries[n].get("status") == "ok":
                problems.add("a link outside INPUT was followed and read", f"{n!r}")
            elif "outside" not in str(entries[n].get("error")):
                problems.add("message: lacks the expected field / limit",
                             f"{n!r}: wants 'outside': {entries[n].get('error')}")
        if not hits and not any(name in p for p in skipped_paths(summary)):
            problems.add("a link outside INPUT neither failed nor listed in summary['skipped']", name)
    if refused:
        if any(refused in n and e.get("status") == "ok" for n, e in entries.items()):
            problems.add("a member refused by tarfile's 'data' filter was reconstructed", refused)
        elif not any(refused in p for p in skipped_paths(summary)) and not any(refused in n for n in entries):
            problems.add("a refused member is neither a failure nor listed in summary['skipped']", refused)
    for sub in spec.skipped:
        if not any(sub in p for p in skipped_paths(summary)):
            problems.add("not listed in summary['skipped']", f"{sub!r}: skipped = {skipped_paths(summary)[:10]}")
    if spec.extra.get("exact_clips") and set(entries) != set(spec.clips):
        problems.add("clips reconstructed more than once (through a link) or missing",
                     f"expected {sorted(spec.clips)}, got {sorted(entries)}")
    check_summary_consistency(problems, out, entries)
    for p in spec.extra.get("stale", []):
        if p.exists():
            problems.add("stale temporary file in OUTPUT not removed", p.relative_to(out).as_posix())
    for p in spec.extra.get("keep", []):
        if not p.exists():
            problems.add("a user's file in OUTPUT was removed", p.relative_to(out).as_posix())
    if spec.umask is not None:
        want = 0o666 & ~spec.umask
        for p in sorted(out.rglob("*")):
            if p.is_file() and not p.name.startswith(".") and stat.S_IMODE(p.stat().st_mode) != want:
                problems.add("file mode is not 0o666 & ~umask",
                             f"{p.relative_to(out)}: {oct(stat.S_IMODE(p.stat().st_mode))}, want {oct(want)}")


def _default_signals() -> None:
    """In the child before exec: SIGINT and SIGTERM unblocked, with their default dispositions, as
    a shell starts a command. A blocked mask and an ignored disposition survive exec, and the
    pytest worker's main thread can have SIGINT blocked by something an earlier test ran (seen
    in the full suite: the run then never saw the signal and finished its 400 clips)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _signal_case(case: F.ArchiveCase, spec: F.RunSpec, sandbox: Sandbox, cache: str) -> Problems:
    """Start the CLI, send the signal once the first result is written, check the exit status,
    summary.json (``interrupted: true``), the finished results and that nothing is half-written."""
    sig = getattr(signal, spec.extra["signal"])
    exclude = _exclude_for(spec, sandbox)
    before = snapshot(sandbox.root, exclude)
    cmd = [sys.executable, "-m", "jmocap.cli", *_argv(spec.input, spec.output, cache, spec.args)]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, env=_env(sandbox.root), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_signals)
    problems = Problems(case.id)
    sent = False
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            entries, _ = read_manifest(spec.output)
            if any(e.get("status") == "ok" for e in entries.values()):
                proc.send_signal(sig)
                sent = True
                break
            time.sleep(0.01)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    run = Run(proc.returncode, stdout, stderr, time.perf_counter() - t)
    problems.title = f"{case.id} (exit {run.rc}, {run.seconds:.1f} s)"
    if not sent:
        problems.add("the run ended (or never wrote a result) before the signal could be sent",
                     f"exit {run.rc}: {stderr[-300:]}")
        return problems
    if run.rc not in case.exit:
        problems.add("exit code", f"expected {sorted(case.exit)}, got {run.rc}: {stderr.strip().splitlines()[-3:]}")
    check_run_hygiene(problems, run, sandbox.root, before, exclude, spec.output, summary_required=True)
    summary = read_summary(spec.output)
    # the issue asks for `"interrupted": true`; the signal's name says as much and more
    if summary is not None and summary.get("interrupted") not in (True, spec.extra["signal"]):
        problems.add("summary.json lacks interrupted: true",
                     json.dumps({k: summary.get(k) for k in ("interrupted", "ok", "failed", "pending")}))
    entries, bad = read_manifest(spec.output)
    for line in bad:
        problems.add("manifest line that is not a JSON object", line)
    for n, e in entries.items():
        if e.get("status") == "ok":
            p = spec.output / str(e.get("file"))
            if not p.is_file() or p.stat().st_size != e.get("bytes"):
                problems.add("a finished result is missing or not its recorded size", n)
    tmp = sorted(p.name for p in spec.output.rglob("*.tmp")) if spec.output.is_dir() else []
    if tmp:
        problems.add("temporary files left in OUTPUT after a graceful stop", ", ".join(tmp[:5]))
    return problems


# =========================================================================================
# slow: every case, every container, every layout
# =========================================================================================


@pytest.mark.slow
def test_full_mixed_folder(sandbox, xla_cache):
    """All per-clip cases in one folder, one run with the shipped body25 parameters."""
    chosen = F.build_folder(sandbox.inp, F.cases(), sandbox.marker)
    problems = mixed_run(sandbox, case_expects(chosen), sandbox.inp, xla_cache,
                         title=f"full mixed folder ({len(chosen)} cases)")
    problems.check("full_mixed_folder")


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["coco17", "h36m17"])
def test_full_layout_run(layout, sandbox, xla_cache, layout_params):
    """The cases whose clips are ``layout``, with parameters of that layout: every valid one
    (COCO, MMPose, VideoPose3D, arrays) gets a result."""
    chosen = F.build_folder(sandbox.inp, F.cases(layout=layout), sandbox.marker)
    problems = mixed_run(sandbox, case_expects(chosen), sandbox.inp, xla_cache, extra=layout_params[layout],
                         run_layout=layout, title=f"{layout} run ({len(chosen)} cases)")
    problems.check(f"full_layout_{layout}")


@pytest.mark.slow
@pytest.mark.parametrize("container", ["zip", "tar", "tar.gz"])
def test_full_container(container, sandbox, xla_cache):
    """The same cases packed into one ``.zip`` / ``.tar`` / ``.tar.gz`` of loose files."""
    staging = sandbox.root / "staging"
    chosen = F.build_folder(staging, F.cases(containers=True), sandbox.marker)
    packed = F.pack(staging, sandbox.inp / f"cases.{container}")
    problems = mixed_run(sandbox, case_expects(chosen), packed, xla_cache,
                         title=f"{container} of loose files ({len(chosen)} cases)")
    problems.check(f"full_container_{container}")


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["folder", "zip", "tar.gz"])
def test_full_clip_archive(kind, sandbox, xla_cache):
    """The jmocap clip cases as members of a clip archive (manifest.jsonl)."""
    dest = sandbox.inp / ("arch" if kind == "folder" else f"arch.{kind}")
    path, members = F.build_clip_archive(dest, kind, F.cases(formats=["clip"]), sandbox.marker,
                                         sandbox.root / "staging")
    expects = [Expect(m.case or m.name, (lambda n, m=m: n == m.name), m.expect, m.layout, m.mention, m.file)
               for m in members]
    problems = mixed_run(sandbox, expects, path, xla_cache, title=f"clip archive {kind} ({len(members)} members)")
    problems.check(f"full_clip_archive_{kind}")
