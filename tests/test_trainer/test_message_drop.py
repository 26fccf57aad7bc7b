"""Training through a lossy radio (TrainConfig.message_drop): each step's stored graph loses
messages at the environment's rate, never an agent's own state, and the rollout buffer holds
the graph the agents heard, so the PPO update trains on it."""

import pytest
import torch

from trainer.config import PRESETS, TrainConfig
from trainer.ppo import drop_messages


def test_dense_graph_loses_messages_at_the_rate_and_keeps_the_diagonal():
    torch.manual_seed(0)
    E, M = 400, 6
    adj = torch.ones(E, M, M, dtype=torch.bool)
    rate = torch.cat([torch.zeros(E // 2), torch.full((E // 2,), 0.3)])
    drop_messages({"adj": adj}, rate)
    eye = torch.eye(M, dtype=torch.bool)
    assert adj[:, eye].all()  # an agent always hears itself
    off = adj[:, ~eye].float()
    assert off[: E // 2].mean() == 1.0  # rate 0: nothing dropped
    assert abs(off[E // 2 :].mean().item() - 0.7) < 0.02  # 12,000 edges: 0.7 +- 0.004 (1 sd)


def test_a_message_already_missing_stays_missing():
    adj = torch.zeros(3, 4, 4, dtype=torch.bool)
    adj[:, 0, 1] = True
    drop_messages({"adj": adj}, torch.zeros(3))
    assert adj.sum() == 3 and adj[:, 0, 1].all()


def test_neighbour_lists_lose_entries_at_the_rate():
    torch.manual_seed(1)
    mask = torch.ones(300, 8, 16, dtype=torch.bool)
    drop_messages({"nbr": torch.zeros(300, 8, 16, dtype=torch.int32), "nbr_mask": mask}, torch.full((300,), 0.5))
    assert abs(mask.float().mean().item() - 0.5) < 0.02


def test_the_rollout_stores_the_graph_the_agents_heard():
    from taichi_swarm import make, runtime
    from trainer.model import ModelConfig, SwarmPolicy
    from trainer.ppo import RewardScaler, Rollout, collect_rollout

    runtime.init("cpu")
    torch.manual_seed(0)
    env = make("coverage", num_envs=16, num_agents=4, comm="uc", seed=3)
    obs = env.reset()
    policy = SwarmPolicy(ModelConfig(hidden=16))
    p = PRESETS["fast"]
    heard = {}
    for drop in (0.0, 0.8):
        buf = Rollout.for_env(8, env)
        collect_rollout(policy, env, obs, buf, RewardScaler(16, p.gamma, p.reward_clip), p, "cpu", message_drop=drop)
        heard[drop] = buf.adj.float().mean().item()
    assert heard[0.0] == 1.0  # UC: everyone hears everyone
    # rates drawn from [0, 0.8]: on average 40% of the 12 of 16 entries that are messages
    assert 0.45 < heard[0.8] < 0.9


def test_message_drop_is_checked():
    with pytest.raises(ValueError, match="message_drop must be in"):
        TrainConfig(message_drop=1.0).validate()
    TrainConfig(message_drop=0.5).validate()
