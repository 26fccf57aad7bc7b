"""Deployment: ONNX pieces equal the torch policy, manifest integrity, the message bus,
clear errors, and the executor running with torch unimportable.

Models are random-init SwarmPolicy networks (no training needed for parity), exported
once per module.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap

import numpy as np
import onnx
import pytest
import torch

import taichi_swarm
from deploy.executor import DeployError, Executor, ExportedModel, MessageBus, Pieces
from deploy.export import export
from swarm_cli.deploy import execute_main, export_main
from trainer import checkpoint
from trainer.model import ModelConfig, SwarmPolicy

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Small torch ops stall with 2 threads on a busy 2-core machine (stack notes)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _save(path: str, policy: SwarmPolicy, task: str, agents: int) -> str:
    checkpoint.save(
        path,
        {
            "model_config": policy.config.to_dict(),
            "model": policy.state_dict(),
            "task": {"task": task, "agents": agents, "comm": "uc", "comm_radius": 1.0},
        },
    )
    return path


@pytest.fixture(scope="module")
def emp(tmp_path_factory):
    """(policy, export dir) of a random-init EMP policy (any L)."""
    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=128, rounds=3, entity_mode="emp")).eval()
    d = tmp_path_factory.mktemp("emp")
    ckpt = _save(str(d / "ckpt.pt"), policy, "coverage", 3)
    export(ckpt, str(d / "onnx"))
    return policy, str(d / "onnx")


@pytest.fixture(scope="module")
def concat(tmp_path_factory):
    """(policy, export dir) of a random-init "concat" policy built for line (L = 2), K = 2."""
    torch.manual_seed(1)
    policy = SwarmPolicy(ModelConfig(hidden=64, rounds=2, entity_mode="concat", num_landmarks=2)).eval()
    d = tmp_path_factory.mktemp("concat")
    ckpt = _save(str(d / "ckpt.pt"), policy, "line", 3)
    export(ckpt, str(d / "onnx"))
    return policy, str(d / "onnx")


def _states(task: str, M: int, n_states: int = 2, B: int = 2, seed: int = 0, radius: float = 0.6):
    """Copied observations of ``task`` after random steps: dicts of self [B,M,4], entities [B,M,L,2] and
    adj [B,M,M] of "rc" within ``radius`` (0.6: sparse graphs, isolated agents included).
    "uc" is the all-ones graph, so one env (one kernel compile per team size) serves both."""
    env = taichi_swarm.make(task, B, M, comm="rc", comm_radius=radius, seed=seed, array="numpy")
    obs = env.reset()
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_states):
        out.append({k: v.copy() for k, v in obs.items()})
        for _ in range(3):
            obs, *_ = env.step(rng.integers(0, 5, size=(B, M), dtype=np.int64))
    return out


def _uc(obs: dict) -> dict:
    return {**obs, "adj": np.ones_like(obs["adj"])}


def _torch_logits(policy: SwarmPolicy, obs: dict) -> np.ndarray:
    with torch.no_grad():
        logits, _ = policy(*(torch.from_numpy(np.array(obs[k])) for k in ("self", "entities", "adj")))
    return logits.numpy()


def _assert_parity(policy, executor: Executor, obs: dict) -> None:
    want = _torch_logits(policy, obs)
    got, actions, attention = executor.decide(obs["self"], obs["entities"], obs["adj"])
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
    # greedy actions equal wherever the top two logits are not a numerical tie
    top2 = np.sort(want, axis=-1)[..., -2:]
    clear = (top2[..., 1] - top2[..., 0]) > 1e-4
    assert (actions == want.argmax(-1))[clear].all()
    np.testing.assert_allclose(attention.sum(-1), 1.0, atol=1e-5)  # every agent hears at least itself


CASES = [("coverage", M) for M in (1, 2, 3, 5, 10, 20)] + [("formation", M) for M in (2, 20)]
CASES += [("line", M) for M in (2, 10)]


@pytest.mark.parametrize("task,M", CASES)
def test_executor_matches_torch(emp, task, M):
    """Same states, "uc" and "rc": ONNX agents' logits equal the batched torch policy's."""
    policy, directory = emp
    executor = Executor(ExportedModel(directory), num_envs=2, num_agents=M)
    states = _states(task, M)
    if task == "coverage" and M >= 5:
        assert any((~s["adj"]).any() for s in states), "rc should give a sparse graph here"
    for obs in states:
        _assert_parity(policy, executor, obs)  # rc
        _assert_parity(policy, executor, _uc(obs))  # uc


@pytest.mark.parametrize("M", [2, 10])
def test_concat_mode_matches_torch(concat, M):
    policy, directory = concat
    executor = Executor(ExportedModel(directory), num_envs=2, num_agents=M)
    for obs in _states("line", M):
        _assert_parity(policy, executor, obs)
        _assert_parity(policy, executor, _uc(obs))


def test_one_session_per_piece_for_every_agent(emp, monkeypatch):
    """B x M agents share one session per ONNX piece (the sessions hold only weights); what
    keeps them apart is that each call gets one agent's arrays (the parity tests above)."""
    import onnxruntime

    opened = []
    real = onnxruntime.InferenceSession

    def counting(*args, **kwargs):
        opened.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(onnxruntime, "InferenceSession", counting)
    _, directory = emp
    model = ExportedModel(directory)  # every piece read by the runtime and checked (heads too)
    assert len(opened) == 4 and sorted(model.sessions) == ["encode", "round", "round_heads"]  # K = 3
    Executor(model, num_envs=50, num_agents=10)
    assert len(opened) == 4  # the executor runs the model's sessions: none more


