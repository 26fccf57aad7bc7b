"""action_space="fine": the paper's five actions unchanged, and four quarter-strength pushes
with which an agent at rest can park within 0.035 of any point (taichi_swarm.physics.FINE)."""

import numpy as np
import pytest

import taichi_swarm
from taichi_swarm.physics import FINE, NUM_FINE_ACTIONS

REST_STEP = 0.2  # a full push from rest moves the resting point by 5 / 1 x 0.1^2 / 0.25


def one_agent(action_space="fine", seed=0):
    env = taichi_swarm.make("coverage", 1, 1, seed=seed, array="numpy", action_space=action_space)
    env.reset()
    env.set_state(pos=np.zeros((1, 1, 2)), vel=np.zeros((1, 1, 2)), landmarks=np.full((1, 1, 2), 0.9))
    return env


def rest_after(env, pushes, coast=45):
    """Where the agent comes to rest after these actions, one a step, then no-ops."""
    for a in [*pushes, *[0] * coast]:
        env.step(np.full((1, 1), a, dtype=np.int64))
    return env.get_state()["pos"][0, 0]


@pytest.mark.parametrize(("fine", "full", "axis", "sign"), [(5, 1, 0, -1), (6, 2, 0, 1), (7, 3, 1, -1), (8, 4, 1, 1)])
def test_a_fine_push_moves_the_resting_point_a_quarter_of_a_full_one(fine, full, axis, sign):
    moved = rest_after(one_agent(), [fine])
    assert moved[axis] == pytest.approx(sign * FINE * REST_STEP, abs=2e-4)
    assert moved[1 - axis] == 0.0
    assert rest_after(one_agent(), [full])[axis] == pytest.approx(sign * REST_STEP, abs=2e-4)


def test_an_agent_at_rest_can_park_within_0035_of_any_point():
    """Full pushes to the nearest multiple of 0.2, quarter pushes to the nearest of 0.05: within
    0.025 per axis; with the paper's five alone the nearest resting point can be 0.141 away."""
    rng = np.random.default_rng(0)
    worst = 0.0
    for goal in rng.uniform(-0.6, 0.6, size=(12, 2)):
        pushes = []
        for axis in (0, 1):
            quarters = int(np.rint(goal[axis] / (FINE * REST_STEP)))
            full, rest = divmod(abs(quarters), 4)
            neg = quarters < 0
            pushes += [1 + 2 * axis + (not neg)] * full + [5 + 2 * axis + (not neg)] * rest
        at = rest_after(one_agent(), pushes, coast=49 - len(pushes))
        worst = max(worst, float(np.linalg.norm(at - goal)))
    assert worst < 0.036


def test_the_papers_actions_are_the_same_in_the_fine_set():
    rng = np.random.default_rng(3)
    a = taichi_swarm.make("formation", 6, 4, seed=2, array="numpy")
    b = taichi_swarm.make("formation", 6, 4, seed=2, array="numpy", action_space="fine")
    a.reset(), b.reset()
    for _ in range(60):  # through the auto-resets
        actions = rng.integers(0, 5, size=(6, 4))
        oa, ra, da, _ = a.step(actions)
        ob, rb, db, _ = b.step(actions)
        for k in oa:
            np.testing.assert_array_equal(oa[k], ob[k])
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(da, db)


def test_each_action_set_refuses_actions_outside_it():
    env = one_agent()
    assert env.num_actions == NUM_FINE_ACTIONS and "action_space='fine'" in repr(env)
    with pytest.raises(ValueError, match=r"0\.\.8, got values in \[9, 9\]"):
        env.step(np.full((1, 1), 9, dtype=np.int64))
    with pytest.raises(ValueError, match=r"0\.\.4, got values in \[5, 5\]"):
        one_agent("discrete").step(np.full((1, 1), 5, dtype=np.int64))
    with pytest.raises(ValueError, match="action_space must be one of"):
        taichi_swarm.make("coverage", 1, 1, action_space="fine9")
