"""The adapters of baselines/: PettingZoo, TorchRL and BenchMARL (the optional ``baselines`` extra).

Each test skips when its library is absent, so the core suite runs without the extra.
"""

import json
import warnings

import numpy as np
import pytest

import taichi_swarm
from baselines.observations import flat_observation, obs_dim


def full_obs_reference(pos, vel, landmarks):
    """The "full" observation [B, M, D] written out per agent with loops: own velocity and
    position, landmarks relative to the agent, then the other agents' positions and their
    velocities relative to the agent's (others in index order)."""
    B, M, _ = pos.shape
    out = np.zeros((B, M, obs_dim("full", M, landmarks.shape[1])), np.float32)
    for b in range(B):
        for i in range(M):
            row = [vel[b, i], pos[b, i]] + [lk - pos[b, i] for lk in landmarks[b]]
            row += [pos[b, j] - pos[b, i] for j in range(M) if j != i]
            row += [vel[b, j] - vel[b, i] for j in range(M) if j != i]
            out[b, i] = np.concatenate(row)
    return out


def hand_set_state(B: int, M: int, L: int):
    rng = np.random.default_rng(7)
    return (
        rng.uniform(-0.9, 0.9, (B, M, 2)).astype(np.float32),
        rng.uniform(-1.5, 1.5, (B, M, 2)).astype(np.float32),
        rng.uniform(-0.9, 0.9, (B, L, 2)).astype(np.float32),
    )


# ---------------------------------------------------------------------- observations
@pytest.mark.parametrize(("task", "M"), [("coverage", 4), ("line", 3), ("coverage", 1)])
def test_full_observation_matches_the_state(task, M):
    env = taichi_swarm.make(task, 3, M, seed=0, array="numpy")
    env.reset()
    pos, vel, lmk = hand_set_state(3, M, env.num_landmarks)
    obs = env.set_state(pos=pos, vel=vel, landmarks=lmk)
    state = env.get_state()
    want = full_obs_reference(state["pos"], state["vel"], state["landmarks"])
    got = flat_observation("full", obs["self"], obs["entities"])
    np.testing.assert_allclose(got, want, atol=1e-6)
    local = flat_observation("local", obs["self"], obs["entities"])
    assert local.shape == (3, M, obs_dim("local", M, env.num_landmarks)) == (3, M, 4 + 2 * env.num_landmarks)
    np.testing.assert_array_equal(got[..., : local.shape[-1]], local)  # full extends local


def test_observation_mode_is_checked():
    with pytest.raises(ValueError, match="obs_mode"):
        obs_dim("global", 3, 3)


# ---------------------------------------------------------------------- PettingZoo
@pytest.mark.parametrize(
    "kwargs",
    [
        dict(task="coverage", num_agents=3),
        dict(task="line", num_agents=4, obs_mode="full", action_space="continuous", max_steps=12),
        dict(task="formation", num_agents=3, comm="rc", comm_radius=0.5, action_space="fine"),
    ],
)
def test_pettingzoo_parallel_api(kwargs):
    pytest.importorskip("pettingzoo")
    from pettingzoo.test import parallel_api_test

    from baselines.pettingzoo_env import SwarmParallelEnv

    env = SwarmParallelEnv(**kwargs, seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=60)
    api = [str(w.message) for w in caught if "pettingzoo" in w.filename]
    assert not api, api


def test_pettingzoo_episode_ends_like_pettingzoo():
    pytest.importorskip("pettingzoo")
    from baselines.pettingzoo_env import SwarmParallelEnv

    env = SwarmParallelEnv("coverage", 3, obs_mode="full", max_steps=4, seed=1)
    obs, infos = env.reset(seed=3)
    assert env.agents == ["agent_0", "agent_1", "agent_2"] and "adj" not in infos["agent_0"]
    noop = dict.fromkeys(env.agents, 0)
    for _ in range(3):
        obs, rew, term, trunc, infos = env.step(noop)
        assert env.agents and not any(term.values()) and not any(trunc.values())
        assert len(set(rew.values())) == 1  # the team reward
    obs, rew, term, trunc, infos = env.step(noop)  # the time limit
    assert env.agents == [] and all(trunc.values()) and not any(term.values())
    ep = infos["agent_1"]["episode"]
    assert ep["length"] == 4 and ep["truncated"] and not ep["success"]
    # the episode's last observation, not the next one's first (the simulator has started it)
    last = env.sim.info["terminal_obs"]
    np.testing.assert_array_equal(obs["agent_2"], flat_observation("full", last["self"], last["entities"])[0, 2])
    now = env.sim.obs
    assert not np.array_equal(obs["agent_2"], flat_observation("full", now["self"], now["entities"])[0, 2])
    with pytest.raises(RuntimeError, match="reset"):
        env.step(noop)
    env.reset()
    # success: every agent on its landmark ends the episode with terminations
    lmk = env.sim.get_state()["landmarks"]
    env.sim.set_state(pos=lmk, vel=np.zeros((1, 3, 2)))
    obs, rew, term, trunc, infos = env.step(noop)
    assert all(term.values()) and not any(trunc.values()) and env.agents == []
    assert infos["agent_2"]["success"] and infos["agent_2"]["episode"]["success"]
    assert infos["agent_0"]["episode"]["length"] == 1


