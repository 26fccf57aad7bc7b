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
    assert buf.adj.diagonal(dim1=-2, dim2=-1).all()  # an agent always keeps its own state


def test_message_drop_is_checked():
    with pytest.raises(ValueError, match="message_drop must be in"):
        TrainConfig.of(message_drop=1.0).validate()
    TrainConfig.of(message_drop=0.5).validate()


def test_drops_per_round_store_a_graph_per_round():
    """drop_per_round: each round of a step loses its own messages (as `swarm execute --drop`)."""
    from taichi_swarm import make, runtime
    from trainer.model import ModelConfig, SwarmPolicy
    from trainer.ppo import RewardScaler, Rollout, collect_rollout

    runtime.init("cpu")
    torch.manual_seed(0)
    env = make("coverage", num_envs=16, num_agents=4, comm="uc", seed=3)
    obs = env.reset()
    p = PRESETS["fast"]
    buf = Rollout.for_env(8, env, rounds=3)
    assert buf.adj.shape == (8, 16, 3, 4, 4)
    policy = SwarmPolicy(ModelConfig(hidden=16))
    collect_rollout(policy, env, obs, buf, RewardScaler(16, p.gamma, p.reward_clip), p, "cpu", message_drop=0.8)
    assert buf.adj.diagonal(dim1=-2, dim2=-1).all()
    assert 0.45 < buf.adj.float().mean().item() < 0.9
    assert (buf.adj[:, :, 0] != buf.adj[:, :, 1]).any()  # the rounds lost different messages
    with pytest.raises(ValueError, match="drop_per_round"):
        TrainConfig.of(drop_per_round=True).validate()
    TrainConfig.of(drop_per_round=True, message_drop=0.3).validate()


@pytest.mark.parametrize("lists", [False, True])
def test_a_graph_per_round_is_the_network_of_each_rounds_graph(lists):
    """The fused forward and the per-agent reference agree on a graph per round; the same graph
    in every round is the shared graph; and each round hears its own (round 0 alone dropped
    changes the output)."""
    from trainer.model import ModelConfig, SwarmPolicy

    torch.manual_seed(4)
    N, M, L, K = 3, 6, 6, 4
    policy = SwarmPolicy(ModelConfig(hidden=16, edge_position="relative"))
    torch.nn.init.normal_(policy.edge_key.weight)
    torch.nn.init.normal_(policy.edge_value.weight)
    self_obs, entities = torch.randn(N, M, 4), torch.randn(N, M, L, 2)
    if lists:
        nbr = torch.stack([torch.randperm(M)[:K] for _ in range(N * M)]).view(N, M, K).int()
        shared = torch.rand(N, M, K) < 0.8
        graph = {"nbr": nbr, "nbr_mask": shared}
        per_round = {"nbr": nbr, "nbr_mask": shared.unsqueeze(1).repeat(1, 3, 1, 1)}
        key = "nbr_mask"
    else:
        shared = (torch.rand(N, M, M) < 0.7) | torch.eye(M, dtype=torch.bool)
        graph, per_round, key = {"adj": shared}, {"adj": shared.unsqueeze(1).repeat(1, 3, 1, 1)}, "adj"
    base = policy(self_obs, entities, **graph)[0]
    torch.testing.assert_close(policy(self_obs, entities, **per_round)[0], base)
    torch.testing.assert_close(policy.forward_reference(self_obs, entities, **per_round)[0], base, atol=1e-5, rtol=1e-5)
    cut = per_round[key].clone()
    cut[:, 0] &= torch.eye(M, dtype=torch.bool) if not lists else False  # round 0 hears only itself
    fused = policy(self_obs, entities, **{**per_round, key: cut})[0]
    ref = policy.forward_reference(self_obs, entities, **{**per_round, key: cut})[0]
    torch.testing.assert_close(fused, ref, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(fused, base)
    with pytest.raises(ValueError, match="per round"):
        policy(self_obs, entities, **{**per_round, key: per_round[key][:, :2]})
