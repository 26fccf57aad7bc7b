"""GAE and the PPO loss against numbers worked out by hand; reward scaling."""

import math

import pytest
import torch

from trainer.ppo import RewardScaler, gae, normalize_per_agent, ppo_loss, sample_actions


def test_gae_by_hand():
    # one env, one agent, T = 3, gamma = 0.5, lambda = 0.5; the episode ends at t = 1
    r = torch.tensor([[[1.0]], [[2.0]], [[3.0]]])
    v = torch.tensor([[[0.5]], [[1.0]], [[2.0]]])
    d = torch.tensor([[False], [True], [False]])
    nv = torch.tensor([[4.0]])
    adv, ret = gae(r, v, d, nv, gamma=0.5, lam=0.5)
    # t=2: delta = 3 + 0.5*4 - 2 = 3;             A2 = 3
    # t=1: done -> delta = 2 - 1 = 1;              A1 = 1 (no carry over the boundary)
    # t=0: delta = 1 + 0.5*1.0 - 0.5 = 1;          A0 = 1 + 0.25 * 1 = 1.25
    torch.testing.assert_close(adv[:, 0, 0], torch.tensor([1.25, 1.0, 3.0]))
    torch.testing.assert_close(ret[:, 0, 0], torch.tensor([1.75, 2.0, 5.0]))


def test_gae_rewards_and_values_are_per_agent():
    r = torch.tensor([[[1.0, 1.0]]])  # the team reward, stored for each agent
    v = torch.tensor([[[0.0, 1.0]]])
    adv, _ = gae(r, v, torch.tensor([[True]]), torch.zeros(1, 2), 0.9, 0.9)
    torch.testing.assert_close(adv[0, 0], torch.tensor([1.0, 0.0]))
    # a time-limit end: each agent's reward holds gamma * its own value of the final state
    r = torch.tensor([[[1.0 + 0.9 * 2.0, 1.0 + 0.9 * 4.0]]])
    adv, ret = gae(r, v, torch.tensor([[True]]), torch.zeros(1, 2), 0.9, 0.9)
    torch.testing.assert_close(ret[0, 0], torch.tensor([2.8, 4.6]))


def test_each_agent_bootstraps_on_its_own_value_at_a_time_limit_end():
    """The rollout's stored reward at a time-limit end is the team reward plus gamma *
    V_i(final state) for each agent i, not the team's mean value."""
    import taichi_swarm
    from trainer.config import PPOConfig
    from trainer.model import ModelConfig, SwarmPolicy, policy_inputs
    from trainer.ppo import Rollout, collect_rollout

    torch.manual_seed(0)
    T = 6
    env = taichi_swarm.make("coverage", 4, 3, seed=0, max_steps=T)  # every episode is cut in the last step
    obs = env.reset(seed=0)
    policy = SwarmPolicy(ModelConfig(hidden=16, rounds=1))
    p = PPOConfig(num_envs=4, num_steps=T, reward_scale=False, bootstrap_time_limit=True)
    last = {}
    real_step = env.step

    def step(action):
        out = real_step(action)
        _, reward, done, info = out
        last.update(raw=reward.clone(), cut=done & info["episode"]["truncated"])
        last["terminal"] = {k: v.clone() for k, v in info["terminal_obs"].items()}
        return out

    env.step = step
    buf = Rollout.for_env(T, env)
    collect_rollout(policy, env, obs, buf, RewardScaler(4, p.gamma, p.reward_clip, enabled=False), p, "cpu")
    cut = last["cut"]
    assert bool(cut.any())
    with torch.no_grad():
        _, v_term = policy(**policy_inputs(last["terminal"], "cpu"))
    expected = last["raw"][cut].unsqueeze(-1) + p.gamma * v_term[cut]
    torch.testing.assert_close(buf.rewards[T - 1][cut], expected)
    assert not torch.allclose(expected[:, 0], expected[:, 1])  # the agents' own values, not one shared


def test_ppo_loss_by_hand():
    # two samples, logits uniform over 5 actions -> log pi = -log 5, entropy = log 5
    logits = torch.zeros(1, 2, 5)
    actions = torch.tensor([[0, 1]])
    old_logp = torch.tensor([[-math.log(5) - 0.5, -math.log(5) + 0.5]])  # ratios e^0.5, e^-0.5
    adv = torch.tensor([[1.0, 1.0]])
    values = torch.tensor([[1.0, 0.0]])
    old_values = torch.tensor([[0.5, 0.0]])
    returns = torch.tensor([[0.0, 1.0]])
    total, info = ppo_loss(
        logits, values, actions, old_logp, old_values, adv, returns, clip=0.2, value_coef=0.5, entropy_coef=0.01
    )
    # policy: sample 0 ratio 1.6487 -> min(1.6487, 1.2) * 1 = 1.2; sample 1 ratio 0.6065 -> 0.6065
    pg = -(1.2 + math.exp(-0.5)) / 2
    # value: sample 0 v=1, clipped 0.5+0.2=0.7, R=0 -> max(1, 0.49) = 1; sample 1 -> max(1, 1) = 1
    v = 0.5 * (1 + 1) / 2
    ent = math.log(5)
    assert info.policy.item() == pytest.approx(pg, abs=1e-6)
    assert info.value.item() == pytest.approx(v, abs=1e-6)
    assert info.entropy.item() == pytest.approx(ent, abs=1e-6)
    assert total.item() == pytest.approx(pg + 0.5 * v - 0.01 * ent, abs=1e-6)
    assert info.clipfrac.item() == pytest.approx(1.0)


