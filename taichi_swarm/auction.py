"""epsilon-optimal assignment for large teams: a warm-started auction over a cell grid of the
targets (``make(..., assignment="auction")``).

Bertsekas' auction (Gauss-Seidel: one bidder at a time), agents bidding for targets at
cost c_ij = |p_i - t_j| plus the target's price p_j >= 0. An agent bids for its best
target j1 (smallest c + p), raising p_j1 by (second best - best) + eps; the target's
former holder bids next. When every agent holds a target and each holds one within eps
of its best (eps-complementary slackness), the total cost is within M eps of the optimum
(Bertsekas 1988): ``bound = M * eps`` on sum_i d*_i, i.e. eps on the mean matched
distance, stated in docs/SWARM.md and checked against scipy in
tests/test_taichi_swarm/test_assignment_large.py.

Best and second best over *all* targets, found locally: prices are >= 0 (kept so by
shifting the smallest to 0; a common shift changes nobody's preferences), so c + p >= c and
a ring of cells whose nearest point is farther than the second best so far can hold
neither. The search walks rings of cells round the agent's cell until that bound stops it,
or scans every target past RING_LIMIT rings (agents far from every target), so the
answer is exact either way.

Warm start: the last step's prices and assignment; an agent keeps its target if that is
still within eps of its best (agents move little per step), the others bid. A fresh
episode starts cold, with eps scaling (eps from the cell side down to EPS by factors of 8,
every agent bidding again each phase), which keeps the bidding wars of a cold start short.
"""

import taichi as ti

from .layout import (
    H_GL,
    H_GT,
    H_KL,
    H_M,
    H_ROUNDS,
    P_BID_EPS,
    P_EPS,
    P_LCELL,
    P_SENSE,
    P_TCELL,
    blocks,
)
from .neighbours import bucket, build, by_distance, cell_of, nearest_in_grid, ring_cell

INF = 1e30
EPS = 1e-3  # default eps: the total matched distance is within M * EPS of the optimum
# Past this many rings of cells, scan every target. The prices of a random instance spread
# over the whole arena (transport across it: 15 at M = 1000 in the density-scaled 20 x 20),
# and the search must then reach that far anyway; with agents near their targets (a
# trained policy) the prices stay small and one or two rings settle it.
RING_LIMIT = 3
RINGS_FROM = 256  # below this many targets a scan of them all costs less than the rings' 49 cells
SCALING = 8.0  # cold start: eps shrinks by this factor per phase


def target_cell(num_agents: int, arena: float) -> float:
    """The targets' cell side: about two targets per cell for targets spread over the
    spawn square (2 arena)^2; any side gives the same answer, this one a short search."""
    return max(2.0 * arena * (2.0 / max(num_agents, 1)) ** 0.5, 0.02)


@ti.func
def _consider(d: ti.f32, j: ti.i32, best: ti.math.vec3) -> ti.math.vec3:
    """best = (w1, w2, j1): fold in a target j of value d."""
    out = best
    if d < best[0]:
        out = ti.math.vec3(d, best[0], ti.cast(j, ti.f32))
    elif d < best[1]:
        out[1] = d
    return out


