"""Neighbour lists through a uniform cell grid, per environment (``make(..., neighbours=K)``).

Every step each environment sorts its agents into square cells of side h (h >= the
comm radius under "rc" and >= the contact reach 2 r + 20 margins, so that everything an
agent hears or touches lies in the 3 x 3 cells round its own). The cells are hashed
into G buckets (G a power of two >= 2 M): agents may wander anywhere, and the memory
stays O(M). A counting sort builds, in one pass each, the bucket counts, their prefix
sums and the bucket-sorted agent list (stable: increasing agent index per bucket).
An agent's own integer cell is stored beside it, so a query for cell (qx, qy) keeps only
the agents of that very cell (two cells hashed to one bucket are never counted twice).

Queries are runtime loops over the 9 cells (not unrolled: the kernels compile to the same
code for every M). The lists hold the K nearest, nearest first, ordered by (squared
distance, index) so that ties come out the same whatever order the cells are visited in.
Landmarks (``landmark_neighbours=KL``) get a grid of their own with side >= sense_radius.
"""

import taichi as ti

HASH_X, HASH_Y = 73856093, 19349663  # Teschner et al. 2003, spatial hashing primes
CELL_LIMIT = 1e8  # cell coordinates are clamped here (int32-safe; far outside any arena)


def buckets(count: int) -> int:
    """G: the power of two >= 2 * count (at least 16)."""
    g = 16
    while g < 2 * count:
        g *= 2
    return g


def cell_side(radius: float) -> float:
    """A side a hair above ``radius``: float32 rounding of x / h can then never put two
    points within ``radius`` of each other two cells apart."""
    return radius * (1.0 + 1e-5) + 1e-6


@ti.func
def cell_of(x: ti.f32, y: ti.f32, h: ti.f32) -> ti.math.ivec2:
    cx = ti.cast(ti.floor(ti.math.clamp(x / h, -CELL_LIMIT, CELL_LIMIT)), ti.i32)
    cy = ti.cast(ti.floor(ti.math.clamp(y / h, -CELL_LIMIT, CELL_LIMIT)), ti.i32)
    return ti.math.ivec2(cx, cy)


@ti.func
def bucket(cx: ti.i32, cy: ti.i32, G: ti.i32) -> ti.i32:
    hx = ti.cast(cx, ti.u32) * ti.u32(HASH_X)
    hy = ti.cast(cy, ti.u32) * ti.u32(HASH_Y)
    return ti.cast((hx ^ hy) & ti.cast(G - 1, ti.u32), ti.i32)


@ti.func
def build(
    f: ti.template(), ib: ti.template(), n: ti.i32, P: ti.i32, h: ti.f32, G: ti.i32, S: ti.i32, I: ti.i32, CELL: ti.i32
):
    """Counting sort of the n points f[P + 2k], f[P + 2k + 1] into G buckets of cells of
    side h: afterwards bucket g holds ib[I + ib[S + g] : I + ib[S + g + 1]] (increasing
    point index) and ib[CELL + 2k : CELL + 2k + 2] is point k's cell."""
    for g in range(G + 1):
        ib[S + g] = 0
    for k in range(n):  # counts, one slot up: ib[S + g + 1] = size of bucket g
        c = cell_of(f[P + 2 * k], f[P + 2 * k + 1], h)
        ib[CELL + 2 * k] = c[0]
        ib[CELL + 2 * k + 1] = c[1]
        g = bucket(c[0], c[1], G) + 1
        ib[S + g] = ib[S + g] + 1  # plain read-modify-write: ``+=`` would be an atomic
    for g in range(G):  # prefix sums: ib[S + g] = start of bucket g
        ib[S + g + 1] = ib[S + g + 1] + ib[S + g]
    for k in range(n):  # scatter, using the starts as cursors (they end at each bucket's end)
        g = bucket(ib[CELL + 2 * k], ib[CELL + 2 * k + 1], G)
        ib[I + ib[S + g]] = k
        ib[S + g] = ib[S + g] + 1
    for t in range(G):  # the cursors now hold the ends: shift them back to the starts
        g = G - t
        ib[S + g] = ib[S + g - 1]
    ib[S] = 0