def test_all_messages_dropped_equals_hearing_only_itself(emp):
    """drop = 1: every agent hears only itself, i.e. the torch policy with adj = identity."""
    policy, directory = emp
    M = 5
    executor = Executor(ExportedModel(directory), 2, M, drop=1.0, seed=3)
    obs = _uc(_states("coverage", M, n_states=1)[0])
    eye = np.broadcast_to(np.eye(M, dtype=bool), obs["adj"].shape)
    want = _torch_logits(policy, {**obs, "adj": eye})
    got, _, attention = executor.decide(obs["self"], obs["entities"], obs["adj"])
    np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
    np.testing.assert_allclose(attention, eye.astype(np.float32), atol=1e-6)


def test_delay_first_steps_hear_only_self_then_old_messages(emp):
    """delay k = 1: step 0 hears only itself; step 1 hears the round-r messages of step 0."""
    policy, directory = emp
    M = 3
    s0, s1 = (_uc(s) for s in _states("coverage", M, n_states=2))
    executor = Executor(ExportedModel(directory), 2, M, delay=1)
    eye = np.broadcast_to(np.eye(M, dtype=bool), s0["adj"].shape)
    got0, _, _ = executor.decide(s0["self"], s0["entities"], s0["adj"])
    np.testing.assert_allclose(got0, _torch_logits(policy, {**s0, "adj": eye}), atol=1e-4, rtol=0)
    got1, _, _ = executor.decide(s1["self"], s1["entities"], s1["adj"])
    assert not np.allclose(got1, _torch_logits(policy, {**s1, "adj": eye}), atol=1e-4)
    assert not np.allclose(got1, _torch_logits(policy, s1), atol=1e-4)  # not this step's messages either
    # an ended episode discards messages in flight: back to hearing only itself
    executor.bus.reset_envs(np.ones(2, bool))
    got2, _, _ = executor.decide(s1["self"], s1["entities"], s1["adj"])
    np.testing.assert_allclose(got2, _torch_logits(policy, {**s1, "adj": eye}), atol=1e-4, rtol=0)


