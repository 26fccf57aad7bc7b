"""Run directories, checkpoints, resume, and a subprocess smoke run of each
trainer command."""

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time

import pytest
import torch

from swarm_cli.main import main as swarm_main
from taichi_swarm.sim import Sim
from trainer import checkpoint
from trainer.config import PPOConfig, TrainConfig
from trainer.model import ModelConfig
from trainer.train import train

TINY_PPO = PPOConfig(num_envs=4, num_steps=8, epochs=1, minibatches=2)
TINY_MODEL = ModelConfig(hidden=16, rounds=1)


def tiny(tmp_path, **kw):
    base = dict(
        task="coverage",
        agents=2,
        updates=3,
        eval_every=2,
        eval_episodes=4,
        checkpoint_every=1,
        run_dir=str(tmp_path / "run"),
        progress=False,
        torch_threads=1,
        model=TINY_MODEL,
        ppo=TINY_PPO,
        compile=False,
    )
    return TrainConfig.of(**(base | kw))


def test_run_dir_resume_and_refusal_to_overwrite(tmp_path):
    cfg = tiny(tmp_path, updates=2)
    train(cfg)
    run = cfg.run_dir
    assert {"config.json", "metrics.jsonl", "checkpoint.pt", "policy.pt", "summary.json", "curves.png"} <= set(
        os.listdir(run)
    )
    with pytest.raises(FileExistsError, match="--resume"):
        train(cfg)
    before = checkpoint.load(run)
    summary = train(resume=run, updates=4)
    after = checkpoint.load(run)
    assert before["counters"]["update"] == 2 and after["counters"]["update"] == 4 == summary["update"]
    lines = [json.loads(x) for x in open(os.path.join(run, "metrics.jsonl"))]
    assert [r["update"] for r in lines] == [1, 2, 3, 4]
    assert not torch.equal(before["model"]["agent_encoder.weight"], after["model"]["agent_encoder.weight"])
    # the CLI's resume takes --progress / --no-progress (a display setting, not part of the experiment)
    assert swarm_main(["train", "--resume", run, "--updates", "5", "--progress"]) == 0
    assert json.load(open(os.path.join(run, "config.json")))["progress"] is True
    assert swarm_main(["train", "--resume", run, "--updates", "6", "--no-progress"]) == 0
    assert json.load(open(os.path.join(run, "config.json")))["progress"] is False
    assert swarm_main(["train", "--resume", run, "--updates", "7"]) == 0  # neither: the run's own setting
    assert json.load(open(os.path.join(run, "config.json")))["progress"] is False
    # where it runs may change too: a run stopped on one machine goes on on another
    assert swarm_main(["train", "--resume", run, "--updates", "8", "--arch", "auto", "--device", "auto"]) == 0
    config = json.load(open(os.path.join(run, "config.json")))
    assert (config["arch"], config["device"], config["updates"]) == ("auto", "auto", 8)
    assert swarm_main(["train", "--resume", run, "--updates", "9"]) == 0
    assert json.load(open(os.path.join(run, "config.json")))["arch"] == "auto"  # kept, as progress is


def test_resume_drops_metrics_written_after_the_checkpoint(tmp_path):
    cfg = tiny(tmp_path, updates=3, checkpoint_every=2)
    train(cfg)  # checkpoints at 2 and at the end (3)
    payload = checkpoint.load(cfg.run_dir)
    counters = payload["counters"]  # pretend the run died right after update 3 was logged
    counters["env_steps"], counters["update"] = counters["env_steps"] // counters["update"] * 2, 2
    checkpoint.save(os.path.join(cfg.run_dir, "checkpoint.pt"), payload)
    train(resume=cfg.run_dir)
    lines = [json.loads(x)["update"] for x in open(os.path.join(cfg.run_dir, "metrics.jsonl"))]
    assert lines == [1, 2, 3]
    # a last line torn by a kill mid-write is dropped; a broken line before it is named
    metrics = os.path.join(cfg.run_dir, "metrics.jsonl")
    with open(metrics, "a") as f:
        f.write('{"update": 4, "rew')
    train(resume=cfg.run_dir, updates=4)
    assert [json.loads(x)["update"] for x in open(metrics)] == [1, 2, 3, 4]
    with open(metrics) as f:
        text = f.read()
    with open(metrics, "w") as f:
        f.write(text.replace('{"update": 2', '{"update": 2 oops', 1))
    with pytest.raises(ValueError, match=r"metrics.jsonl: line 2 is not JSON"):
        train(resume=cfg.run_dir, updates=5)


