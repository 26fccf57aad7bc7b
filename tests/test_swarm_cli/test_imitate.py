"""tools/imitate.py: DAgger from the greedy coverage controller writes a policy that the
trainer's loader reads, with the network fitted towards the controller's actions."""

import importlib.util
import json
import os

import pytest
import torch

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
spec = importlib.util.spec_from_file_location("imitate", os.path.join(ROOT, "tools", "imitate.py"))
imitate = importlib.util.module_from_spec(spec)
spec.loader.exec_module(imitate)


def test_imitation_writes_a_loadable_policy_that_moved_towards_the_controller(tmp_path, monkeypatch):
    from trainer import checkpoint
    from trainer.zoo import get

    monkeypatch.setattr(imitate, "AGENTS_PER_ROLLOUT", 40)  # 8 environments of 5
    out = tmp_path / "p" / "policy.pt"
    imitate.main(
        ["--init", "coverage-rc-m10-swarm", "--sizes", "5", "--iterations", "3", "--lr", "1e-3", "--out", str(out)]
    )
    policy, payload = checkpoint.load_policy(str(out))
    start, _ = checkpoint.load_policy(get("coverage-rc-m10-swarm").path)
    assert payload["swarm"] == checkpoint.load(get("coverage-rc-m10-swarm").path)["swarm"]  # runs on the same lists
    moved = [k for k, v in policy.state_dict().items() if not torch.equal(v, start.state_dict()[k])]
    assert moved
    log = [json.loads(line) for line in open(str(out) + ".log.jsonl")]
    assert [r["iteration"] for r in log] == [0, 1, 2] and log[0]["expert_share"] == 1.0
    assert log[-1]["loss"] < log[0]["loss"]  # the fit to the labels improves


def test_a_policy_without_lists_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="not trained on lists"):
        imitate.main(["--init", "coverage-rc-m10", "--iterations", "1", "--out", str(tmp_path / "x.pt")])


LINE = os.path.join(ROOT, "results", "reproduce-swarm", "s-line-rc-rows-m50-k12", "s0", "stage-m50", "policy.pt")


def test_the_window_teacher_labels_a_line_policy_in_its_own_fine_actions(tmp_path, monkeypatch):
    from trainer import checkpoint

    monkeypatch.setattr(imitate, "AGENTS_PER_ROLLOUT", 40)
    monkeypatch.setattr(imitate, "STEPS", 10)
    seen = []
    real = imitate.expert_actions

    def spy(env, obs, teacher, window_radius):
        a = real(env, obs, teacher, window_radius)
        seen.append((env.action_space, teacher, window_radius, a[0].shape[-1]))
        return a

    monkeypatch.setattr(imitate, "expert_actions", spy)
    out = tmp_path / "line.pt"
    imitate.main(["--init", LINE, "--teacher", "window", "--window-radius", "2", "--sizes", "10", "--iterations", "1",
                  "--out", str(out)])  # fmt: skip
    assert {s[:3] for s in seen} == {("fine", "window", 2.0)}
    assert {s[3] for s in seen} == {9}  # a cost for each of the fine action space's nine
    _, payload = checkpoint.load_policy(str(out))
    assert payload["task"]["task"] == "line" and payload["swarm"]["action_space"] == "fine"


def test_the_greedy_teacher_drives_coverage_only_and_the_radius_is_checked(tmp_path, capsys):
    with pytest.raises(SystemExit, match="greedy teacher drives coverage, and .* is a line policy"):
        imitate.main(["--init", LINE, "--iterations", "1", "--out", str(tmp_path / "x.pt")])
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--teacher", "window", "--window-radius", "-1", "--out", str(tmp_path / "x.pt")])
    assert "--window-radius must be > 0, got -1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--teacher", "window", "--soft", "-0.5", "--out", str(tmp_path / "x.pt")])
    assert "--soft and --direction-beyond must be >= 0, got -0.5 and 0" in capsys.readouterr().err
    assert not os.listdir(tmp_path)  # a refused command leaves nothing behind


def test_soft_labels_spread_over_near_equal_actions_and_stay_sharp_far_from_the_goal():
    import numpy as np

    rng = np.random.default_rng(0)
    pos = rng.uniform(-1, 1, (500, 2)).astype(np.float32)
    vel = np.zeros_like(pos)
    near = imitate.steer_costs(pos, vel, pos + rng.uniform(-0.03, 0.03, pos.shape).astype(np.float32), "fine")
    far = imitate.steer_costs(pos, vel, pos + rng.uniform(1.0, 2.0, pos.shape).astype(np.float32), "fine")
    near, far = torch.from_numpy(near), torch.from_numpy(far)
    hard = imitate.targets(near, 0.0)
    assert torch.equal(hard.argmax(-1), near.argmin(-1)) and torch.all(hard.sum(-1) == 1) and hard.max() == 1
    soft_near, soft_far = imitate.targets(near, 0.01), imitate.targets(far, 0.01)
    assert torch.equal(soft_far.argmax(-1), far.argmin(-1))  # the teacher's action stays the most likely
    assert soft_far.max(-1).values.mean() > 0.9 > soft_near.max(-1).values.mean()


