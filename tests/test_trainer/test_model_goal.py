"""goal_pass: a goal network of the same shape runs first, and the landmark attention's query
is raised by W_g h, h its final embedding. The fast and reference paths, dense and lists, are one
function with gradients; a zero W_g is the network without it; ``landmark_scores`` are the
scores the second pass's attention takes; export refuses it in one line."""

import pytest
import torch
from test_model_lists import TOL, team
from test_model_occupancy import assert_one_function, occupied

from trainer.model import MASK_FILL, ModelConfig, SwarmPolicy

CONFIG = dict(hidden=32, landmark_occupancy=True, edge_position="relative", self_position="none")


def goal_policy(randomise=True):
    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(goal_pass=True, **CONFIG))
    if randomise:  # it starts at zero; a test of what it does needs it non-zero
        with torch.no_grad():
            policy.goal_query.weight.normal_(0.0, 0.5)
    return policy


def test_fast_reference_dense_and_lists_are_one_function():
    policy = goal_policy()
    assert_one_function(policy, "goal_query.weight")
    assert_one_function(policy, "goal_net.agent_encoder.weight")  # the goal network learns through W_g


def test_a_zero_goal_query_is_the_network_without_it():
    s, e, adj = team(2, 5, 3, seed=3, radius=0.9)
    e = occupied(e)
    torch.manual_seed(1)
    plain = SwarmPolicy(ModelConfig(**CONFIG))
    goal = goal_policy(randomise=False)
    missing, unexpected = goal.load_state_dict(plain.state_dict(), strict=False)
    net = {f"goal_net.{k}" for k in plain.state_dict() if not k.startswith(("policy_head", "value_head"))}
    assert set(missing) == {"goal_query.weight"} | net and not unexpected
    for path in ("forward", "forward_reference"):
        torch.testing.assert_close(getattr(goal, path)(s, e, adj)[0], getattr(plain, path)(s, e, adj)[0], **TOL)
    torch.testing.assert_close(goal.landmark_scores(s, e, adj), plain.landmark_scores(s, e, adj), **TOL)
    with torch.no_grad():
        goal.goal_query.weight.normal_(0.0, 0.5)
    assert not torch.allclose(goal.landmark_scores(s, e, adj), plain.landmark_scores(s, e, adj), **TOL)


def test_landmark_scores_are_the_second_pass_attention_scores():
    """q . k / sqrt(H) of the agent's own encoding and each landmark's, plus (W_g h) . e with
    h the goal network's final embedding, written out from the reference pieces; an unsensed
    slot scores MASK_FILL."""
    s, e, adj = team(2, 5, 4, seed=4, radius=0.9)
    e = occupied(e)
    policy = goal_policy()
    sensed = torch.ones(2, 5, 4, dtype=torch.bool)
    sensed[0, 0, 1] = False
    masks, slots = policy._graph(s, adj, None, None)
    g = policy.goal_net  # its own weights: the goal network's final h
    h, _ = g._rounds_reference(g.encode(s, e, sensed), s, masks, slots)
    own = torch.relu(policy.agent_encoder(policy.own_input(s)))
    emb = policy.embed_entities(e)
    att = policy.entity_attention
    want = (att.w_q(own).unsqueeze(-2) * att.w_k(emb)).sum(-1) / 32**0.5
    want = want + (policy.goal_query(h).unsqueeze(-2) * emb).sum(-1)
    got = policy.landmark_scores(s, e, adj, entity_mask=sensed)
    assert got[0, 0, 1] == MASK_FILL
    torch.testing.assert_close(got[sensed], want[sensed], **TOL)


def test_goal_pass_needs_emp_and_export_refuses_it(tmp_path):
    from deploy.export import export
    from trainer.checkpoint import CheckpointError, save_policy_only

    with pytest.raises(ValueError, match="goal_pass needs entity_mode 'emp'"):
        ModelConfig(entity_mode="padded", goal_pass=True)
    policy = goal_policy()
    path = str(tmp_path / "policy.pt")
    payload = dict(
        model_config=policy.config.to_dict(),
        model=policy.state_dict(),
        task={"task": "coverage", "agents": 3, "comm": "rc", "comm_radius": 1.0},
    )
    save_policy_only(payload, path)
    with pytest.raises(CheckpointError, match="goal network .* export does not write yet"):
        export(path, str(tmp_path / "out"))
    assert not (tmp_path / "out").exists()  # a refused export leaves nothing behind


def test_a_run_fine_tunes_into_a_goal_pass_and_not_back(tmp_path):
    """--init-from a policy without a goal pass into --model.goal-pass starts from the same
    function (W_g zero) and trains W_g; the reverse would drop weights and is refused."""
    import dataclasses
    import os

    from test_fine_actions_training import config

    from trainer import checkpoint
    from trainer.train import build_state, train

    base = dataclasses.replace(config(tmp_path, "base"), task="coverage")  # formation's one landmark scores alone
    train(base)
    start = os.path.join(base.run_dir, "policy.pt")
    grown = config(tmp_path, "goal", init_from=start)
    grown = dataclasses.replace(grown, task="coverage", model=dataclasses.replace(grown.model, goal_pass=True))
    state = build_state(grown, None, "cpu")
    plain, _ = checkpoint.load_policy(start)
    assert state.policy.goal_query.weight.abs().sum() == 0
    assert all(torch.equal(v, state.policy.state_dict()[k]) for k, v in plain.state_dict().items())
    train(grown)
    policy, _ = checkpoint.load_policy(os.path.join(grown.run_dir, "policy.pt"))
    assert policy.config.goal_pass and policy.goal_query.weight.abs().sum() > 0
    back = dataclasses.replace(
        config(tmp_path, "back", init_from=os.path.join(grown.run_dir, "policy.pt")), task="coverage"
    )
    with pytest.raises(checkpoint.CheckpointError, match="this run wants"):
        build_state(back, None, "cpu")
