"""landmark_occupancy: each landmark input is (dx, dy, occupancy), the third through its own
weights. The fast and reference paths, dense and lists, are one function with gradients;
zero occupancy weights are the network without them; a wrong feature count is refused."""

import pytest
import torch
from test_model_edges import assert_same
from test_model_lists import TOL, lists_from_adj, outputs_and_grads, team

from trainer.model import ModelConfig, SwarmPolicy


def occupied(e, seed=0):
    """The entities with an occupancy feature appended (values in [0, 1])."""
    g = torch.Generator().manual_seed(seed)
    return torch.cat([e, torch.rand(*e.shape[:-1], 1, generator=g)], dim=-1)


def occupancy_policy(randomise=True, **config):
    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=32, landmark_occupancy=True, **config))
    if randomise:  # it starts at zero; a test of what it does needs it non-zero
        with torch.no_grad():
            policy.entity_occupancy.weight.normal_(0.0, 0.5)
    return policy


def assert_one_function(policy, weight: str) -> None:
    """The fast and reference paths of an occupancy ``policy``, dense and on lists, give the
    same outputs and gradients, and the parameter ``weight`` gets a gradient."""
    s, e, adj = team(3, 6, 4, seed=1, radius=0.8)
    e = occupied(e)
    nbr, mask = lists_from_adj(adj, 7)
    ref = outputs_and_grads(policy, "forward_reference", s, e, adj)
    assert_same(outputs_and_grads(policy, "forward", s, e, adj), ref)
    assert_same(outputs_and_grads(policy, "forward", s, e, nbr=nbr, nbr_mask=mask), ref)
    grads = dict(zip((n for n, _ in policy.named_parameters()), ref[2], strict=True))
    assert grads[weight].abs().sum() > 0


@pytest.mark.parametrize("edge_position", ["none", "relative"])
def test_fast_reference_dense_and_lists_are_one_function(edge_position):
    assert_one_function(occupancy_policy(edge_position=edge_position), "entity_occupancy.weight")


def test_zero_occupancy_weights_are_the_network_without_them():
    s, e, adj = team(2, 5, 3, seed=3, radius=0.9)
    plain = SwarmPolicy(ModelConfig(hidden=32))
    occ = occupancy_policy(randomise=False)
    missing, unexpected = occ.load_state_dict(plain.state_dict(), strict=False)
    assert missing == ["entity_occupancy.weight"] and not unexpected
    for path in ("forward", "forward_reference"):
        torch.testing.assert_close(
            getattr(occ, path)(s, occupied(e), adj)[0], getattr(plain, path)(s, e, adj)[0], **TOL
        )
    randomised = occupancy_policy()
    randomised.load_state_dict({**plain.state_dict(), **{k: randomised.state_dict()[k] for k in missing}})
    assert not torch.allclose(randomised(s, occupied(e), adj)[0], plain(s, e, adj)[0], **TOL)


def test_the_feature_count_is_checked():
    s, e, adj = team(2, 4, 3, seed=2)
    with pytest.raises(ValueError, match=r"3 features per landmark \(dx, dy, occupancy"):
        occupancy_policy()(s, e, adj)
    with pytest.raises(ValueError, match=r"2 features per landmark \(dx, dy\), got 3"):
        SwarmPolicy(ModelConfig(hidden=32))(s, occupied(e), adj)
    with pytest.raises(ValueError, match="landmark_occupancy needs entity_mode 'emp'"):
        ModelConfig(entity_mode="padded", landmark_occupancy=True)
