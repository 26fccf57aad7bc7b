"""Local, exact per-step quantities for large teams (``make(..., assignment="free")``).

The min-sum assignment behind the exact reward is not local (the W1 dual
potential has slope 1 along transport rays, so no bounded search settles it). This mode
computes instead, per env and step, only quantities that are local and exact:

- d_t = min_i |p_i - t_t|, the distance from each target to its nearest agent (DIST; MPE
  simple_spread's reward), found through the agents' cell grid (neighbours.py, side h):
  rings of cells round the target's cell, stopping once the nearest found is no farther
  than the nearest point of the next ring; past RING_LIMIT rings (or below SCAN_BELOW
  agents) every agent is scanned. Written to matched_dist [M] (per target t).
- each agent's own reward's d, into lap_dist [M] (per agent i): the distance to the target
  the matching below gives the agent or, where it has none, to the nearest target the matching
  leaves free (``agent_free``), searched through the targets' cell grid.
- a maximum bipartite matching of agents to targets over the edges |p_i - t_t| <
  success_threshold (strict, as the success rule): augmenting paths by breadth-first
  search from each free target (Kuhn), warm-started from the last step's matching (the
  pairs that are still edges and whose agent is still its target's nearest) and from each
  free target's nearest unmatched agent within the threshold (so that of two agents on one
  target the nearer holds it, which each of them can tell from its occupancy reading). A
  free target with no augmenting path keeps none after later augmentations, so one search
  per free target gives a maximum matching. Edges are found through the agents' grid
  (within ceil(threshold / h) rings of the target's cell).
  assignment [M]: agent i's matched target, -1 where unmatched.

Work arrays: lap_y (target -> agent), lap_cols (the search's queue of targets), lap_pred
(the target an agent was reached from), lap_x (the root whose search last visited the agent).
"""

import taichi as ti

from .layout import H_G, H_GT, H_M, P_CELL, P_SUCCESS, P_TCELL, blocks
from .neighbours import bucket, build, cell_of, ring_cell

INF = 1e30


def target_cell(num_agents: int, arena: float) -> float:
    """The targets' cell side: about two targets per cell for targets spread over the
    spawn square (2 arena)^2; any side gives the same answer, this one a short search."""
    return max(2.0 * arena * (2.0 / max(num_agents, 1)) ** 0.5, 0.02)


RING_LIMIT = 3  # rings of cells searched before every point is scanned
SCAN_BELOW = 32  # below this many points, scan them all (cheaper than the 9 cells' bookkeeping)
SAFE = 0.999  # a ring's distance bound, shrunk for float32 rounding of the cell coordinates
PAD = 1e-3  # a cell's sides, pushed out by this many cells for the same rounding


@ti.func
def nearest(
    f: ti.template(),
    ib: ti.template(),
    px: ti.f32,
    py: ti.f32,
    P: ti.i32,
    n: ti.i32,
    h: ti.f32,
    G: ti.i32,
    S: ti.i32,
    I: ti.i32,
    CELL: ti.i32,
    Y: ti.i32,
) -> ti.f32:
    """The distance from (px, py) to the nearest of the n points f[P + 2k], f[P + 2k + 1],
    through their cell grid (side h, G buckets at S, I, CELL: neighbours.build); with Y >= 0,
    only the points k with ib[Y + k] < 0 count (the targets the matching leaves free). Exact:
    a ring at Chebyshev distance rho holds no point nearer than (rho - 1) h, a cell farther
    than the nearest so far is skipped, and past RING_LIMIT rings every point is scanned
    (INF where no point counts)."""
    best = INF  # squared
    finished = False
    if n >= SCAN_BELOW:
        c = cell_of(px, py, h)
        for rho in range(RING_LIMIT + 2):
            bound = (rho - 1) * h * SAFE
            if rho >= 1 and best <= bound * bound:  # nothing from this ring on is nearer
                finished = True
                break
            if rho <= RING_LIMIT:
                for t in range(ti.max(8 * rho, 1)):
                    q = ring_cell(c, rho, t)
                    # the cell's distance from (px, py), its sides pushed out by PAD cells (rounding)
                    ex = ti.max(ti.max(q[0] * h - px, px - (q[0] + 1) * h) - PAD * h, 0.0)
                    ey = ti.max(ti.max(q[1] * h - py, py - (q[1] + 1) * h) - PAD * h, 0.0)
                    if ex * ex + ey * ey >= best:  # no point of it is nearer than the nearest so far
                        continue
                    g = bucket(q[0], q[1], G)
                    for s in range(ib[S + g], ib[S + g + 1]):
                        j = ib[I + s]
                        if ib[CELL + 2 * j] == q[0] and ib[CELL + 2 * j + 1] == q[1] and (Y < 0 or ib[Y + j] < 0):
                            dx, dy = f[P + 2 * j] - px, f[P + 2 * j + 1] - py
                            best = ti.min(best, dx * dx + dy * dy)
    if not finished:  # few points, or none near: every point
        best = INF
        for j in range(n):
            if Y < 0 or ib[Y + j] < 0:
                dx, dy = f[P + 2 * j] - px, f[P + 2 * j + 1] - py
                best = ti.min(best, dx * dx + dy * dy)
    return ti.sqrt(best)


