"""The network over neighbour lists is the dense network when the lists hold the same
graph: outputs and gradients, both forward paths, every entity mode; list order and
masked slots change nothing."""

import os

import pytest
import torch

from trainer.model import ModelConfig, SwarmPolicy, lists_to_adj, lists_to_dense, neighbour_slots, policy_inputs

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
TOL = dict(atol=2e-5, rtol=2e-5)


def team(N, M, L, seed=0, radius=None):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(N, M, 2, generator=g) * 2 - 1
    vel = torch.randn(N, M, 2, generator=g) * 0.3
    lmk = torch.rand(N, L, 2, generator=g) * 2 - 1
    self_obs = torch.cat([vel, pos], -1)
    entities = lmk[:, None] - pos[:, :, None]
    adj = torch.ones(N, M, M, dtype=torch.bool) if radius is None else torch.cdist(pos, pos) <= radius
    return self_obs, entities, adj


def lists_from_adj(adj, K, seed=0, pad=-1):
    """The simulator's layout from a dense adj: the heard agents other than self, in a
    random order, padded to K slots with ``pad`` (masked)."""
    N, M, _ = adj.shape
    g = torch.Generator().manual_seed(seed)
    nbr = torch.full((N, M, K), pad, dtype=torch.int32)
    mask = torch.zeros(N, M, K, dtype=torch.bool)
    for n in range(N):
        for i in range(M):
            heard = [j for j in torch.randperm(M, generator=g).tolist() if j != i and adj[n, i, j]]
            assert len(heard) <= K, "K too small for this graph"
            nbr[n, i, : len(heard)] = torch.tensor(heard, dtype=torch.int32)
            mask[n, i, : len(heard)] = True
    return nbr, mask


def make_policy(mode, L, rounds=3, seed=0):
    torch.manual_seed(seed)
    return SwarmPolicy(ModelConfig(hidden=32, rounds=rounds, entity_mode=mode, num_landmarks=L))


def outputs_and_grads(policy, path, *args, **kwargs):
    policy.zero_grad()
    logits, value = getattr(policy, path)(*args, **kwargs)
    (logits.square().sum() + value.sum()).backward()
    return logits.detach(), value.detach(), [p.grad.clone() for p in policy.parameters()]


@pytest.mark.parametrize("mode", ["emp", "concat", "padded"])
@pytest.mark.parametrize("path", ["forward", "forward_reference"])
@pytest.mark.parametrize("radius,extra", [(None, 0), (None, 3), (0.8, 2)])
def test_lists_equal_dense_outputs_and_gradients(mode, path, radius, extra):
    """K = M - 1 + extra (more slots than agents: padding); radius 0.8: an RC graph whose
    lists hold exactly each agent's heard set."""
    N, M, L = 3, 6, 4
    s, e, adj = team(N, M, L, seed=1, radius=radius)
    nbr, mask = lists_from_adj(adj, M - 1 + extra)
    policy = make_policy(mode, L)
    dense = outputs_and_grads(policy, path, s, e, adj)
    lists = outputs_and_grads(policy, path, s, e, nbr=nbr, nbr_mask=mask)
    torch.testing.assert_close(lists[0], dense[0], **TOL)
    torch.testing.assert_close(lists[1], dense[1], **TOL)
    for gl, gd in zip(lists[2], dense[2], strict=True):
        torch.testing.assert_close(gl, gd, atol=1e-4, rtol=1e-4)


def test_fast_and_reference_paths_agree_on_lists():
    s, e, adj = team(4, 9, 5, seed=2, radius=0.7)
    nbr, mask = lists_from_adj(adj, 8)
    policy = make_policy("emp", 5)
    fast = policy(s, e, nbr=nbr, nbr_mask=mask, return_attention=True)
    ref = policy.forward_reference(s, e, nbr=nbr, nbr_mask=mask, return_attention=True)
    for a, b in zip(fast[:2], ref[:2], strict=True):
        torch.testing.assert_close(a, b, **TOL)
    for wa, wb in zip(fast[2], ref[2], strict=True):
        assert wa.shape == (4, 9, 9)  # [self; 8 listed]
        torch.testing.assert_close(wa, wb, **TOL)