def test_zero_neighbour_round(emp):
    """Nothing arrived (n = 0): the round attends to the agent's own message alone, like an
    isolated agent (adj row = only itself) in the batched torch policy."""
    policy, directory = emp
    model = ExportedModel(directory)
    pieces = Pieces(model)
    H = model.hidden
    rng = np.random.default_rng(0)
    h, _ = pieces.encode(rng.normal(size=4).astype(np.float32), rng.normal(size=(3, 2)).astype(np.float32))
    nothing = np.zeros((0, 2, H), np.float32)
    h_out, message, weights = pieces._round.run(None, {"h": h, "heard": nothing})
    assert weights.shape == (1,) and message.shape == (2, H)
    np.testing.assert_allclose(weights, [1.0], atol=1e-6)
    with torch.no_grad():
        ht = torch.from_numpy(h)[None, None]  # [1, 1, H]: one team of one agent
        key, value = policy.message(ht)
        want, _ = policy.update(ht, key, value, torch.ones(1, 1, 1, dtype=torch.bool))
        want_key, want_value = policy.message(want)
    np.testing.assert_allclose(h_out, want[0, 0].numpy(), atol=1e-5)
    np.testing.assert_allclose(message, np.stack([want_key[0, 0].numpy(), want_value[0, 0].numpy()]), atol=1e-5)
    logits, _, w, _ = pieces._final.run(None, {"h": h, "heard": nothing})
    assert logits.shape == (5,) and w.shape == (1,) and np.isfinite(logits).all()


def test_message_bus_delivers_only_along_edges():
    B, M, H = 1, 3, 4
    bus = MessageBus(B, M, rounds=1)
    msgs = np.arange(B * M * 2 * H, dtype=np.float32).reshape(B, M, 2, H)
    adj = np.array([[[1, 1, 0], [0, 1, 0], [1, 1, 1]]], dtype=bool)  # 0 hears 1; 2 hears 0, 1
    arrived, edges = bus.exchange(0, msgs, adj)
    assert edges.tolist() == [[[False, True, False], [False, False, False], [True, True, False]]]
    assert bus.sent == 3 and bus.delivered == 3
    dropped = MessageBus(B, M, rounds=1, drop=0.5, seed=0)
    counts = sum(int(dropped.exchange(0, msgs, np.ones((B, M, M), bool))[1].sum()) for _ in range(400))
    assert 0.4 < counts / (400 * 6) < 0.6  # each off-diagonal edge kept with probability 1 - p


def test_message_bus_bursty_loss_has_its_rate_and_burst_length():
    """Gilbert-Elliott per link: the stationary loss and the mean burst length it is given, on
    the dense graph and on lists alike (a link's chain is the same whichever layout carries it)."""
    B, M, H, n = 50, 3, 4, 400
    msgs = np.zeros((B, M, 2, H), np.float32)
    bus = MessageBus(B, M, rounds=1, seed=1, burst_loss=0.3, burst_len=4.0)
    lost = np.stack([~bus.exchange(0, msgs, np.ones((B, M, M), bool))[1][:, 0, 1] for _ in range(n)])  # [n, B]
    assert 0.25 < lost.mean() < 0.35
    starts = (lost[1:] & ~lost[:-1]).sum()
    assert 3.0 < lost[1:].sum() / starts < 5.0  # mean length of a run of losses
    nbr = np.array([[1, 2], [0, 2], [0, 1]])[None].repeat(B, 0)
    # the same draws: what the dense bus lost, the lists lose
    a = MessageBus(B, M, rounds=1, seed=2, burst_loss=0.3)
    b = MessageBus(B, M, rounds=1, seed=2, burst_loss=0.3)
    for _ in range(5):
        dense = a.exchange(0, msgs, np.ones((B, M, M), bool))[1]
        _, edges, senders = b.exchange_lists(0, msgs, nbr, np.ones((B, M, 2), bool))
        assert (np.take_along_axis(dense, senders, axis=2) == edges).all()
    with pytest.raises(DeployError, match="--burst-loss"):
        MessageBus(B, M, rounds=1, burst_loss=1.0)