@ti.func
def _dist(f: ti.template(), ib: ti.template(), P0: ti.i32, i: ti.i32, T0: ti.i32, t: ti.i32) -> ti.f32:
    """|p_i - t_t|, computed as the other assignments compute it."""
    dx, dy = blocks.pos.get2(f, ib, P0, i) - blocks.targets.get2(f, ib, T0, t)
    return ti.sqrt(dx * dx + dy * dy)


@ti.func
def solve(f: ti.template(), ib: ti.template(), b: ti.i32):
    """Env b's d_t (matched_dist), the maximum threshold matching (assignment) and each agent's
    own d (lap_dist: ``agent_free``'s). The
    agents' and the targets' grids must hold the current positions (kernels.nearest_setup
    builds them just before). kernels.step_wide_kernel runs the same pieces with the searches
    parallel over targets and agents."""
    M = ib[H_M]
    for t in range(M):
        target_nearest(f, ib, b, t)
    matching(f, ib, b)
    for i in range(M):
        agent_free(f, ib, b, i)


@ti.func
def targets_grid(f: ti.template(), ib: ti.template(), b: ti.i32):
    TS, TI, TC = blocks.tgrid_start.env(ib, b), blocks.tgrid_items.env(ib, b), blocks.tgrid_cell.env(ib, b)
    build(f, ib, ib[H_M], blocks.targets.env(ib, b), f[P_TCELL], ib[H_GT], TS, TI, TC)


@ti.func
def target_nearest(f: ti.template(), ib: ti.template(), b: ti.i32, t: ti.i32):
    """d_t: target t's distance to its nearest agent, through the agents' grid."""
    GS, GI, GC = blocks.grid_start.env(ib, b), blocks.grid_items.env(ib, b), blocks.grid_cell.env(ib, b)
    tp = blocks.targets.get2(f, ib, blocks.targets.env(ib, b), t)
    d = nearest(f, ib, tp[0], tp[1], blocks.pos.env(ib, b), ib[H_M], f[P_CELL], ib[H_G], GS, GI, GC, -1)
    f[blocks.matched_dist.env(ib, b) + t] = d


