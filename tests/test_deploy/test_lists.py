"""The exported per-agent pieces and the executor over the simulator's neighbour lists:
each agent hears only its listed neighbours, senses only its listed landmarks, and
decides what the torch policy decides on the same lists."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

import taichi_swarm
from deploy.executor import DeployError, Executor, ExportedModel, lists_to_dense
from deploy.export import export
from trainer import checkpoint
from trainer.model import ModelConfig, SwarmPolicy


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _save_and_export(policy: SwarmPolicy, d, task: str = "coverage") -> ExportedModel:
    """``policy`` as a checkpoint in folder ``d`` (trained on ``task``, M = 3, rc), exported."""
    path = str(d / "ckpt.pt")
    setting = {"task": task, "agents": 3, "comm": "rc", "comm_radius": 0.8}
    checkpoint.save(path, {"model_config": policy.config.to_dict(), "model": policy.state_dict(), "task": setting})
    export(path, str(d / "onnx"))
    return ExportedModel(str(d / "onnx"))


def _train_and_export(tmp_path, *options: str) -> tuple[str, dict]:
    """One tiny `swarm train` of coverage at M = 3 on lists (K = 2) with ``options``, exported:
    (the export's folder, its contract's swarm options)."""
    import json

    from swarm_cli.deploy import export_main
    from swarm_cli.main import main as swarm_main

    run = str(tmp_path / "run")
    args = ["train", "--task", "coverage", "--agents", "3", "--comm", "rc", "--neighbours", "2", "--updates", "1"]
    args += ["--ppo.num-envs", "2", "--ppo.num-steps", "4", "--ppo.minibatches", "1", "--eval-every", "100"]
    args += ["--model.hidden", "8", "--run-dir", run, "--no-progress", "--transfer-offsets", *options]
    assert swarm_main(args) == 0
    out = str(tmp_path / "onnx-trained")
    assert export_main([os.path.join(run, "policy.pt"), "--out", out]) == 0
    with open(os.path.join(out, "manifest.json")) as f:
        return out, json.load(f)["contract"]["swarm"]


def _export(tmp_path_factory, mode: str, task: str, seed: int):
    torch.manual_seed(seed)
    policy = SwarmPolicy(ModelConfig(hidden=32, rounds=2, entity_mode=mode)).eval()
    return policy, _save_and_export(policy, tmp_path_factory.mktemp(mode), task)


@pytest.fixture(scope="module")
def emp(tmp_path_factory):
    return _export(tmp_path_factory, "emp", "coverage", 0)


@pytest.fixture(scope="module")
def padded(tmp_path_factory):
    return _export(tmp_path_factory, "padded", "coverage", 1)


def _states(M: int, K: int, radius: float = 0.7, B: int = 2, **lists) -> list[dict]:
    env = taichi_swarm.make(
        "coverage", B, M, comm="rc", comm_radius=radius, seed=3, array="numpy", neighbours=K, **lists
    )
    obs = env.reset()
    rng = np.random.default_rng(0)
    out = []
    for _ in range(2):
        out.append({k: v.copy() for k, v in obs.items()})
        for _ in range(3):
            obs, *_ = env.step(rng.integers(0, 5, size=(B, M), dtype=np.int64))
    return out


def _torch(policy, obs: dict):
    from trainer.model import policy_inputs

    with torch.no_grad():
        logits, _, att = policy(
            **policy_inputs({k: torch.from_numpy(v) for k, v in obs.items()}), return_attention=True
        )
    return logits.numpy(), att[-1].numpy()


@pytest.mark.parametrize("M,K", [(6, 5), (12, 3)])
def test_executor_on_lists_matches_torch_on_lists(emp, M, K):
    """K = M - 1 (everyone in range listed) and K = 3 < M - 1 (lists cut to the 3 nearest)."""
    policy, model = emp
    executor = Executor(model, 2, M)
    for obs in _states(M, K):
        assert "adj" not in obs
        want, want_att = _torch(policy, obs)
        got, actions, att = executor.decide(obs["self"], obs["entities"], nbr=obs["nbr"], nbr_mask=obs["nbr_mask"])
        np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
        assert att.shape == (2, M, 1 + K)
        np.testing.assert_allclose(att, want_att, atol=1e-5)  # slot 0 self, 1 + k the k-th listed
        np.testing.assert_allclose(att.sum(-1), 1.0, atol=1e-5)


def test_an_agent_hears_only_its_listed_neighbours(emp):
    """Whatever an unlisted agent would say does not reach the agent: its decision is the
    same when every unlisted agent's observation is changed."""
    _, model = emp
    M, K = 8, 2
    obs = _states(M, K, radius=2.0)[0]
    executor = Executor(model, 2, M, seed=0)
    got, *_ = executor.decide(obs["self"], obs["entities"], nbr=obs["nbr"], nbr_mask=obs["nbr_mask"])
    i = 0
    for b in range(2):
        heard = set(obs["nbr"][b, i][obs["nbr_mask"][b, i]].tolist()) | {i}
        # a message reaches i in round 2 from what its neighbours heard in round 1: keep those too
        second = set()
        for j in heard:
            second |= set(obs["nbr"][b, j][obs["nbr_mask"][b, j]].tolist())
        far = [j for j in range(M) if j not in heard | second]
        if not far:
            continue
        changed = {k: v.copy() for k, v in obs.items()}
        changed["self"][b, far] += 5.0
        changed["entities"][b, far] += 5.0
        again, *_ = Executor(model, 2, M, seed=0).decide(
            changed["self"], changed["entities"], nbr=obs["nbr"], nbr_mask=obs["nbr_mask"]
        )
        np.testing.assert_allclose(again[b, i], got[b, i], atol=1e-6)
        assert not np.allclose(again[b, far], got[b, far])
        return
    pytest.skip("every agent within two hops of agent 0 in these states")