def test_advantages_normalised_per_agent():
    adv = torch.stack([torch.arange(10.0), 100 + 5 * torch.arange(10.0)], -1).reshape(5, 2, 2)
    n = normalize_per_agent(adv).reshape(-1, 2)
    torch.testing.assert_close(n.mean(0), torch.zeros(2), atol=1e-6, rtol=0)
    torch.testing.assert_close(n.std(0), torch.ones(2), atol=1e-4, rtol=0)
    torch.testing.assert_close(n[:, 0], n[:, 1], atol=1e-5, rtol=0)


def test_reward_scaler_divides_by_return_std_and_clips():
    s = RewardScaler(num_envs=2, gamma=0.9, clip=10.0)
    out = None
    for _ in range(200):
        out = s(torch.tensor([1.0, -1.0]), torch.tensor([False, False]))
    # returns converge to +-10: std ~ 10 -> scaled rewards ~ +-0.1
    assert out[0].item() == pytest.approx(0.1, rel=0.2) and out[1].item() == pytest.approx(-0.1, rel=0.2)
    s = RewardScaler(num_envs=1, gamma=0.9, clip=2.0)
    s(torch.tensor([1e-3]), torch.tensor([False]))
    assert s(torch.tensor([1e3]), torch.tensor([True])).item() == 2.0
    assert s.ret.item() == 0.0  # reset at the episode end


def test_reward_scaler_without_reset_keeps_the_return_like_the_published_code():
    s = RewardScaler(num_envs=1, gamma=0.5, clip=10.0, reset_at_done=False)
    s(torch.tensor([1.0]), torch.tensor([True]))
    s(torch.tensor([1.0]), torch.tensor([True]))
    assert s.ret.item() == pytest.approx(1.5)  # 0.5 * 1 + 1: never reset


def test_loss_matches_categorical_reference():
    """The loss without torch.distributions is the same function (fixed batch, fixed seed)."""
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(64, 3, 5, generator=g, requires_grad=True)
    values = torch.randn(64, 3, generator=g, requires_grad=True)
    actions = torch.randint(0, 5, (64, 3), generator=g)
    old_lp, old_v, adv, ret = (torch.randn(64, 3, generator=g) for _ in range(4))
    old_lp = old_lp.clamp(max=-0.1)
    loss, info = ppo_loss(logits, values, actions, old_lp, old_v, adv, ret, 0.2, 0.5, 0.01)
    dist = torch.distributions.Categorical(logits=logits)
    ratio = (dist.log_prob(actions) - old_lp).exp()
    pg = torch.max(-adv * ratio, -adv * ratio.clamp(0.8, 1.2)).mean()
    vc = old_v + (values - old_v).clamp(-0.2, 0.2)
    vl = 0.5 * torch.max((values - ret) ** 2, (vc - ret) ** 2).mean()
    want = pg + 0.5 * vl - 0.01 * dist.entropy().mean()
    torch.testing.assert_close(loss, want, atol=1e-6, rtol=1e-6)
    g1 = torch.autograd.grad(loss, [logits, values])
    g2 = torch.autograd.grad(want, [logits, values])
    for a, b in zip(g1, g2, strict=False):
        torch.testing.assert_close(a, b, atol=1e-7, rtol=1e-5)


def test_sampled_actions_and_log_probs():
    torch.manual_seed(0)
    logits = torch.tensor([[0.0, 0.0, 5.0, -5.0, 0.0]]).expand(20000, 5)
    actions, logp = sample_actions(logits)
    freq = torch.bincount(actions.view(-1), minlength=5).float() / actions.numel()
    probs = logits[0].softmax(-1)
    torch.testing.assert_close(freq, probs, atol=0.01, rtol=0)
    torch.testing.assert_close(logp, probs.log()[actions], atol=1e-6, rtol=0)


def test_bf16_update_is_the_fp32_update_to_bf16_tolerance():
    """precision="bf16" (autocast) computes the same loss and gradient as fp32, to the
    precision of bfloat16; fp32 stays exact."""
    from types import SimpleNamespace

    from trainer.model import ModelConfig, SwarmPolicy
    from trainer.ppo import make_loss_fn

    torch.manual_seed(0)
    N, M = 64, 4
    policy = SwarmPolicy(ModelConfig(hidden=64))
    p = SimpleNamespace(clip=0.2, value_coef=0.5, entropy_coef=0.01)
    batch = (
        torch.randn(N, M, 4), torch.randn(N, M, M, 2), torch.rand(N, M, M) < 0.7,
        torch.randint(0, 5, (N, M)), -1.6 + 0.1 * torch.randn(N, M), torch.randn(N, M), torch.randn(N, M),
        torch.randn(N, M),
    )  # fmt: skip
    results = {}
    for precision in ("fp32", "bf16"):
        policy.zero_grad()
        loss, stats = make_loss_fn(policy, p, precision=precision)(*batch)
        loss.backward()
        grad = torch.cat([q.grad.flatten() for q in policy.parameters()])
        results[precision] = loss.detach(), stats, grad
    (l32, s32, g32), (l16, s16, g16) = results["fp32"], results["bf16"]
    assert l16.dtype == torch.float32 and torch.isfinite(g16).all()
    assert abs(float(l16 - l32)) < 0.02 * (1 + abs(float(l32)))
    assert torch.allclose(s16, s32, rtol=0.05, atol=0.02)
    assert torch.nn.functional.cosine_similarity(g16, g32, dim=0) > 0.99
    with pytest.raises(ValueError, match="precision"):
        make_loss_fn(policy, p, precision="fp16")
