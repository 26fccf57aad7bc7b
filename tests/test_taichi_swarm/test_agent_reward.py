"""Each agent's own reward (info["agent_reward"], the task's named per-agent terms) is its
share of the team reward: their mean is the team reward at every step, in both layouts,
and both are 0 after a reset; with ``hold_reward`` an agent within the success threshold of
its target gains it on top, and the team reward stays the paper's."""

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
    for spec in TASK_SPECS.values():
        assert spec.reward_terms == ("matched_distance", "on_target")
        for term in spec.reward_terms:
            assert callable(getattr(spec.funcs, term))


@pytest.mark.parametrize(
    "task, kw",
    [
        ("coverage", {}),
        ("coverage", dict(neighbours=4, landmark_neighbours=4, sense_radius=1.0, scale="density")),
        ("formation", dict(neighbours=4, landmark_neighbours=4, sense_radius=1.0, scale="density")),
    ],
)
def test_hold_reward_pays_each_agent_within_the_threshold(task, kw):
    """Half the agents a hair off a landmark (its targets, here), half well off: with
    hold_reward the first half gain it on their own reward, and nothing else changes."""
    runs = {}
    for hold in (0.0, 0.5):
        env = taichi_swarm.make(task, 4, 6, comm="rc", seed=3, array="numpy", hold_reward=hold, **kw)
        env.reset()
        lmk = env.get_state()["landmarks"]  # [4, 6, 2]: coverage's landmarks, formation's lattice
        off = np.where(np.arange(6)[None, :, None] < 3, 0.01, 0.4) * np.array([1.0, 0.0])
        env.set_state(pos=(lmk + off).astype(np.float32), vel=np.zeros((4, 6, 2), np.float32))
        _, reward, _, info = env.step(np.zeros((4, 6), np.int64))
        runs[hold] = (reward.copy(), info["agent_reward"].copy(), env.matched_dist.copy())
    (r0, a0, d0), (r1, a1, d1) = runs[0.0], runs[0.5]
    np.testing.assert_array_equal(r1, r0)  # the team reward stays the paper's
    np.testing.assert_array_equal(d1, d0)
    within = d1 < env.params["success_threshold"]
    assert within.sum() >= 4 and (~within).sum() >= 4  # both kinds, in every case
    np.testing.assert_allclose(a1, a0 + 0.5 * within, atol=1e-6)