def test_full_lists_equal_the_dense_executor(emp):
    _, model = emp
    M = 5
    env = taichi_swarm.make("coverage", 2, M, comm="rc", comm_radius=0.7, seed=3, array="numpy")
    dense = env.reset()
    lists = _states(M, M - 1)[0]
    np.testing.assert_array_equal(dense["self"], lists["self"])  # the same first state
    a = Executor(model, 2, M).decide(dense["self"], dense["entities"], dense["adj"])
    b = Executor(model, 2, M).decide(lists["self"], lists["entities"], nbr=lists["nbr"], nbr_mask=lists["nbr_mask"])
    np.testing.assert_allclose(b[0], a[0], atol=1e-5)
    np.testing.assert_allclose(lists_to_dense(b[2], lists["nbr"], lists["nbr_mask"]), a[2], atol=1e-6)


@pytest.mark.parametrize("which", ["emp", "padded"])
def test_landmark_lists_match_torch(emp, padded, which):
    policy, model = emp if which == "emp" else padded
    M = 6
    states = _states(M, 3, landmark_neighbours=3, sense_radius=0.8)
    assert any((~s["entity_mask"]).any() for s in states), "some landmark slots should be unsensed here"
    executor = Executor(model, 2, M)
    for obs in states:
        want, _ = _torch(policy, obs)
        graph = {k: obs[k] for k in ("nbr", "nbr_mask", "entity_mask")}
        got, *_ = executor.decide(obs["self"], obs["entities"], **graph)
        np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)


def test_drops_on_lists_and_bad_graphs(emp):
    policy, model = emp
    M = 5
    obs = _states(M, 4, radius=2.0)[0]
    executor = Executor(model, 2, M, drop=1.0, seed=1)
    got, _, att = executor.decide(obs["self"], obs["entities"], nbr=obs["nbr"], nbr_mask=obs["nbr_mask"])
    alone = {**obs, "nbr_mask": np.zeros_like(obs["nbr_mask"])}
    np.testing.assert_allclose(got, _torch(policy, alone)[0], atol=1e-4, rtol=0)
    np.testing.assert_allclose(att[..., 0], 1.0, atol=1e-6)
    assert executor.bus.sent == int(obs["nbr_mask"].sum()) * 2 and executor.bus.delivered == 0  # K = 2 rounds
    with pytest.raises(DeployError, match="either dense"):
        executor.decide(obs["self"], obs["entities"])
    with pytest.raises(DeployError, match="either dense"):
        executor.decide(obs["self"], obs["entities"], nbr=obs["nbr"])