@ti.func
def best_two(f: ti.template(), ib: ti.template(), i: ti.i32, b: ti.i32, M: ti.i32) -> ti.math.vec3:
    """(w1, w2, j1): the smallest and second smallest c_ij + p_j over every target j of env
    b, and the target of the smallest (as a float: exact below 2^24 targets)."""
    P0, T0, V = blocks.pos.env(ib, b), blocks.targets.env(ib, b), blocks.prices.env(ib, b)
    G, h = ib[H_GT], f[P_TCELL]
    GS, GI, GC = blocks.tgrid_start.env(ib, b), blocks.tgrid_items.env(ib, b), blocks.tgrid_cell.env(ib, b)
    p = blocks.pos.get2(f, ib, P0, i)
    c = cell_of(p[0], p[1], h)
    best = ti.math.vec3(INF, INF, -1.0)
    finished = False
    for rho in range(RING_LIMIT + 1 if M >= RINGS_FROM else 0):
        if rho >= 2 and (rho - 1) * h >= best[1]:  # every target from this ring on is farther than w2
            finished = True
            break
        cells = ti.max(8 * rho, 1)
        for t in range(cells):
            q = ring_cell(c, rho, t)
            g = bucket(q[0], q[1], G)
            for k in range(ib[GS + g], ib[GS + g + 1]):
                j = ib[GI + k]
                if ib[GC + 2 * j] == q[0] and ib[GC + 2 * j + 1] == q[1]:
                    dx, dy = p - blocks.targets.get2(f, ib, T0, j)
                    best = _consider(ti.sqrt(dx * dx + dy * dy) + f[V + j], j, best)
    if not finished:  # past RING_LIMIT rings (or fewer than two targets): look at them all
        best = ti.math.vec3(INF, INF, -1.0)
        for j in range(M):
            dx, dy = p - blocks.targets.get2(f, ib, T0, j)
            best = _consider(ti.sqrt(dx * dx + dy * dy) + f[V + j], j, best)
    return best


@ti.func
def _bid(
    f: ti.template(),
    ib: ti.template(),
    b: ti.i32,
    eps: ti.f32,
    num_free: ti.i32,
    V: ti.i32,
    X: ti.i32,
    Y: ti.i32,
    FREE: ti.i32,
    best: ti.template(),
    M: ti.i32,
):
    """Gauss-Seidel bidding until the stack FREE[:num_free] of agents still to bid is empty: each
    bids for its best target (``best(f, ib, b, i, M)`` -> (w1, w2, j1); j1 < 0: it stays out),
    raising that target's price V by w2 - w1 + eps; the target's former holder (Y: target ->
    agent) bids next (X: agent -> target)."""
    top = num_free
    while top > 0:
        top -= 1
        i = ib[FREE + top]
        prev = _place_bid(f, ib, i, best(f, ib, b, i, M), eps, V, X, Y)
        if prev >= 0:
            ib[FREE + top] = prev
            top += 1


@ti.func
def _place_bid(f: ti.template(), ib: ti.template(), i: ti.i32, w: ti.math.vec3, eps: ti.f32, V, X, Y) -> ti.i32:
    """Agent i's bid, given its (w1, w2, j1) (j1 < 0: it stays out, no bid): target j1's price V
    raised by w2 - w1 + eps, j1 held by i (Y: target -> agent, X: agent -> target). Returns the
    agent it outbid, now holding nothing (-1: none)."""
    j = ti.cast(w[2], ti.i32)
    prev = -1
    if j >= 0:
        raise_by = eps
        if w[1] < INF:
            raise_by = w[1] - w[0] + eps
        f[V + j] = f[V + j] + raise_by
        prev = ib[Y + j]
        ib[Y + j] = i
        ib[X + i] = j
        if prev >= 0:
            ib[X + prev] = -1
    return prev


@ti.func
def _global_best(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, M: ti.i32) -> ti.math.vec3:
    """``best_two`` in ``_bid``'s form."""
    return best_two(f, ib, i, b, M)


@ti.func
def _bid_until_assigned(f: ti.template(), ib: ti.template(), b: ti.i32, M: ti.i32, eps: ti.f32, num_free: ti.i32):
    """Auction rounds until the stack of free agents (lap_cols) is empty."""
    V, X, Y = blocks.prices.env(ib, b), blocks.lap_x.env(ib, b), blocks.lap_y.env(ib, b)
    _bid(f, ib, b, eps, num_free, V, X, Y, blocks.lap_cols.env(ib, b), _global_best, M)


