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
    buf = Rollout.for_env(8, env)  # in bursts: on average the same share lost
    collect_rollout(
        policy, env, obs, buf, RewardScaler(16, p.gamma, p.reward_clip), p, "cpu", message_drop=0.8, message_burst=4
    )
    assert 0.45 < buf.adj.float().mean().item() < 0.9
    assert buf.adj.diagonal(dim1=-2, dim2=-1).all()


def test_message_drop_is_checked():
    with pytest.raises(ValueError, match="message_drop must be in"):
        TrainConfig(message_drop=1.0).validate()
    TrainConfig(message_drop=0.5).validate()
    for burst in (0.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="message_burst must be"):
            TrainConfig(message_drop=0.3, message_burst=burst).validate()
    with pytest.raises(ValueError, match="with message_drop > 0"):
        TrainConfig(message_burst=4.0).validate()
    TrainConfig(message_drop=0.3, message_burst=4.0).validate()


def test_bursts_have_the_rate_and_the_length():
    """The chain's stationary loss is the env's rate and a burst lasts burst_len steps on average."""
    from trainer.ppo import burst_start, burst_step

    torch.manual_seed(2)
    rate = torch.full((200,), 0.3)
    bad = burst_start(rate, 10)
    steps = [bad]
    for _ in range(400):
        bad = burst_step(bad, rate, 4.0)
        steps.append(bad)
    run = torch.stack(steps)  # [T, E, M]
    assert abs(run.float().mean().item() - 0.3) < 0.02
    ends = (run[:-1] & ~run[1:]).sum().item()  # a burst ends where bad turns good
    assert abs(run[:-1].sum().item() / ends - 4.0) < 0.2  # bad steps per burst


def test_a_sender_in_a_burst_reaches_nobody():
    from trainer.ppo import drop_senders

    E, M, K = 2, 4, 3
    bad = torch.tensor([[False, True, False, False], [False, False, False, False]])
    adj = torch.ones(E, M, M, dtype=torch.bool)
    drop_senders({"adj": adj}, bad)
    assert not adj[0, [0, 2, 3], 1].any() and adj[0, 1, 1]  # nobody hears 1; 1 keeps itself
    assert adj[0][:, [0, 2, 3]].all() and adj[1].all()
    nbr = torch.tensor([[[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]] * E, dtype=torch.int32)
    mask = torch.ones(E, M, K, dtype=torch.bool)
    drop_senders({"nbr": nbr, "nbr_mask": mask}, bad)
    assert (mask[0] == (nbr[0] != 1)).all() and mask[1].all()
