"""Exact minimum-cost assignment in a kernel, per environment.

cost[i, j] = |p_i - t_j| (agent i, target j). Two exact methods:
  - M <= SMALL_M: every one of the M! permutations is scored with the costs
    held in registers (unrolled at compile time); at M = 3 that is 6 sums of
    3, far cheaper than any augmenting-path bookkeeping.
  - larger M: shortest augmenting paths (Jonker & Volgenant 1987, "LAPJV", a
    Dijkstra search per unassigned agent), O(n^3) worst case, warm-started from
    the column prices of the environment's previous solve: agents move little
    per step, so most agents' cheapest reduced-cost targets are still distinct
    and only the few left over need a search (2.4 of 10 on average under random
    actions, against about 4 from scratch).

Each environment solves its own M x M problem serially inside the parallel
loop over environments: the large-M cost matrix is cached in the packed buffers;
the solver's work arrays live on the thread's stack for small teams and in the
packed buffers for large ones (one compile for every large M). ``solve`` writes the
assignment and the matched distances d*_i = cost[i, assignment[i]].
"""

import itertools

import taichi as ti

from .layout import (
    H_M,
    blocks,
)

INF = 1e30
SMALL_M = 4  # up to here: enumerate the M! permutations (24 at M = 4)
PERMUTATIONS = {n: tuple(itertools.permutations(range(n))) for n in range(1, SMALL_M + 1)}


STACK_CAP = 64  # work arrays of up to this many entries live on the thread's stack