def test_goal_cloning_fits_the_landmark_attention_and_keeps_the_actor(tmp_path, monkeypatch):
    """--goal trains the landmark attention's query and key weights alone, towards the listed
    landmark the teacher heads for; --goal-pass adds a goal network (a copy of the policy's
    layers, W_g zero) and trains it and W_g alone."""
    from trainer import checkpoint

    monkeypatch.setattr(imitate, "AGENTS_PER_ROLLOUT", 40)
    monkeypatch.setattr(imitate, "STEPS", 10)
    start, _ = checkpoint.load_policy(LINE)
    out = tmp_path / "goal.pt"
    imitate.main(["--init", LINE, "--teacher", "first", "--goal", "--sizes", "10", "--iterations", "2", "--lr", "1e-3",
                  "--out", str(out)])  # fmt: skip
    policy, _ = checkpoint.load_policy(str(out))
    moved = {k for k, v in policy.state_dict().items() if not torch.equal(v, start.state_dict()[k])}
    assert moved == {"entity_attention.w_q.weight", "entity_attention.w_k.weight"}
    log = [json.loads(line) for line in open(str(out) + ".log.jsonl")]
    assert all(0 < r["accuracy"] <= 1 for r in log)

    out = tmp_path / "pass.pt"
    imitate.main(["--init", LINE, "--teacher", "first", "--goal", "--goal-pass", "--sizes", "10", "--iterations", "1",
                  "--lr", "1e-3", "--out", str(out)])  # fmt: skip
    policy, payload = checkpoint.load_policy(str(out))
    assert policy.config.goal_pass and payload["model_config"]["goal_pass"]
    before = start.state_dict()
    moved = {k for k, v in policy.state_dict().items() if k not in before or not torch.equal(v, before[k])}
    assert "goal_query.weight" in moved and policy.goal_query.weight.abs().sum() > 0
    assert all(k.startswith(("goal_query.", "goal_net.")) for k in moved)  # the policy's own layers are kept
    assert any(k.startswith("goal_net.") for k in moved)

    out = tmp_path / "frozen.pt"
    imitate.main(["--init", LINE, "--teacher", "first", "--goal", "--goal-pass", "--freeze-goal-net", "--sizes", "10",
                  "--iterations", "1", "--lr", "1e-3", "--out", str(out)])  # fmt: skip
    policy, _ = checkpoint.load_policy(str(out))
    moved = {k for k, v in policy.state_dict().items() if k not in before or not torch.equal(v, before[k])}
    assert {k for k in moved if not k.startswith("goal_net.")} == {"goal_query.weight"}
    assert all(torch.equal(v, before[k]) for k, v in policy.goal_net.state_dict().items())  # still the copy


def test_goal_slots_find_the_listed_goal_and_skip_an_unlisted_one():
    ent = torch.tensor([[[0.5, 0.0, 1.0], [0.0, 0.2, 1.0], [1.0, 1.0, 0.0]]])  # one agent, three listed
    x = {"entities": ent[None], "entity_mask": torch.tensor([[[True, True, False]]])}
    slot, listed = imitate.goal_slots(x, torch.tensor([[[0.0, 0.2]]]))
    assert slot.item() == 1 and listed.item()
    _, listed = imitate.goal_slots(x, torch.tensor([[[1.0, 1.0]]]))  # the third is not sensed
    assert not listed.item()


def test_goal_pass_needs_goal(tmp_path, capsys):
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--teacher", "window", "--goal-pass", "--out", str(tmp_path / "x.pt")])
    assert "--goal-pass fits the landmark attention: add --goal" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--goal", "--freeze-goal-net", "--out", str(tmp_path / "x.pt")])
    assert "--freeze-goal-net keeps a goal network: add --goal-pass" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--teacher", "window", "--goal", "--soft", "1", "--out", str(tmp_path / "x.pt")])
    assert "--goal fits the teacher's landmark: it takes neither --soft" in capsys.readouterr().err
    assert not os.listdir(tmp_path)


def test_aggregate_fits_over_the_last_rollouts_of_each_size(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(imitate, "AGENTS_PER_ROLLOUT", 40)
    monkeypatch.setattr(imitate, "STEPS", 3)
    seen = []
    real = imitate.fit

    def spy(policy, optimizer, inputs, labels, rng, **kw):
        seen.append((inputs[0]["self_obs"].shape[1], len(inputs), len(labels)))
        return real(policy, optimizer, inputs, labels, rng, **kw)

    monkeypatch.setattr(imitate, "fit", spy)
    imitate.main(["--init", LINE, "--teacher", "first", "--goal", "--sizes", "5", "8", "--iterations", "6",
                  "--aggregate", "2", "--passes", "1", "--out", str(tmp_path / "agg.pt")])  # fmt: skip
    assert seen == [(5, 3, 3), (8, 3, 3), (5, 6, 6), (8, 6, 6), (5, 6, 6), (8, 6, 6)]  # never mixing sizes
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--aggregate", "0", "--out", str(tmp_path / "x.pt")])
    assert "--iterations and --aggregate must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()


def test_with_goal_pass_starts_the_goal_network_as_a_copy_and_is_the_same_function():
    from trainer import checkpoint

    start, payload = checkpoint.load_policy(LINE)
    policy, grown = imitate.with_goal_pass(start, payload)
    assert grown["model_config"]["goal_pass"] and not payload["model_config"].get("goal_pass")
    own = start.state_dict()
    net = policy.goal_net.state_dict()
    assert net and all(torch.equal(v, own[k]) for k, v in net.items()) and "policy_head.0.weight" not in net
    assert all(torch.equal(v, policy.state_dict()[k]) for k, v in own.items())
    assert imitate.with_goal_pass(policy, grown)[0] is policy  # one already there is kept