def test_message_bus_hold_replaces_a_lost_message_by_the_last_heard_for_hold_steps():
    """hold A: an edge of this step's graph whose message is lost delivers the sender's last
    message of that round heard at most A steps ago, dense and on lists alike; never one older,
    never along an edge not in the graph, and nothing across an episode's end."""
    B, M, H, A = 1, 3, 4, 2
    nbr, mask = np.array([[[1, 2], [0, 2], [0, 1]]]), np.ones((B, M, 2), bool)
    everyone, offdiag = np.ones((B, M, M), bool), ~np.eye(M, dtype=bool)[None]
    for lists in (False, True):
        bus = MessageBus(B, M, rounds=1, hold=A)

        def step(t, drop, adj=everyone, bus=bus, lists=lists):
            bus.drop = drop
            msgs = np.full((B, M, 2, H), float(t), np.float32) + np.arange(M, dtype=np.float32)[None, :, None, None]
            if lists:
                arrived, edges, senders = bus.exchange_lists(0, msgs, nbr, mask & np.take_along_axis(adj, nbr, 2))
                dense = np.zeros((B, M, M), bool)
                np.put_along_axis(dense, senders, edges, 2)
                edges = dense
            else:
                arrived, edges = bus.exchange(0, msgs, adj)
            # what agent 0 hears from 1 and 2: the step each message was sent (value - sender)
            heard = [
                bus.gather(0, arrived, 0, 0, np.array([j]))[0, 0, 0] - j if edges[0, 0, j] else None for j in (1, 2)
            ]
            return edges, heard

        edges, heard = step(0, 0.0)
        assert (edges == offdiag).all() and heard == [0, 0]
        assert step(1, 1.0)[1] == [0, 0] and step(2, 1.0)[1] == [0, 0]  # held: 1 and 2 steps old
        assert step(3, 1.0)[1] == [None, None]  # 3 steps old: gone
        assert step(4, 0.0)[1] == [4, 4]
        only_1 = np.zeros((B, M, M), bool)
        only_1[0, 0, 1] = True
        edges, heard = step(5, 1.0, only_1)
        assert heard == [4, None] and edges.sum() == 1  # 2 is out of the graph: not held
        bus.reset_envs(np.ones(B, bool))
        assert step(6, 1.0)[1] == [None, None]  # an ended episode holds nothing
        assert bus.held == 6 + 6 + 1
    with pytest.raises(DeployError, match="hold must be >= 0 steps"):
        MessageBus(B, M, rounds=1, delay=1, hold=1)


def test_manifest_hashes_checker_single_file(emp):
    _, directory = emp
    with open(os.path.join(directory, "manifest.json")) as f:
        manifest = json.load(f)
    assert manifest["rounds"] == 3 and manifest["hidden"] == 128
    assert manifest["action_meanings"] == ["noop", "-x", "+x", "-y", "+y"]
    assert manifest["task"] == {"task": "coverage", "agents": 3, "comm": "uc", "comm_radius": 1.0}
    assert manifest["message"]["kind"] == "key_value"
    assert {"torch", "onnx", "onnxruntime", "taichi-swarm"} <= set(manifest["versions"])
    assert set(manifest["files"]) == {"encode", "round", "heads", "round_heads"}
    for entry in manifest["files"].values():
        path = os.path.join(directory, entry["file"])
        with open(path, "rb") as f:
            assert hashlib.sha256(f.read()).hexdigest() == entry["sha256"]
        onnx.checker.check_model(path, full_check=True)
    assert sorted(os.listdir(directory)) == [
        "encode.onnx",
        "heads.onnx",
        "manifest.json",
        "round.onnx",
        "round_heads.onnx",
    ]  # no external .data files


# ------------------------------------------------------------------------------ errors
def _run(main, argv, capsys) -> tuple[int, str]:
    code = main(argv)
    return code, capsys.readouterr().err


def test_missing_directory(capsys, tmp_path):
    code, err = _run(execute_main, [str(tmp_path / "nope"), "--task", "coverage", "--agents", "3"], capsys)
    assert code == 2 and "swarm execute: error:" in err and "does not exist" in err and "Traceback" not in err
    code, err = _run(execute_main, [str(tmp_path), "--task", "coverage"], capsys)
    assert code == 2 and "manifest.json" in err


