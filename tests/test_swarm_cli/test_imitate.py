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
