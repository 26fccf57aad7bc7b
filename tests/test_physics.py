"""Physics equals MPE's (contact forces included) to float32 rounding."""

import numpy as np
import pytest
from mpe_reference import mpe_step

import taichi_swarm


def test_terminal_speed_is_two_under_a_held_action():
    env = taichi_swarm.make("coverage", 1, 1, seed=0, array="numpy")
    env.reset()
    env.set_state(pos=np.zeros((1, 1, 2)), vel=np.zeros((1, 1, 2)))
    speeds = []
    for _ in range(40):  # stays under the 50-step limit; one agent never succeeds by chance here
        env.step(np.full((1, 1), 2, dtype=np.int64))  # +x
        speeds.append(env.get_state()["vel"][0, 0, 0])
    # v_n = 0.75 v_{n-1} + 0.5  ->  v* = 0.5 / 0.25 = 2.0 units/s, 0.2 units per step
    assert speeds[0] == pytest.approx(0.5)
    assert speeds[1] == pytest.approx(0.875)
    assert speeds[-1] == pytest.approx(2.0, abs=1e-4)
    assert env.get_state()["vel"][0, 0, 1] == 0.0


def test_overlapping_agents_are_pushed_apart_symmetrically():
    env = taichi_swarm.make("coverage", 1, 2, seed=0, array="numpy")
    env.reset()
    pos = np.array([[[-0.02, 0.0], [0.02, 0.0]]])  # 0.04 apart, radii 0.05 + 0.05
    env.set_state(pos=pos, vel=np.zeros((1, 2, 2)), landmarks=np.array([[[0.9, 0.9], [-0.9, 0.9]]]))
    env.step(np.zeros((1, 2), dtype=np.int64))
    vel = env.get_state()["vel"][0]
    # penetration = k softplus((0.1 - 0.04)/k) = 0.06 (+ k e^-60); F = 100 * 0.06 = 6 along x
    assert vel[0, 0] == pytest.approx(-0.6, rel=1e-5)
    assert vel[1, 0] == pytest.approx(0.6, rel=1e-5)
    assert vel[0, 1] == 0.0 and vel[1, 1] == 0.0
    assert vel[0, 0] == -vel[1, 0]


@pytest.mark.parametrize("task", ["coverage", "line"])  # agent radii 0.05 and 0.03
@pytest.mark.parametrize("M", [1, 2, 5, 20])
def test_random_states_match_numpy_reference(task, M):
    if task == "line" and M < 2:
        pytest.skip("line needs 2 agents")
    B = 16
    rng = np.random.default_rng(M)
    env = taichi_swarm.make(task, B, M, seed=1, array="numpy")
    env.reset()
    # crowded states so that many pairs are in contact
    pos = rng.uniform(-0.15, 0.15, size=(B, M, 2)).astype(np.float32)
    vel = rng.uniform(-2, 2, size=(B, M, 2)).astype(np.float32)
    env.set_state(pos=pos, vel=vel, step=np.zeros(B, dtype=np.int32))
    radius = taichi_swarm.TASK_SPECS[task].agent_radius
    for _ in range(3):
        actions = rng.integers(0, 5, size=(B, M))
        state = env.get_state()
        env.step(actions)
        new = env.get_state()
        for b in range(B):
            if env.done[b]:
                continue
            ref_pos, ref_vel = mpe_step(state["pos"][b], state["vel"][b], actions[b], radius)
            np.testing.assert_allclose(new["vel"][b], ref_vel, rtol=2e-5, atol=2e-5)
            np.testing.assert_allclose(new["pos"][b], ref_pos, rtol=2e-5, atol=2e-6)