def test_execute_takes_a_zoo_name_and_leaves_no_export_behind(capsys, monkeypatch, tmp_path):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    code, err = _run(execute_main, ["coverage-uc-m3", "--episodes", "2"], capsys)
    assert code == 0, err
    assert not list(tmp_path.glob("swarm-execute-*"))  # the export went to a temporary directory, removed
    code, err = _run(execute_main, ["coverage-uc-m33", "--episodes", "2"], capsys)
    assert code == 2 and "not a file, a run directory or a model zoo name" in err


def test_corrupted_file_is_refused(emp, tmp_path, capsys):
    _, directory = emp
    bad = tmp_path / "bad"
    shutil.copytree(directory, bad)
    with open(bad / "round.onnx", "ab") as f:
        f.write(b"\0")
    code, err = _run(execute_main, [str(bad), "--episodes", "1"], capsys)
    assert code == 2 and "sha256" in err and "round.onnx" in err
    os.remove(bad / "heads.onnx")
    with pytest.raises(DeployError, match="missing"):
        ExportedModel(str(bad))


def test_wrong_task_for_concat_model(concat, capsys, tmp_path):
    _, directory = concat
    code, err = _run(execute_main, [directory, "--task", "coverage", "--agents", "5", "--episodes", "1"], capsys)
    assert code == 2 and "holds a line policy" in err and "coverage" in err  # another task: refused as such
    # with outputs asked for: the same error, and nothing written or replaced
    old, gif = tmp_path / "old.rrd", tmp_path / "x.gif"
    old.write_bytes(b"RRF2 a recording from before")
    argv = [directory, "--task", "coverage", "--agents", "5", "--episodes", "1"]
    argv += ["--record", str(old), "--video", str(gif)]
    code, err = _run(execute_main, argv, capsys)
    assert code == 2 and "holds a line policy" in err
    assert old.read_bytes() == b"RRF2 a recording from before" and not gif.exists()
    assert sorted(os.listdir(tmp_path)) == ["old.rrd"]  # no temp file left either


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["--agents", "0"], "--agents must be >= 1"),
        (["--episodes", "0"], "--episodes must be >= 1"),
        (["--drop", "1.5"], "probabilities"),
        (["--delay", "-1"], "--delay must be >= 0"),
        (["--task", "soccer"], "task must be one of"),
    ],
)
def test_bad_execute_options(emp, capsys, argv, needle):
    _, directory = emp
    code, err = _run(execute_main, [directory, *argv], capsys)
    assert code == 2 and needle in err and "Traceback" not in err