@ti.func
def solve(f: ti.template(), ib: ti.template(), b: ti.i32):
    """Writes assignment[b, i] and matched_dist[b, i] = |p_i - t_assignment[i]|, the total
    within M * eps of the optimum."""
    M = ib[H_M]
    P0, T0, V = blocks.pos.env(ib, b), blocks.targets.env(ib, b), blocks.prices.env(ib, b)
    X, Y, FREE = blocks.lap_x.env(ib, b), blocks.lap_y.env(ib, b), blocks.lap_cols.env(ib, b)
    G = ib[H_GT]
    h = f[P_TCELL]
    GS, GI, GC = blocks.tgrid_start.env(ib, b), blocks.tgrid_items.env(ib, b), blocks.tgrid_cell.env(ib, b)
    build(f, ib, M, T0, h, G, GS, GI, GC)
    eps_final = f[P_EPS]
    if ib[blocks.step.env(ib, b)] == 0:  # a fresh episode: cold start, eps scaling
        for j in range(M):
            f[V + j] = 0.0
        eps = ti.max(h, eps_final)
        while True:
            for j in range(M):
                ib[Y + j] = -1
            for i in range(M):
                ib[X + i] = -1
                ib[FREE + i] = M - 1 - i  # agent 0 bids first
            _bid_until_assigned(f, ib, b, M, eps, M)
            if eps <= eps_final:
                break
            eps = ti.max(eps / SCALING, eps_final)
    else:  # warm: keep the agents still within eps of their best
        for j in range(M):
            ib[Y + j] = -1
        for i in range(M):  # last step's assignment, read defensively (any array works)
            j = ib[X + i]
            if 0 <= j < M:
                if ib[Y + j] < 0:
                    ib[Y + j] = i
                else:
                    ib[X + i] = -1
            else:
                ib[X + i] = -1
        num_free = 0
        for i in range(M):
            j = ib[X + i]
            keep = False
            if j >= 0:
                dx, dy = blocks.pos.get2(f, ib, P0, i) - blocks.targets.get2(f, ib, T0, j)
                keep = ti.sqrt(dx * dx + dy * dy) + f[V + j] <= best_two(f, ib, i, b, M)[0] + eps_final
            if not keep:
                if j >= 0:
                    ib[Y + j] = -1
                ib[X + i] = -1
                ib[FREE + num_free] = i
                num_free += 1
        # reversed: agents bid in increasing index (the stack pops from the top)
        for k in range(num_free // 2):
            a = ib[FREE + k]
            ib[FREE + k] = ib[FREE + num_free - 1 - k]
            ib[FREE + num_free - 1 - k] = a
        _bid_until_assigned(f, ib, b, M, eps_final, num_free)
    low = INF  # shift the prices so that the smallest is 0 (they only rise)
    for j in range(M):
        low = ti.min(low, f[V + j])
    for j in range(M):
        f[V + j] = f[V + j] - low
    A, MD = blocks.assignment.env(ib, b), blocks.matched_dist.env(ib, b)
    for i in range(M):
        j = ib[X + i]
        ib[A + i] = j
        dx, dy = blocks.pos.get2(f, ib, P0, i) - blocks.targets.get2(f, ib, T0, j)
        f[MD + i] = ti.sqrt(dx * dx + dy * dy)


# ---------------------------------------------------------------------------------------------
# The agents' own auction (landmark_order="auction"): each agent bids only for the landmarks it
# senses, and the landmark it wins is what it sees.
#
# The same bidding as ``solve``, with three differences, all for locality: an agent's targets
# are its KL nearest landmarks within sense_radius (``candidates``), not every target; it may
# stay out (a dummy target of cost OUT x sense_radius, which also bounds every price, so the
# bidding ends however crowded a region is); and it is solved afresh every step from the
# current positions, in one phase at LOCAL_EPS, so the answer depends on this step's positions
# alone. What an agent needs is each sensed landmark's price and whether it outbid the holder: a
# price kept at the landmark, as a beacon would keep it. Run to the end each step, the result
# is the min-sum matching of agents to the landmarks they sense (staying out allowed), within
# LOCAL_EPS per agent of the optimum (tests/test_taichi_swarm/test_local_auction.py).
#
# With a budget of bid rounds per step (auction_rounds = R, header H_ROUNDS), the auction is
# what a radio allows: R exchanges with the beacons a step. It then carries over from step to
# step (prices and holders kept at the landmarks, reset with the episode): at each step an
# agent keeps its landmark while it still senses it and no other option is better by more than
# HOLD_SLACK increments, else lets it go, and a landmark let go drops its price to 0. Then up to
# R rounds in which every agent that holds nothing bids once (``_bid_rounds``), raising prices by
# at least the increment (ROUND_EPS: 50 times LOCAL_EPS, so that a bidding war ends in few
# rounds). Every holder stays within HOLD_SLACK increments of its best (one where it won this
# step), every agent that stays out has no better option, and every landmark nobody holds is at
# price 0; so once the rounds stop finding bids the matching is within HOLD_SLACK increments per
# agent of the optimum (one from an episode's start, agents unmoved); until then, an agent still
# bidding reads claim-zero lists.
OUT = 2.0  # staying out costs this many sense radii: more than any sensed landmark's distance
LOCAL_EPS = 0.01  # the local auction's final eps: each agent within 0.01 of its best
# With a budget of rounds, each bid raises a price by at least the increment ROUND_EPS
# (header P_BID_EPS). A bidding war's rounds grow as the prices it must
# climb (3-5 at M = 100 from a random start) over the increment, and a policy needs its landmark
# within its first steps (docs/SWARM.md measures S% against both). The matching is then within
# the increment per agent of the optimum: at most that much more travel for an agent.
ROUND_EPS = 0.5
# A holder keeps its landmark until another option is better by HOLD_SLACK increments: more than
# a fresh winner's one (it won at its second best plus the increment), with room for a step's
# motion; each release reopens the bidding for the landmark at price 0.
HOLD_SLACK = 2.0


@ti.func
def candidates(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    """Agent i's targets in the local auction: its KL nearest landmarks within sense_radius,
    nearest first (bid_cand, their squared distances in bid_d2, how many in bid_count)."""
    P0, LM = blocks.pos.env(ib, b), blocks.landmarks.env(ib, b)
    GS, GI, GC = blocks.lgrid_start.env(ib, b), blocks.lgrid_items.env(ib, b), blocks.lgrid_cell.env(ib, b)
    p = blocks.pos.get2(f, ib, P0, i)
    d2 = blocks.bid_d2.row(ib, blocks.bid_d2.env(ib, b), i)
    idx = blocks.bid_cand.row(ib, blocks.bid_cand.env(ib, b), i)
    found = nearest_in_grid(
        f, ib, p[0], p[1], -1, LM, f[P_SENSE] * f[P_SENSE], f[P_LCELL], ib[H_GL], GS, GI, GC, d2, idx, ib[H_KL],
        by_distance, ti.math.ivec2(0, 0),
    )  # fmt: skip
    ib[blocks.bid_count.env(ib, b) + i] = found[0]


@ti.func
def _local_best(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, M: ti.i32) -> ti.math.vec3:
    """(w1, w2, j1) over agent i's candidates and staying out (cost OUT x sense_radius; j1 = -1
    when best). ``M`` is unused: ``_bid`` passes every ``best`` the team size."""
    out = OUT * f[P_SENSE]
    V = blocks.bid_price.env(ib, b)
    d2 = blocks.bid_d2.row(ib, blocks.bid_d2.env(ib, b), i)
    idx = blocks.bid_cand.row(ib, blocks.bid_cand.env(ib, b), i)
    best = ti.math.vec3(out, out, -1.0)
    for k in range(ib[blocks.bid_count.env(ib, b) + i]):
        j = ib[idx + k]
        best = _consider(ti.sqrt(f[d2 + k]) + f[V + j], j, best)
    return best


@ti.func
def local_solve(f: ti.template(), ib: ti.template(), b: ti.i32, M: ti.i32, L: ti.i32):
    """The local auction of env b: bid_won[i], the landmark agent i wins (-1: none), by
    Gauss-Seidel bidding to the end (bid_price, bid_holder: landmark -> agent, bid_stack:
    the agents still to bid), or with a budget of rounds (H_ROUNDS > 0) by ``_bid_rounds``
    from the last step's state."""
    V, Y, FREE = blocks.bid_price.env(ib, b), blocks.bid_holder.env(ib, b), blocks.bid_stack.env(ib, b)
    X = blocks.bid_won.env(ib, b)
    rounds = ib[H_ROUNDS]
    if rounds == 0 or ib[blocks.step.env(ib, b)] == 0:  # afresh: every step, or a budget's new episode
        for j in range(L):
            f[V + j] = 0.0
            ib[Y + j] = -1
        for i in range(M):
            ib[X + i] = -1
    if rounds == 0:
        for i in range(M):
            ib[FREE + i] = M - 1 - i  # agent 0 bids first
        # One phase at the final eps, no eps scaling: a landmark once bid for stays held, so every
        # landmark left unheld keeps price 0, which eps-optimality needs when some agents stay out
        # (scaling restarts the bidding on raised prices and can leave a priced landmark unheld).
        _bid(f, ib, b, LOCAL_EPS, M, V, X, Y, FREE, _local_best, M)
    else:
        _release_stale(f, ib, b, M)
        _bid_rounds(f, ib, b, M, rounds)


@ti.func
def _release_stale(f: ti.template(), ib: ti.template(), b: ti.i32, M: ti.i32):
    """A budget's warm start: agent i keeps the landmark it holds while it senses it (among its
    candidates) within HOLD_SLACK increments of its best; else it lets it go, and the landmark,
    held by nobody, drops its price to 0 (an unheld landmark at a price would break
    eps-optimality for the agents that stay out). A price dropped can put another holder past
    the slack, so the passes repeat until one releases nothing (each releases a holder or ends:
    at most M + 1 passes)."""
    V, Y, X = blocks.bid_price.env(ib, b), blocks.bid_holder.env(ib, b), blocks.bid_won.env(ib, b)
    D2, CAND, COUNT = blocks.bid_d2.env(ib, b), blocks.bid_cand.env(ib, b), blocks.bid_count.env(ib, b)
    slack = HOLD_SLACK * f[P_BID_EPS]
    released = 1
    while released > 0:
        released = 0
        for i in range(M):
            j = ib[X + i]
            if j >= 0:
                d2, idx = blocks.bid_d2.row(ib, D2, i), blocks.bid_cand.row(ib, CAND, i)
                sensed = False
                value = 0.0
                for k in range(ib[COUNT + i]):
                    if ib[idx + k] == j:
                        sensed = True
                        value = ti.sqrt(f[d2 + k]) + f[V + j]
                if not sensed or value > _local_best(f, ib, b, i, M)[0] + slack:
                    ib[X + i] = -1
                    ib[Y + j] = -1
                    f[V + j] = 0.0
                    released += 1


@ti.func
def _bid_rounds(f: ti.template(), ib: ti.template(), b: ti.i32, M: ti.i32, rounds: ti.i32):
    """Up to ``rounds`` rounds (fewer once nobody bids), in each of which every agent that holds
    no landmark bids once, in index order, at the prices the landmarks hold when it bids (as a
    beacon answers one bid at a time): its best candidate's price raised by its second best minus
    its best plus the increment P_BID_EPS (staying out: no bid). An agent it outbids holds nothing and bids
    when its turn comes, in this round if it comes later in the order, else in the next."""
    V, Y, X = blocks.bid_price.env(ib, b), blocks.bid_holder.env(ib, b), blocks.bid_won.env(ib, b)
    eps = f[P_BID_EPS]
    for _ in range(rounds):
        bids = 0
        for i in range(M):
            if ib[X + i] < 0:
                w = _local_best(f, ib, b, i, M)
                bids += ti.cast(w[2] >= 0.0, ti.i32)
                _place_bid(f, ib, i, w, eps, V, X, Y)
        if bids == 0:
            break
