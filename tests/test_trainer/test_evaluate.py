"""swarm eval's two action modes: greedy (argmax, the paper's) and sampled (a diagnostic)."""

import pytest
import torch

from taichi_swarm import Sim
from trainer.evaluate import evaluate


class FixedPolicy:
    """Every agent gets the same action logits, whatever it observes."""

    def __init__(self, logits):
        self.logits = torch.tensor(logits, dtype=torch.float32)

    def fused_weights(self):
        return None

    def __call__(self, self_obs, entities, adj, fused=None):
        B, M = self_obs.shape[:2]
        return self.logits.expand(B, M, -1), torch.zeros(B, M)


def run(policy, actions, seed=5):
    return evaluate(policy, Sim("coverage", 3), episodes=16, seed=seed, actions=actions)


def test_sampled_equals_greedy_when_the_policy_is_certain():
    certain = FixedPolicy([0.0, 50.0, -50.0, -50.0, -50.0])  # action 1 with probability ~1
    greedy, sampled = run(certain, "greedy"), run(certain, "sampled")
    assert greedy["actions"] == "greedy" and sampled["actions"] == "sampled"
    assert sampled["per_episode"] == greedy["per_episode"]


def test_sampled_actions_are_drawn_and_seeded():
    uniform = FixedPolicy([0.0] * 5)  # argmax of a tie: always action 0
    greedy, a, b = run(uniform, "greedy"), run(uniform, "sampled"), run(uniform, "sampled")
    assert a["per_episode"] == b["per_episode"]  # same seed, same draws
    assert a["per_episode"]["dist"] != greedy["per_episode"]["dist"]
    assert run(uniform, "sampled", seed=6)["per_episode"]["dist"] != a["per_episode"]["dist"]


def test_unknown_action_mode_is_refused():
    with pytest.raises(ValueError, match="actions must be one of"):
        run(FixedPolicy([0.0] * 5), "softmax")
