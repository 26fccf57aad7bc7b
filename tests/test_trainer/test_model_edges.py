"""edge_position "relative": a receiver adds the sender's offset p_j - p_i to its key and
value. The fast and the reference paths, dense and lists (dense and gathered rounds), are
the same function, gradients included; zero edge weights are the network without them; with
self_position "none" the policy does not depend on where the team stands."""

import pytest
import torch
from test_model_lists import TOL, lists_from_adj, outputs_and_grads, sparse_team, team

from trainer.model import ModelConfig, SwarmPolicy


def edge_policy(mode="emp", L=4, seed=0, self_position="absolute", randomise=True):
    torch.manual_seed(seed)
    policy = SwarmPolicy(
        ModelConfig(hidden=32, entity_mode=mode, num_landmarks=L, edge_position="relative", self_position=self_position)
    )
    if randomise:  # they start at zero; a test of what they do needs them non-zero
        with torch.no_grad():
            policy.edge_key.weight.normal_(0.0, 0.5)
            policy.edge_value.weight.normal_(0.0, 0.5)
    return policy


def assert_same(a, b):
    torch.testing.assert_close(a[0], b[0], **TOL)
    torch.testing.assert_close(a[1], b[1], **TOL)
    for ga, gb in zip(a[2], b[2], strict=True):
        torch.testing.assert_close(ga, gb, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("mode", ["emp", "padded"])
@pytest.mark.parametrize("radius", [None, 0.8])
def test_fast_reference_dense_and_lists_are_one_function(mode, radius):
    s, e, adj = team(3, 6, 4, seed=1, radius=radius)
    nbr, mask = lists_from_adj(adj, 7)
    policy = edge_policy(mode)
    ref = outputs_and_grads(policy, "forward_reference", s, e, adj)
    assert_same(outputs_and_grads(policy, "forward", s, e, adj), ref)
    assert_same(outputs_and_grads(policy, "forward", s, e, nbr=nbr, nbr_mask=mask), ref)
    assert_same(outputs_and_grads(policy, "forward_reference", s, e, nbr=nbr, nbr_mask=mask), ref)
    # the edge weights get gradients, and change the outputs
    grads = dict(zip((n for n, _ in policy.named_parameters()), ref[2], strict=True))
    assert grads["edge_key.weight"].abs().sum() > 0 and grads["edge_value.weight"].abs().sum() > 0


def test_gathered_rounds_equal_dense_with_edges():
    s, e, adj, K = sparse_team()
    nbr, mask = lists_from_adj(adj, K)
    policy = edge_policy()
    dense = outputs_and_grads(policy, "forward_reference", s, e, adj)
    assert_same(outputs_and_grads(policy, "forward", s, e, nbr=nbr, nbr_mask=mask), dense)
    fast = policy(s, e, nbr=nbr, nbr_mask=mask, return_attention=True)
    ref = policy.forward_reference(s, e, nbr=nbr, nbr_mask=mask, return_attention=True)
    for wa, wb in zip(fast[2], ref[2], strict=True):
        torch.testing.assert_close(wa, wb, **TOL)


def test_zero_edge_weights_are_the_network_without_them():
    s, e, adj = team(2, 5, 3, seed=3, radius=0.9)
    plain = SwarmPolicy(ModelConfig(hidden=32))
    edges = edge_policy(L=3, randomise=False)
    missing, unexpected = edges.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == ["edge_key.weight", "edge_value.weight"] and not unexpected
    for path in ("forward", "forward_reference"):
        torch.testing.assert_close(getattr(edges, path)(s, e, adj)[0], getattr(plain, path)(s, e, adj)[0], **TOL)
    randomised = edge_policy(L=3)
    randomised.load_state_dict({**plain.state_dict(), **{k: randomised.state_dict()[k] for k in missing}})
    assert not torch.allclose(randomised(s, e, adj)[0], plain(s, e, adj)[0], **TOL)


def test_relative_inputs_make_the_policy_translation_invariant():
    """self_position "none" and relative edges: shifting the whole team (and its landmark
    offsets, which are relative already) changes nothing; with absolute edges off, the
    teammates' offsets are what the policy knows of where they are."""
    s, e, adj = team(2, 6, 4, seed=4)
    policy = edge_policy(self_position="none")
    shifted = s.clone()
    shifted[..., 2:4] += torch.tensor([7.5, -3.25])
    torch.testing.assert_close(policy(shifted, e, adj)[0], policy(s, e, adj)[0], atol=1e-4, rtol=1e-4)
    moved = s.clone()
    moved[:, 0, 2:4] += 0.3  # one agent elsewhere: its teammates see it move
    assert not torch.allclose(policy(moved, e, adj)[0][:, 1:], policy(s, e, adj)[0][:, 1:], **TOL)


def test_bad_edge_position_is_refused():
    with pytest.raises(ValueError, match="edge_position must be one of"):
        ModelConfig(edge_position="absolute")
    policy = edge_policy()
    h = torch.zeros(1, 32)
    with pytest.raises(ValueError, match="needs the offsets"):
        policy.update(h, torch.zeros(2, 32), torch.zeros(2, 32), None)
