"""Coverage (MPE simple_spread): M agents cover M landmarks (docs/PAPER.md s.2).

Landmarks uniform in [-1, 1]^2; the targets are the landmarks themselves; reward
clip(-mean_i d*_i, -15, 15); DIST is reported.

``scale="density"`` (make): agents and landmarks uniform in [-w, w]^2 with
w = sqrt(M / 10), so the agents (and landmarks) per unit area stay those of the paper's
M = 10 (2.5 per unit area) and w = 1 at M = 10 exactly; the distance an agent must travel
to its landmark then stays the same at every M (the nearest-neighbour spacing of a
uniform density, not the arena's side, sets it). scale=None is the paper's geometry.
"""

import sys
from dataclasses import dataclass

import taichi as ti

from .. import rng
from ..layout import P_ARENA, blocks, team_size
from .base import Context, Task


@dataclass(frozen=True)
class CoverageParams:
    success_threshold: float = 0.1
    """Success: every matched distance below this."""


@ti.func
def landmark_count(sm: ti.template(), ib: ti.template()) -> ti.i32:
    return team_size(sm, ib)


@ti.func
def spawn_landmarks(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    L = team_size(sm, ib)
    lmk = blocks.landmarks.env(ib, b)
    w = f[P_ARENA]
    for k in range(L):
        blocks.landmarks.set2(f, ib, lmk, k, rng.uniform2(ib, b, -w, w))


@ti.func
def place_targets(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    lmk = blocks.landmarks.env(ib, b)
    tgt = blocks.targets.env(ib, b)
    for k in range(M):
        blocks.targets.set2(f, ib, tgt, k, blocks.landmarks.get2(f, ib, lmk, k))


@ti.func
def matched_distance(f: ti.template(), ctx: Context) -> ti.f32:
    """-d*_i: the agent's share of the team reward, whose mean it is (the clip at 15 binds
    only in arenas far larger than the paper's)."""
    return ti.math.clamp(-ctx.d, -15.0, 15.0)


TASK = Task(
    name="coverage",
    task_id=0,
    agent_radius=0.05,
    landmark_radius=0.05,
    min_agents=1,
    params_type=CoverageParams,
    landmarks=lambda num_agents: num_agents,
    funcs=sys.modules[__name__],
    reports_dist=True,
    density_scale=True,
    landmark_lists=True,
    reward_terms=("matched_distance",),
    doc="M agents cover M landmarks (MPE simple_spread with matched distances).",
)