def test_swarm_execute_on_lists(emp, capsys):
    from swarm_cli.deploy import execute_main

    _, model = emp
    args = [model.directory, "--agents", "6", "--episodes", "3", "--neighbours", "5"]
    assert execute_main(args) == 0
    out = capsys.readouterr().out
    row = out.splitlines()[-1]
    assert execute_main([model.directory, "--agents", "6", "--episodes", "3"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == row  # everyone listed: the dense run
    with pytest.raises(SystemExit) as refused:
        execute_main([model.directory, "--neighbours", "0"])
    assert refused.value.code == 2 and "--neighbours must be >= 1" in capsys.readouterr().err


def test_recordings_draw_the_graph_of_the_lists(emp, tmp_path):
    """comm_graph from the lists is the dense adj when everyone in range is listed; swarm
    eval --video / --record run on lists."""
    from deploy.trajectory import comm_graph
    from swarm_cli.train import eval_main

    M = 6
    dense = taichi_swarm.make("coverage", 2, M, comm="rc", comm_radius=0.7, seed=3, array="numpy").reset()
    lists = _states(M, M - 1)[0]
    np.testing.assert_array_equal(comm_graph(lists, 2), comm_graph(dense, 2))
    policy, _ = emp
    ckpt = str(tmp_path / "p.pt")
    checkpoint.save(
        ckpt,
        {
            "model_config": policy.config.to_dict(),
            "model": policy.state_dict(),
            "task": {"task": "coverage", "agents": M, "comm": "rc", "comm_radius": 0.7},
        },
    )
    gif, rrd = str(tmp_path / "x.gif"), str(tmp_path / "x.rrd")
    assert eval_main([ckpt, "--episodes", "2", "--neighbours", "3", "--video", gif, "--record", rrd]) == 0
    assert os.path.getsize(gif) > 0 and os.path.getsize(rrd) > 0


def test_a_swarm_video_draws_the_density_scaled_arena(tmp_path):
    """M = 300 on lists with scale="density": frames and the Rerun recording carry the
    arena's half side, and the swarm is drawn as points (no trails)."""
    from deploy.recording import write_rrd
    from deploy.trajectory import TrajectoryRecorder
    from deploy.video import frames, render_trajectory

    M = 300
    env = taichi_swarm.make("coverage", 1, M, comm="rc", comm_radius=0.5, seed=0, neighbours=8, scale="density")
    rec = TrajectoryRecorder("coverage", 1, M, 1, comm="rc", comm_radius=0.5)
    rng = np.random.default_rng(0)
    env.reset()
    for step in range(3):
        actions = torch.from_numpy(rng.integers(0, 5, size=(1, M)))
        rec.log_step(step, env, actions)
        env.step(actions)
    traj = rec.trajectory()
    write_rrd(traj, str(tmp_path / "x.rrd"))
    assert traj.arrays["arena"][0] == pytest.approx((M / 10) ** 0.5) and os.path.getsize(tmp_path / "x.rrd") > 0
    first = frames(traj)[0]
    assert first["arena"] == pytest.approx((M / 10) ** 0.5) and first["adj"].shape == (1, M, M)
    assert len(traj.arrays["graph_index"]) < 3 * M * 10  # the graph kept as its edges, not M^2 cells
    render_trajectory(traj, str(tmp_path / "frames"))
    names = sorted(os.listdir(tmp_path / "frames"))
    assert len(names) >= 3 and names[0] == "frame_0000.png"


def test_a_policy_trained_on_lists_exports_and_executes_on_them(tmp_path):
    """The export's contract names the lists the policy trained on; swarm execute runs on
    them unless --neighbours says otherwise."""
    import json

    from swarm_cli.deploy import execute_main

    out, swarm = _train_and_export(tmp_path)
    assert swarm == {"neighbours": 2}
    for extra, K in (([], 2), (["--neighbours", "1"], 1)):
        rows = str(tmp_path / f"rows{K}.json")
        assert execute_main([out, "--episodes", "2", "--json", rows, *extra]) == 0
        with open(rows) as f:
            assert json.load(f)["rows"][0]["neighbours"] == K


def test_an_export_without_absolute_position_matches_torch(tmp_path):
    """self_position "none" is inside the exported encoder: the executor's actions are
    torch's, and its manifest says so."""
    torch.manual_seed(4)
    policy = SwarmPolicy(ModelConfig(hidden=32, rounds=2, self_position="none")).eval()
    model = _save_and_export(policy, tmp_path)
    assert model.manifest["model_config"]["self_position"] == "none"
    executor = Executor(model, 2, 6)
    for obs in _states(6, 5):
        want, _ = _torch(policy, obs)
        got, _, _ = executor.decide(obs["self"], obs["entities"], nbr=obs["nbr"], nbr_mask=obs["nbr_mask"])
        np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)


def test_an_export_with_landmark_occupancy_matches_torch_and_executes(tmp_path):
    """landmark_occupancy: the exported encoder takes entities [L, 3] and decides what torch
    decides; trained through the CLI, the export's contract carries the option and swarm
    execute runs on it."""
    import json

    from swarm_cli.deploy import execute_main

    torch.manual_seed(5)
    policy = SwarmPolicy(ModelConfig(hidden=32, rounds=2, landmark_occupancy=True)).eval()
    with torch.no_grad():
        policy.entity_occupancy.weight.normal_(0.0, 0.5)  # it starts at zero: make it matter
    model = _save_and_export(policy, tmp_path)
    assert model.manifest["observation"]["entities"]["shape"] == ["L", 3]
    executor = Executor(model, 2, 6)
    for obs in _states(6, 3, landmark_neighbours=3, sense_radius=0.8, landmark_occupancy=True):
        assert obs["entities"].shape[-1] == 3
        want, _ = _torch(policy, obs)
        graph = {k: obs[k] for k in ("nbr", "nbr_mask", "entity_mask")}
        got, *_ = executor.decide(obs["self"], obs["entities"], **graph)
        np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)

    out, swarm = _train_and_export(
        tmp_path, "--landmark-neighbours", "2", "--sense-radius", "1.0", "--landmark-occupancy"
    )
    assert swarm == {"neighbours": 2, "landmark_neighbours": 2, "sense_radius": 1.0, "landmark_occupancy": True}
    rows = str(tmp_path / "rows.json")
    assert execute_main([out, "--episodes", "2", "--json", rows]) == 0
    with open(rows) as f:
        assert json.load(f)["rows"][0]["landmark_occupancy"] is True