def test_pettingzoo_local_mode_reports_the_comm_graph():
    pytest.importorskip("pettingzoo")
    from baselines.pettingzoo_env import SwarmParallelEnv

    env = SwarmParallelEnv("coverage", 3, obs_mode="local", comm="rc", comm_radius=0.5, seed=0)
    env.reset()
    env.sim.set_state(pos=np.array([[[0.0, 0.0], [0.3, 0.0], [0.9, 0.0]]]), vel=np.zeros((1, 3, 2)))
    _, _, _, _, infos = env.step(dict.fromkeys(env.agents, 0))
    assert infos["agent_0"]["adj"].tolist() == [True, True, False]
    assert infos["agent_2"]["adj"].tolist() == [False, False, True]


def test_pettingzoo_rejects_bad_arguments():
    pytest.importorskip("pettingzoo")
    from baselines.pettingzoo_env import SwarmParallelEnv

    with pytest.raises(ValueError, match="obs_mode"):
        SwarmParallelEnv(obs_mode="global")
    with pytest.raises(ValueError, match="task"):
        SwarmParallelEnv(task="swarming")
    with pytest.raises(ValueError, match="action_space"):
        SwarmParallelEnv(action_space="box")
    env = SwarmParallelEnv("coverage", 2, seed=0)
    with pytest.raises(ValueError, match="agent must be one of"):
        env.action_space("agent_9")
    env.reset()
    with pytest.raises(ValueError, match="missing agent"):
        env.step({"agent_0": 1})
    with pytest.raises(ValueError, match="unknown or finished agent"):
        env.step({"agent_0": 1, "agent_1": 1, "agent_7": 0})
    with pytest.raises(ValueError, match=r"actions\['agent_1'\] must be an integer in 0..4"):
        env.step({"agent_0": 1, "agent_1": 5})
    with pytest.raises(ValueError, match=r"actions\['agent_0'\]"):
        env.step({"agent_0": 0.5, "agent_1": 1})
    cont = SwarmParallelEnv("coverage", 2, action_space="continuous", seed=0)
    cont.reset()
    with pytest.raises(ValueError, match=r"actions\['agent_0'\] must have shape \(2,\)"):
        cont.step({"agent_0": np.zeros(3), "agent_1": np.zeros(2)})
    with pytest.raises(ValueError, match="NaN"):
        cont.step({"agent_0": [np.nan, 0.0], "agent_1": np.zeros(2)})


# ---------------------------------------------------------------------- TorchRL
@pytest.mark.parametrize("obs_mode", ["local", "full"])
@pytest.mark.parametrize("continuous", [False, True])
def test_torchrl_check_env_specs(obs_mode, continuous):
    pytest.importorskip("torchrl")
    from torchrl.envs.utils import check_env_specs

    from baselines.torchrl_env import SwarmTorchRLEnv

    env = SwarmTorchRLEnv("formation", 4, 3, obs_mode=obs_mode, continuous_actions=continuous, seed=0, max_steps=3)
    check_env_specs(env, seed=0, break_when_any_done="both")
    td = env.rollout(7, break_when_any_done=False)  # crosses two episode ends
    assert td["next", "done"].sum() == 2 * 4
    assert td["next", "agents", "observation"].shape == (4, 7, 3, obs_dim(obs_mode, 3, 1))
    assert ("agents", "adj") in td.keys(True) if obs_mode == "local" else ("agents", "adj") not in td.keys(True)
    assert (td["next", "episode", "length"][td["next", "done"]] == 3).all()


def _scripted_policy(actions):
    """A TorchRL policy that plays actions[t] at its t-th call."""
    calls = iter(range(len(actions)))

    def policy(td):
        return td.set(("agents", "action"), actions[next(calls)].clone())

    return policy


