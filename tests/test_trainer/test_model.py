"""The GNN's invariances: permutation, locality of "rc", isolation, any M."""

import pytest
import torch

from trainer.model import ModelConfig, SwarmPolicy


def team(N, M, L, seed=0, radius=None):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(N, M, 2, generator=g) * 2 - 1
    vel = torch.randn(N, M, 2, generator=g) * 0.3
    lmk = torch.rand(N, L, 2, generator=g) * 2 - 1
    self_obs = torch.cat([vel, pos], -1)
    entities = lmk[:, None] - pos[:, :, None]
    if radius is None:
        adj = torch.ones(N, M, M, dtype=torch.bool)
    else:
        adj = torch.cdist(pos, pos) <= radius
    return self_obs, entities, adj, pos, lmk


@pytest.fixture(scope="module")
def policy():
    torch.manual_seed(0)
    return SwarmPolicy(ModelConfig()).eval()


def test_permuting_agents_permutes_outputs(policy):
    s, e, a, _, _ = team(4, 6, 6, radius=0.9)
    perm = torch.randperm(6)
    logits, value = policy(s, e, a)
    logits_p, value_p = policy(s[:, perm], e[:, perm], a[:, perm][:, :, perm])
    torch.testing.assert_close(logits_p, logits[:, perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(value_p, value[:, perm], atol=1e-5, rtol=1e-5)


def test_permuting_landmarks_changes_nothing(policy):
    s, e, a, _, _ = team(4, 5, 5)
    perm = torch.randperm(5)
    torch.testing.assert_close(policy(s, e[:, :, perm], a)[0], policy(s, e, a)[0], atol=1e-5, rtol=1e-5)


def test_rc_agent_out_of_range_does_not_affect_others(policy):
    s, e, a, pos, lmk = team(1, 5, 5, seed=3)
    pos = torch.tensor([[[0.0, 0.0], [0.3, 0.0], [0.0, 0.4], [-0.2, -0.3], [5.0, 5.0]]])
    s = torch.cat([s[..., :2], pos], -1)
    e = lmk[:, None] - pos[:, :, None]
    adj = torch.cdist(pos, pos) <= 1.0
    out = policy(s, e, adj)[0]
    moved = pos.clone()
    moved[0, 4] = torch.tensor([-6.0, 4.0])  # still out of everyone's range
    s2 = torch.cat([s[..., :2], moved], -1)
    e2 = lmk[:, None] - moved[:, :, None]
    out2 = policy(s2, e2, torch.cdist(moved, moved) <= 1.0)[0]
    torch.testing.assert_close(out2[:, :4], out[:, :4])
    assert not torch.allclose(out2[:, 4], out[:, 4])
    # and the same agent *in* range does change the others
    near = pos.clone()
    near[0, 4] = torch.tensor([0.2, 0.2])
    s3 = torch.cat([s[..., :2], near], -1)
    out3 = policy(s3, lmk[:, None] - near[:, :, None], torch.cdist(near, near) <= 1.0)[0]
    assert not torch.allclose(out3[:, :4], out[:, :4])


def test_isolated_agent_and_masked_rows_are_finite(policy):
    s, e, _, _, _ = team(3, 4, 4)
    only_self = torch.eye(4, dtype=torch.bool).expand(3, 4, 4).clone()
    logits, value = policy(s, e, only_self)
    assert torch.isfinite(logits).all() and torch.isfinite(value).all()
    nobody = torch.zeros(3, 4, 4, dtype=torch.bool)  # not even itself: still no NaN
    logits, value = policy(s, e, nobody)
    assert torch.isfinite(logits).all() and torch.isfinite(value).all()


@pytest.mark.parametrize("M", [1, 3, 10, 50])
def test_same_weights_any_team_size(policy, M):
    s, e, a, _, _ = team(2, M, M)
    logits, value = policy(s, e, a)
    assert logits.shape == (2, M, 5) and value.shape == (2, M)
    assert torch.isfinite(logits).all()


def test_parameter_count_is_the_papers_and_independent_of_team_size():
    H = 128
    heads = 2 * (H * H + H) + (H * 5 + 5) + (H + 1)
    attention = 4 * H * H
    comm = attention + (2 * H * H + H)
    expected = {
        "emp": (4 * H + H) + (2 * H + H) + attention + (2 * H * H + H) + comm + heads,
        "padded": (24 * H + H) + comm + heads,
        "concat": (8 * H + H) + comm + heads,
    }
    for mode, kw in [("emp", {}), ("padded", {}), ("concat", {"num_landmarks": 2})]:
        assert SwarmPolicy(ModelConfig(entity_mode=mode, **kw)).num_parameters() == expected[mode], mode
    p = SwarmPolicy(ModelConfig(entity_mode="padded"))
    for M in (2, 7):
        s, e, a, _, _ = team(1, M, M)
        assert p(s, e, a)[0].shape == (1, M, 5)
    with pytest.raises(ValueError, match="at most 10"):
        p(*team(1, 11, 11)[:3])
    c = SwarmPolicy(ModelConfig(entity_mode="concat", num_landmarks=2))
    with pytest.raises(ValueError, match="concatenates 2"):
        c(*team(1, 3, 3)[:3])
    # a config may leave L to the trainer (the task's: train.model_config_for); a network cannot
    with pytest.raises(ValueError, match="needs num_landmarks >= 1"):
        SwarmPolicy(ModelConfig(entity_mode="concat"))
    from trainer.config import TrainConfig
    from trainer.train import model_config_for

    cfg = TrainConfig.of(task="formation", agents=4, model=ModelConfig(entity_mode="concat"))
    assert model_config_for(cfg).num_landmarks == 1


def test_paper_initialisation():
    p = SwarmPolicy()
    w = p.agent_encoder.weight
    torch.testing.assert_close(w.T @ w, torch.eye(w.shape[1]), atol=1e-4, rtol=0)  # orthonormal columns
    u = p.comm_update.weight  # [128, 256]: orthonormal rows
    torch.testing.assert_close(u @ u.T, torch.eye(u.shape[0]), atol=1e-4, rtol=0)
    assert (p.agent_encoder.bias == 0).all()
    assert p.comm_attention.w_q.weight.abs().max() <= 1 / 128**0.5
    assert p.comm_attention.w_q.bias is None
    # K rounds share weights: the parameter count does not grow with K
    assert SwarmPolicy(ModelConfig(rounds=1)).num_parameters() == SwarmPolicy(ModelConfig(rounds=5)).num_parameters()


@pytest.mark.parametrize("mode,L", [("emp", 4), ("concat", 2), ("padded", 3)])
@pytest.mark.parametrize("radius", [None, 0.8])
def test_fast_forward_is_the_reference_network(mode, L, radius):
    """forward() rearranges the algebra (W_q W_k^T, W_v W_out folded into the update);
    it must compute the network as written, outputs and gradients, to float rounding."""
    torch.manual_seed(1)
    p = SwarmPolicy(ModelConfig(entity_mode=mode, num_landmarks=L if mode == "concat" else 0))
    M = 5
    s, e, a, _, _ = team(16, M, L, seed=2, radius=radius)
    fast = p(s, e, a, return_attention=True)
    ref = p.forward_reference(s, e, a, return_attention=True)
    for x, y in zip(fast[:2], ref[:2], strict=False):
        torch.testing.assert_close(x, y, atol=1e-5, rtol=1e-5)
    for x, y in zip(fast[2], ref[2], strict=False):
        torch.testing.assert_close(x, y, atol=1e-6, rtol=1e-5)
    grads = []
    for fn in (p.forward, p.forward_reference):
        p.zero_grad()
        logits, value = fn(s, e, a)
        (logits.square().sum() + value.sum()).backward()
        grads.append({n: q.grad.clone() for n, q in p.named_parameters()})
    for name in grads[0]:
        torch.testing.assert_close(grads[0][name], grads[1][name], atol=2e-5, rtol=1e-4, msg=name)
    cached = p(s, e, a, fused=p.fused_weights())
    torch.testing.assert_close(cached[0], fast[0])
