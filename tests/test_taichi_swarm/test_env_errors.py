"""Bad input gets a ValueError naming the argument."""

import numpy as np
import pytest

import taichi_swarm


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(task="swarming"), "task"),
        (dict(num_envs=0), "num_envs"),
        (dict(num_envs=2.5), "num_envs"),
        (dict(num_agents=0), "agents"),
        (dict(task="formation", num_agents=1), "agents"),
        (dict(comm="xx"), "comm"),
        (dict(comm_radius=-1.0), "comm_radius"),
        (dict(arch="tpu"), "arch"),
        (dict(array="jax"), "array"),
        (dict(seed=-3), "seed"),
        (dict(max_steps=0), "max_steps"),
        (dict(line_length=2.0), "line_length"),  # not a coverage parameter
        (dict(action_space="box"), "action_space"),
    ],
)
def test_make_rejects(kwargs, match):
    args = dict(task="coverage", num_envs=2, num_agents=3) | kwargs
    with pytest.raises(ValueError, match=match):
        taichi_swarm.make(**args)


def test_step_rejects_bad_actions():
    import torch

    env = taichi_swarm.make("coverage", 2, 3, seed=0)
    env.reset()
    with pytest.raises(ValueError, match="dtype"):
        env.step(torch.zeros((2, 3), dtype=torch.int32))
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros((3, 2), dtype=torch.int64))
    with pytest.raises(ValueError, match="0..4"):
        env.step(torch.full((2, 3), 5, dtype=torch.int64))
    with pytest.raises(ValueError, match="0..4"):
        env.step(torch.full((2, 3), -1, dtype=torch.int64))
    with pytest.raises(ValueError, match="contiguous"):
        env.step(torch.zeros((3, 2), dtype=torch.int64).t())
    with pytest.raises(ValueError, match="contiguous"):
        env.step(np.zeros((3, 2), dtype=np.int64).T)
    with pytest.raises(ValueError, match="actions must be"):
        env.step([[0, 0, 0], [0, 0, 0]])
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="device"):
            env.step(torch.zeros((2, 3), dtype=torch.int64, device="cuda"))
    state = env.get_state()  # nothing stepped
    assert (state["step"] == 0).all()


def test_set_state_rejects_bad_shapes_and_values():
    env = taichi_swarm.make("coverage", 2, 3, seed=0, array="numpy")
    env.reset()
    with pytest.raises(ValueError, match="pos"):
        env.set_state(pos=np.zeros((2, 4, 2)))
    with pytest.raises(ValueError, match="vel"):
        env.set_state(vel=np.full((2, 3, 2), np.nan))
    with pytest.raises(ValueError, match="step"):
        env.set_state(step=np.full(2, -1))


def test_step_before_reset_is_an_error():
    env = taichi_swarm.make("coverage", 1, 2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((1, 2), dtype=np.int64))


def test_set_state_checks_values_as_stored():
    import numpy as np

    env = taichi_swarm.make("coverage", 2, 3, array="numpy", seed=0)
    env.reset()
    pos = np.zeros((2, 3, 2))
    with pytest.raises(ValueError, match="float32"):
        env.set_state(pos=pos + 1e39)
    with pytest.raises(ValueError, match="real numbers"):
        env.set_state(pos=pos.astype(np.complex64))
    with pytest.raises(ValueError, match="real numbers"):
        env.set_state(pos=pos.astype(bool))
    with pytest.raises(ValueError, match="step must be <="):
        env.set_state(step=np.full(2, 2**31 + 5, dtype=np.int64))
    with pytest.raises(ValueError, match="non-negative integers"):
        env.set_state(step=np.ones(2, dtype=bool))
    with pytest.raises(ValueError, match="comm_radius"):
        taichi_swarm.make("coverage", 2, 3, comm="rc", comm_radius=1e40)
    env.set_state(pos=pos + 0.5, step=np.full(2, 7))
    assert float(env.get_state()["pos"][0, 0, 0]) == 0.5


def test_oversized_batches_are_refused_with_the_memory_they_would_need():
    with pytest.raises(ValueError, match="GiB of memory"):
        taichi_swarm.make("coverage", 10_000_000, 100, array="numpy")


def test_step_rejects_bad_continuous_actions():
    import torch

    env = taichi_swarm.make("coverage", 2, 3, seed=0, action_space="continuous")
    env.reset()
    with pytest.raises(ValueError, match="continuous actions must have dtype"):
        env.step(torch.zeros((2, 3, 2), dtype=torch.float64))
    with pytest.raises(ValueError, match="continuous actions must have dtype"):
        env.step(torch.zeros((2, 3), dtype=torch.int64))  # discrete actions into a continuous env
    with pytest.raises(ValueError, match="continuous actions must have shape"):
        env.step(torch.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="continuous actions must have shape"):
        env.step(np.zeros((2, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.full((2, 3, 2), float("nan")))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full((2, 3, 2), np.nan, dtype=np.float32))
    with pytest.raises(ValueError, match="contiguous"):
        env.step(torch.zeros((2, 2, 3)).transpose(1, 2))
    with pytest.raises(ValueError, match="contiguous"):
        env.step(np.zeros((2, 2, 3), dtype=np.float32).transpose(0, 2, 1))
    with pytest.raises(ValueError, match="continuous actions must be"):
        env.step([[[0.0, 0.0]] * 3] * 2)
    assert (env.get_state()["step"] == 0).all()  # nothing stepped
    discrete = taichi_swarm.make("coverage", 2, 3, seed=0)
    discrete.reset()
    with pytest.raises(ValueError, match="actions must have dtype torch.int64"):
        discrete.step(torch.zeros((2, 3, 2)))  # continuous actions into a discrete env


def test_reset_envs_rejects_bad_masks():
    env = taichi_swarm.make("coverage", 2, 3, seed=0, array="numpy")
    with pytest.raises(RuntimeError, match="reset"):
        env.reset_envs(np.ones(2, dtype=bool))
    env.reset()
    with pytest.raises(ValueError, match="mask must have dtype bool"):
        env.reset_envs(np.ones(2, dtype=np.int64))
    with pytest.raises(ValueError, match="mask must have shape"):
        env.reset_envs(np.ones(3, dtype=bool))


@pytest.mark.parametrize(
    "kw, says",
    [
        (dict(neighbours=10**8), "neighbours must be <= 1024"),
        (dict(neighbours=4, landmark_neighbours=10**8, sense_radius=1.0, scale="density"), "landmark_neighbours"),
        (dict(neighbours=4, landmark_neighbours=4, sense_radius=0.0, scale="density"), "sense_radius must be > 0"),
    ],
)
def test_list_sizes_and_a_zero_sense_radius_are_refused_before_allocation(kw, says):
    with pytest.raises(ValueError, match=says):
        taichi_swarm.make("coverage", 2, 5, array="numpy", **kw)


@pytest.mark.parametrize("kw", [{}, {"neighbours": 3}])
def test_warm_up_compiles_and_leaves_the_env_as_made(kw):
    """``warm_up`` (what swarm world calls before its agents start): the same episodes after it as
    without it, from the first reset on."""
    made = [taichi_swarm.make("coverage", 3, 4, seed=5, array="numpy", **kw) for _ in range(2)]
    made[1].warm_up()
    first = [env.reset() for env in made]
    assert all(np.array_equal(first[0][k], first[1][k]) for k in first[0])
    actions = np.random.default_rng(0).integers(0, 5, size=(4, 3, 4))
    for a in actions:
        steps = [env.step(a) for env in made]
        assert np.array_equal(steps[0][1], steps[1][1]) and np.array_equal(steps[0][0]["self"], steps[1][0]["self"])
