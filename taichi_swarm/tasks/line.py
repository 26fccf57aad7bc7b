"""Line: M agents spread evenly on the segment between two landmarks (docs/PAPER.md s.2).

Landmark 0 uniform in [-0.25, 0.25]^2, landmark 1 at distance ``line_length`` in a
random direction (turned by 5 degrees until it lies inside the arena); the targets
are fixed for the episode: t_k = l0 + k (l1 - l0) / (M - 1); reward
-mean_i clip(d*_i, 0, 2).

``scale="density"``: keeping the paper's spacing on one segment makes it grow linearly with M,
beyond any agent's reach in 50 steps. So the targets become ``rows(M)`` = round(sqrt(M / 10))
parallel segments (at least one), line_length apart, each of ``per_row(M)`` = ceil(M / rows)
targets at the paper's M = 10 spacing line_length / 9, filled row by row (the last may be
short): a block of side ~ sqrt(M). Landmark 0 is the start and landmark 1 the end of the
first row (so they give the direction; the block is centred on a point uniform in
[-0.25, 0.25]^2, in a uniformly random direction), and the agents spawn uniformly over the
block's footprint (half a spacing / half a row gap round it), so each agent's travel is
bounded by the row gap and the spacing, not by M. Its two landmarks are always seen.

With landmark lists (``landmark_neighbours``, density-scaled only) every target is a landmark,
landmark k target k (so landmark 1 is the first row's second target, not its end), and each
agent senses the nearest of them, as coverage's agents sense theirs: the rows become points an
agent can fill by a local rule, as formation's lattice does (formation.py). Landmark k is target
k because the kernels read a listed landmark's holder in the matching by its index
(``kernels.claimed``). The targets, reward and success are unchanged; only what an agent sees
is."""

import math
import sys
from dataclasses import dataclass

import taichi as ti

from .. import rng
from ..layout import H_DENSITY, H_L, P_TASK_PARAM, blocks, team_size
from .base import Task
from .base import clipped_matched_distance as matched_distance  # noqa: F401 - the reward term (reward_terms) line and formation share

TURN = 5.0 * math.pi / 180.0  # turn the heading by 5 degrees until l1 fits


@dataclass(frozen=True)
class LineParams:
    success_threshold: float = 0.05
    """Success: every matched distance below this."""
    line_length: float = 1.25
    """Distance between the two landmarks."""


@ti.func
def landmark_count(sm: ti.template(), ib: ti.template()) -> ti.i32:
    return ib[H_L]  # 2; with landmark lists the M targets (Task.listed_landmarks)


PAPER_GAPS = 9  # the paper's M = 10 line: 9 gaps of line_length / 9


def rows(num_agents: int) -> int:
    """Parallel segments of the density-scaled line (the kernels' ``_rows``)."""
    return max(1, int(math.floor(math.sqrt(num_agents / 10.0) + 0.5)))


def per_row(num_agents: int) -> int:
    return -(-num_agents // rows(num_agents))


@ti.func
def _rows(M: ti.i32) -> ti.i32:
    return ti.max(1, ti.cast(ti.floor(ti.sqrt(M / 10.0) + 0.5), ti.i32))


@ti.func
def spawn_landmarks(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    if ib[H_DENSITY] != 0:
        spawn_rows(sm, f, ib, b)
    else:
        spawn_segment(sm, f, ib, b)


@ti.func
def spawn_rows(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    n = _rows(M)
    m = (M + n - 1) // n
    gap = f[P_TASK_PARAM]
    spacing = gap / PAPER_GAPS
    centre = rng.uniform2(ib, b, -0.25, 0.25)
    theta = 2.0 * math.pi * rng.uniform(ib, b)
    along = ti.math.vec2(ti.cos(theta), ti.sin(theta))
    across = ti.math.vec2(-along[1], along[0])
    l0 = centre - 0.5 * (m - 1) * spacing * along - 0.5 * (n - 1) * gap * across
    for i in range(M):  # the agents, re-drawn over the block's footprint
        a = -0.5 * spacing + (m * spacing) * rng.uniform(ib, b)
        c = -0.5 * gap + (n * gap) * rng.uniform(ib, b)
        blocks.pos.store(f, ib, b, i, l0 + a * along + c * across)
    blocks.landmarks.store(f, ib, b, 0, l0)
    if ib[H_L] == 2:  # the first row's ends
        blocks.landmarks.store(f, ib, b, 1, l0 + (m - 1) * spacing * along)
    else:  # landmark lists: every target, landmark k target k (no draws)
        for k in range(1, ib[H_L]):
            blocks.landmarks.store(f, ib, b, k, l0 + (k % m) * spacing * along + (k // m) * gap * across)


@ti.func
def spawn_segment(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    length = f[P_TASK_PARAM]
    l0 = rng.uniform2(ib, b, -0.25, 0.25)
    theta = 2.0 * math.pi * rng.uniform(ib, b)
    l1 = l0 + length * ti.math.vec2(ti.cos(theta), ti.sin(theta))
    turns = 0
    while (ti.abs(l1[0]) >= 1.0 or ti.abs(l1[1]) >= 1.0) and turns < 72:
        theta += TURN
        l1 = l0 + length * ti.math.vec2(ti.cos(theta), ti.sin(theta))
        turns += 1
    blocks.landmarks.store(f, ib, b, 0, l0)
    blocks.landmarks.store(f, ib, b, 1, l1)


@ti.func
def place_targets(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    M = team_size(sm, ib)
    tgt = blocks.targets.env(ib, b)
    l0 = blocks.landmarks.load(f, ib, b, 0)
    l1 = blocks.landmarks.load(f, ib, b, 1)
    if ib[H_L] != 2:  # landmark lists: the targets are the landmarks (spawn_rows)
        for k in range(M):
            blocks.targets.set2(f, ib, tgt, k, blocks.landmarks.load(f, ib, b, k))
    elif ib[H_DENSITY] != 0:
        n = _rows(M)
        m = (M + n - 1) // n
        step = (l1 - l0) / (m - 1)
        across = ti.math.vec2(-step[1], step[0]) * (f[P_TASK_PARAM] / step.norm())
        for k in range(M):
            blocks.targets.set2(f, ib, tgt, k, l0 + (k % m) * step + (k // m) * across)
    else:
        for k in range(M):
            blocks.targets.set2(f, ib, tgt, k, l0 + (l1 - l0) * (k / (M - 1)))


TASK = Task(
    name="line",
    task_id=2,
    agent_radius=0.03,
    landmark_radius=0.02,
    min_agents=2,
    params_type=LineParams,
    landmarks=lambda num_agents: 2,
    listed_landmarks=lambda num_agents: num_agents,
    funcs=sys.modules[__name__],
    kernel_param="line_length",
    density_scale=True,
    landmark_lists=True,
    reward_terms=("matched_distance",),
    doc="M agents spread evenly on the segment between two landmarks.",
)