def test_export_errors(tmp_path, capsys):
    code, err = _run(export_main, [str(tmp_path / "missing.pt"), "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and "does not exist" in err
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    code, err = _run(export_main, [str(junk), "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and "swarm export: error:" in err
    # a task setting the network cannot take is refused: its manifest would run nowhere
    policy = SwarmPolicy(ModelConfig(hidden=16, rounds=1, entity_mode="concat", num_landmarks=2)).eval()
    ckpt = _save(str(tmp_path / "coverage-m2.pt"), policy, "coverage", 2)
    argv = [ckpt, "--out", str(tmp_path / "o2"), "--task", "coverage", "--agents", "5"]
    code, err = _run(export_main, argv, capsys)
    assert code == 2 and "concatenates 2 landmark offsets" in err and "coverage with 5 agents has 5" in err
    assert not (tmp_path / "o2").exists()
    padded = SwarmPolicy(ModelConfig(hidden=16, rounds=1, entity_mode="padded")).eval()
    ckpt = _save(str(tmp_path / "padded.pt"), padded, "coverage", 3)
    code, err = _run(export_main, [ckpt, "--out", str(tmp_path / "o3"), "--agents", "11"], capsys)
    assert code == 2 and "at most 10 landmarks" in err


# ------------------------------------------------------------------------------ no torch
NO_TORCH = textwrap.dedent("""
    import sys

    class _NoTorch:
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ImportError("torch is blocked in this test")
            return None

    sys.meta_path.insert(0, _NoTorch())
    from swarm_cli.main import main

    code = main(["execute", sys.argv[1], "--agents", "3", "--episodes", "2", "--comm", "rc", "--drop", "0", "0.5"])
    assert code == 0, code
    assert "torch" not in sys.modules and "rerun" not in sys.modules, "imported torch or rerun"
    code = main(["execute", sys.argv[1], "--agents", "3", "--episodes", "2", "--delay", "2", "--record", sys.argv[2]])
    assert code == 0, code
    assert "torch" not in sys.modules
    print("NO_TORCH_OK")
""")


def test_executor_runs_without_torch(emp, tmp_path):
    _, directory = emp
    rrd = str(tmp_path / "run.rrd")
    proc = subprocess.run(
        [sys.executable, "-c", NO_TORCH, directory, rrd], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "NO_TORCH_OK" in proc.stdout
    assert "S%" in proc.stdout and "0.50" in proc.stdout  # the drop-rate table
    assert os.path.getsize(rrd) > 0


def test_execute_equals_swarm_eval(emp):
    """Whole loop: decentralised ONNX agents give the same episodes as `swarm eval` (same seed)."""
    from deploy.executor import resolve_settings, run_episodes
    from taichi_swarm import Sim
    from trainer.evaluate import evaluate

    policy, directory = emp
    model = ExportedModel(directory)
    got = run_episodes(model, resolve_settings(model, "coverage", 3, "rc", 0.6, episodes=4, seed=7))
    want = evaluate(policy, Sim("coverage", 3, "rc", 0.6), episodes=4, seed=7)
    assert got["per_episode"]["success"] == want["per_episode"]["success"]
    assert got["per_episode"]["length"] == want["per_episode"]["length"]
    np.testing.assert_allclose(got["per_episode"]["dist"], want["per_episode"]["dist"], atol=1e-4)


@pytest.mark.parametrize(
    "edit,needle",
    [
        (lambda m: m.update(rounds=2), "changed after export"),
        (lambda m: m.update(rounds=-1), "rounds"),
        (lambda m: m.pop("rounds"), "rounds"),
        (lambda m: m.update(entity_mode="bogus"), "entity_mode"),
        (lambda m: m["files"]["encode"].pop("sha256"), "sha256"),
        (lambda m: m["task"].update(comm_radius=-1.0), "comm_radius"),
    ],
)
def test_edited_manifest_is_refused(emp, tmp_path, capsys, edit, needle):
    _, directory = emp
    bad = tmp_path / "bad"
    shutil.copytree(directory, bad)
    manifest = json.loads((bad / "manifest.json").read_text())
    edit(manifest)
    (bad / "manifest.json").write_text(json.dumps(manifest))
    code, err = _run(execute_main, [str(bad), "--episodes", "1"], capsys)
    assert code == 2 and needle in err and "Traceback" not in err, err


def test_resealed_manifest_must_still_fit_the_onnx_files(emp, tmp_path):
    from deploy.manifest import seal

    _, directory = emp
    bad = tmp_path / "bad"
    shutil.copytree(directory, bad)
    manifest = json.loads((bad / "manifest.json").read_text())
    manifest["files"]["round"]["inputs"] = ["h", "messages"]
    (bad / "manifest.json").write_text(json.dumps(seal(manifest)))
    with pytest.raises(DeployError, match="takes"):
        ExportedModel(str(bad))
    manifest = json.loads((tmp_path / "bad" / "manifest.json").read_text())
    manifest["files"]["round"]["inputs"] = ["h", "heard"]
    rng = np.random.default_rng(0)
    garbage = rng.bytes(4096)
    (bad / "round.onnx").write_bytes(garbage)
    manifest["files"]["round"]["sha256"] = hashlib.sha256(garbage).hexdigest()
    (bad / "manifest.json").write_text(json.dumps(seal(manifest)))
    with pytest.raises(DeployError, match="not a readable ONNX"):
        ExportedModel(str(bad))


def test_export_refuses_an_unknown_task(tmp_path, capsys):
    policy = SwarmPolicy(ModelConfig(hidden=16, rounds=1))
    ckpt = _save(str(tmp_path / "c.pt"), policy, "coverage", 3)
    with pytest.raises(ValueError, match="task"):
        export(ckpt, str(tmp_path / "o"), task={"task": "foo"})


# ------------------------------------------------------------------------------ resealed manifests
def _resealed(directory: str, tmp_path, edit) -> str:
    """A copy of the export whose manifest, edited, carries a valid seal (as a buggy writer would
    leave it): only the cross-checks and the ONNX files themselves can refuse it."""
    from deploy.manifest import content_hash

    bad = tmp_path / "resealed"
    shutil.copytree(directory, bad)
    manifest = json.loads((bad / "manifest.json").read_text())
    edit(manifest)
    manifest["manifest_sha256"] = content_hash(manifest)  # (seal itself would refuse some)
    (bad / "manifest.json").write_text(json.dumps(manifest))
    return str(bad)


def _rounds(k: int):
    def edit(m):
        m["rounds"] = m["model_config"]["rounds"] = m["contract"]["rounds"] = k

    return edit


def _task(name: str):
    def edit(m):
        m["task"]["task"] = name

    return edit


def _actions(m):
    m["num_actions"] = m["model_config"]["num_actions"] = 9
    m["action_meanings"] = [str(i) for i in range(9)]


def _hidden(m):
    m["hidden"] = m["model_config"]["hidden"] = 64


@pytest.mark.parametrize(
    "edit, needle",
    [
        (_rounds(2), "rounds"),  # a 3-round policy run with 2: S% 100 -> 0 before the graphs named K
        (_rounds(0), "rounds"),
        (_task("line"), "task"),
        (_actions, "num_actions"),  # (the graphs' own shapes too: 5 logits)
        (_hidden, "hidden"),
        (lambda m: m["contract"].update(rounds=2), "contract.rounds"),
        (lambda m: m["contract"].update(comm="rc"), "contract.comm"),
        (lambda m: m["contract"].update(comm_radius=0.5), "contract.comm_radius"),
    ],
    ids=["rounds-2", "rounds-0", "task", "actions", "hidden", "contract-rounds", "contract-comm", "contract-radius"],
)
def test_a_resealed_manifest_that_misdescribes_its_graphs_is_refused(emp, tmp_path, capsys, edit, needle):
    _, directory = emp
    bad = _resealed(directory, tmp_path, edit)
    with pytest.raises(DeployError, match=needle):
        ExportedModel(bad)
    code, err = _run(execute_main, [bad, "--episodes", "1"], capsys)
    assert code == 2 and needle in err and "Traceback" not in err and err.count("\n") == 1, err


def test_the_graphs_carry_the_model_config_and_task_they_were_exported_with(emp):
    from deploy.manifest import META_MODEL, META_TASK

    _, directory = emp
    manifest = json.loads(open(os.path.join(directory, "manifest.json")).read())
    for entry in manifest["files"].values():
        props = {p.key: json.loads(p.value) for p in onnx.load(os.path.join(directory, entry["file"])).metadata_props}
        assert props[META_MODEL] == manifest["model_config"] and props[META_MODEL]["rounds"] == 3
        assert props[META_TASK] == manifest["task"]


@pytest.mark.parametrize("depth", [100_000, 40])
def test_a_deeply_nested_manifest_is_one_line(emp, tmp_path, capsys, depth):
    _, directory = emp
    bad = tmp_path / "deep"
    shutil.copytree(directory, bad)
    (bad / "manifest.json").write_text('{"format": ' + "[" * depth + "]" * depth + "}")
    with pytest.raises(DeployError, match="nested"):
        ExportedModel(str(bad))
    code, err = _run(execute_main, [str(bad), "--episodes", "1"], capsys)
    assert code == 2 and "nested" in err and err.count("\n") == 1, err