def test_bad_checkpoints_give_clear_errors(tmp_path):
    with pytest.raises(checkpoint.CheckpointError, match="does not exist"):
        checkpoint.load(str(tmp_path / "nope.pt"))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(checkpoint.CheckpointError, match="corrupted"):
        checkpoint.load(str(bad))
    cfg = tiny(tmp_path, updates=1)
    train(cfg)
    good = os.path.join(cfg.run_dir, "checkpoint.pt")
    data = open(good, "rb").read()
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(checkpoint.CheckpointError, match="truncated"):
        checkpoint.load(str(trunc))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        train(resume=str(tmp_path / "missing-run"))
    # weights into a mismatched network
    from trainer.model import SwarmPolicy

    with pytest.raises(checkpoint.CheckpointError, match="do not fit"):
        checkpoint.load_weights(SwarmPolicy(ModelConfig(hidden=32)), checkpoint.load(good)["model"])
    with pytest.raises(checkpoint.CheckpointError, match="has model"):
        train(tiny(tmp_path, run_dir=str(tmp_path / "r2"), init_from=good, model=ModelConfig(hidden=32)))
    # a directory: its checkpoint.pt, else its policy.pt (a results/ folder), else a clear error
    published = tmp_path / "published"
    published.mkdir()
    with pytest.raises(checkpoint.CheckpointError, match="without checkpoint.pt or policy.pt"):
        checkpoint.load(str(published))
    shutil.copy(os.path.join(cfg.run_dir, "policy.pt"), published / "policy.pt")
    assert checkpoint.load(str(published))["counters"] == checkpoint.load(good)["counters"]


def test_config_validation_names_the_option(tmp_path):
    with pytest.raises(ValueError, match="task"):
        tiny(tmp_path, task="soccer").validate()
    with pytest.raises(ValueError, match="ppo.lr"):
        tiny(tmp_path, ppo=PPOConfig(lr=-1)).validate()
    with pytest.raises(ValueError, match="agents"):
        tiny(tmp_path, agents=0).validate()
    with pytest.raises(ValueError, match="repeated offset"):  # one key per size in eval_transfer
        tiny(tmp_path, transfer_offsets=(2, 2)).validate()


