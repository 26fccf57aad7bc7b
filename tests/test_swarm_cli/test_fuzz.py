"""Fuzzing the public API and the CLI with bad inputs (fixed seed, a few hundred calls).

Every call must either work or fail with the project's clear error (ValueError from
the API; exit code 1 or 2 and one "error:" line from the CLI). Any other exception, a
traceback, or a non-finite/negative value silently accepted where only finite
positive values make sense, fails the test.
"""

from __future__ import annotations

import contextlib
import io
import math
import random

import numpy as np
import pytest

import taichi_swarm
from swarm_cli.main import main as swarm

BAD_NUMBERS = [float("nan"), float("inf"), -float("inf"), -1, 0, -1e-9, 1e40, 2**31 + 5, 2**63, 1.5]
BAD_TEXT = ["", "abc", "nan", "inf", "-1", "0", "1e9", "99999999999999999999", "None", "3;rm", "\x00"]


def _api_call(rng: random.Random):
    """One random make()/step()/set_state() call with at least one suspicious argument."""
    kwargs = dict(task="coverage", num_envs=2, num_agents=3, comm="rc", comm_radius=1.0, seed=0, array="numpy")
    name = rng.choice(list(kwargs) + ["max_steps", "success_threshold", "formation_radius"])
    pool = BAD_NUMBERS + ["coverage", "line", "soccer", None, True, "3", [3]]
    kwargs[name] = rng.choice(pool)
    task = kwargs.pop("task")
    args = (task, kwargs.pop("num_envs"), kwargs.pop("num_agents"))
    return args, kwargs, name


def _must_refuse(name: str, value) -> bool:
    """Values no argument of this name may silently take."""
    if isinstance(value, float) and not math.isfinite(value):
        return True
    if name in ("num_envs", "num_agents", "max_steps") and isinstance(value, (int, float)) and value < 1:
        return True
    return (
        name in ("comm_radius", "success_threshold", "formation_radius")
        and isinstance(value, (int, float))
        and (value < 0 or value > 3.4e38)
    )


def test_api_fuzz():
    rng = random.Random(1234)
    accepted = refused = 0
    for _ in range(200):
        args, kwargs, name = _api_call(rng)
        value = kwargs.get(name, dict(zip(("task", "num_envs", "num_agents"), args, strict=True)).get(name))
        if isinstance(args[1], (int, float)) and not isinstance(args[1], bool) and args[1] > 4096:
            continue  # valid but huge batches are the oversize test's business, not a fuzz call's
        try:
            env = taichi_swarm.make(*args, **kwargs)
        except ValueError:
            refused += 1
            continue
        assert not _must_refuse(name, value), f"make{args} {kwargs} accepted {name}={value!r}"
        accepted += 1
        env.reset()
        B, M = env.num_envs, env.num_agents
        bad_actions = rng.choice(
            [
                np.full((B, M), 7, dtype=np.int64),
                np.full((B, M), -1, dtype=np.int64),
                np.zeros((B, M + 1), dtype=np.int64),
                np.zeros((B, M), dtype=np.float64),
                np.zeros((B, M), dtype=np.int64),
            ]
        )
        try:
            env.step(bad_actions)
        except ValueError:
            pass
        else:
            assert bad_actions.dtype == np.int64 and bad_actions.shape == (B, M) and bad_actions.min() >= 0
            assert bad_actions.max() < 5
        state = env.get_state()
        bad = state["pos"] * rng.choice([np.nan, np.inf, 1e39, 1.0])
        try:
            env.set_state(pos=bad)
        except ValueError:
            assert not np.isfinite(bad.astype(np.float32)).all()
        else:
            assert np.isfinite(bad.astype(np.float32)).all()
        obs = env.step(np.zeros((B, M), dtype=np.int64))[0]
        assert np.isfinite(obs["self"]).all() and np.isfinite(obs["entities"]).all()
    print(f"\napi fuzz: 200 tried, {refused} refused with ValueError, {accepted} accepted and stepped cleanly")
    assert accepted > 10 and refused > 50  # the fuzz exercised both sides


@pytest.fixture(scope="module")
def tiny_policy(tiny_policy_file, tmp_path_factory):
    """(conftest's tiny policy file, a folder of this module's own for outputs)"""
    return tiny_policy_file, tmp_path_factory.mktemp("fuzz")


