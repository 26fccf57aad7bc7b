"""tools/pinned_attention.py: the policy run with its landmark attention pinned to one listed
landmark. A pinned mask holds exactly the goal's slot where the goal is listed; the committed
line policy, pinned to the window plan's landmark, completes a one-row line it otherwise
fails; bad inputs are refused in one line and leave nothing behind."""

import importlib.util
import json
import os

import numpy as np
import pytest
import torch

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
spec = importlib.util.spec_from_file_location("pinned_attention", os.path.join(ROOT, "tools", "pinned_attention.py"))
pinned = importlib.util.module_from_spec(spec)
spec.loader.exec_module(pinned)

LINE = os.path.join(
    ROOT, "results", "reproduce-swarm", "s-line-rc-rows-m50-k12-claim-zero", "s0", "stage-m50", "policy.pt"
)


def test_the_mask_is_cut_to_the_goal_slot_where_it_is_listed():
    ent = torch.tensor([[[[0.5, 0.0, 1.0], [0.0, 0.2, 1.0], [1.0, 1.0, 0.0]], [[0.1, 0.1, 1.0]] * 3]])
    sensed = torch.tensor([[[True, True, False], [False, True, True]]])
    state = {"pos": np.zeros((1, 2, 2))}
    goals = np.array([[[0.0, 0.2], [5.0, 5.0]]])  # agent 0's goal is its slot 1; agent 1's is not listed
    mask, listed = pinned.pinned_mask({"entities": ent, "entity_mask": sensed}, goals, state)
    assert listed.tolist() == [[True, False]]
    assert mask.tolist() == [[[False, True, False], [False, True, True]]]  # agent 1 keeps its own
    mask, listed = pinned.pinned_mask({"entities": ent, "entity_mask": sensed}, None, state)  # "first"
    assert listed.tolist() == [[True, False]] and mask[0, 0].tolist() == [True, False, False]


def test_pinned_to_the_window_plan_the_line_policy_fills_its_rows(tmp_path, capsys):
    out = tmp_path / "rows.json"
    pinned.main([LINE, "--agents", "8", "--pins", "none", "window", "--episodes", "20", "--json", str(out)])
    rows = {r["pin"]: r for r in json.loads(out.read_text())}
    assert rows["window"]["listed"] > 0.95 and rows["none"]["listed"] is None
    assert rows["window"]["success_rate"] >= rows["none"]["success_rate"]
    assert rows["window"]["success_rate"] >= 0.9
    assert "window" in capsys.readouterr().out


def test_bad_inputs_are_refused_in_one_line(tmp_path, capsys):
    for argv, message in [
        (["--window-radius", "0"], "--window-radius must be > 0, got 0"),
        (["--episodes", "0"], "--episodes must be >= 1 and every size >= 2"),
        (["--pins", "best"], "invalid choice: 'best'"),
    ]:
        with pytest.raises(SystemExit):
            pinned.main([LINE, "--json", str(tmp_path / "x.json"), *argv])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit, match="has no landmark attention over lists to pin"):
        pinned.main(["coverage-rc-m10", "--json", str(tmp_path / "x.json")])
    assert not os.listdir(tmp_path)
