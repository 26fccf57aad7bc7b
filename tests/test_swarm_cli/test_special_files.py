"""Special files and sizes: a FIFO or a device given as an input is refused in one line
without blocking (taichi_swarm.files.read_input / check_input), one given as an output is
refused before the work and left as it was (ensure_writable), '' is refused rather than
skipped, and counts no run can reach are refused up front."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal

import pytest

from swarm_cli.main import main as swarm


class Hung(BaseException):
    """Raised by the guard below: a BaseException, so that no command catches it as an error."""


@contextlib.contextmanager
def no_hang(seconds: int = 120):
    """Turn a command blocked on a FIFO into a failure instead of a hung suite (the signal
    interrupts the blocking open or read). Not a timing assertion: nothing here takes long."""

    def hung(signum, frame):
        raise Hung(f"blocked for {seconds} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def refused(argv: list[str], *words: str, command=swarm) -> str:
    """``command argv`` (``swarm``, or a benchmark's main) exits 2 with one error line holding
    ``words``; no traceback."""
    out, err = io.StringIO(), io.StringIO()
    with no_hang(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = command(argv)
    lines = [line for line in err.getvalue().splitlines() if line.strip() and not line.startswith("[Taichi]")]
    assert code == 2, f"{argv} exited {code}: {err.getvalue()[-600:]}"
    assert len(lines) == 1 and "error:" in lines[0], f"{argv}: {lines}"
    assert "Traceback" not in err.getvalue()
    for word in words:
        assert word in lines[0], f"{argv}: {word!r} not in {lines[0]!r}"
    return lines[0]


@pytest.fixture(scope="module")
def policy(tiny_policy_file):
    return tiny_policy_file  # (conftest's: read, never written)


@pytest.fixture(scope="module")
def exported(policy, tmp_path_factory):
    from deploy.export import export

    out = str(tmp_path_factory.mktemp("export") / "ex")
    export(policy, out)
    return out


def fifo(path) -> str:
    os.mkfifo(path)
    return str(path)


def is_fifo(path) -> bool:
    import stat

    return stat.S_ISFIFO(os.lstat(path).st_mode)


# ----------------------------------------------------------------------------- inputs
def test_fifo_and_device_inputs_are_refused_without_blocking(policy, exported, tmp_path):
    manifest_fifo = tmp_path / "manifest-fifo"
    manifest_fifo.mkdir()
    fifo(manifest_fifo / "manifest.json")
    refused(["execute", str(manifest_fifo), "--episodes", "1"], "manifest", "FIFO")

    onnx_file = json.load(open(os.path.join(exported, "manifest.json")))["files"]["encode"]["file"]
    for name, make, kind in (
        ("onnx-fifo", lambda p: os.mkfifo(p), "FIFO"),
        ("onnx-zero", lambda p: os.symlink("/dev/zero", p), "character device"),
    ):
        d = tmp_path / name
        shutil.copytree(exported, d)
        os.unlink(d / onnx_file)
        make(d / onnx_file)
        refused(["execute", str(d), "--episodes", "1"], "ONNX model", kind)

    refused(["reproduce", "--spec", fifo(tmp_path / "spec.toml"), "--dry-run"], "--spec", "FIFO")
    out = tmp_path / "z.png"
    refused(["plot", "--zero-shot", fifo(tmp_path / "zs.json"), "--out", str(out)], "--zero-shot", "FIFO")
    assert not out.exists()
    os.symlink("/dev/zero", tmp_path / "zero.pt")
    refused(["eval", str(tmp_path / "zero.pt"), "--episodes", "1"], "checkpoint", "character device")
    refused(["replay", fifo(tmp_path / "rec.npz"), "--stats"], "recording", "FIFO")


def test_read_input_bounds_the_size(tmp_path):
    from taichi_swarm.files import InputFileError, read_input

    (tmp_path / "big.json").write_bytes(b"x" * 100)
    assert read_input(str(tmp_path / "big.json"), "--spec", 100) == b"x" * 100
    with pytest.raises(InputFileError, match="--spec"):
        read_input(str(tmp_path / "big.json"), "--spec", 99)


# ----------------------------------------------------------------------------- outputs
def test_fifo_empty_and_dirless_outputs_are_refused_and_left_alone(policy, exported, tmp_path):
    pipe = fifo(tmp_path / "out")
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.jsonl").write_text('{"update": 1, "env_steps": 64, "reward": -0.5}\n')
    zero_shot = tmp_path / "zs.json"
    zero_shot.write_text(json.dumps({"results": [{"agents": 3, "success_rate": 0.5}]}))
    for argv, option in (
        (["eval", policy, "--episodes", "1", "--json", pipe], "--json"),
        (["eval", policy, "--episodes", "1", "--record", pipe], "--record"),
        (["eval", policy, "--episodes", "1", "--json", ""], "--json"),
        (["eval", policy, "--episodes", "1", "--record", ""], "--record"),
        (["eval", policy, "--episodes", "1", "--video", ""], "--video"),
        (["eval", policy, "--episodes", "1", "--json", str(tmp_path / "nodir" / "r.json")], "--json"),
        (["zero-shot", policy, "--episodes", "1", "--json", ""], "--json"),
        (["execute", exported, "--episodes", "1", "--json", pipe], "--json"),
        (["execute", exported, "--episodes", "1", "--record", ""], "--record"),
        (["plot", str(run), "--out", pipe], "--out"),
        (["plot", "--zero-shot", str(zero_shot), "--out", pipe], "--out"),
    ):
        refused(argv, option)
        assert is_fifo(pipe), argv
    from benchmarks.sim import main as bench_sim

    for out in (pipe, ""):
        refused(["--quick", "--json", out], "--json", command=bench_sim)
        assert is_fifo(pipe)
    assert sorted(os.listdir(tmp_path)) == ["out", "run", "zs.json"]
    assert os.listdir(run) == ["metrics.jsonl"]


def test_world_record_fifo_is_refused(tmp_path):
    pytest.importorskip("zenoh")
    pipe = fifo(tmp_path / "rec.npz")
    refused(["world", "--export", str(tmp_path / "ex"), "--record", pipe], "--record", "FIFO")
    assert is_fifo(pipe)


def test_the_atomic_writer_leaves_no_temp_file_and_replaces_no_fifo(tmp_path):
    from taichi_swarm.files import atomic_write_bytes, atomic_write_json

    def fails(f):
        f.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write_bytes(str(tmp_path / "a.json"), fails)
    assert os.listdir(tmp_path) == []
    pipe = fifo(tmp_path / "p.json")
    with pytest.raises(ValueError, match="FIFO"):
        atomic_write_json(pipe, {"a": 1})
    assert is_fifo(pipe) and os.listdir(tmp_path) == ["p.json"]


# ----------------------------------------------------------------------------- sizes
def test_counts_no_run_can_reach_are_refused_up_front(exported, tmp_path):
    refused(["execute", exported, "--episodes", "1", "--hold", str(10**8)], "--hold", "episode length")
    refused(["execute", exported, "--episodes", "1", "--delay", str(10**8)], "--delay", "episode length")
    refused(["execute", exported, "--episodes", "1", "--burst-loss", "0.1", "--burst-len", "inf"], "--burst-len")
    refused(["models", "coverage-uc-m3", "--task", "line"], "--task")

    head = 'name = "x"\ndescription = "x"\n[[cells]]\nid = "c"\ntable = 1\ntask = "coverage"\ncomm = "uc"\n'
    for body, word in (
        ('kind = "train"\nagents = 3\nupdates = 1_000_000_000_000\n', "updates"),
        ('kind = "train"\nagents = 3\nupdates = 2\npolish_updates = 1_000_000_000_000\n', "polish_updates"),
        ('kind = "train"\nagents = 3\nupdates = 2\neval_episodes = 1_000_000_000_000\n', "eval_episodes"),
        ('kind = "curriculum"\nsizes = [3, 4]\nmax_updates_per_stage = 1_000_000_000_000\n', "max_updates_per_stage"),
    ):
        spec = tmp_path / "spec.toml"
        spec.write_text(head + body)
        refused(["reproduce", "--spec", str(spec), "--dry-run"], word)

    run_dir = tmp_path / "cur"
    refused(
        ["curriculum", "--sizes", "3", "--max-updates-per-stage", "1", "--polish-updates", "1",
         "--polish-lr", "inf", "--run-dir", str(run_dir)],
        "--polish-lr",
    )  # fmt: skip
    assert not run_dir.exists()  # refused before stage 1 trains: no polish-of.json, no run at all
