"""Physics equals MPE's (contact forces included) to float32 rounding."""

import numpy as np
import pytest
from mpe_reference import mpe_step, mpe_step_continuous

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


@pytest.mark.parametrize(("task", "M"), [("coverage", 3), ("line", 5), ("formation", 6)])  # compiled M, generic M
def test_continuous_actions_match_numpy_reference(task, M):
    """action_space="continuous": force = 5 clip(u, -1, 1) per axis, then MPE physics."""
    B = 16
    rng = np.random.default_rng(M)
    env = taichi_swarm.make(task, B, M, seed=1, array="numpy", action_space="continuous")
    env.reset()
    pos = rng.uniform(-0.15, 0.15, size=(B, M, 2)).astype(np.float32)  # crowded: contacts
    env.set_state(pos=pos, vel=rng.uniform(-2, 2, size=(B, M, 2)), step=np.zeros(B, dtype=np.int32))
    radius = taichi_swarm.TASK_SPECS[task].agent_radius
    for _ in range(3):
        u = rng.uniform(-2.5, 2.5, size=(B, M, 2)).astype(np.float32)  # half of them beyond the clip
        u[0, 0] = (np.inf, -np.inf)  # clipped like any other value
        state = env.get_state()
        env.step(u)
        new = env.get_state()
        for b in range(B):
            if env.done[b]:
                continue
            ref_pos, ref_vel = mpe_step_continuous(state["pos"][b], state["vel"][b], u[b], radius)
            np.testing.assert_allclose(new["vel"][b], ref_vel, rtol=2e-5, atol=2e-5)
            np.testing.assert_allclose(new["pos"][b], ref_pos, rtol=2e-5, atol=2e-6)


def test_continuous_unit_actions_equal_the_discrete_ones():
    """u = a unit axis vector gives the same step, bit for bit, as the discrete action."""
    import torch

    B, M = 5, 4
    disc = taichi_swarm.make("coverage", B, M, seed=3)
    cont = taichi_swarm.make("coverage", B, M, seed=3, action_space="continuous")
    disc.reset(), cont.reset()
    dirs = torch.tensor([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    for _ in range(60):  # past the time limit: auto-resets agree too
        a = torch.randint(0, 5, (B, M), generator=gen)
        _, r_d, done_d, _ = disc.step(a)
        _, r_c, done_c, _ = cont.step(dirs[a].contiguous())
        assert torch.equal(r_d, r_c) and torch.equal(done_d, done_c)
        for k in ("pos", "vel", "landmarks"):
            assert torch.equal(disc.get_state()[k], cont.get_state()[k])


def test_reset_envs_restarts_only_the_masked_environments():
    env = taichi_swarm.make("formation", 4, 3, seed=0, array="numpy")
    env.reset()
    for _ in range(5):
        env.step(np.full((4, 3), 2, dtype=np.int64))
    before = env.get_state()
    env.reset_envs(np.array([False, True, False, True]))
    after = env.get_state()
    assert after["step"].tolist() == [5, 0, 5, 0]
    for k in ("pos", "vel", "landmarks"):
        np.testing.assert_array_equal(after[k][[0, 2]], before[k][[0, 2]])
        assert not np.array_equal(after[k][[1, 3]], before[k][[1, 3]]) or k == "vel"
    assert (after["vel"][[1, 3]] == 0).all()  # a fresh episode starts at rest
    np.testing.assert_array_equal(env.obs["self"][1, :, 2:], after["pos"][1])  # observations rewritten
    env.reset_envs(np.zeros(4, dtype=bool))  # nothing to do
    assert env.get_state()["step"].tolist() == [5, 0, 5, 0]
