"""Adding a task is one module and a register() call (docs/ARCHITECTURE.md, "How to add
a task"): done here for a toy task, "gather", whose M agents all go to one landmark, paid by
two named per-agent terms: their distance and, as VMAS's scenarios do, a collision penalty.

(No ``from __future__ import annotations`` here: Taichi reads the annotations.)"""

import sys
from dataclasses import dataclass

import numpy as np
import pytest
import taichi as ti

import taichi_swarm
from taichi_swarm import rng, tasks
from taichi_swarm.layout import P_TASK_PARAM, blocks, team_size
from taichi_swarm.tasks.base import Context, Task


# --- the toy task: what a task module holds ---------------------------------------------
@dataclass(frozen=True)
class GatherParams:
    success_threshold: float = 0.4
    """Success: every agent this close to the landmark."""
    spread: float = 0.5
    """The landmark is drawn uniformly in [-spread, spread]^2."""


@ti.func
def landmark_count(sm: ti.template(), ib: ti.template()) -> ti.i32:
    return 1


@ti.func
def spawn_landmarks(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    s = f[P_TASK_PARAM]
    blocks.landmarks.store(f, ib, b, 0, rng.uniform2(ib, b, -s, s))


@ti.func
def place_targets(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    for k in range(M):  # every target on the landmark
        blocks.targets.store(f, ib, b, k, blocks.landmarks.load(f, ib, b, 0))


@ti.func
def distance(f: ti.template(), ctx: Context) -> ti.f32:  # the named per-agent terms: their sum pays the agent
    return -2.0 * ctx.d


@ti.func
def collision(f: ti.template(), ctx: Context) -> ti.f32:
    return -1.0 * ctx.contacts  # every teammate it touched this step


GATHER = Task(
    name="gather",
    task_id=99,
    agent_radius=0.05,
    landmark_radius=0.05,
    min_agents=1,
    params_type=GatherParams,
    landmarks=lambda num_agents: 1,
    funcs=sys.modules[__name__],
    kernel_param="spread",
    reward_terms=("distance", "collision"),
    doc="M agents gather round one landmark (a test task).",
)


@pytest.fixture
def gather():
    tasks.register(GATHER)
    yield GATHER
    tasks.unregister("gather")


def test_a_new_task_is_one_module_and_a_register_call(gather):
    B, M = 16, 3
    env = taichi_swarm.make("gather", B, M, seed=1, array="numpy", spread=0.25)
    obs = env.reset()
    lmk = env.get_state()["landmarks"]  # [B, 1, 2]
    assert obs["entities"].shape == (B, M, 1, 2)
    assert np.all(np.abs(lmk) <= 0.25)  # its parameter reached its spawn function
    # agents round the landmark: the reward is the toy's, the success rule the common one
    offsets = np.array([[0.1, 0.0], [0.0, -0.2], [-0.3, 0.0]], np.float32)
    pos = (lmk + offsets[None]).astype(np.float32)
    env.set_state(pos=pos, vel=np.zeros_like(pos))
    _, reward, done, info = env.step(np.zeros((B, M), np.int64))
    assert done.all() and info["episode"]["success"].all()  # every d < 0.4
    d = info["episode"]["matched_dist"]  # [B, M] at the end
    np.testing.assert_allclose(reward, -2.0 * d.mean(-1), rtol=1e-5)
    np.testing.assert_allclose(info["agent_reward"], -2.0 * d, rtol=1e-5)  # its named terms: nobody touched
    np.testing.assert_allclose(info["reward_terms"]["distance"], -2.0 * d, rtol=1e-5)
    assert set(info["reward_terms"]) == {"distance", "collision"} and (info["reward_terms"]["collision"] == 0).all()
    # too far: no success; the time limit ends the episode
    env.reset()
    far = (env.get_state()["landmarks"] + np.array([[0.9, 0.0]] * M, np.float32)[None]).astype(np.float32)
    env.set_state(pos=far, vel=np.zeros_like(far))
    _, _, done, _ = env.step(np.zeros((B, M), np.int64))
    assert not done.any()


@pytest.mark.parametrize("lists", [False, True])
def test_a_collision_penalty_is_a_term_of_the_task_alone(gather, lists):
    """Agents 0 and 1 start on top of each other, agent 2 apart: the penalty pays 0 and 1 for one
    contact each, in the dense layout and through the neighbour lists' grid alike."""
    B, M = 2, 3
    env = taichi_swarm.make("gather", B, M, seed=1, array="numpy", **(dict(neighbours=2) if lists else {}))
    env.reset()
    lmk = env.get_state()["landmarks"]
    offsets = np.array([[0.3, 0.0], [0.33, 0.0], [-0.3, 0.0]], np.float32)  # 0.03 < the two radii, 0.1
    pos = (lmk + offsets[None]).astype(np.float32)
    env.set_state(pos=pos, vel=np.zeros_like(pos))
    _, reward, _, info = env.step(np.zeros((B, M), np.int64))
    terms = info["reward_terms"]
    np.testing.assert_array_equal(terms["collision"], [[-1.0, -1.0, 0.0]] * B)
    np.testing.assert_allclose(info["agent_reward"], terms["distance"] + terms["collision"], rtol=1e-6)
    np.testing.assert_allclose(terms["distance"], -2.0 * env.matched_dist, rtol=1e-5)  # (exact: d*_i per agent)


def test_registry_errors():
    with pytest.raises(ValueError, match="task must be one of"):
        taichi_swarm.make("gather", 2, 2)  # not registered
    with pytest.raises(ValueError, match="already registered"):
        tasks.register(tasks.TASK_SPECS["coverage"])
    with pytest.raises(ValueError, match="task id 0 is taken"):
        tasks.register(Task(**{**GATHER.__dict__, "task_id": 0}))
    with pytest.raises(ValueError, match="lack the Taichi functions"):
        Task(**{**GATHER.__dict__, "funcs": object()})
    with pytest.raises(ValueError, match=r"lack the Taichi functions \['bump'\]"):
        Task(**{**GATHER.__dict__, "reward_terms": ("distance", "bump")})
    with pytest.raises(ValueError, match="reward_terms must name"):
        Task(**{**GATHER.__dict__, "reward_terms": ()})
    with pytest.raises(ValueError, match="kernel_param 'nope'"):
        Task(**{**GATHER.__dict__, "kernel_param": "nope"})


def test_each_builtin_task_is_one_module():
    for name in taichi_swarm.TASKS:
        task = tasks.TASK_SPECS[name]
        assert task.funcs.__name__ == f"taichi_swarm.tasks.{name}"
        assert "success_threshold" in task.params
