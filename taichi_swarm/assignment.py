"""Exact minimum-cost assignment in a kernel, per environment.

cost[i, j] = |p_i - t_j| (agent i, target j). Two exact methods:
  - M <= SMALL_M: every one of the M! permutations is scored with the costs
    held in registers (unrolled at compile time); at M = 3 that is 6 sums of
    3, far cheaper than any augmenting-path bookkeeping.
  - larger M: the O(n^3) Hungarian method with potentials (Kuhn 1955;
    Jonker-Volgenant shortest augmenting paths, in the compact form of e-maxx
    "Hungarian algorithm"), after an exact shortcut (every agent's nearest
    target distinct -> that is the optimum) and a column-reduction start.

Each environment solves its own M x M problem serially inside the parallel
loop over environments: the Hungarian cost matrix is cached in the packed
buffers, its work arrays live on the thread's stack. ``solve`` writes the
assignment and the matched distances d*_i = cost[i, assignment[i]].
"""

import itertools

import taichi as ti

from .layout import (
    H_M,
    O_ASSIGN,
    O_HU_COST,
    O_MATCHED,
    O_POS,
    O_TGT,
)

INF = 1e30
SMALL_M = 4  # up to here: enumerate the M! permutations (24 at M = 4)
PERMUTATIONS = {n: tuple(itertools.permutations(range(n))) for n in range(1, SMALL_M + 1)}


@ti.func
def solve(f: ti.template(), ib: ti.template(), cap: ti.template(), b: ti.i32):
    """Writes assignment[b, i] = the target of agent i, minimising the total distance,
    and matched_dist[b, i] = its distance.

    ``cap`` (compile-time, >= M + 1: see ``capacity``) sizes the per-thread work
    arrays and selects which team sizes are solved by enumeration.
    """
    M = ib[H_M]
    if ti.static(cap == 4):  # M in 1..3
        if M == 3:
            _enumerate(3, f, ib, b)
        elif M == 2:
            _enumerate(2, f, ib, b)
        else:
            _enumerate(1, f, ib, b)
    elif ti.static(cap == 8 and SMALL_M >= 4):  # M in 4..7
        if M == 4:
            _enumerate(4, f, ib, b)
        else:
            _solve_large(f, ib, cap, b)
    else:
        _solve_large(f, ib, cap, b)