@ti.func
def agent_free(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    """Agent i's own d: its distance to the target the threshold matching gives it or, where it
    has none, to the nearest target the matching leaves free. An agent that stands on a held
    target (a duplicate) is then measured to a target it alone can fill, where its nearest
    target would pay it for staying. Needs ``matching``
    first. There is a free target whenever an agent is unmatched (M agents, M targets)."""
    A = blocks.assignment.env(ib, b)
    j = ib[A + i]
    d = 0.0
    if j >= 0:
        d = _dist(f, ib, blocks.pos.env(ib, b), i, blocks.targets.env(ib, b), j)
    else:
        TS, TI, TC = blocks.tgrid_start.env(ib, b), blocks.tgrid_items.env(ib, b), blocks.tgrid_cell.env(ib, b)
        p = blocks.pos.get2(f, ib, blocks.pos.env(ib, b), i)
        T0, Y = blocks.targets.env(ib, b), blocks.lap_y.env(ib, b)
        d = nearest(f, ib, p[0], p[1], T0, ib[H_M], f[P_TCELL], ib[H_GT], TS, TI, TC, Y)
    f[blocks.lap_dist.env(ib, b) + i] = d


@ti.func
def matching(f: ti.template(), ib: ti.template(), b: ti.i32):
    """The maximum threshold matching, from the d_t just computed (a target farther than the
    threshold from every agent has no edge); last step's pairs are kept while the agent is still
    the target's nearest, else a nearer newcomer takes it over. A training signal (rewards and
    success), never an observation: no agent reads it."""
    M = ib[H_M]
    P0, T0 = blocks.pos.env(ib, b), blocks.targets.env(ib, b)
    G, h = ib[H_G], f[P_CELL]
    GS, GI, GC = blocks.grid_start.env(ib, b), blocks.grid_items.env(ib, b), blocks.grid_cell.env(ib, b)
    MD = blocks.matched_dist.env(ib, b)
    thr = f[P_SUCCESS]
    A, Y = blocks.assignment.env(ib, b), blocks.lap_y.env(ib, b)
    Q, PR, ST = blocks.lap_cols.env(ib, b), blocks.lap_pred.env(ib, b), blocks.lap_x.env(ib, b)
    for t in range(M):
        ib[Y + t] = -1
    for i in range(M):  # warm start: last step's pairs that are still edges (read defensively)
        j = ib[A + i]
        ib[ST + i] = -1
        keep = False
        if 0 <= j < M:
            if ib[Y + j] < 0 and f[MD + j] < thr:
                d = _dist(f, ib, P0, i, T0, j)
                # ... and whose agent is still the target's nearest (d_t, the same float32
                # computation): a nearer newcomer takes the target over (the holders' pass below)
                keep = d < thr and d <= f[MD + j]
        if keep:
            ib[Y + j] = i
        else:
            ib[A + i] = -1
    rings = ti.max(1, ti.cast(ti.ceil(thr / h * 1.001), ti.i32))  # an edge is within this many rings
    side = 2 * rings + 1
    # Holders: each target left free takes its nearest unmatched agent within the threshold (ties
    # by index). Of two agents on one target the nearer then holds it, the one whose occupancy
    # reading (the other agent farther than itself) tells it so, and the other is the one
    # assignment="free" pays for leaving: a rule an agent can see, where the incumbent (who came
    # first) is not. The searches below only augment, so the matching stays maximum.
    for t in range(M):
        if ib[Y + t] >= 0 or f[MD + t] >= thr:
            continue
        tp = blocks.targets.get2(f, ib, T0, t)
        c = cell_of(tp[0], tp[1], h)
        best, holder = thr, -1
        for q in range(side * side):
            qx, qy = c[0] + q % side - rings, c[1] + q // side - rings
            g = bucket(qx, qy, G)
            for s in range(ib[GS + g], ib[GS + g + 1]):
                i = ib[GI + s]
                if ib[A + i] < 0 and ib[GC + 2 * i] == qx and ib[GC + 2 * i + 1] == qy:
                    d = _dist(f, ib, P0, i, T0, t)
                    if d < best or (d == best and i < holder):
                        best, holder = d, i
        if holder >= 0:
            ib[Y + t] = holder
            ib[A + holder] = t
    for root in range(M):  # one breadth-first search per free target with an edge
        if ib[Y + root] >= 0 or f[MD + root] >= thr:
            continue
        head, tail, found = 0, 1, -1
        ib[Q] = root
        while head < tail and found < 0:
            u = ib[Q + head]
            head += 1
            tp = blocks.targets.get2(f, ib, T0, u)
            c = cell_of(tp[0], tp[1], h)
            for q in range(side * side):
                if found >= 0:
                    break
                qx, qy = c[0] + q % side - rings, c[1] + q // side - rings
                g = bucket(qx, qy, G)
                for s in range(ib[GS + g], ib[GS + g + 1]):
                    i = ib[GI + s]
                    if ib[ST + i] != root and ib[GC + 2 * i] == qx and ib[GC + 2 * i + 1] == qy:
                        if _dist(f, ib, P0, i, T0, u) < thr:
                            ib[ST + i] = root
                            ib[PR + i] = u
                            if ib[A + i] < 0:
                                found = i
                                break
                            ib[Q + tail] = ib[A + i]
                            tail += 1
        i = found
        while i >= 0:  # flip the path: each agent on it takes the target it was reached from
            u = ib[PR + i]
            prev = ib[Y + u]
            ib[Y + u] = i
            ib[A + i] = u
            i = prev
