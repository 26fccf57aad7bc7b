"""Each agent's own reward (info["agent_reward"], the task's named per-agent terms) is its
share of the team reward: their mean is the team reward at every step, in both layouts,
and both are 0 after a reset."""

import numpy as np
import pytest

import taichi_swarm
from taichi_swarm.tasks import TASK_SPECS


@pytest.mark.parametrize("task", ["coverage", "formation", "line"])
@pytest.mark.parametrize("lists", [False, True])
def test_the_team_reward_is_the_mean_of_the_agents(task, lists):
    kw = dict(neighbours=4) if lists else {}
    env = taichi_swarm.make(task, 6, 5, comm="rc", seed=2, array="numpy", **kw)
    env.reset()
    assert np.all(env.info["agent_reward"] == 0)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(60):  # past the 50-step limit: auto-resets happen on the way
        _, reward, done, info = env.step(rng.integers(0, 5, size=(6, 5)))
        per_agent = info["agent_reward"]
        assert per_agent.shape == (6, 5) and np.all(per_agent <= 0)
        np.testing.assert_allclose(per_agent.mean(axis=1), reward, atol=1e-6)
        d = env.info["episode"]["matched_dist"][done] if done.any() else None
        ended += int(done.sum())
        if d is not None:  # the step that ended an episode is rewarded on its final d*_i
            want = np.clip(-d, -15, 15) if task == "coverage" else -np.clip(d, 0, 2)
            np.testing.assert_allclose(per_agent[done], want, atol=1e-6)
    assert ended >= 6


def test_every_task_names_its_reward_terms():
    for name in taichi_swarm.TASKS:
        spec = TASK_SPECS[name]
        assert spec.reward_terms == ("matched_distance",)
        for term in spec.reward_terms:
            assert callable(getattr(spec.funcs, term))
    env = taichi_swarm.make("coverage", 2, 3, seed=0, array="numpy")
    env.reset()
    _, _, _, info = env.step(np.zeros((2, 3), np.int64))
    np.testing.assert_array_equal(info["reward_terms"]["matched_distance"], info["agent_reward"])
