"""The three tasks of Agarwal et al. 2019 (docs/PAPER.md s.2).

Each task is a small contract, written as Taichi functions called from the
fused kernels with the task id as a compile-time constant:
  - ``spawn(b)``: sample landmarks (and agents) for a new episode of env b;
  - ``place_targets(b)``: where the M targets are, from the current state;
  - ``reward(mean_d, mean_clipped_d)``: the team reward from matched distances.
Success is "every matched distance below ``success_threshold``" for all tasks.
Adding a task: a new id, its ``TaskSpec`` in ``TASK_SPECS`` and a branch in
each of the three functions below.
"""

import math
from dataclasses import dataclass, field

import taichi as ti

from . import rng
from .layout import O_LMK, O_POS, O_TGT, O_VEL, P_TASK_PARAM, team_size

COVERAGE, FORMATION, LINE = 0, 1, 2


@dataclass(frozen=True)
class TaskSpec:
    """Static description of a task; ``params`` are the overridable defaults."""

    task_id: int
    agent_radius: float
    landmark_radius: float
    min_agents: int
    params: dict = field(default_factory=dict)
    doc: str = ""

    def num_landmarks(self, num_agents: int) -> int:
        return num_agents if self.task_id == COVERAGE else 1 if self.task_id == FORMATION else 2


# Overridable per-task parameters (``taichi_swarm.make(..., **task_params)``).
COMMON_PARAMS = {"max_steps": 50}
TASK_SPECS: dict[str, TaskSpec] = {
    "coverage": TaskSpec(
        COVERAGE,
        0.05,
        0.05,
        1,
        {"success_threshold": 0.1},
        "M agents cover M landmarks (MPE simple_spread with matched distances).",
    ),
    "formation": TaskSpec(
        FORMATION,
        0.05,
        0.03,
        2,
        {"success_threshold": 0.05, "formation_radius": 0.5},
        "M agents form a regular M-gon round one landmark.",
    ),
    "line": TaskSpec(
        LINE,
        0.03,
        0.02,
        2,
        {"success_threshold": 0.05, "line_length": 1.25},
        "M agents spread evenly on the segment between two landmarks.",
    ),
}
TASKS = tuple(TASK_SPECS)

LINE_TURN = 5.0 * math.pi / 180.0  # turn the heading by 5 degrees until l1 fits


@ti.func
def landmark_count(task: ti.template(), sm: ti.template(), ib: ti.template()) -> ti.i32:
    """L (``TaskSpec.num_landmarks``): M for coverage, else a compile-time constant."""
    n = 0
    if ti.static(task == COVERAGE):
        n = team_size(sm, ib)
    elif ti.static(task == FORMATION):
        n = 1
    else:
        n = 2
    return n


@ti.func
def _get2(f: ti.template(), base: ti.i32) -> ti.math.vec2:
    return ti.math.vec2(f[base], f[base + 1])


@ti.func
def _set2(f: ti.template(), base: ti.i32, v: ti.math.vec2):
    f[base] = v[0]
    f[base + 1] = v[1]


@ti.func
def spawn(task: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """Fresh episode for env b: agents U[-1,1]^2 at rest, landmarks per task."""
    M, L = team_size(sm, ib), landmark_count(task, sm, ib)
    for i in range(M):
        _set2(f, ib[O_POS] + (b * M + i) * 2, rng.uniform2(ib, b, -1.0, 1.0))
        _set2(f, ib[O_VEL] + (b * M + i) * 2, ti.math.vec2(0.0, 0.0))
    lmk = ib[O_LMK] + b * L * 2
    if ti.static(task == COVERAGE):
        for k in range(L):
            _set2(f, lmk + 2 * k, rng.uniform2(ib, b, -1.0, 1.0))
    elif ti.static(task == FORMATION):
        _set2(f, lmk, rng.uniform2(ib, b, -0.5, 0.5))
    elif ti.static(task == LINE):
        length = f[P_TASK_PARAM]
        l0 = rng.uniform2(ib, b, -0.25, 0.25)
        theta = 2.0 * math.pi * rng.uniform(ib, b)
        l1 = l0 + length * ti.math.vec2(ti.cos(theta), ti.sin(theta))
        turns = 0
        while (ti.abs(l1[0]) >= 1.0 or ti.abs(l1[1]) >= 1.0) and turns < 72:
            theta += LINE_TURN
            l1 = l0 + length * ti.math.vec2(ti.cos(theta), ti.sin(theta))
            turns += 1
        _set2(f, lmk, l0)
        _set2(f, lmk + 2, l1)


@ti.func
def place_targets(task: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """Write the M targets of env b from its current landmarks and agents."""
    M, L = team_size(sm, ib), landmark_count(task, sm, ib)
    lmk = ib[O_LMK] + b * L * 2
    tgt = ib[O_TGT] + b * M * 2
    if ti.static(task == COVERAGE):  # targets are the landmarks themselves
        for k in range(M):
            _set2(f, tgt + 2 * k, _get2(f, lmk + 2 * k))
    elif ti.static(task == FORMATION):
        # Re-anchored every step on the agent with the smallest angle round the landmark.
        centre = _get2(f, lmk)
        theta0 = 1e9
        for i in range(M):
            d = _get2(f, ib[O_POS] + (b * M + i) * 2) - centre
            ang = ti.atan2(d[1], d[0])
            if ang < 0.0:
                ang += 2.0 * math.pi
            theta0 = ti.min(theta0, ang)
        radius = f[P_TASK_PARAM]
        for k in range(M):
            ang = theta0 + 2.0 * math.pi * k / M
            _set2(f, tgt + 2 * k, centre + radius * ti.math.vec2(ti.cos(ang), ti.sin(ang)))
    elif ti.static(task == LINE):
        # t_k = l0 + k * (|l1 - l0| / (M - 1)) * heading, i.e. evenly from l0 to l1.
        l0 = _get2(f, lmk)
        l1 = _get2(f, lmk + 2)
        for k in range(M):
            _set2(f, tgt + 2 * k, l0 + (l1 - l0) * (k / (M - 1)))


@ti.func
def reward(task: ti.template(), mean_d: ti.f32, mean_clipped_d: ti.f32) -> ti.f32:
    """Team reward from the mean matched distance (and its clip(d, 0, 2) mean)."""
    r = 0.0
    if ti.static(task == COVERAGE):
        r = ti.math.clamp(-mean_d, -15.0, 15.0)
    else:
        r = -mean_clipped_d
    return r
