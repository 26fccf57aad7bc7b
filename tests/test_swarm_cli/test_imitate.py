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
        seen.append((env.action_space, teacher, window_radius, int(a.max())))
        return a

    monkeypatch.setattr(imitate, "expert_actions", spy)
    out = tmp_path / "line.pt"
    imitate.main(["--init", LINE, "--teacher", "window", "--window-radius", "2", "--sizes", "10", "--iterations", "1",
                  "--out", str(out)])  # fmt: skip
    assert {s[:3] for s in seen} == {("fine", "window", 2.0)}
    assert max(s[3] for s in seen) <= 8  # the fine action space's nine
    _, payload = checkpoint.load_policy(str(out))
    assert payload["task"]["task"] == "line" and payload["swarm"]["action_space"] == "fine"


def test_the_greedy_teacher_drives_coverage_only_and_the_radius_is_checked(tmp_path, capsys):
    with pytest.raises(SystemExit, match="greedy teacher drives coverage, and .* is a line policy"):
        imitate.main(["--init", LINE, "--iterations", "1", "--out", str(tmp_path / "x.pt")])
    with pytest.raises(SystemExit):
        imitate.main(["--init", LINE, "--teacher", "window", "--window-radius", "-1", "--out", str(tmp_path / "x.pt")])
    assert "--window-radius must be > 0, got -1" in capsys.readouterr().err
    assert not os.listdir(tmp_path)  # a refused command leaves nothing behind