@pytest.mark.parametrize("continuous", [False, True])
def test_torchrl_rollout_equals_stepping_the_simulator(continuous):
    pytest.importorskip("torchrl")
    import torch

    from baselines.torchrl_env import SwarmTorchRLEnv

    B, M, T = 6, 2, 24
    # a success threshold of 0.6 ends some episodes early (terminated), the rest at 5 steps (truncated)
    kw = dict(seed=5, max_steps=5, success_threshold=0.6)
    env = SwarmTorchRLEnv("coverage", B, M, obs_mode="full", continuous_actions=continuous, **kw)
    sim = taichi_swarm.make(
        "coverage", B, M, action_space="continuous" if continuous else "discrete", array="torch", **kw
    )
    gen = torch.Generator().manual_seed(0)
    if continuous:
        actions = torch.rand((T, B, M, 2), generator=gen) * 2 - 1
    else:
        actions = torch.randint(0, 5, (T, B, M), generator=gen)
    td = env.rollout(T, policy=_scripted_policy(actions), break_when_any_done=False)  # [B, T]
    sim.reset()
    ended = terminated = 0
    for t in range(T):
        obs, reward, done, info = sim.step(actions[t].contiguous())
        nxt = td[:, t]["next"]
        torch.testing.assert_close(nxt["agents", "reward"], reward[:, None, None].expand(B, M, 1))
        assert torch.equal(nxt["done"][:, 0], done)
        assert torch.equal(nxt["terminated"][:, 0], done & info["episode"]["success"])
        assert torch.equal(nxt["truncated"][:, 0], done & info["episode"]["truncated"])
        assert torch.equal(nxt["agents", "done"][..., 0], done[:, None].expand(B, M))
        src = {k: torch.where(done.view(-1, *[1] * (v.dim() - 1)), info["terminal_obs"][k], v) for k, v in obs.items()}
        torch.testing.assert_close(nxt["agents", "observation"], flat_observation("full", src["self"], src["entities"]))
        if t + 1 < T:  # after the auto-reset: the new episode's first observation
            torch.testing.assert_close(td[:, t + 1]["agents", "observation"], flat_observation("full", *obs_pair(obs)))
        ended += int(done.sum())
        terminated += int((done & info["episode"]["success"]).sum())
    assert 0 < terminated < ended  # both kinds of episode end were exercised


def obs_pair(obs):
    return obs["self"], obs["entities"]


def test_torchrl_partial_reset_restarts_running_environments_only():
    pytest.importorskip("torchrl")
    import torch
    from torchrl.envs.utils import step_mdp

    from baselines.torchrl_env import SwarmTorchRLEnv

    env = SwarmTorchRLEnv("line", 3, 2, seed=0)
    td = step_mdp(env.rand_step(env.reset()))
    assert env.sim.get_state()["step"].tolist() == [1, 1, 1]
    out = env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))  # a collector truncating env 1
    assert env.sim.get_state()["step"].tolist() == [1, 0, 1]
    torch.testing.assert_close(out["agents", "observation"][1], flat_observation("local", *obs_pair(env.sim.obs))[1])
    # an explicit reset of fresh episodes keeps them; of running ones starts new ones
    first = env.reset()["agents", "observation"]
    assert env.sim.get_state()["step"].tolist() == [0, 0, 0]
    assert torch.equal(env.reset()["agents", "observation"], first)


def test_torchrl_full_observation_of_a_hand_set_state():
    pytest.importorskip("torchrl")
    import torch

    from baselines.torchrl_env import SwarmTorchRLEnv

    env = SwarmTorchRLEnv("coverage", 2, 3, obs_mode="full", seed=0)
    env.reset()
    pos, vel, lmk = hand_set_state(2, 3, 3)
    env.sim.set_state(pos=pos, vel=vel, landmarks=lmk)
    td = env.reset()  # the episodes are fresh (never stepped): reset keeps the state just set
    state = env.sim.get_state()
    want = full_obs_reference(state["pos"].numpy(), state["vel"].numpy(), state["landmarks"].numpy())
    torch.testing.assert_close(td["agents", "observation"], torch.from_numpy(want))