@ti.func
def before(d2: ti.f32, j: ti.i32, other_d2: ti.f32, other_j: ti.i32) -> ti.i32:
    """(d2, j) < (other_d2, other_j), lexicographically: nearest first, ties by index."""
    return d2 < other_d2 or (d2 == other_d2 and j < other_j)


@ti.func
def insert(
    f: ti.template(), ib: ti.template(), D2: ti.i32, IDX: ti.i32, kept: ti.i32, K: ti.i32, d2: ti.f32, j: ti.i32
) -> ti.i32:
    """Insert (d2, j) into the sorted list ib[IDX : IDX + kept] (squared distances at
    f[D2 ...]) of at most K entries; returns the new length."""
    pos = kept
    grown = kept
    if kept < K:
        grown = kept + 1
    elif before(d2, j, f[D2 + K - 1], ib[IDX + K - 1]):
        pos = K - 1
    else:
        pos = -1
    if pos >= 0:
        while pos > 0 and before(d2, j, f[D2 + pos - 1], ib[IDX + pos - 1]):
            f[D2 + pos] = f[D2 + pos - 1]
            ib[IDX + pos] = ib[IDX + pos - 1]
            pos -= 1
        f[D2 + pos] = d2
        ib[IDX + pos] = j
    return grown


@ti.func
def nearest_in_grid(
    f: ti.template(),
    ib: ti.template(),
    px: ti.f32,
    py: ti.f32,
    skip: ti.i32,
    P: ti.i32,
    r2: ti.f32,
    h: ti.f32,
    G: ti.i32,
    S: ti.i32,
    I: ti.i32,
    CELL: ti.i32,
    D2: ti.i32,
    IDX: ti.i32,
    K: ti.i32,
) -> ti.math.ivec2:
    """The K nearest points (not ``skip``) with squared distance <= r2 from (px, py), into
    the sorted list at IDX / D2; returns (listed, in range)."""
    c = cell_of(px, py, h)
    kept, in_range = 0, 0
    for q in range(9):
        qx, qy = c[0] + q % 3 - 1, c[1] + q // 3 - 1
        g = bucket(qx, qy, G)
        for s in range(ib[S + g], ib[S + g + 1]):
            j = ib[I + s]
            if j != skip and ib[CELL + 2 * j] == qx and ib[CELL + 2 * j + 1] == qy:
                dx, dy = f[P + 2 * j] - px, f[P + 2 * j + 1] - py
                d2 = dx * dx + dy * dy
                if d2 <= r2:
                    in_range += 1
                    kept = insert(f, ib, D2, IDX, kept, K, d2, j)
    return ti.math.ivec2(kept, in_range)


@ti.func
def next_contact(
    f: ti.template(),
    ib: ti.template(),
    i: ti.i32,
    last: ti.i32,
    P: ti.i32,
    reach2: ti.f32,
    h: ti.f32,
    G: ti.i32,
    S: ti.i32,
    I: ti.i32,
    CELL: ti.i32,
    none: ti.i32,
) -> ti.i32:
    """The smallest agent index j > last (j != i) within the contact reach of agent i
    (0 < d2 < reach2, where the contact force is non-zero), or ``none``. Contacts are
    summed in increasing j, the order of the dense all-pairs loop (and MPE's)."""
    px, py = f[P + 2 * i], f[P + 2 * i + 1]
    c = ti.math.ivec2(ib[CELL + 2 * i], ib[CELL + 2 * i + 1])
    best = none
    for q in range(9):
        qx, qy = c[0] + q % 3 - 1, c[1] + q // 3 - 1
        g = bucket(qx, qy, G)
        for s in range(ib[S + g], ib[S + g + 1]):
            j = ib[I + s]
            if j > last and j < best and j != i and ib[CELL + 2 * j] == qx and ib[CELL + 2 * j + 1] == qy:
                dx, dy = f[P + 2 * j] - px, f[P + 2 * j + 1] - py
                d2 = dx * dx + dy * dy
                if d2 > 0.0 and d2 < reach2:
                    best = j
    return best