def test_cli_fuzz(tiny_policy):
    path, d = tiny_policy
    cases = {
        "eval": ([path, "--episodes", "2"], ["--agents", "--episodes", "--seed", "--comm-radius", "--comm", "--task"]),
        "zero-shot": ([path, "--sizes", "2", "--episodes", "2"], ["--sizes", "--episodes", "--comm-radius", "--seed"]),
        "train": (
            ["--run-dir", str(d / "never"), "--updates", "1", "--no-compile", "--no-progress", "--ppo.num-envs", "2"],
            [
                "--ppo.lr",
                "--ppo.clip",
                "--ppo.gamma",
                "--ppo.entropy-coef",
                "--ppo.value-coef",
                "--agents",
                "--torch-threads",
                "--seed",
                "--comm-radius",
                "--ppo.num-steps",
                "--eval-episodes",
                "--ppo.minibatches",
            ],
        ),
        "import": ([path, "--out", str(d / "x.pt")], ["--comm-radius", "--task", "--comm"]),
        "replay": ([path, "--stats"], ["--port"]),
    }
    # options whose value must be a finite number in a range: nan/inf/negative must never run
    numeric = {
        "--episodes",
        "--agents",
        "--comm-radius",
        "--ppo.lr",
        "--ppo.clip",
        "--ppo.entropy-coef",
        "--ppo.value-coef",
        "--torch-threads",
        "--ppo.num-steps",
        "--eval-episodes",
        "--ppo.minibatches",
        "--updates",
        "--threads",
        "--num-envs",
    }
    rng = random.Random(99)
    outcomes = {"refused": 0, "ran": 0}
    for _ in range(120):
        command = rng.choice(list(cases))
        base, options = cases[command]
        option = rng.choice(options)
        value = rng.choice([str(x) for x in BAD_NUMBERS] + BAD_TEXT)
        argv = [command, *base, option, value]
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = swarm(argv)
            except SystemExit as exc:  # argparse / tyro refusing the value
                code = exc.code
        text = err.getvalue()
        assert "Traceback" not in text, f"{argv}: {text[-800:]}"
        if code == 0:
            outcomes["ran"] += 1
            bad_number = value.lower() in ("nan", "inf", "-inf") or value.startswith("-")
            assert not (option in numeric and bad_number), f"{argv} was accepted"
        else:
            assert code in (1, 2), f"{argv} exited {code}: {text[-500:]}"
            said = text.lower()  # "error: ..." (our checks, argparse) or tyro's "invalid choice ... for --x"
            assert "error" in said or "invalid" in said, f"{argv}: no error message: {text[-500:]}"
            outcomes["refused"] += 1
    print(
        f"\ncli fuzz: {sum(outcomes.values())} tried, {outcomes['refused']} refused in one line, {outcomes['ran']} ran"
    )
    assert outcomes["refused"] > 50