def test_torchrl_rejects_bad_arguments():
    pytest.importorskip("torchrl")
    import torch

    from baselines.torchrl_env import SwarmTorchRLEnv

    with pytest.raises(ValueError, match="obs_mode"):
        SwarmTorchRLEnv(obs_mode="global")
    with pytest.raises(ValueError, match="task"):
        SwarmTorchRLEnv(task="swarming")
    with pytest.raises(ValueError, match="continuous_actions"):
        SwarmTorchRLEnv(continuous_actions="yes")
    with pytest.raises(ValueError, match="device"):
        SwarmTorchRLEnv(device="meta")
    env = SwarmTorchRLEnv("coverage", 2, 3, seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match=r"\('agents', 'action'\) must have shape \(2, 3\)"):
        env.step(td.set(("agents", "action"), torch.zeros(2, 3, 2)))
    with pytest.raises(ValueError, match=r"\('agents', 'action'\) must have dtype"):
        env.step(td.set(("agents", "action"), torch.zeros(2, 3)))
    with pytest.raises(ValueError, match="0..4"):
        env.step(td.set(("agents", "action"), torch.full((2, 3), 7)))
    cont = SwarmTorchRLEnv("coverage", 2, 3, continuous_actions=True, seed=0)
    td = cont.reset()
    with pytest.raises(ValueError, match=r"\('agents', 'action'\) must have shape \(2, 3, 2\)"):
        cont.step(td.set(("agents", "action"), torch.zeros(2, 3, 1)))
    with pytest.raises(ValueError, match="NaN"):
        cont.step(td.set(("agents", "action"), torch.full((2, 3, 2), float("nan"))))
    with pytest.raises(ValueError, match="device"):
        env.to("meta")


# ---------------------------------------------------------------------- BenchMARL
def test_benchmarl_tasks_and_their_config():
    pytest.importorskip("benchmarl")
    from baselines.benchmarl_tasks import SwarmTask, SwarmTaskClass, get_task

    assert [t.name for t in SwarmTask] == ["COVERAGE", "FORMATION", "LINE"]
    task = get_task("line", {"num_agents": 4, "obs_mode": "local", "action_space": "discrete", "max_steps": 30})
    assert isinstance(task, SwarmTaskClass) and task.config["comm"] == "uc"
    assert task.supports_discrete_actions() and not task.supports_continuous_actions()
    env = task.get_env_fun(num_envs=2, continuous_actions=False, seed=0, device="cpu")()
    assert task.max_steps(env) == 30 and env.max_steps == 30
    assert task.group_map(env) == {"agents": ["agent_0", "agent_1", "agent_2", "agent_3"]}
    assert list(task.observation_spec(env)["agents"].keys()) == ["observation"]  # no comm graph for the models
    assert task.observation_spec(env)["agents", "observation"].shape == (4, obs_dim("local", 4, 2))
    assert task.action_spec(env)["agents", "action"].shape == (4,)
    assert task.state_spec(env) is None and task.info_spec(env) is None and not task.has_render(env)
    assert task.env_name() == "taichi_swarm"
    assert SwarmTask.COVERAGE.get_from_yaml().config["obs_mode"] == "full"  # the defaults
    with pytest.raises(ValueError, match="task must be one of"):
        get_task("swarming")
    with pytest.raises(ValueError, match="obs_mode"):
        get_task("coverage", {"obs_mode": "global"})
    with pytest.raises(ValueError, match="unknown task config key"):
        get_task("coverage", {"team": 3})
    with pytest.raises(ValueError, match="action_space"):
        get_task("coverage", {"action_space": "box"})
    with pytest.raises(ValueError, match="continuous_actions"):
        task.get_env_fun(num_envs=2, continuous_actions=True, seed=0, device="cpu")


TINY = [
    "--frames",
    "200",
    "--num-envs",
    "4",
    "--frames-per-batch",
    "100",
    "--eval-episodes",
    "20",
    "--experiment",
    "on_policy_minibatch_size=50",
    "--experiment",
    "on_policy_n_minibatch_iters=1",
    "--experiment",
    "off_policy_n_optimizer_steps=2",
    "--experiment",
    "off_policy_train_batch_size=32",
    "--experiment",
    "lr=3e-4",  # YAML 1.1 reads this as a string: the override parser must not
]