def test_list_attention_scatters_back_to_the_dense_attention():
    s, e, adj = team(2, 7, 3, seed=3, radius=0.9)
    nbr, mask = lists_from_adj(adj, 6)
    policy = make_policy("emp", 3)
    _, _, dense_att = policy(s, e, adj, return_attention=True)
    _, _, list_att = policy(s, e, nbr=nbr, nbr_mask=mask, return_attention=True)
    slots, listed = neighbour_slots(nbr, mask)
    for wd, wl in zip(dense_att, list_att, strict=True):
        torch.testing.assert_close(lists_to_dense(wl, slots, listed), wd, **TOL)


def test_list_order_does_not_matter():
    s, e, adj = team(3, 8, 4, seed=4, radius=0.9)
    nbr, mask = lists_from_adj(adj, 10, seed=0)
    nbr2, mask2 = lists_from_adj(adj, 10, seed=1)  # other order
    assert not torch.equal(nbr, nbr2)
    perm = torch.randperm(10)  # and padding slots moved in among the listed ones
    nbr3, mask3 = nbr[..., perm], mask[..., perm]
    policy = make_policy("emp", 4)
    ref = policy(s, e, nbr=nbr, nbr_mask=mask)
    for a, b in ((nbr2, mask2), (nbr3, mask3)):
        out = policy(s, e, nbr=a, nbr_mask=b)
        torch.testing.assert_close(out[0], ref[0], **TOL)
        torch.testing.assert_close(out[1], ref[1], **TOL)


def test_padding_value_and_self_in_the_list_change_nothing():
    """Masked slots may hold anything (-1, the agent's own index, another agent); a listed
    self is not counted twice (self is always heard, once)."""
    s, e, adj = team(2, 5, 3, seed=5, radius=0.9)
    nbr, mask = lists_from_adj(adj, 6, pad=-1)
    policy = make_policy("emp", 3)
    ref = policy(s, e, nbr=nbr, nbr_mask=mask)[0]
    junk = torch.where(mask, nbr, torch.randint(0, 5, nbr.shape, dtype=torch.int32))
    torch.testing.assert_close(policy(s, e, nbr=junk, nbr_mask=mask)[0], ref, **TOL)
    me = torch.arange(5, dtype=torch.int32).view(1, 5, 1).expand(2, 5, 1)
    with_self = torch.cat([nbr, me], -1), torch.cat([mask, torch.ones(2, 5, 1, dtype=torch.bool)], -1)
    torch.testing.assert_close(policy(s, e, nbr=with_self[0], nbr_mask=with_self[1])[0], ref, **TOL)


def test_empty_lists_are_the_isolated_agent():
    s, e, _ = team(2, 4, 3, seed=6)
    eye = torch.eye(4, dtype=torch.bool).expand(2, 4, 4)
    nbr, mask = torch.full((2, 4, 3), -1, dtype=torch.int32), torch.zeros(2, 4, 3, dtype=torch.bool)
    policy = make_policy("emp", 3)
    torch.testing.assert_close(policy(s, e, nbr=nbr, nbr_mask=mask)[0], policy(s, e, eye)[0], **TOL)
    nbr0, mask0 = torch.zeros(2, 4, 0, dtype=torch.int32), torch.zeros(2, 4, 0, dtype=torch.bool)  # K = 0
    torch.testing.assert_close(policy(s, e, nbr=nbr0, nbr_mask=mask0)[0], policy(s, e, eye)[0], **TOL)