# ----------------------------------------------------------------------------- settings that would run wrongly
def refused(argv: list[str], *words: str) -> str:
    """``swarm argv`` exits 2 with one error line naming ``words``: no traceback, no tyro box."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = swarm(argv)
    lines = [line for line in err.getvalue().splitlines() if line.strip() and not line.startswith("[Taichi]")]
    assert code == 2, f"{argv} exited {code}: {err.getvalue()[-600:]}"
    assert len(lines) == 1 and "error:" in lines[0], f"{argv}: {lines}"
    assert "│" not in lines[0] and "Traceback" not in err.getvalue()
    for word in words:
        assert word in lines[0], f"{argv}: {word!r} not in {lines[0]!r}"
    return lines[0]


def _policy_file(path: str, task: str, agents: int = 3) -> str:
    import torch

    from trainer.checkpoint import save
    from trainer.model import ModelConfig, SwarmPolicy

    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=8, rounds=1))
    setting = {"task": task, "agents": agents, "comm": "uc", "comm_radius": 1.0}
    save(path, {"model_config": policy.config.to_dict(), "model": policy.state_dict(), "task": setting})
    return path


def test_settings_that_would_run_wrongly_are_refused(tiny_policy, tmp_path):
    path, _ = tiny_policy
    formation = _policy_file(str(tmp_path / "formation.pt"), "formation")
    refused(["eval", formation, "--task", "coverage", "--episodes", "1"], "formation", "coverage")
    refused(["zero-shot", formation, "--task", "line", "--sizes", "3", "--episodes", "1"], "formation", "line")
    refused(["eval", path, "--seed", str(2**40), "--episodes", "1"], "--seed", "2^40")
    refused(["zero-shot", path, "--seed", "-1", "--sizes", "2", "--episodes", "1"], "--seed")
    base = ["train", "--updates", "1", "--no-compile", "--no-progress"]
    for option, value, words in (
        ("--ppo.lr-end", "5", ("lr_end", "<= 1")),
        ("--seed", str(2**31), ("seed", "2^31")),
        ("--seed", str(2**64), ("seed",)),
        ("--model.rounds", "1000000", ("rounds", "64")),
        ("--model.hidden", "1000000", ("hidden", "4096")),
        ("--ppo.num-steps", str(10**12), ("num_steps",)),
        ("--ppo.num-envs", str(10**9), ("num_envs",)),
        ("--task", "soccer", ("task",)),
        ("--agents", "0", ("agents",)),
    ):
        run_dir = tmp_path / f"never-{option.strip('-')}"
        line = refused([*base, "--run-dir", str(run_dir), option, value], *words)
        assert "Overflow" not in line
        assert not run_dir.exists(), f"a refused train ({option} {value}) left {run_dir}"
    sizes = ["curriculum", "--run-dir", str(tmp_path / "cur"), "--sizes", "3", "3", "--no-compile", "--no-progress"]
    refused(sizes, "--sizes", "repeat")
    refused(["curriculum", "--run-dir", str(tmp_path / "cur"), "--task", "soccer"], "task")
    refused(["curriculum", "--run-dir", str(tmp_path / "cur"), "--ppo.lr-end", "5"], "lr_end")
    assert not (tmp_path / "cur").exists()


def test_a_rollout_larger_than_memory_is_refused_with_the_memory_it_needs(tmp_path):
    from trainer.config import PPOConfig, TrainConfig

    cfg = TrainConfig.of(agents=5000, ppo=PPOConfig(num_envs=2**20, num_steps=2**16), run_dir=str(tmp_path / "r"))
    with pytest.raises(ValueError, match=r"needs \d[\d.]* GiB for its rollout, this machine has"):
        cfg.validate()


def test_cuda_on_a_machine_without_it_is_one_line(tiny_policy, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    path, _ = tiny_policy
    refused(["eval", path, "--arch", "cuda", "--episodes", "1"], "cuda")
    run_dir = tmp_path / "gpu"
    refused(["train", "--arch", "cuda", "--run-dir", str(run_dir), "--updates", "1", "--no-progress"], "cuda")
    refused(["train", "--device", "cuda", "--run-dir", str(run_dir), "--updates", "1", "--no-progress"], "cuda")
    assert not run_dir.exists()
    import subprocess
    import sys

    code = "import taichi_swarm\ntry:\n    taichi_swarm.make('coverage', 2, 3, arch='cuda')\n"
    code += "except ValueError as e:\n    print(e)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "no CUDA GPU" in out.stdout and "Traceback" not in out.stderr, out.stdout + out.stderr  # (a fresh Taichi)


def test_unsigned_crafted_and_special_policy_files_are_one_line(tiny_policy, tmp_path):
    import os

    import torch

    from trainer.checkpoint import load, save

    path, _ = tiny_policy
    payload = load(path)
    unsigned = tmp_path / "unsigned.pt"
    torch.save({k: v for k, v in payload.items() if k not in ("sha256", "model_sha256")} | {"version": 1}, unsigned)
    refused(["eval", str(unsigned), "--episodes", "1"], "no sha256", "--trust-unsigned")
    refused(["export", str(unsigned), "--out", str(tmp_path / "ex")], "--trust-unsigned")
    assert not (tmp_path / "ex").exists()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        assert swarm(["eval", str(unsigned), "--episodes", "1", "--trust-unsigned"]) == 0, err.getvalue()
    crafted = tmp_path / "rounds.pt"
    save(str(crafted), payload | {"model_config": payload["model_config"] | {"rounds": 10**9}})
    refused(["eval", str(crafted), "--episodes", "1"], "rounds", "64")
    flipped = bytearray(open(path, "rb").read())
    flipped[_middle_of_largest_record(path)] ^= 0xFF  # (not a zip trailer byte, which holds no content)
    (tmp_path / "flipped.pt").write_bytes(bytes(flipped))
    refused(["eval", str(tmp_path / "flipped.pt"), "--episodes", "1"], "corrupted")
    os.mkfifo(tmp_path / "fifo.pt")
    refused(["eval", str(tmp_path / "fifo.pt"), "--episodes", "1"], "not a regular file")


def _middle_of_largest_record(path: str) -> int:
    """The offset of the middle byte of the largest record's data in a torch zip file."""
    import struct
    import zipfile

    with open(path, "rb") as f, zipfile.ZipFile(path) as z:
        info = max(z.infolist(), key=lambda i: i.compress_size)
        f.seek(info.header_offset)
        name_len, extra_len = struct.unpack("<HH", f.read(30)[26:30])
    return info.header_offset + 30 + name_len + extra_len + info.compress_size // 2