@pytest.mark.parametrize(
    ("algorithm", "task", "extra", "actions"),
    [
        ("mappo", "coverage", ["--actions", "discrete"], "discrete"),  # on-policy
        ("maddpg", "line", ["--obs-mode", "local"], "continuous"),  # off-policy, continuous only
        ("iql", "formation", [], "discrete"),  # off-policy, discrete only
    ],
)
def test_run_baselines_trains_and_evaluates(tmp_path, algorithm, task, extra, actions):
    pytest.importorskip("benchmarl")
    from baselines.run import main

    out = tmp_path / algorithm
    assert main(["--algorithm", algorithm, "--task", task, "--agents", "3", "--out", str(out), *TINY, *extra]) == 0
    result = json.loads((out / "results.json").read_text())
    assert result["algorithm"] == algorithm and result["task"] == task and result["actions"] == actions
    assert result["frames"] == 200 and result["episodes"] == 20 and result["seed"] == 12345
    assert 0.0 <= result["S%"] <= 100.0 and 1.0 <= result["T"] <= 50.0
    assert (result["DIST"] is None) == (task != "coverage")
    assert len(result["per_episode"]["success"]) == 20
    assert list(out.glob("*/checkpoints/checkpoint_200.pt"))


def test_evaluation_reads_the_simulators_episode_statistics():
    """Greedy evaluation of a scripted policy: S%, T and DIST equal those of the simulator stepped
    directly with the same actions (same seed: the same 64 episodes)."""
    pytest.importorskip("benchmarl")
    import torch

    from baselines.benchmarl_tasks import get_task
    from baselines.run import evaluate_policy
    from taichi_swarm.metrics import FirstEpisodes

    B, M = 64, 1
    kw = dict(max_steps=8, success_threshold=0.4)  # some succeed, at various steps; the rest time out
    config = {"num_agents": M, "obs_mode": "local", "max_steps": 8, "task_params": {"success_threshold": 0.4}}
    task = get_task("coverage", config)
    gen = torch.Generator().manual_seed(1)
    actions = torch.randint(0, 5, (kw["max_steps"], B, M), generator=gen)
    result = evaluate_policy(_scripted_policy(actions), task, continuous_actions=False, episodes=B, seed=4)
    sim = taichi_swarm.make("coverage", B, M, seed=4, **kw)
    sim.reset()
    tally = FirstEpisodes(B)
    for a in actions:
        _, _, done, info = sim.step(a)
        tally.add(done, info["episode"])
    assert tally.all_done()
    want = tally.summary("coverage")
    assert result["per_episode"] == want["per_episode"]
    assert 0 < result["success_rate"] < 1 and result["mean_length"] == want["mean_length"] < kw["max_steps"]


def test_run_baselines_rejects_bad_arguments(tmp_path, capsys):
    pytest.importorskip("benchmarl")
    from baselines.run import main

    out = ["--out", str(tmp_path / "x")]
    for args, name in [
        (["--algorithm", "dqn"], "algorithm"),
        (["--task", "swarming"], "task"),
        (["--obs-mode", "global"], "obs_mode"),
        (["--actions", "box"], "action_space"),
        (["--frames", "0"], "frames must be >= 1"),
        (["--experiment", "nonsense=1"], "--experiment"),
        (["--experiment", "lr"], "--experiment"),
    ]:
        assert main([*args, *out]) == 2
        assert name in capsys.readouterr().err
    assert not (tmp_path / "x" / "results.json").exists()