@ti.func
def solve(cap: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """Writes assignment[b, i] = the target of agent i, minimising the total distance,
    and matched_dist[b, i] = its distance.

    ``sm`` (compile-time) is M when the kernels are specialised for it (then M <=
    SMALL_M: enumeration), else 0; ``cap`` (>= M + 1: see ``capacity``) sizes work arrays
    on the stack when it is at most STACK_CAP; 0 or larger: the work arrays are blocks of
    the buffers (the same compiled code for every M).
    """
    if ti.static(0 < sm <= SMALL_M):
        _enumerate(sm, f, ib, b)
    elif ti.static(0 < cap <= STACK_CAP):
        _solve_stack(f, ib, cap, b)
    else:
        _solve_large(f, ib, b)


@ti.func
def _enumerate(n: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """M = n (compile-time, <= SMALL_M): the best of all n! permutations."""
    P0, T0 = blocks.pos.env(ib, b), blocks.targets.env(ib, b)
    c = ti.Matrix.zero(ti.f32, n, n)  # registers: every index below is static
    for i in ti.static(range(n)):
        for j in ti.static(range(n)):
            dx, dy = blocks.pos.get2(f, ib, P0, i) - blocks.targets.get2(f, ib, T0, j)
            c[i, j] = ti.sqrt(dx * dx + dy * dy)
    perms = ti.static(PERMUTATIONS[n])
    best = INF
    chosen = ti.Vector(perms[0], dt=ti.i32)
    chosen_d = ti.Vector([c[i, perms[0][i]] for i in range(n)], dt=ti.f32)
    for k in ti.static(range(len(perms))):
        d = ti.Vector([c[i, perms[k][i]] for i in range(n)], dt=ti.f32)
        total = d.sum()
        better = total < best  # strict: ties keep the first permutation
        # selects, not branches: which permutation wins is unpredictable
        best = ti.select(better, total, best)
        chosen = ti.select(better, ti.Vector(perms[k], dt=ti.i32), chosen)
        chosen_d = ti.select(better, d, chosen_d)
    A, D = blocks.assignment.env(ib, b), blocks.matched_dist.env(ib, b)
    for i in ti.static(range(n)):
        ib[A + i] = chosen[i]
        f[D + i] = chosen_d[i]


@ti.func
def _solve_large(f: ti.template(), ib: ti.template(), b: ti.i32):
    """Shortest augmenting paths (Jonker & Volgenant 1987, dense LAPJV), warm-started;
    any M >= 1 (M from the header).

    Column prices v, kept per environment between calls; a row's dual is implicit
    (min_j cost[i, j] - v[j]). Start: every agent takes the column of its smallest
    reduced cost if that column is still free, so each assigned row sits at a
    minimum of its reduced costs (LAPJV's invariant, true for *any* prices). If all
    rows got one, that is optimal (complementary slackness) and we are done. With
    last step's prices few rows are left free (agents move little per step);
    each free row finds the shortest augmenting path by Dijkstra over
    the columns, scanning whole levels of equal distance at once, and only the
    settled columns' prices move. Exact for any starting prices.

    The work arrays are blocks of the packed buffers (not the thread's stack), so the
    kernels compile to the same code for every M.
    """
    M = ib[H_M]
    C = blocks.assign_cost.env(ib, b)  # cost[i, j] = |p_i - t_j|, row-major, 0-based
    P0, T0 = blocks.pos.env(ib, b), blocks.targets.env(ib, b)
    V = blocks.prices.env(ib, b)  # f[V + j]: price of column j
    D = blocks.lap_dist.env(ib, b)  # f[D + j]: path length to column j
    X, Y = blocks.lap_x.env(ib, b), blocks.lap_y.env(ib, b)  # ib[X + i]: column of row i, ib[Y + j]: its row (-1: free)
    COLS = blocks.lap_cols.env(ib, b)  # columns: [0, lo) settled, [lo, hi) to scan, [hi, M) to do
    PRED = blocks.lap_pred.env(ib, b)  # the row before column j on the path
    for j in range(M):
        ib[Y + j] = -1
    num_free = 0
    for i in range(M):
        p = blocks.pos.get2(f, ib, P0, i)
        best, arg = INF, 0
        for j in range(M):
            dx, dy = p - blocks.targets.get2(f, ib, T0, j)
            c = ti.sqrt(dx * dx + dy * dy)
            f[C + i * M + j] = c
            reduced = c - f[V + j]
            if reduced < best:
                best, arg = reduced, j
        ib[X + i] = -1
        if ib[Y + arg] < 0:
            ib[X + i] = arg
            ib[Y + arg] = i
        else:
            num_free += 1
    if num_free > 0:
        for free_row in range(M):
            if ib[X + free_row] >= 0:
                continue
            row = C + free_row * M
            for k in range(M):
                ib[COLS + k] = k
                ib[PRED + k] = free_row
                f[D + k] = f[row + k] - f[V + k]
            lo, hi, num_settled, final_j = 0, 0, 0, -1
            mind = 0.0
            while final_j < 0:
                if lo == hi:  # next level: the to-do columns of smallest d move to [lo, hi)
                    num_settled = lo
                    hi = lo + 1
                    mind = f[D + ib[COLS + lo]]
                    for k in range(lo + 1, M):
                        j = ib[COLS + k]
                        if f[D + j] <= mind:
                            if f[D + j] < mind:
                                hi = lo
                                mind = f[D + j]
                            ib[COLS + k] = ib[COLS + hi]
                            ib[COLS + hi] = j
                            hi += 1
                    for k in range(lo, hi):
                        if ib[Y + ib[COLS + k]] < 0:
                            final_j = ib[COLS + k]
                while final_j < 0 and lo != hi:  # scan the level: relax through each column's row
                    j = ib[COLS + lo]
                    lo += 1
                    i = ib[Y + j]
                    row_i = C + i * M
                    h = f[row_i + j] - f[V + j] - mind
                    for k in range(hi, M):
                        jj = ib[COLS + k]
                        reduced = f[row_i + jj] - f[V + jj] - h
                        if reduced < f[D + jj]:
                            f[D + jj] = reduced
                            ib[PRED + jj] = i
                            if reduced == mind:
                                if ib[Y + jj] < 0:
                                    final_j = jj
                                    break
                                ib[COLS + k] = ib[COLS + hi]
                                ib[COLS + hi] = jj
                                hi += 1
            for k in range(num_settled):  # prices of the columns settled before the last level
                j = ib[COLS + k]
                # plain read-modify-write (``+=`` on an ndarray element is an atomic add)
                f[V + j] = f[V + j] + (f[D + j] - mind)
            i, j = -1, final_j
            while i != free_row:  # flip the path
                i = ib[PRED + j]
                ib[Y + j] = i
                nxt = ib[X + i]
                ib[X + i] = j
                j = nxt
        # Prices only ever fall: shift them so that the largest is 0 (a common shift
        # changes no row's order of reduced costs) to keep float32 precision over time.
        top = -INF
        for j in range(M):
            top = ti.max(top, f[V + j])
        for j in range(M):
            f[V + j] = f[V + j] - top
    A, MD = blocks.assignment.env(ib, b), blocks.matched_dist.env(ib, b)
    for i in range(M):
        ib[A + i] = ib[X + i]
        f[MD + i] = f[C + i * M + ib[X + i]]


@ti.func
def _solve_stack(f: ti.template(), ib: ti.template(), cap: ti.template(), b: ti.i32):
    """``_solve_large`` with its work arrays on the thread's stack (``cap`` entries each):
    registers and L1 at small M (8% faster a step at M = 10 than the buffers), but each
    ``cap`` is a compile of its own, and large ones compile for minutes.
    """
    M = ib[H_M]
    C = blocks.assign_cost.env(ib, b)  # cost[i, j] = |p_i - t_j|, row-major, 0-based
    P0, T0, V0 = blocks.pos.env(ib, b), blocks.targets.env(ib, b), blocks.prices.env(ib, b)
    v = ti.Vector.zero(ti.f32, cap)  # column prices
    d = ti.Vector.zero(ti.f32, cap)  # path lengths to each column
    x = ti.Vector.zero(ti.i32, cap)  # x[i]: column of row i (-1: free)
    y = ti.Vector.zero(ti.i32, cap)  # y[j]: row of column j (-1: free)
    cols = ti.Vector.zero(ti.i32, cap)  # [0, lo) settled, [lo, hi) to scan, [hi, M) to do
    pred = ti.Vector.zero(ti.i32, cap)  # the row before column j on the path
    for j in range(M):
        v[j] = f[V0 + j]
        y[j] = -1
    num_free = 0
    for i in range(M):
        p = blocks.pos.get2(f, ib, P0, i)
        best, arg = INF, 0
        for j in range(M):
            dx, dy = p - blocks.targets.get2(f, ib, T0, j)
            c = ti.sqrt(dx * dx + dy * dy)
            f[C + i * M + j] = c
            reduced = c - v[j]
            if reduced < best:
                best, arg = reduced, j
        x[i] = -1
        if y[arg] < 0:
            x[i] = arg
            y[arg] = i
        else:
            num_free += 1
    if num_free > 0:
        for free_row in range(M):
            if x[free_row] >= 0:
                continue
            row = C + free_row * M
            for k in range(M):
                cols[k] = k
                pred[k] = free_row
                d[k] = f[row + k] - v[k]
            lo, hi, num_settled, final_j = 0, 0, 0, -1
            mind = 0.0
            while final_j < 0:
                if lo == hi:  # next level: the to-do columns of smallest d move to [lo, hi)
                    num_settled = lo
                    hi = lo + 1
                    mind = d[cols[lo]]
                    for k in range(lo + 1, M):
                        j = cols[k]
                        if d[j] <= mind:
                            if d[j] < mind:
                                hi = lo
                                mind = d[j]
                            cols[k] = cols[hi]
                            cols[hi] = j
                            hi += 1
                    for k in range(lo, hi):
                        if y[cols[k]] < 0:
                            final_j = cols[k]
                while final_j < 0 and lo != hi:  # scan the level: relax through each column's row
                    j = cols[lo]
                    lo += 1
                    i = y[j]
                    row_i = C + i * M
                    h = f[row_i + j] - v[j] - mind
                    for k in range(hi, M):
                        jj = cols[k]
                        reduced = f[row_i + jj] - v[jj] - h
                        if reduced < d[jj]:
                            d[jj] = reduced
                            pred[jj] = i
                            if reduced == mind:
                                if y[jj] < 0:
                                    final_j = jj
                                    break
                                cols[k] = cols[hi]
                                cols[hi] = jj
                                hi += 1
            for k in range(num_settled):  # prices of the columns settled before the last level
                j = cols[k]
                v[j] += d[j] - mind
            i, j = -1, final_j
            while i != free_row:  # flip the path
                i = pred[j]
                y[j] = i
                x[i], j = j, x[i]
        # Prices only ever fall: shift them so that the largest is 0 (a common shift
        # changes no row's order of reduced costs) to keep float32 precision over time.
        top = -INF
        for j in range(M):
            top = ti.max(top, v[j])
        for j in range(M):
            f[V0 + j] = v[j] - top
    A, D = blocks.assignment.env(ib, b), blocks.matched_dist.env(ib, b)
    for i in range(M):
        ib[A + i] = x[i]
        f[D + i] = f[C + i * M + x[i]]


def capacity(num_agents: int) -> int:
    """Compile-time size of the work arrays: the next power of two >= M + 1."""
    cap = 4
    while cap < num_agents + 1:
        cap *= 2
    return cap