def test_tyro_refusals_are_one_line(tiny_policy):
    path, _ = tiny_policy
    refused(["eval", path, "--episodes", "abc"], "--episodes")
    refused(["eval", path, "--bogus"], "--bogus")
    refused(["eval"], "CHECKPOINT")
    refused(["train", "--ppo.num-envs", "x"], "--ppo.num-envs")
    refused(["export", path], "--out")


def test_spec_bounds_are_checked_before_a_dry_run(tmp_path):
    from baselines.config import ALGORITHMS
    from reproduce.spec import SpecError, load_spec

    head = 'name = "x"\ndescription = "x"\n[[cells]]\nid = "c"\ntable = 1\ntask = "coverage"\ncomm = "uc"\n'
    train = head + 'kind = "train"\nupdates = 2\n'
    baseline = head + 'kind = "baseline"\nframes = 1000\nagents = 3\n'
    for body, words in (
        (train + "agents = 1000000\n", "agents"),
        (train + "agents = 3\nppo = { num_envs = 1_000_000_000_000 }\n", "num_envs"),
        (train + "agents = 3\npolish_updates = 2\npolish_lr = inf\n", "polish_lr"),
        (train + "agents = 3\nfinal_episodes = 1_000_000_000\n", "final_episodes"),
        (baseline + 'algorithm = "ppo2"\n', "algorithm"),
        (baseline + 'algorithm = "mappo"\nnum_envs = 1_000_000_000_000\n', "num_envs"),
    ):
        spec = tmp_path / "spec.toml"
        spec.write_text(body)
        with pytest.raises(SpecError, match=words):
            load_spec(str(spec))
    try:
        from benchmarl.algorithms import algorithm_config_registry
    except ImportError:
        return
    assert tuple(sorted(algorithm_config_registry)) == ALGORITHMS


def test_sizes_and_hangs_are_refused_up_front(tiny_policy, tmp_path):
    import os
    import socket
    import time

    from swarm_cli.reproduce import check_address

    path, _ = tiny_policy
    refused(["zero-shot", path, "--sizes", "1-1000000000", "--episodes", "1"], "--sizes", "1000")
    refused(["execute", str(tmp_path), "--threads", "1000000"], "--threads")
    refused(["execute", str(tmp_path), "--episodes", "100000"], "--episodes")
    refused(["reproduce", "--spec", "smoke", "--seeds", "1000000000", "--dry-run"], "--seeds")
    refused(["reproduce", "--spec", "smoke", "--first-seed", str(2**31), "--dry-run"], "--seeds")
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    start = time.perf_counter()
    with pytest.raises(ValueError, match="no Ray head answers"):
        check_address(f"127.0.0.1:{port}", timeout=2.0)
    with pytest.raises(ValueError, match="HOST:PORT"):
        check_address("nowhere")
    assert time.perf_counter() - start < 10
    assert not os.listdir(tmp_path)


def test_crafted_inputs_of_import_and_reproduce_are_one_line(tmp_path):
    import torch

    torch.save({"models": [{"encoder.0.weight": 3}], "ob_rms": None}, tmp_path / "pub.pt")
    refused(["import", str(tmp_path / "pub.pt"), "--out", str(tmp_path / "o.pt")], "non-tensor")
    (tmp_path / "deep.toml").write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    refused(["reproduce", "--spec", str(tmp_path / "deep.toml"), "--dry-run"], "nested too deeply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["deep.toml", "pub.pt"]