def test_run_baselines_resumes_from_its_latest_checkpoint(tmp_path, capsys):
    """A run given the same command again continues from BenchMARL's checkpoint (here: extended
    from 200 to 400 env steps) with its optimisers' state, the last two checkpoints kept; another
    run's options are refused with config.pkl left as it was, and so is an unreadable checkpoint."""
    pytest.importorskip("benchmarl")
    import torch

    from baselines.run import latest_checkpoint, main

    out = tmp_path / "mappo"
    base = ["--algorithm", "mappo", "--task", "coverage", "--agents", "2", "--out", str(out), *TINY]
    base += ["--actions", "discrete", "--checkpoint-every", "1"]
    assert main(base) == 0
    assert latest_checkpoint(str(out)).endswith("checkpoint_200.pt")
    assert len(list(out.glob("*/checkpoints/*.pt"))) == 2  # the last two kept: 100 and 200
    folder = next(out.glob("*/checkpoints"))
    (folder / "checkpoint_final.pt").write_text("not ours")  # ignored

    def adam_steps(path):
        state = torch.load(path, weights_only=False)["optimizers"]["agents"]
        return {name: int(s["state"][0]["step"]) for name, s in state.items() if s["state"]}

    steps_at_200 = adam_steps(folder / "checkpoint_200.pt")
    assert steps_at_200 and all(n > 0 for n in steps_at_200.values())
    frames_at = base.index("--frames") + 1
    longer = [*base[:frames_at], "400", *base[frames_at + 1 :]]
    assert main(longer) == 0
    assert "resuming from" in capsys.readouterr().err
    result = json.loads((out / "results.json").read_text())
    assert result["frames"] == 400 and result["resumed_from"].endswith("checkpoint_200.pt")
    assert len(list(out.glob("*"))) == 3  # one experiment folder (with config.pkl), results.json, curves.png
    assert sorted(p.name for p in folder.iterdir()) == ["checkpoint_300.pt", "checkpoint_400.pt", "checkpoint_final.pt"]
    # Adam continued where it stopped: twice the steps after twice the iterations
    assert adam_steps(folder / "checkpoint_400.pt") == {k: 2 * n for k, n in steps_at_200.items()}
    pkl = (folder.parent / "config.pkl").read_bytes()
    even_longer = [*base[:frames_at], "500", *base[frames_at + 1 :]]
    for change, named in [
        (["--algorithm", "iql"], "--algorithm"),
        (["--agents", "3"], "task config"),
        (["--seed", "1"], "--seed"),
        (["--experiment", "lr=0.001"], "lr"),
        (["--num-envs", "2"], "n_envs_per_worker"),
    ]:
        assert main([*even_longer, *change]) == 2
        assert named in capsys.readouterr().err
        assert (folder.parent / "config.pkl").read_bytes() == pkl
    assert sorted(p.name for p in folder.iterdir()) == ["checkpoint_300.pt", "checkpoint_400.pt", "checkpoint_final.pt"]
    (folder / "checkpoint_500.pt").write_bytes((folder / "checkpoint_400.pt").read_bytes()[:1000])  # a save cut short
    assert main(even_longer) == 2
    assert "cannot resume" in (err := capsys.readouterr().err) and "checkpoint_500.pt" in err
    assert (folder.parent / "config.pkl").read_bytes() == pkl


def test_run_baselines_refuses_a_batch_that_is_not_a_multiple_of_the_envs(tmp_path, capsys):
    pytest.importorskip("benchmarl")
    from baselines.run import main

    args = ["--out", str(tmp_path / "x"), *TINY, "--num-envs", "3"]  # 100 frames per batch
    assert main(args) == 2
    assert "frames_per_batch (100) must be a multiple of num_envs (3)" in capsys.readouterr().err


def test_a_run_whose_actions_become_nan_names_its_last_checkpoint(tmp_path, capsys, monkeypatch):
    """A diverged policy (NaN actions, which the simulator refuses) is reported as divergence,
    naming the latest checkpoint and the --frames that evaluates it; that command then works
    (and says so too when the checkpoint itself holds diverged weights)."""
    pytest.importorskip("benchmarl")
    import torch

    import baselines.run as run_module

    out = tmp_path / "ippo"
    base = ["--algorithm", "ippo", "--task", "coverage", "--agents", "2", "--out", str(out), *TINY]
    base += ["--actions", "continuous", "--checkpoint-every", "1"]
    assert run_module.main(base) == 0
    (out / "results.json").unlink()

    env = taichi_swarm.make("coverage", num_envs=1, num_agents=2, action_space="continuous")
    env.reset(seed=0)
    with pytest.raises(ValueError) as refused:  # the simulator's own error, as a diverged run meets it
        env.step(torch.full((1, 2, 2), float("nan")))

    def diverging_train(*args, **kwargs):
        raise refused.value

    monkeypatch.setattr(run_module, "train", diverging_train)
    frames_at = base.index("--frames") + 1
    longer = [*base[:frames_at], "400", *base[frames_at + 1 :]]
    assert run_module.main(longer) == 3
    err = capsys.readouterr().err
    assert "training diverged" in err and "NaN" in err
    assert "checkpoint_200.pt" in err and "--frames 200" in err
    assert not (out / "results.json").exists()
    monkeypatch.undo()
    monkeypatch.setattr(run_module, "evaluate_policy", diverging_train)  # a checkpoint that holds NaN weights
    assert run_module.main(base) == 3
    assert "weights diverged" in capsys.readouterr().err
    monkeypatch.undo()
    assert run_module.main(base) == 0  # --frames 200: evaluates the checkpoint, trains no further
    assert json.loads((out / "results.json").read_text())["frames"] == 200

    fresh = tmp_path / "fresh"
    monkeypatch.setattr(run_module, "train", diverging_train)
    assert run_module.main([*base[: base.index("--out")], "--out", str(fresh), *base[base.index("--out") + 2 :]]) == 3
    assert "No checkpoint was written" in capsys.readouterr().err