def swarm(*args, cwd):
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    return subprocess.run(
        [sys.executable, "-m", "swarm_cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


@pytest.mark.slow
def test_cli_train_eval_zero_shot_curriculum_plot(tmp_path):
    common = [
        "--updates",
        "2",
        "--eval-every",
        "2",
        "--eval-episodes",
        "4",
        "--no-progress",
        "--ppo.num-envs",
        "4",
        "--ppo.num-steps",
        "8",
        "--ppo.minibatches",
        "2",
        "--ppo.epochs",
        "1",
        "--model.hidden",
        "16",
        "--model.rounds",
        "1",
        "--torch-threads",
        "1",
        "--no-compile",
    ]
    r = swarm(
        "train", "--task", "formation", "--agents", "3", "--comm", "rc", "--run-dir", "run", *common, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert "eval S%" in r.stdout
    r = swarm("eval", "run", "--agents", "4", "--episodes", "5", "--json", "ev.json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    result = json.load(open(tmp_path / "ev.json"))
    assert "formation" in r.stdout and result["agents"] == 4 and result["actions"] == "greedy"
    r = swarm(
        "zero-shot", "run/checkpoint.pt", "--sizes", "2-3", "--episodes", "3", "--sampled", "--json", "zs.json",
        cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "sampled actions" in r.stdout
    zs = json.load(open(tmp_path / "zs.json"))  # the dense layout: no lists of its own
    assert zs["trained_agents"] == 3 and zs["trained_swarm"] == {} and len(zs["results"]) == 2
    curriculum = [
        "curriculum",
        "--task",
        "coverage",
        "--sizes",
        "2",
        "3",
        "--threshold",
        "0.99",
        "--max-updates-per-stage",
        "2",
        "--run-dir",
        "cur",
        "--fresh-eval-episodes",
        "6",
        *common[2:],  # (the stages set --updates)
    ]
    r = swarm(*curriculum, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    stages = json.load(open(tmp_path / "cur" / "curriculum.json"))["stages"]
    assert [s["agents"] for s in stages] == [2, 3]
    carried = [json.load(open(tmp_path / "cur" / f"stage-m{m}" / "config.json")) for m in (2, 3)]
    assert carried[1]["init_from"].endswith(os.path.join("stage-m2", "checkpoint.pt"))
    fresh = [s["fresh_eval"] for s in stages]  # each stage's final policy on fresh episodes
    assert [(f["episodes"], f["seed"], f["update"]) for f in fresh] == [(6, 777, 2), (6, 777, 2)]
    assert "fresh S%" in r.stdout and "6 greedy episodes, seed 777" in r.stdout
    saved = tmp_path / "cur" / "stage-m3" / "fresh-eval.json"
    before = saved.stat().st_mtime_ns
    assert fresh[1]["agents"] == 3 and fresh[1]["comm"] == "uc"  # the setting the stage trained in
    # resumed (with another radius, which a finished stage ignores): stages and evaluations are kept
    r = swarm(*curriculum, "--comm-radius", "0.5", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert saved.stat().st_mtime_ns == before
    assert json.load(open(tmp_path / "cur" / "curriculum.json"))["stages"] == stages
    r = swarm("plot", "run", cwd=tmp_path)
    assert r.returncode == 0 and (tmp_path / "run" / "curves.png").exists()
    # errors are one clear line, not a traceback
    r = swarm("eval", "missing.pt", cwd=tmp_path)
    assert r.returncode == 2 and "does not exist" in r.stderr and "Traceback" not in r.stderr
    r = swarm("train", "--task", "soccer", "--run-dir", "x", *common, cwd=tmp_path)
    assert r.returncode != 0 and "Traceback" not in r.stderr


def test_learning_rate_decays_linearly_to_lr_end(tmp_path):
    import dataclasses

    ppo = dataclasses.replace(TINY_PPO, lr=1e-3, lr_end=1e-4)
    lrs = []
    train(tiny(tmp_path, updates=4, ppo=ppo), on_update=lambda r: lrs.append(r["lr"]))
    assert lrs == pytest.approx([1e-3, 7e-4, 4e-4, 1e-4])


def test_transfer_sizes_are_evaluated_and_logged(tmp_path):
    cfg = tiny(tmp_path, agents=3, updates=2, transfer_offsets=(-2, -1, 1))
    summary = train(cfg)
    assert set(summary["last_eval"]["transfer"]) == {"1", "2", "4"}
    lines = [json.loads(x) for x in open(os.path.join(cfg.run_dir, "metrics.jsonl"))]
    assert set(lines[-1]["eval_transfer"]) == {"1", "2", "4"}
    line = tiny(tmp_path, task="line", agents=3, transfer_offsets=(-2, -1, 1), run_dir=str(tmp_path / "l"))
    from trainer.train import transfer_sizes

    assert transfer_sizes(line) == [2, 4]  # line needs M >= 2
    # sizes the network cannot take are left out (else the first evaluation raises, on every resume)
    padded = dataclasses.replace(
        cfg, sim=cfg.sim_at(10), transfer_offsets=(-1, 1, 2), model=ModelConfig(entity_mode="padded")
    )
    assert transfer_sizes(padded) == [9]  # coverage M = 11, 12: more landmarks than its 10 slots
    concat_model = ModelConfig(entity_mode="concat", num_landmarks=3)
    concat = dataclasses.replace(cfg, transfer_offsets=(-1, 1, 2), model=concat_model)
    assert transfer_sizes(concat) == []  # coverage's number of landmarks changes with M
    assert transfer_sizes(dataclasses.replace(concat, sim=Sim("formation", 3))) == [2, 4, 5]  # formation's does not


def test_non_finite_loss_never_reaches_the_weights(tmp_path):
    from trainer.model import SwarmPolicy
    from trainer.ppo import Rollout, ppo_update

    torch.manual_seed(0)
    policy = SwarmPolicy(TINY_MODEL)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    buf = Rollout.allocate(4, 2, 3, 3)
    zeros = torch.zeros(4, 2, 3)

    def nan_loss(*batch):
        logits, _ = policy(*batch[:3])
        return logits.sum() * float("nan"), torch.zeros(5)

    stats, skipped = ppo_update(policy, opt, [(buf, zeros, zeros)], TINY_PPO, nan_loss)
    assert skipped == TINY_PPO.epochs * TINY_PPO.minibatches
    for k, v in policy.state_dict().items():
        assert torch.equal(v, before[k]), k


@pytest.mark.parametrize(
    "flag,value", [("--ppo.clip", "nan"), ("--ppo.lr", "inf"), ("--ppo.entropy-coef", "nan"), ("--torch-threads", "0")]
)
def test_non_finite_hyperparameters_are_refused(tmp_path, capsys, flag, value):
    from swarm_cli.main import main as swarm

    assert swarm(["train", "--run-dir", str(tmp_path / "r"), flag, value, "--updates", "1"]) == 2
    err = capsys.readouterr().err
    assert flag.lstrip("-").replace("-", "_").split(".")[-1] in err.replace("-", "_")


def test_nan_weights_are_refused_on_load(tmp_path):
    cfg = tiny(tmp_path, updates=1)
    train(cfg)
    payload = checkpoint.load(cfg.run_dir)
    payload["model"]["comm_update.bias"][0] = float("nan")
    checkpoint.save(str(tmp_path / "nan.pt"), payload)
    with pytest.raises(checkpoint.CheckpointError, match="NaN"):
        checkpoint.load_policy(str(tmp_path / "nan.pt"))


@pytest.mark.slow
def test_compiled_update_trains(tmp_path):
    summary = train(tiny(tmp_path, updates=2, compile=True))
    assert summary["update"] == 2


def test_second_process_on_a_run_dir_is_refused_and_a_dead_holder_is_taken_over(tmp_path, lock_held_elsewhere):
    from trainer.rundir import RunDirLock, RunDirLocked, is_held

    run = str(tmp_path / "run")
    assert not is_held(run)  # (no lock file: nothing is created by asking)
    assert not os.path.exists(run)
    with lock_held_elsewhere(run) as pid:
        assert is_held(run)
        with pytest.raises(RunDirLocked, match=f"pid {pid}"):
            train(tiny(tmp_path, run_dir=run))
    assert not is_held(run)  # the holder was killed: the kernel dropped the lock
    with RunDirLock(run):  # the stale lock is taken over
        pass
    assert train(tiny(tmp_path, run_dir=run, updates=1))["update"] == 1


def test_several_team_sizes_in_one_run(tmp_path):
    seen = []
    cfg = tiny(
        tmp_path,
        agents=3,
        team_sizes=(2, 3),
        updates=2,
        transfer_offsets=(1,),
        ppo=PPOConfig(num_envs=4, num_steps=8, epochs=1, minibatches=2),
    )
    summary = train(cfg, on_update=seen.append)
    assert summary["update"] == 2 and summary["env_steps"] == 2 * 4 * 8
    payload = checkpoint.load(cfg.run_dir)
    assert len(payload["reward_scalers"]) == 2
    assert train(resume=cfg.run_dir, updates=3)["update"] == 3
    with pytest.raises(ValueError, match="multiple of the number of team_sizes"):
        train(tiny(tmp_path, team_sizes=(2, 3, 4), run_dir=str(tmp_path / "x")))
    with pytest.raises(ValueError, match="team_sizes must be >= 2"):
        train(tiny(tmp_path, task="line", team_sizes=(1, 2), run_dir=str(tmp_path / "y")))


def test_flipped_byte_in_weights_is_refused_and_leftovers_are_cleaned(tmp_path):
    cfg = tiny(tmp_path, updates=1)
    train(cfg)
    payload = checkpoint.load(cfg.run_dir)
    payload["model"]["comm_update.bias"][3] += 1e-3  # what a flipped byte does to a tensor...
    torch.save(payload, str(tmp_path / "flipped.pt"))  # ...saved without a new digest
    with pytest.raises(checkpoint.CheckpointError, match="sha256"):
        checkpoint.load(str(tmp_path / "flipped.pt"))
    # a kill between the checkpoint and policy writes, and a temp file left by a kill
    stale = checkpoint.load(os.path.join(cfg.run_dir, "policy.pt"))
    open(os.path.join(cfg.run_dir, ".tmp-abc"), "wb").close()
    train(resume=cfg.run_dir, updates=2)
    assert not [n for n in os.listdir(cfg.run_dir) if n.startswith(".tmp-")]
    final = checkpoint.load(os.path.join(cfg.run_dir, "policy.pt"))
    assert final["counters"] == checkpoint.load(os.path.join(cfg.run_dir, "checkpoint.pt"))["counters"]
    assert final["counters"]["update"] == 2 != stale["counters"]["update"]


def test_tensorboard_gets_the_same_scalars(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = tiny(tmp_path, updates=2, eval_every=2, tensorboard=True, transfer_offsets=(1,))
    train(cfg)
    acc = EventAccumulator(os.path.join(cfg.run_dir, "tensorboard"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"reward", "loss_value", "eval_success_rate", "eval_transfer/M3"} <= tags
    lines = [json.loads(x) for x in open(os.path.join(cfg.run_dir, "metrics.jsonl"))]
    assert [e.value for e in acc.Scalars("reward")] == pytest.approx([r["reward"] for r in lines], rel=1e-6)


def _weights(run_dir):
    return checkpoint.load(os.path.join(run_dir, "checkpoint.pt"))["model"]


def test_resume_continues_bit_identically(tmp_path):
    whole = tiny(tmp_path, updates=4, eval_every=100, run_dir=str(tmp_path / "whole"))
    train(whole)
    part = tiny(tmp_path, updates=2, eval_every=100, run_dir=str(tmp_path / "part"))
    train(part)
    train(resume=part.run_dir, updates=4)
    a, b = _weights(whole.run_dir), _weights(part.run_dir)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    la = [json.loads(x)["reward"] for x in open(os.path.join(whole.run_dir, "metrics.jsonl"))]
    lb = [json.loads(x)["reward"] for x in open(os.path.join(part.run_dir, "metrics.jsonl"))]
    assert la == lb


@pytest.mark.slow
def test_kill_9_during_training_then_resume_equals_an_uninterrupted_run(tmp_path):
    import signal
    import time

    whole = tiny(tmp_path, updates=8, eval_every=100, run_dir=str(tmp_path / "whole"))
    train(whole)
    run = str(tmp_path / "killed")
    code = (
        "import sys; sys.path.insert(0, {root!r}); sys.path.insert(0, {tests!r})\n"
        "from test_train_cli import tiny; from trainer.train import train; import pathlib\n"
        "train(tiny(pathlib.Path({tmp!r}), updates=8, eval_every=100, run_dir={run!r}))\n"
    ).format(
        root=os.path.join(os.path.dirname(__file__), "..", ".."),
        tests=os.path.dirname(__file__),
        tmp=str(tmp_path),
        run=run,
    )
    proc = subprocess.Popen([sys.executable, "-c", code])
    metrics = os.path.join(run, "metrics.jsonl")
    deadline = time.time() + 120
    while time.time() < deadline and (not os.path.exists(metrics) or len(open(metrics).readlines()) < 4):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(open(metrics).readlines()) < 8, "the run finished before it could be killed"
    train(resume=run, updates=8)
    a, b = _weights(whole.run_dir), _weights(run)
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_unwritable_outputs_fail_before_the_work_and_os_errors_are_one_line(tmp_path, capsys):
    from swarm_cli.main import main as swarm

    cfg = tiny(tmp_path, updates=1)
    train(cfg)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = swarm(["eval", cfg.run_dir, "--episodes", "2", "--json", str(blocker / "out.json")])
    err = capsys.readouterr().err
    assert code == 2 and "--json" in err and "not a writable directory" in err
    code = swarm(["eval", cfg.run_dir, "--episodes", "2", "--json", str(tmp_path)])
    assert code == 2 and "is a directory" in capsys.readouterr().err

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device", str(tmp_path / "run" / "checkpoint.pt"))

    import swarm_cli.train

    original = swarm_cli.train.eval_main
    swarm_cli.train.eval_main = full_disk
    try:
        assert swarm(["eval", "x"]) == 1
    finally:
        swarm_cli.train.eval_main = original
    err = capsys.readouterr().err
    assert "No space left on device" in err and "checkpoint.pt" in err and "Traceback" not in err


def test_checkpoints_that_cannot_resume_are_named(tmp_path):
    cfg = tiny(tmp_path, updates=1)
    train(cfg)
    ckpt = os.path.join(cfg.run_dir, "checkpoint.pt")
    payload = checkpoint.load(ckpt)
    del payload["counters"]
    checkpoint.save(ckpt, payload)
    with pytest.raises(checkpoint.CheckpointError, match="lacks"):
        train(resume=cfg.run_dir)
    payload = checkpoint.load(os.path.join(cfg.run_dir, "policy.pt"))
    full = tiny(tmp_path, updates=1, run_dir=str(tmp_path / "b"))
    train(full)
    payload = checkpoint.load(os.path.join(full.run_dir, "checkpoint.pt"))
    payload["train_config"]["bogus"] = 1
    checkpoint.save(os.path.join(full.run_dir, "checkpoint.pt"), payload)
    with pytest.raises(checkpoint.CheckpointError, match="bogus"):
        train(resume=full.run_dir)


def test_zero_shot_plot(tmp_path):
    from swarm_cli.main import main as swarm

    data = {"trained_agents": 3, "results": [{"agents": m, "success_rate": 1 / m} for m in (2, 3, 4)]}
    path = tmp_path / "z.json"
    path.write_text(json.dumps(data))
    out = tmp_path / "z.png"
    assert swarm(["plot", "--zero-shot", str(path), "--labels", "x", "--out", str(out)]) == 0
    assert out.stat().st_size > 5000
    assert swarm(["plot", "--zero-shot", str(path)]) == 2  # needs --out


def test_sigterm_takes_the_ctrl_c_path_and_exits_143(monkeypatch):
    import signal
    import time
    import types

    from swarm_cli.main import dispatch

    seen = []

    def command(argv):  # a command that is stopped by SIGTERM while it works
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(30)
        except KeyboardInterrupt as exc:
            seen.append(str(exc))
            raise
        return 0

    monkeypatch.setitem(sys.modules, "fake_swarm_command", types.SimpleNamespace(run=command))
    before = signal.getsignal(signal.SIGTERM)
    assert dispatch("swarm", {"work": ("fake_swarm_command:run", "")}, ["work"]) == 143
    assert seen == ["stopped by SIGTERM"]
    assert signal.getsignal(signal.SIGTERM) is before  # the handler lives only while the command runs
    assert dispatch("swarm", {"ok": ("fake_swarm_command:run", "")}, ["ok", "x"]) == 143  # still handled
    monkeypatch.setitem(sys.modules, "fake_swarm_command", types.SimpleNamespace(run=lambda argv: 0))
    assert dispatch("swarm", {"ok": ("fake_swarm_command:run", "")}, ["ok"]) == 0


@pytest.mark.slow
def test_kill_stops_a_background_training_run_with_its_checkpoint(tmp_path):
    """`kill PID` (SIGTERM) on `swarm train` saves the checkpoint at the update it stopped at,
    even when the shell that started the run in the background ignores SIGINT for it."""
    import signal
    import time

    run = str(tmp_path / "run")
    cmd = [sys.executable, "-m", "swarm_cli", "train", "--task", "coverage", "--agents", "2", "--updates", "400",
           "--ppo.num-envs", "4", "--ppo.num-steps", "8", "--ppo.minibatches", "2", "--eval-every", "1000",
           "--checkpoint-every", "1000", "--no-compile", "--no-progress", "--run-dir", run]  # fmt: skip
    root = os.path.join(os.path.dirname(__file__), "..", "..")
    proc = subprocess.Popen(
        cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),  # as `cmd &` in a script
    )  # fmt: skip
    metrics = os.path.join(run, "metrics.jsonl")
    deadline = time.time() + 180
    while time.time() < deadline and (not os.path.exists(metrics) or len(open(metrics).readlines()) < 3):
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)  # ignored, as Ctrl-C is for a background job of a script
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 143, out
    assert "interrupted: checkpoint saved at update" in out and "swarm train --resume" in out
    done = len(open(metrics).readlines())
    assert 3 <= done < 400
    assert checkpoint.load(os.path.join(run, "checkpoint.pt"))["counters"]["update"] == done


def test_probing_a_lock_never_makes_acquire_refuse(tmp_path):
    """`swarm reproduce --status` probes cells' locks (is_held) from another process while
    their runs may be starting: a probe holds the file for microseconds, and acquire waits
    that out (without its retries about 1 acquire in 10 is refused beside this prober)."""
    from trainer.rundir import RunDirLock

    run = str(tmp_path / "run")
    RunDirLock(run).acquire().release()  # (the file exists: the probes really lock it)
    prober = subprocess.Popen(
        [sys.executable, "-c", f"from trainer.rundir import is_held\nprint(flush=True)\nwhile True: is_held({run!r})"],
        stdout=subprocess.PIPE,
        text=True,
        cwd=os.path.join(os.path.dirname(__file__), "..", ".."),
    )
    try:
        prober.stdout.readline()  # probing from here on
        end = time.time() + 1.0
        while time.time() < end:
            RunDirLock(run).acquire().release()
        assert prober.poll() is None  # (it probed all along)
    finally:
        prober.kill()
        prober.wait()


@pytest.fixture
def python_ctrl_c():
    """Python's own Ctrl-C handler while a test sends SIGINT: a shell's background job (`.ci/run &`)
    inherits SIGINT ignored, and the trainer rightly leaves an ignored signal ignored."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_mid_update_finishes_the_update_then_stops(tmp_path, monkeypatch, python_ctrl_c):
    """Ctrl-C in the middle of an update's PPO epochs: the update, its evaluation and its
    checkpoint finish first, so the checkpoint is that of a whole update (the weights of a
    run that ended there), never a half-stepped one labelled with the update before."""
    import signal

    import trainer.train as train_mod

    whole = tiny(tmp_path, updates=1, eval_every=1, run_dir=str(tmp_path / "whole"))
    train(whole)
    real_clip, calls = torch.nn.utils.clip_grad_norm_, {"n": 0}

    def clip_then_ctrl_c(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:  # before the first of update 1's two optimiser steps
            os.kill(os.getpid(), signal.SIGINT)
        return real_clip(*args, **kwargs)

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", clip_then_ctrl_c)
    cut = tiny(tmp_path, updates=5, eval_every=1, checkpoint_every=100, run_dir=str(tmp_path / "cut"))
    with pytest.raises(KeyboardInterrupt):
        train_mod.train(cut)
    assert calls["n"] == 2  # update 1's second step ran after the signal; update 2 never began
    saved, reference = checkpoint.load(cut.run_dir), checkpoint.load(whole.run_dir)
    assert saved["counters"]["update"] == 1 and len(saved["evals"]) == 1
    for name, tensor in reference["model"].items():
        assert torch.equal(saved["model"][name], tensor), name
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers restored


def test_an_interrupted_curriculum_says_the_same_command_resumes_it(tmp_path, monkeypatch, capsys):
    """Ctrl-C (or the campaign's `timeout -s INT`) inside a stage: exit 130, the stage's own
    resume line and the curriculum's, and the same command then finishes every stage."""
    import trainer.train as train_mod
    from swarm_cli.train import curriculum_main

    argv = ["--task", "coverage", "--sizes", "2", "3", "--threshold", "0.99", "--max-updates-per-stage", "2",
            "--eval-every", "2", "--eval-episodes", "4", "--fresh-eval-episodes", "4", "--no-progress",
            "--ppo.num-envs", "4", "--ppo.num-steps", "8", "--ppo.minibatches", "2", "--ppo.epochs", "1",
            "--model.hidden", "16", "--model.rounds", "1", "--no-compile",
            "--run-dir", str(tmp_path / "cur")]  # fmt: skip
    real = train_mod.one_update

    def interrupted(state, cfg, *args, **kwargs):  # Ctrl-C in the middle of stage M = 3's second update
        if cfg.sim.agents == 3 and state.counters["update"] == 1:
            raise KeyboardInterrupt
        return real(state, cfg, *args, **kwargs)

    monkeypatch.setattr(train_mod, "one_update", interrupted)
    assert curriculum_main(argv) == 130
    out = capsys.readouterr()
    assert "swarm train --resume" in out.out and "the same swarm curriculum command resumes it" in out.err
    metrics = tmp_path / "cur" / "stage-m3" / "metrics.jsonl"
    first = metrics.read_text().splitlines()
    assert len(first) == 1  # update 1 of stage M = 3, saved
    monkeypatch.setattr(train_mod, "one_update", real)
    assert curriculum_main(argv) == 0
    assert metrics.read_text().splitlines()[:1] == first  # resumed, not restarted (wall_time would differ)
    stages = json.load(open(tmp_path / "cur" / "curriculum.json"))["stages"]
    assert [s["agents"] for s in stages] == [2, 3] and [s["updates"] for s in stages] == [2, 2]