@pytest.mark.parametrize("path", ["forward", "forward_reference"])
def test_masked_landmark_slots_equal_leaving_them_out(path):
    N, M, L = 3, 5, 6
    s, e, adj = team(N, M, L, seed=7, radius=0.9)
    nbr, mask = lists_from_adj(adj, 4)
    g = torch.Generator().manual_seed(0)
    sensed = torch.rand(N, M, L, generator=g) < 0.6
    sensed[..., 0] = True  # (every agent senses at least one: the row with none is below)
    policy = make_policy("emp", L)
    run = getattr(policy, path)
    masked = run(s, e, nbr=nbr, nbr_mask=mask, entity_mask=sensed)
    junk = torch.where(sensed.unsqueeze(-1), e, torch.randn_like(e) * 9)  # what masked slots hold: nothing
    torch.testing.assert_close(run(s, junk, nbr=nbr, nbr_mask=mask, entity_mask=sensed)[0], masked[0], **TOL)
    # each agent alone, with only its sensed landmarks: the same outputs without the rounds
    solo = make_policy("emp", L, rounds=0)
    masked_solo = getattr(solo, path)(s, e, adj, entity_mask=sensed)[0]
    for n in range(N):
        for i in range(M):
            kept = e[n, i, sensed[n, i]].view(1, 1, -1, 2)
            out = getattr(solo, path)(s[n : n + 1, i : i + 1], kept, torch.ones(1, 1, 1, dtype=torch.bool))[0]
            torch.testing.assert_close(out[0, 0], masked_solo[n, i], **TOL)
    # and with the rounds, landmarks nobody senses are the same as landmarks that do not exist
    nobody = torch.ones(N, M, L, dtype=torch.bool)
    nobody[..., L - 2 :] = False
    torch.testing.assert_close(run(s, e, adj, entity_mask=nobody)[0], run(s, e[:, :, : L - 2], adj)[0], **TOL)


def test_no_landmark_sensed_is_finite():
    s, e, adj = team(2, 4, 3, seed=8)
    policy = make_policy("emp", 3)
    logits, value = policy(s, e, adj, entity_mask=torch.zeros(2, 4, 3, dtype=torch.bool))
    assert torch.isfinite(logits).all() and torch.isfinite(value).all()


def test_padded_mode_treats_an_unsensed_slot_as_a_zero_slot():
    s, e, adj = team(2, 4, 5, seed=9)
    sensed = torch.rand(2, 4, 5) < 0.5
    policy = make_policy("padded", 5)
    zeroed = e * sensed.unsqueeze(-1)
    torch.testing.assert_close(policy(s, e, adj, entity_mask=sensed)[0], policy(s, zeroed, adj)[0], **TOL)


