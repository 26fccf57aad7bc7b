"""A command that fails leaves the directory as it found it: no temp file of a video, a
recording, a plot or a benchmark's JSON, no run directory of a refused or failed run; and
it says why in one line."""

from __future__ import annotations

import contextlib
import errno
import io
import os

import pytest

from swarm_cli.main import main as swarm


def run(argv: list[str], command=swarm) -> tuple[int, str]:
    """``command(argv)`` (``swarm``, or a benchmark's main): its exit status and last error line."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = command(argv)
    lines = [line for line in err.getvalue().splitlines() if "error:" in line]
    assert "Traceback" not in err.getvalue(), err.getvalue()[-800:]
    return code, lines[-1] if lines else ""


def disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.fixture(scope="module")
def policy(tiny_policy_file):
    return tiny_policy_file


def test_a_video_that_fails_to_write_leaves_nothing(policy, tmp_path, monkeypatch):
    import matplotlib.animation

    def half_written(self, filename, *args, **kwargs):
        open(filename, "wb").write(b"GIF89a")  # the writer got this far, then the disk filled
        disk_full()

    monkeypatch.setattr(matplotlib.animation.Animation, "save", half_written)
    code, line = run(["eval", policy, "--episodes", "1", "--video", str(tmp_path / "v.gif")])
    assert code == 1 and "No space left" in line
    assert os.listdir(tmp_path) == []
    import matplotlib.figure

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", disk_full)
    code, line = run(["eval", policy, "--episodes", "1", "--video", str(tmp_path / "frames")])
    assert code == 1 and os.listdir(tmp_path) == []  # the PNG folder it made is gone too


def test_a_recording_that_fails_to_write_leaves_nothing(policy, tmp_path, monkeypatch):
    import rerun as rr

    def flush_fails(self, *args, **kwargs):
        raise RuntimeError("Failed to write: No space left on device (os error 28)")

    monkeypatch.setattr(rr.RecordingStream, "flush", flush_fails)
    code, line = run(["eval", policy, "--episodes", "1", "--record", str(tmp_path / "e.rrd")])
    assert code == 1 and "cannot write the recording" in line
    assert os.listdir(tmp_path) == []


def test_outputs_that_cannot_be_written_are_refused_before_any_work(policy):
    from benchmarks.sim import main as bench_sim

    for argv, command in (
        (["eval", policy, "--episodes", "1", "--record", "/proc/x.rrd"], swarm),
        (["eval", policy, "--episodes", "1", "--video", "/proc/x.gif"], swarm),
        (["eval", policy, "--episodes", "1", "--json", "/proc/x.json"], swarm),
        (["--quick", "--json", "/proc/x.json"], bench_sim),
    ):
        code, line = run(argv, command)
        assert code == 2 and "cannot write" in line and "/proc" in line, (argv, line)


def test_a_plot_that_fails_to_write_leaves_nothing(tmp_path, monkeypatch):
    import json

    import matplotlib.figure

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    rows = [{"update": u, "env_steps": 64 * u, "reward": -0.5 + 0.1 * u} for u in (1, 2)]
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))

    def half_written(self, fname, *args, **kwargs):
        open(fname, "wb").write(b"\x89PNG")
        disk_full()

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", half_written)
    code, line = run(["plot", str(run_dir)])
    assert code == 1 and "No space left" in line
    assert sorted(os.listdir(run_dir)) == ["metrics.jsonl"]


def test_plot_refuses_files_that_are_not_what_it_draws(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.jsonl").write_text('{"update": 1}\n')
    code, line = run(["plot", str(run_dir)])
    assert code == 2 and "env_steps" in line
    (tmp_path / "list.json").write_text("[1, 2]")
    code, line = run(["plot", "--zero-shot", str(tmp_path / "list.json"), "--out", str(tmp_path / "z.png")])
    assert code == 2 and "zero-shot --json" in line
    assert sorted(os.listdir(tmp_path)) == ["list.json", "run"] and os.listdir(run_dir) == ["metrics.jsonl"]


def test_a_benchmark_json_that_fails_to_write_leaves_nothing(tmp_path, monkeypatch):
    from benchmarks import sim as bench_sim

    monkeypatch.setattr(bench_sim.json, "dump", disk_full)
    with pytest.raises(OSError):
        bench_sim.write_json(str(tmp_path / "b.json"), {"rows": []})
    assert os.listdir(tmp_path) == []


def test_a_run_that_fails_before_its_first_checkpoint_leaves_no_run_directory(tmp_path, monkeypatch):
    import taichi_swarm
    from trainer.config import PPOConfig, TrainConfig
    from trainer.model import ModelConfig
    from trainer.train import train

    def make_fails(*args, **kwargs):
        raise ValueError("the simulator refused")

    monkeypatch.setattr(taichi_swarm, "make", make_fails)
    run_dir = tmp_path / "runs" / "r"
    cfg = TrainConfig.of(
        agents=2, updates=1, run_dir=str(run_dir), progress=False, compile=False,
        model=ModelConfig(hidden=8, rounds=1), ppo=PPOConfig(num_envs=2, num_steps=4, epochs=1, minibatches=1),
    )  # fmt: skip
    with pytest.raises(ValueError, match="simulator refused"):
        train(cfg)
    assert not run_dir.exists()
    run_dir.mkdir(parents=True)  # a directory that was there before stays
    with pytest.raises(ValueError, match="simulator refused"):
        train(cfg)
    assert run_dir.is_dir()


def test_a_stopped_replay_viewer_takes_its_server_with_it(tmp_path, monkeypatch):
    """`swarm replay --serve-web` stopped by Ctrl-C or `kill PID` (both arrive as a
    KeyboardInterrupt) stops the viewer's whole process group, the server it started too."""
    import signal
    import sys
    import time

    from deploy import replay

    launcher = (
        "import subprocess, sys, time\n"
        "server = subprocess.Popen(['sleep', '60'])\n"
        "open(sys.argv[1], 'w').write(str(server.pid))\n"
        "time.sleep(60)\n"
    )
    monkeypatch.setattr(replay, "rerun_command", lambda: [sys.executable, "-c", launcher])
    pid_file = tmp_path / "server.pid"

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 2.0)
        assert replay.view(str(pid_file)) == 0
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    server = int(pid_file.read_text())

    def running(pid: int) -> bool:
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().split(")")[-1].split()[0] != "Z"  # (a zombie has exited)
        except FileNotFoundError:
            return False

    deadline = time.time() + 10
    while running(server) and time.time() < deadline:
        time.sleep(0.1)
    assert not running(server), "the viewer's server outlived the command"


def test_bench_train_defaults_fit_the_machine():
    from benchmarks.train import default_presets
    from trainer.config import PRESETS

    assert "gpu" in PRESETS and "gpu" not in default_presets("cpu") and "fast" in default_presets("cpu")
    assert default_presets("cuda") == tuple(PRESETS)
