"""Formation: M agents form a regular M-gon round one landmark (docs/PAPER.md s.2).

One landmark uniform in [-0.5, 0.5]^2; the targets, a regular M-gon of radius
``formation_radius`` round it, are re-anchored every step on the agent with the
smallest angle round the landmark; reward -mean_i clip(d*_i, 0, 2).

``scale="density"`` is refused (ValueError): the ring's spacing 2 pi r / M shrinks below
the agents' width past M = 30, and keeping the spacing makes the ring (and each agent's
travel) grow linearly with M. The rule that bounds both, a filled hexagonal lattice of
side ~ sqrt(M) round the landmark, is not built yet (docs/SWARM.md). Its one landmark is
always seen (no landmark lists)."""

import math
import sys
from dataclasses import dataclass

import taichi as ti

from .. import rng
from ..layout import O_LMK, O_POS, O_TGT, P_TASK_PARAM, agent_at, team_size
from .base import Task, get2, set2


@dataclass(frozen=True)
class FormationParams:
    success_threshold: float = 0.05
    """Success: every matched distance below this."""
    formation_radius: float = 0.5
    """Radius of the M-gon round the landmark."""


@ti.func
def landmark_count(sm: ti.template(), ib: ti.template()) -> ti.i32:
    return 1


@ti.func
def spawn_landmarks(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    set2(f, ib[O_LMK] + b * 2, rng.uniform2(ib, b, -0.5, 0.5))


@ti.func
def place_targets(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    centre = get2(f, ib[O_LMK] + b * 2)
    tgt = ib[O_TGT] + b * M * 2
    theta0 = 1e9
    for i in range(M):
        d = get2(f, agent_at(ib, O_POS, b, M, i, 2)) - centre
        ang = ti.atan2(d[1], d[0])
        if ang < 0.0:
            ang += 2.0 * math.pi
        theta0 = ti.min(theta0, ang)
    radius = f[P_TASK_PARAM]
    for k in range(M):
        ang = theta0 + 2.0 * math.pi * k / M
        set2(f, tgt + 2 * k, centre + radius * ti.math.vec2(ti.cos(ang), ti.sin(ang)))


@ti.func
def reward(mean_d: ti.f32, mean_clipped_d: ti.f32) -> ti.f32:
    return -mean_clipped_d


TASK = Task(
    name="formation",
    task_id=1,
    agent_radius=0.05,
    landmark_radius=0.03,
    min_agents=2,
    params_type=FormationParams,
    landmarks=lambda num_agents: 1,
    funcs=sys.modules[__name__],
    kernel_param="formation_radius",
    doc="M agents form a regular M-gon round one landmark.",
)
