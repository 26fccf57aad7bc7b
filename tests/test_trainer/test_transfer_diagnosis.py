"""tools/transfer_diagnosis.py: how a coverage policy fails at a team size it was not
trained at, pinned on two committed M = 3 policies (docs/FINDINGS.md, "Why some M = 3
policies carry and others do not"): the one that does not carry piles agents up."""

from __future__ import annotations

import importlib.util
import os

import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
RECIPE = os.path.join(ROOT, "results", "reproduce-recipe", "t1-coverage-uc-m3")


def _tool():
    path = os.path.join(ROOT, "tools", "transfer_diagnosis.py")
    spec = importlib.util.spec_from_file_location("transfer_diagnosis", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_policy_that_does_not_carry_piles_agents_up():
    from taichi_swarm import runtime
    from trainer.checkpoint import load_policy

    tool = _tool()
    runtime.init("cpu")
    carries, _ = load_policy(os.path.join(RECIPE, "s0", "polish", "policy.pt"))  # 94.2% at M = 5
    stuck, _ = load_policy(os.path.join(RECIPE, "s1", "polish", "policy.pt"))  # 17.2% at M = 5
    good = tool.diagnose(carries.eval(), 5, 60, 777, "uc")
    bad = tool.diagnose(stuck.eval(), 5, 60, 777, "uc")
    assert bad["failures"] > 2 * good["failures"] > 0
    assert bad["success_rate"] == 1 - bad["failures"] / 60
    for r in (good, bad):
        assert 0 <= r["covered"] < 5 and 1 <= r["claimed"] <= 5 and 0 <= r["stacked"] <= 5
    assert bad["claimed"] < good["claimed"] - 0.5 and bad["stacked"] > good["stacked"] + 0.4


def test_it_names_what_is_wrong(capsys):
    tool = _tool()
    from trainer.zoo import get

    formation = get("formation-uc-m3").path
    coverage = os.path.join(RECIPE, "s0", "polish", "policy.pt")
    assert tool.main([coverage, formation, "--sizes", "3", "--episodes", "2"]) == 2
    out = capsys.readouterr()
    assert "a formation policy" in out.err and "policy.pt" not in out.out  # checked before any evaluation
    with pytest.raises(SystemExit):
        tool.main([formation, "--episodes", "0"])
