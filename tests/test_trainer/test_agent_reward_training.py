"""Training on each agent's own reward (TrainConfig.reward = "agent"): the rollout stores
every agent's own terms, not the team's, and a run on them checkpoints and resumes."""

import dataclasses
import json
import os

import pytest
import torch

from trainer.config import PRESETS, TrainConfig
from trainer.model import ModelConfig, SwarmPolicy
from trainer.ppo import RewardScaler, Rollout, collect_rollout


class Recorded:
    """The env, with a copy of every step's per-agent and team rewards kept."""

    def __init__(self, env):
        self.env, self.own, self.team = env, [], []

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, action):
        out = self.env.step(action)
        self.own.append(out[3]["agent_reward"].clone())
        self.team.append(out[1].clone())
        return out


@pytest.mark.parametrize("per_agent", [False, True])
def test_the_rollout_stores_each_agents_own_reward(per_agent):
    from taichi_swarm import make, runtime

    runtime.init("cpu")
    torch.manual_seed(0)
    env = Recorded(make("coverage", num_envs=8, num_agents=4, comm="uc", seed=5))
    obs = env.reset()
    p = dataclasses.replace(PRESETS["fast"], reward_scale=False, bootstrap_time_limit=False)
    buf = Rollout.for_env(6, env)
    scaler = RewardScaler(8 * 4 if per_agent else 8, p.gamma, p.reward_clip, enabled=False)
    collect_rollout(SwarmPolicy(ModelConfig(hidden=16)), env, obs, buf, scaler, p, "cpu", per_agent=per_agent)
    own, team = torch.stack(env.own), torch.stack(env.team)  # [T, E, M], [T, E]
    want = own if per_agent else team.unsqueeze(-1).expand_as(own)
    torch.testing.assert_close(buf.rewards, want)
    assert (own != team.unsqueeze(-1)).any()  # the agents' terms differ: the two modes are told apart


def test_a_run_on_agent_rewards_resumes(tmp_path):
    from trainer.train import train

    cfg = TrainConfig.of(
        task="coverage",
        agents=3,
        updates=2,
        eval_every=2,
        eval_episodes=2,
        checkpoint_every=1,
        run_dir=str(tmp_path / "run"),
        progress=False,
        transfer_offsets=(),
        reward="agent",
        model=ModelConfig(hidden=16, rounds=1),
        ppo=dataclasses.replace(PRESETS["fast"], num_envs=4, num_steps=8, epochs=1, minibatches=2),
        compile=False,
    )
    train(dataclasses.replace(cfg, updates=1))
    summary = train(resume=cfg.run_dir, updates=2)
    assert summary["update"] == 2
    assert json.load(open(os.path.join(cfg.run_dir, "config.json")))["reward"] == "agent"
    with pytest.raises(ValueError, match="reward"):
        TrainConfig.of(reward="own").validate()
