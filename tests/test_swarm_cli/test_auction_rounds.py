"""tools/auction_rounds.py: the rounds the agents' own auction takes to settle from an episode's
start (docs/SWARM.md's radio cost), counted right, and the tool end to end."""

import importlib.util
import os

import numpy as np

import taichi_swarm

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
PATH = os.path.join(ROOT, "tools", "auction_rounds.py")
spec = importlib.util.spec_from_file_location("auction_rounds", PATH)
tool = importlib.util.module_from_spec(spec)
spec.loader.exec_module(tool)


def _env(rounds, B=3, M=30):
    return taichi_swarm.make(
        "coverage", B, M, comm="rc", neighbours=8, landmark_neighbours=8, sense_radius=3.0, scale="density",
        landmark_occupancy=True, landmark_order="auction", assignment="free", auction_rounds=rounds, seed=5,
        array="numpy",
    )  # fmt: skip


def test_the_rounds_counted_are_those_after_which_no_bid_is_placed():
    rounds, held = tool.settle(_env(1), max_rounds=2000, budgets=(1, 4))
    assert (rounds >= 2).all() and (rounds <= 2000).all() and set(held) == {1, 4}
    assert 0 < held[1] <= held[4] <= 1
    # the same start with a budget of that many rounds in one step: settled, one round less: not
    for b, r in enumerate(rounds):
        done, short = _env(int(r)), _env(int(r) - 1)
        more = _env(int(r) + 5)
        for env in (done, short, more):
            env.reset()
        price = {k: np.asarray(e._view("bid_price"))[b] for k, e in (("done", done), ("short", short), ("more", more))}
        np.testing.assert_array_equal(price["done"], price["more"])
        assert (price["short"] != price["done"]).any()


def test_the_tool_reports_a_policy_and_refuses_one_without_auction_lists(capsys):
    assert tool.main(["coverage-rc-m100-auction", "--agents", "20", "--episodes", "2", "--max-rounds", "500"]) == 0
    out = capsys.readouterr().out
    assert "coverage-rc-m100-auction" in out and "held@16" in out and " 0.5 " in out
    assert tool.main(["coverage-rc-m100-claim-zero", "--agents", "20", "--episodes", "2"]) == 2
    assert "was not trained on auction lists" in capsys.readouterr().err
