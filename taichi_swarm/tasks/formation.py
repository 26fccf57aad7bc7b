"""Formation: M agents form a regular M-gon round one landmark (docs/PAPER.md s.2).

One landmark uniform in [-0.5, 0.5]^2; the targets, a regular M-gon of radius
``formation_radius`` round it, are re-anchored every step on the agent with the
smallest angle round the landmark; reward -mean_i clip(d*_i, 0, 2).

``scale="density"``: the ring's spacing 2 pi r / M shrinks below the agents' width past
M = 30, and keeping the spacing instead makes the ring, and each agent's travel, grow
linearly with M. So the targets become a filled hexagonal lattice round the landmark,
spacing LATTICE_SPACING (the chord of the paper's M = 10 ring, 2 r sin(pi / 10) = 0.309),
the first M points of its hexagonal spiral (ring n holds 6 n points; size ~ sqrt(M)), in a
fixed orientation (no re-anchoring: a lattice has no vertex to anchor on). The agents spawn
uniformly in the disc round the landmark with the lattice's own area (M hexagonal cells),
so that, as in density-scaled coverage, the distance each agent must travel is set by the
spacing and not by M. Its one landmark is always seen.

With landmark lists (``landmark_neighbours``, density-scaled only) the M lattice points
themselves are the landmarks (landmark 0, the centre, is point 0) and each agent senses the
nearest of them as coverage's agents sense theirs, with occupancy where asked: the lattice is
then a shape an agent can fill by a local rule (move to the nearest free point it senses),
which the first M points of a spiral round one landmark are not (where they lie depends on
M). The targets, the reward and success are unchanged; only what an agent sees is."""

import math
import sys
from dataclasses import dataclass

import taichi as ti

from .. import rng
from ..layout import H_DENSITY, H_L, P_TASK_PARAM, blocks, team_size
from .base import Task
from .base import clipped_matched_distance as matched_distance  # noqa: F401 - the reward term (reward_terms) line and formation share


@dataclass(frozen=True)
class FormationParams:
    success_threshold: float = 0.05
    """Success: every matched distance below this."""
    formation_radius: float = 0.5
    """Radius of the M-gon round the landmark."""


@ti.func
def landmark_count(sm: ti.template(), ib: ti.template()) -> ti.i32:
    return ib[H_L]  # 1; with landmark lists the M lattice points (Task.listed_landmarks)


LATTICE_SPACING = 2.0 * 0.5 * math.sin(math.pi / 10.0)  # the paper's M = 10 ring: neighbours 0.309 apart
SQRT3 = math.sqrt(3.0)


def lattice_disc_radius(num_agents: int) -> float:
    """Radius of the disc with the area of M hexagonal cells of the lattice (sqrt(3)/2 s^2 each)."""
    return LATTICE_SPACING * math.sqrt(num_agents * SQRT3 / (2.0 * math.pi))


@ti.func
def spawn_landmarks(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    centre = rng.uniform2(ib, b, -0.5, 0.5)
    blocks.landmarks.store(f, ib, b, 0, centre)
    if ib[H_DENSITY] != 0:  # the agents, re-drawn over the lattice's own disc
        M = team_size(sm, ib)
        radius = LATTICE_SPACING * ti.sqrt(M * SQRT3 / (2.0 * math.pi))
        for i in range(M):
            r = radius * ti.sqrt(rng.uniform(ib, b))
            ang = 2.0 * math.pi * rng.uniform(ib, b)
            blocks.pos.store(f, ib, b, i, centre + r * ti.math.vec2(ti.cos(ang), ti.sin(ang)))
        for k in range(1, ib[H_L]):  # landmark lists: every lattice point is a landmark (no draws)
            blocks.landmarks.store(f, ib, b, k, centre + LATTICE_SPACING * lattice_point(k))


@ti.func
def lattice_point(k: ti.i32) -> ti.math.vec2:
    """Point k of the hexagonal spiral of unit spacing: 0 the centre, then ring n = 1, 2, ...
    (6 n points from the corner n * (-1, 1) in axial coordinates, one side after another)."""
    out = ti.math.vec2(0.0, 0.0)
    if k > 0:
        n = ti.cast((3.0 + ti.sqrt(12.0 * k - 3.0)) / 6.0, ti.i32)
        while 3 * n * (n + 1) + 1 <= k:  # float rounding of the closed form
            n += 1
        while 3 * n * (n - 1) + 1 > k:
            n -= 1
        p = k - (3 * n * (n - 1) + 1)
        side, step = p // n, p % n
        # axial directions d0..d5 = (1, 0), (1, -1), (0, -1), (-1, 0), (-1, 1), (0, 1)
        dq = ti.Vector([1, 1, 0, -1, -1, 0])
        dr = ti.Vector([0, -1, -1, 0, 1, 1])
        q, r = -n, n  # n * d4
        for t in range(side):
            q += n * dq[t]
            r += n * dr[t]
        q += step * dq[side]
        r += step * dr[side]
        out = ti.math.vec2(q + 0.5 * r, 0.5 * SQRT3 * r)
    return out


@ti.func
def place_targets(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    if ib[H_DENSITY] != 0:
        place_lattice(sm, f, ib, b)
    else:
        place_ring(sm, f, ib, b)


@ti.func
def place_lattice(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    centre = blocks.landmarks.load(f, ib, b, 0)
    tgt = blocks.targets.env(ib, b)
    for k in range(M):
        blocks.targets.set2(f, ib, tgt, k, centre + LATTICE_SPACING * lattice_point(k))


@ti.func
def place_ring(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    centre = blocks.landmarks.load(f, ib, b, 0)
    tgt = blocks.targets.env(ib, b)
    theta0 = 1e9
    for i in range(M):
        d = blocks.pos.load(f, ib, b, i) - centre
        ang = ti.atan2(d[1], d[0])
        if ang < 0.0:
            ang += 2.0 * math.pi
        theta0 = ti.min(theta0, ang)
    radius = f[P_TASK_PARAM]
    for k in range(M):
        ang = theta0 + 2.0 * math.pi * k / M
        blocks.targets.set2(f, ib, tgt, k, centre + radius * ti.math.vec2(ti.cos(ang), ti.sin(ang)))


TASK = Task(
    name="formation",
    task_id=1,
    agent_radius=0.05,
    landmark_radius=0.03,
    min_agents=2,
    params_type=FormationParams,
    landmarks=lambda num_agents: 1,
    listed_landmarks=lambda num_agents: num_agents,
    funcs=sys.modules[__name__],
    kernel_param="formation_radius",
    density_scale=True,
    landmark_lists=True,
    reward_terms=("matched_distance",),
    doc="M agents form a regular M-gon round one landmark.",
)