@ti.func
def _enumerate(n: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """M = n (compile-time, <= SMALL_M): the best of all n! permutations."""
    P0, T0 = ib[O_POS] + b * n * 2, ib[O_TGT] + b * n * 2
    c = ti.Matrix.zero(ti.f32, n, n)  # registers: every index below is static
    for i in ti.static(range(n)):
        for j in ti.static(range(n)):
            dx, dy = f[P0 + 2 * i] - f[T0 + 2 * j], f[P0 + 2 * i + 1] - f[T0 + 2 * j + 1]
            c[i, j] = ti.sqrt(dx * dx + dy * dy)
    perms = ti.static(PERMUTATIONS[n])
    best = INF
    chosen = ti.Vector(perms[0], dt=ti.i32)
    chosen_d = ti.Vector([c[i, perms[0][i]] for i in range(n)], dt=ti.f32)
    for k in ti.static(range(len(perms))):
        d = ti.Vector([c[i, perms[k][i]] for i in range(n)], dt=ti.f32)
        total = d.sum()
        if total < best:  # strict: ties keep the first permutation
            best = total
            chosen = ti.Vector(perms[k], dt=ti.i32)
            chosen_d = d
    A, D = ib[O_ASSIGN] + b * n, ib[O_MATCHED] + b * n
    for i in ti.static(range(n)):
        ib[A + i] = chosen[i]
        f[D + i] = chosen_d[i]


@ti.func
def _solve_large(f: ti.template(), ib: ti.template(), cap: ti.template(), b: ti.i32):
    M = ib[H_M]
    C = ib[O_HU_COST] + b * M * M  # cost[i, j] = |p_i - t_j|, row-major, 0-based
    P0, T0 = ib[O_POS] + b * M * 2, ib[O_TGT] + b * M * 2
    distinct_row_minima = True  # then "each agent takes its closest target" is optimal
    taken = ti.Vector.zero(ti.i32, cap)
    best_col = ti.Vector.zero(ti.i32, cap)
    for i in range(M):
        px, py = f[P0 + 2 * i], f[P0 + 2 * i + 1]
        best, arg = INF, 0
        for j in range(M):
            dx, dy = px - f[T0 + 2 * j], py - f[T0 + 2 * j + 1]
            c = ti.sqrt(dx * dx + dy * dy)
            f[C + i * M + j] = c
            if c < best:
                best, arg = c, j
        best_col[i] = arg
        if taken[arg] != 0:
            distinct_row_minima = False
        taken[arg] = 1
    A = ib[O_ASSIGN] + b * M
    if distinct_row_minima:
        for i in range(M):
            ib[A + i] = best_col[i]
    else:
        _hungarian(f, ib, cap, b, C)
    D = ib[O_MATCHED] + b * M
    for i in range(M):
        f[D + i] = f[C + i * M + ib[A + i]]


@ti.func
def _hungarian(f: ti.template(), ib: ti.template(), cap: ti.template(), b: ti.i32, C: ti.i32):
    M = ib[H_M]
    # 1-based work arrays; index 0 is the algorithm's virtual row/column
    u = ti.Vector.zero(ti.f32, cap)
    v = ti.Vector.zero(ti.f32, cap)
    minv = ti.Vector.zero(ti.f32, cap)
    p = ti.Vector.zero(ti.i32, cap)
    way = ti.Vector.zero(ti.i32, cap)
    used = ti.Vector.zero(ti.i32, cap)
    # Column reduction (Jonker & Volgenant 1987): v[j] = min_i cost[i, j] keeps the duals
    # feasible (u = 0) and makes each column's cheapest edge tight, so every column can take
    # its cheapest row if that row is still free; only the rows left over need augmenting.
    row_taken = ti.Vector.zero(ti.i32, cap)
    for j in range(1, M + 1):
        best, arg = INF, 1
        for i in range(1, M + 1):
            c = f[C + (i - 1) * M + j - 1]
            if c < best:
                best, arg = c, i
        v[j] = best
        if row_taken[arg] == 0:
            p[j] = arg
            row_taken[arg] = 1
    for i in range(1, M + 1):
        if row_taken[i] != 0:
            continue
        p[0] = i
        j0 = 0
        for j in range(M + 1):
            minv[j] = INF
            used[j] = 0
        while True:
            used[j0] = 1
            i0 = p[j0]
            u_i0 = u[i0]
            row = C + (i0 - 1) * M - 1  # f[row + j] = cost[i0 - 1, j - 1]
            delta = INF
            j1 = 0
            first_unused = 0
            for j in range(1, M + 1):
                if used[j] == 0:
                    if first_unused == 0:
                        first_unused = j
                    cur = f[row + j] - u_i0 - v[j]
                    if cur < minv[j]:
                        minv[j] = cur
                        way[j] = j0
                    if minv[j] < delta:
                        delta = minv[j]
                        j1 = j
            if j1 == 0:  # only non-finite costs left (NaN positions): still terminate
                j1 = first_unused
                delta = 0.0
            for j in range(M + 1):
                if used[j] != 0:
                    u[p[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if p[j0] == 0:
                break
        while j0 != 0:  # unwind the augmenting path
            j1 = way[j0]
            p[j0] = p[j1]
            j0 = j1
    for j in range(1, M + 1):
        ib[ib[O_ASSIGN] + b * M + p[j] - 1] = j - 1


def capacity(num_agents: int) -> int:
    """Compile-time size of the work arrays: the next power of two >= M + 1."""
    cap = 4
    while cap < num_agents + 1:
        cap *= 2
    return cap