def test_bad_graph_inputs_are_refused():
    s, e, adj = team(2, 4, 3)
    nbr, mask = lists_from_adj(adj, 3)
    policy = make_policy("emp", 3)
    with pytest.raises(ValueError, match="either dense"):
        policy(s, e, adj, nbr=nbr, nbr_mask=mask)
    with pytest.raises(ValueError, match="either dense"):
        policy(s, e)
    with pytest.raises(ValueError, match="needs nbr_mask"):
        policy(s, e, nbr=nbr)
    with pytest.raises(ValueError, match="nbr and nbr_mask"):
        policy(s, e, nbr=nbr, nbr_mask=mask[..., :2])
    with pytest.raises(ValueError, match="adj must be"):
        policy(s, e, adj[:, :3])
    with pytest.raises(ValueError, match="entity_mask must be"):
        policy(s, e, adj, entity_mask=torch.ones(2, 4, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="concat"):
        make_policy("concat", 3)(s, e, adj, entity_mask=torch.ones(2, 4, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="neither 'adj' nor 'nbr'"):
        policy_inputs({"self": s, "entities": e})


def test_policy_inputs_maps_the_simulator_keys():
    s, e, adj = team(1, 3, 2)
    nbr, mask = lists_from_adj(adj, 2)
    dense = policy_inputs({"self": s, "entities": e, "adj": adj})
    assert set(dense) == {"self_obs", "entities", "adj"}
    lists = policy_inputs({"self": s, "entities": e, "nbr": nbr, "nbr_mask": mask, "entity_mask": mask})
    assert set(lists) == {"self_obs", "entities", "nbr", "nbr_mask", "entity_mask"}


@pytest.mark.parametrize(
    "rel",
    [
        "coverage-uc-m3",  # emp (a model zoo name)
        "formation-uc-m5",  # concat (padded networks: the random-weight tests above)
    ],
)
def test_committed_policies_give_the_same_outputs_on_full_lists(rel):
    from trainer import checkpoint

    # committed files are read as they are (some carry no digest): never rewritten
    path = os.path.join(ROOT, rel) if rel.startswith("results/") else rel
    payload = checkpoint.load(path, trust_unsigned=True)
    policy = checkpoint.policy_from_payload(payload).eval()
    L = policy.config.num_landmarks or 3
    M = 5 if policy.config.entity_mode == "concat" else 6
    s, e, adj = team(4, M, L, seed=10)
    nbr, mask = lists_from_adj(adj, M - 1)
    with torch.no_grad():
        dense = policy(s, e, adj)
        lists = policy(s, e, nbr=nbr, nbr_mask=mask)
    torch.testing.assert_close(lists[0], dense[0], atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(lists[1], dense[1], atol=1e-4, rtol=1e-5)


class ListsFromAdj:
    """A simulator whose observations carry the neighbour lists (everyone heard, in a
    shuffled order) instead of adj: what ``make(..., neighbours=K)`` gives with K >= M - 1."""

    def __init__(self, env, K):
        self.env, self.K = env, K

    def __getattr__(self, name):
        return getattr(self.env, name)

    def lists(self, obs):
        nbr, mask = lists_from_adj(obs["adj"].bool(), self.K, seed=int(obs["self"].abs().sum() * 1e3) % 1000)
        out = {k: v.clone() for k, v in obs.items() if k != "adj"}
        return {**out, "nbr": nbr, "nbr_mask": mask}

    def reset(self):
        return self.lists(self.env.reset())

    def step(self, actions):
        obs, reward, done, info = self.env.step(actions)
        if "terminal_obs" in info:
            info = {**info, "terminal_obs": self.lists(info["terminal_obs"])}
        return self.lists(obs), reward, done, info


@pytest.mark.parametrize("comm,M", [("uc", 3), ("rc", 5)])
def test_a_committed_policy_scores_on_full_lists_what_it_scores_dense(monkeypatch, comm, M):
    """The zoo's coverage-uc-m3, evaluated greedily: every episode's success, length and
    DIST the same on lists as on the dense graph."""
    import taichi_swarm
    from trainer import checkpoint, evaluate

    payload = checkpoint.load("coverage-uc-m3")
    policy = checkpoint.policy_from_payload(payload).eval()
    common = dict(sim=taichi_swarm.Sim("coverage", M, comm, 0.8), episodes=12, seed=4321)
    dense = evaluate.evaluate(policy, **common)
    make = taichi_swarm.make
    monkeypatch.setattr(taichi_swarm, "make", lambda *a, **k: ListsFromAdj(make(*a, **k), M + 1))
    lists = evaluate.evaluate(policy, **common)
    assert lists["per_episode"] == dense["per_episode"]
    assert 0 < dense["success_rate"] or comm == "rc"  # (a policy that does something)
    assert lists["success_rate"] == dense["success_rate"] and lists["dist"] == dense["dist"]


@pytest.mark.parametrize("comm", ["uc", "rc"])
def test_the_zoo_policy_scores_on_the_simulators_full_lists_what_it_scores_dense(comm):
    """make(..., neighbours=M - 1): the simulator's own lists, everyone listed."""
    from taichi_swarm import Sim
    from trainer import checkpoint, evaluate

    policy = checkpoint.policy_from_payload(checkpoint.load("coverage-rc-m5")).eval()
    dense = evaluate.evaluate(policy, Sim("coverage", 5, comm, 0.8), episodes=16, seed=777)
    lists = evaluate.evaluate(policy, Sim("coverage", 5, comm, 0.8, neighbours=4), episodes=16, seed=777)
    assert lists["neighbours"] == 4 and "neighbours" not in dense
    assert lists["per_episode"] == dense["per_episode"]
    assert lists["success_rate"] > 0.5
    if "covered" in dense:  # the fraction of landmarks covered, where the simulator reports it
        assert lists["covered"] == dense["covered"] and dense["covered"] >= dense["success_rate"]


def sparse_team(N=3, M=14, L=4, seed=11, radius=0.45):
    """An RC team whose lists need fewer slots than teammates (1 + K < M): the gather path."""
    s, e, adj = team(N, M, L, seed=seed, radius=radius)
    K = int((adj.sum(-1) - 1).max())
    assert 1 + K < M
    return s, e, adj, K


@pytest.mark.parametrize("mode", ["emp", "padded"])
@pytest.mark.parametrize("path", ["forward", "forward_reference"])
def test_gathered_rounds_equal_dense_outputs_and_gradients(mode, path):
    s, e, adj, K = sparse_team()
    nbr, mask = lists_from_adj(adj, K)
    policy = make_policy(mode, 4)
    dense = outputs_and_grads(policy, path, s, e, adj)
    lists = outputs_and_grads(policy, path, s, e, nbr=nbr, nbr_mask=mask)
    torch.testing.assert_close(lists[0], dense[0], **TOL)
    torch.testing.assert_close(lists[1], dense[1], **TOL)
    for gl, gd in zip(lists[2], dense[2], strict=True):
        torch.testing.assert_close(gl, gd, atol=1e-4, rtol=1e-4)


def test_gathered_rounds_ignore_list_order():
    s, e, adj, K = sparse_team(seed=12)
    a, b = lists_from_adj(adj, K + 2, seed=0), lists_from_adj(adj, K + 2, seed=1)
    perm = torch.randperm(K + 2)
    policy = make_policy("emp", 4)
    ref = policy(s, e, nbr=a[0], nbr_mask=a[1])[0]
    torch.testing.assert_close(policy(s, e, nbr=b[0], nbr_mask=b[1])[0], ref, **TOL)
    torch.testing.assert_close(policy(s, e, nbr=a[0][..., perm], nbr_mask=a[1][..., perm])[0], ref, **TOL)


def test_a_team_that_fits_in_its_lists_takes_the_dense_rounds_with_the_same_result():
    """M <= 1 + K: forward scatters the lists into adj (cheaper); return_attention keeps
    the gather; both the same function."""
    s, e, adj = team(3, 6, 4, seed=13, radius=0.9)
    nbr, mask = lists_from_adj(adj, 8)
    policy = make_policy("emp", 4)
    switched = policy(s, e, nbr=nbr, nbr_mask=mask)
    gathered = policy(s, e, nbr=nbr, nbr_mask=mask, return_attention=True)
    torch.testing.assert_close(switched[0], gathered[0], **TOL)
    torch.testing.assert_close(switched[1], gathered[1], **TOL)
    slots, listed = neighbour_slots(nbr, mask)
    assert torch.equal(lists_to_adj(slots, listed), adj)


def test_self_position_none_feeds_the_encoder_no_absolute_position():
    """self_position "none": moving the whole team (positions change, every offset stays)
    changes nothing, on both forward paths and both layouts; "absolute" does see it."""
    N, M, L, K = 2, 6, 6, 5
    self_obs, entities, adj = team(N, M, L, seed=3)
    shifted = self_obs.clone()
    shifted[..., 2:] += torch.tensor([3.0, -2.0])
    nbr, mask = lists_from_adj(adj, K)
    for mode in ("emp", "padded"):
        torch.manual_seed(0)
        policy = SwarmPolicy(ModelConfig(hidden=16, rounds=2, entity_mode=mode, self_position="none"))
        for graph in (dict(adj=adj), dict(nbr=nbr, nbr_mask=mask)):
            for fn in (policy, policy.forward_reference):
                a, va = fn(self_obs, entities, **graph)
                b, vb = fn(shifted, entities, **graph)
                torch.testing.assert_close(a, b, **TOL)
                torch.testing.assert_close(va, vb, **TOL)
        absolute = SwarmPolicy(ModelConfig(hidden=16, rounds=2, entity_mode=mode))
        absolute.load_state_dict(policy.state_dict())  # the same weights, the same shapes
        assert not torch.allclose(absolute(self_obs, entities, adj)[0], absolute(shifted, entities, adj)[0])
    with pytest.raises(ValueError, match="self_position must be one of"):
        ModelConfig(self_position="relative")
