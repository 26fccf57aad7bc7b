"""The tasks of Agarwal et al. 2019 (docs/PAPER.md s.2), one module each, registered here.

``TASK_SPECS`` maps a task's name to its ``Task`` (base.py); the kernels call the four
dispatchers below with the task id as a compile-time constant, so each kernel is
compiled for one task and calls that task's functions directly. An unknown task is
an error (``make`` names it; a kernel compiled for an unregistered id fails to build),
never a default branch.

Adding a task (docs/ARCHITECTURE.md "How to add a task"): write ``mytask.py`` like
``formation.py`` (parameters dataclass, four Taichi functions, ``TASK``), and
``register(mytask.TASK)``; tests/test_taichi_swarm/test_task_registry.py does it for a toy task.
"""

import taichi as ti

from .. import rng
from ..layout import P_ARENA, blocks, team_size
from . import coverage, formation, line
from .base import COMMON_PARAMS, Context, Task

TASK_SPECS: dict[str, Task] = {}
_FUNCS_BY_ID: dict[int, object] = {}
_TERMS_BY_ID: dict[int, tuple] = {}  # each task's per-agent reward terms, as Taichi functions


def register(task: Task) -> Task:
    """Make ``task`` available to ``taichi_swarm.make`` by its name."""
    if task.name in TASK_SPECS:
        raise ValueError(f"a task named {task.name!r} is already registered")
    if task.task_id in _FUNCS_BY_ID:
        raise ValueError(f"task id {task.task_id} is taken (by {_name_of(task.task_id)!r})")
    TASK_SPECS[task.name] = task
    _FUNCS_BY_ID[task.task_id] = task.funcs
    _TERMS_BY_ID[task.task_id] = tuple(getattr(task.funcs, name) for name in task.reward_terms)
    return task


def unregister(name: str) -> None:
    """Remove a task registered at run time (tests)."""
    task = TASK_SPECS.pop(name)
    del _FUNCS_BY_ID[task.task_id], _TERMS_BY_ID[task.task_id]


def _name_of(task_id: int) -> str:
    return next(t.name for t in TASK_SPECS.values() if t.task_id == task_id)


for _task in (coverage.TASK, formation.TASK, line.TASK):
    register(_task)
TASKS = tuple(TASK_SPECS)  # the paper's three tasks
COVERAGE, FORMATION, LINE = (TASK_SPECS[name].task_id for name in TASKS)


# --- the kernels' side: compile-time dispatch on the task id ----------------------------


@ti.func
def landmark_count(task: ti.template(), sm: ti.template(), ib: ti.template()) -> ti.i32:
    """L of the env's team (``Task.num_landmarks``)."""
    return _FUNCS_BY_ID[task].landmark_count(sm, ib)


@ti.func
def spawn(task: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """Fresh episode for env b: agents U[-w, w]^2 at rest (every task; w = 1, or the
    density-scaled half-width), then the task's landmarks."""
    M = team_size(sm, ib)
    w = f[P_ARENA]
    for i in range(M):
        blocks.pos.store(f, ib, b, i, rng.uniform2(ib, b, -w, w))
        blocks.vel.store(f, ib, b, i, ti.math.vec2(0.0, 0.0))
    _FUNCS_BY_ID[task].spawn_landmarks(sm, f, ib, b)


@ti.func
def place_targets(task: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """Write the M targets of env b from its current landmarks and agents."""
    _FUNCS_BY_ID[task].place_targets(sm, f, ib, b)


@ti.func
def agent_reward(task: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, ctx: Context):
    """Agent i's own reward: the task's named terms of its context, each written by name
    (reward_terms [B, M, T], info["reward_terms"]), and their sum (agent_reward [B, M])."""
    row = blocks.reward_terms.at(ib, b, i)
    total = 0.0
    for k in ti.static(range(len(_TERMS_BY_ID[task]))):
        value = _TERMS_BY_ID[task][k](f, ctx)
        f[row + k] = value
        total += value
    f[blocks.agent_reward.at(ib, b, i)] = total


__all__ = [
    "COMMON_PARAMS",
    "COVERAGE",
    "Context",
    "FORMATION",
    "LINE",
    "TASKS",
    "TASK_SPECS",
    "Task",
    "register",
    "unregister",
]
