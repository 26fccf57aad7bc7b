"""Line: M agents spread evenly on the segment between two landmarks (docs/PAPER.md s.2).

Landmark 0 uniform in [-0.25, 0.25]^2, landmark 1 at distance ``line_length`` in a
random direction (turned by 5 degrees until it lies inside the arena); the targets
are fixed for the episode: t_k = l0 + k (l1 - l0) / (M - 1); reward
-mean_i clip(d*_i, 0, 2).

``scale="density"`` is refused (ValueError): keeping the spacing line_length / (M - 1)
makes the segment grow linearly with M, beyond any agent's reach in 50 steps; the rule
that bounds both spacing and travel (parallel segments, ~ sqrt(M) of them) is not built
yet (docs/SWARM.md). Its two landmarks are always seen (no landmark lists)."""

import math
import sys
from dataclasses import dataclass

import taichi as ti

from .. import rng
from ..layout import O_LMK, O_TGT, P_TASK_PARAM, team_size
from .base import Task, get2, set2

TURN = 5.0 * math.pi / 180.0  # turn the heading by 5 degrees until l1 fits


@dataclass(frozen=True)
class LineParams:
    success_threshold: float = 0.05
    """Success: every matched distance below this."""
    line_length: float = 1.25
    """Distance between the two landmarks."""


@ti.func
def landmark_count(sm: ti.template(), ib: ti.template()) -> ti.i32:
    return 2


@ti.func
def spawn_landmarks(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    lmk = ib[O_LMK] + b * 4
    length = f[P_TASK_PARAM]
    l0 = rng.uniform2(ib, b, -0.25, 0.25)
    theta = 2.0 * math.pi * rng.uniform(ib, b)
    l1 = l0 + length * ti.math.vec2(ti.cos(theta), ti.sin(theta))
    turns = 0
    while (ti.abs(l1[0]) >= 1.0 or ti.abs(l1[1]) >= 1.0) and turns < 72:
        theta += TURN
        l1 = l0 + length * ti.math.vec2(ti.cos(theta), ti.sin(theta))
        turns += 1
    set2(f, lmk, l0)
    set2(f, lmk + 2, l1)


@ti.func
def place_targets(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    lmk = ib[O_LMK] + b * 4
    tgt = ib[O_TGT] + b * M * 2
    l0 = get2(f, lmk)
    l1 = get2(f, lmk + 2)
    for k in range(M):
        set2(f, tgt + 2 * k, l0 + (l1 - l0) * (k / (M - 1)))


@ti.func
def reward(mean_d: ti.f32, mean_clipped_d: ti.f32) -> ti.f32:
    return -mean_clipped_d


TASK = Task(
    name="line",
    task_id=2,
    agent_radius=0.03,
    landmark_radius=0.02,
    min_agents=2,
    params_type=LineParams,
    landmarks=lambda num_agents: 2,
    funcs=sys.modules[__name__],
    kernel_param="line_length",
    doc="M agents spread evenly on the segment between two landmarks.",
)
