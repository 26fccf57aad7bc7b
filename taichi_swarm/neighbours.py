"""Neighbour lists through a uniform cell grid, per environment (``make(..., neighbours=K)``).

Every step each environment sorts its agents into square cells of side h (h >= the
comm radius under "rc" and >= the contact reach 2 r + 20 margins). The cells are hashed
into G buckets (G a power of two >= 2 M): agents may wander anywhere, and the memory
stays O(M). A counting sort builds, in one pass each, the bucket counts, their prefix
sums and the bucket-sorted agent list (stable: increasing agent index per bucket).
An agent's own integer cell is stored beside it, so a query keeps only the agents of the
cells it asked for (two cells hashed to one bucket are never counted twice).

A query of radius r round p scans, row by row, only the cells that meet the disc of radius
r (padded for float32 rounding; the row and column spans come from floor((p -+ r) / h),
monotone in p, so no cell holding a point within r is missed): about 8 cells of side h for
the lists, 1 to 4 for the contacts (reach ~0.12 against h = 1), where the 3 x 3 block used
to scan 9 for both. A row's cells hash to consecutive buckets (row hash + column), so a
row's span is one run of the sorted items, not one bucket lookup per cell. The row hash
is MurmurHash3's finalizer: Teschner's xor of two products mapped many nearby cells to
one bucket (359 occupied cells of an M = 1000 arena into 283 of 2048 buckets).

Queries are runtime loops (not unrolled: the kernels compile to the same code for every
M). The lists hold the K nearest, nearest first, ordered by (squared distance, index) so
that ties come out the same whatever order the cells are visited in; contacts are summed
in increasing index. Landmarks (``landmark_neighbours=KL``) get a grid of their own with
side >= sense_radius. Finer cells (side h / SPLIT, SPLIT = 2 or 3: less area scanned) were
measured slower: more rows per query cost more than the fewer points saved.
"""

import taichi as ti

HASH_Y = 19349663  # Teschner et al. 2003, a spatial hashing prime
CELL_LIMIT = 1e8  # cell coordinates are clamped here (int32-safe; far outside any arena)
SPLIT = 1  # cells per radius (side ~radius / SPLIT); 2 and 3 measured slower: docs/SWARM.md
RADIUS_PAD = 1.001  # a query's disc, widened for float32 rounding of the distances
PAD = 1e-3  # a row's gap to the query point, shrunk by this many cells (rounding of the cells)


def buckets(count: int, split: int = 1) -> int:
    """G: the power of two >= 2 * split^2 * count (at least 16). A query scans about
    (2 split + 1)^2 - 4 cells and each holds on average count / G points of other cells
    hashed to its bucket: G grows with the cells per radius to keep those few."""
    g = 16
    while g < 2 * split * split * count:
        g *= 2
    return g


def cell_side(radius: float, split: int = 1) -> float:
    """The side of cells ``split`` to a ``radius`` (a hair above radius / split)."""
    return (radius * (1.0 + 1e-5) + 1e-6) / split


@ti.func
def axis_cell(x: ti.f32, h: ti.f32) -> ti.i32:
    """floor(x / h), clamped: monotone in x, so a query's span of cells computed from
    p - r and p + r holds every point in [p - r, p + r] whatever the rounding."""
    return ti.cast(ti.floor(ti.math.clamp(x / h, -CELL_LIMIT, CELL_LIMIT)), ti.i32)


@ti.func
def cell_of(x: ti.f32, y: ti.f32, h: ti.f32) -> ti.math.ivec2:
    return ti.math.ivec2(axis_cell(x, h), axis_cell(y, h))


@ti.func
def padded(r: ti.f32) -> ti.f32:
    """A query radius a little above r: float32 distances that pass d2 <= r^2 are below it."""
    return r * RADIUS_PAD + 1e-6


@ti.func
def rows(py: ti.f32, rp: ti.f32, h: ti.f32) -> ti.math.ivec2:
    """The first and last rows of cells within rp of y = py."""
    return ti.math.ivec2(axis_cell(py - rp, h), axis_cell(py + rp, h))


@ti.func
def columns(px: ti.f32, py: ti.f32, rp: ti.f32, qy: ti.i32, h: ti.f32) -> ti.math.ivec2:
    """The first and last cells of row qy that meet the disc of radius rp round (px, py)
    (first > last: none). The row's gap to py is shrunk by PAD cells and a relative 1e-6
    (float32 rounding of the points' cells), so no cell holding a point within the radius
    is left out; the cells that only the square round the disc meets are."""
    ey = ti.max(qy * h - py, py - (qy + 1) * h)
    ey = ti.max(ey - PAD * h - 1e-6 * ti.abs(py), 0.0)
    span = ti.math.ivec2(1, 0)
    w2 = rp * rp - ey * ey
    if w2 >= 0.0:
        w = ti.sqrt(w2)
        span = ti.math.ivec2(axis_cell(px - w, h), axis_cell(px + w, h))
    return span


@ti.func
def ring_cell(c: ti.math.ivec2, rho: ti.i32, t: ti.i32) -> ti.math.ivec2:
    """Cell t of the ring at Chebyshev distance rho round cell c (8 rho cells; 1 at rho = 0)."""
    qx, qy = c[0], c[1]
    if rho > 0:  # the ring's perimeter, each cell once: four edges of 2 rho cells
        e, s = t // (2 * rho), t % (2 * rho)
        if e == 0:
            qx, qy = c[0] - rho + s, c[1] - rho
        elif e == 1:
            qx, qy = c[0] + rho, c[1] - rho + s
        elif e == 2:
            qx, qy = c[0] + rho - s, c[1] + rho
        else:
            qx, qy = c[0] - rho, c[1] + rho - s
    return ti.math.ivec2(qx, qy)


@ti.func
def bucket(cx: ti.i32, cy: ti.i32, G: ti.i32) -> ti.i32:
    """Cell (cx, cy)'s bucket: the row's hash (MurmurHash3's finalizer of cy * HASH_Y,
    spread over all 32 bits) plus cx, so that a row's consecutive cells lie in consecutive
    buckets (mod G) and a query reads a row's span of cells as one run of items."""
    h = ti.cast(cy, ti.u32) * ti.u32(HASH_Y)
    h = h ^ (h >> 16)
    h = h * ti.u32(0x85EBCA6B)
    h = h ^ (h >> 13)
    h = h * ti.u32(0xC2B2AE35)
    h = h ^ (h >> 16)
    return ti.cast((h + ti.cast(cx, ti.u32)) & ti.cast(G - 1, ti.u32), ti.i32)


@ti.func
def row_run(ib: ti.template(), span: ti.math.ivec2, qy: ti.i32, G: ti.i32, S: ti.i32) -> ti.math.ivec3:
    """The items of the cells span[0] .. span[1] of row qy (and of the other cells hashed to
    their buckets): (first slot, count, total), slot first + t taken mod total (the run may
    wrap past bucket G - 1). Each bucket is read at most once, so no item twice."""
    n = ti.min(ti.max(span[1] - span[0] + 1, 0), G)
    g0 = bucket(span[0], qy, G)
    total = ib[S + G]
    start = ib[S + g0]
    count = 0
    if g0 + n <= G:
        count = ib[S + g0 + n] - start
    else:
        count = ib[S + g0 + n - G] + total - start
    return ti.math.ivec3(start, count, total)


@ti.func
def run_item(
    ib: ti.template(), run: ti.math.ivec3, t: ti.i32, span: ti.math.ivec2, qy: ti.i32, I: ti.i32, CELL: ti.i32
) -> ti.i32:
    """Item t of a row run (``row_run``), or -1 where it lies in another cell hashed to the
    same buckets (not in row qy's span): the one walk every grid query shares."""
    s = run[0] + t
    if s >= run[2]:
        s -= run[2]
    j = ib[I + s]
    cx = ib[CELL + 2 * j]
    if ib[CELL + 2 * j + 1] != qy or cx < span[0] or cx > span[1]:
        j = -1
    return j


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
def by_distance(f: ti.template(), ib: ti.template(), ctx: ti.math.ivec2, j: ti.i32, d2: ti.f32) -> ti.f32:
    """The rank of ``nearest_in_grid``'s plain lists: nearest first."""
    return d2


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
    rank: ti.template(),
    ctx: ti.math.ivec2,
) -> ti.math.ivec2:
    """The K points (not ``skip``) with squared distance <= r2 from (px, py) that rank first,
    into the sorted list at IDX (their ranks at D2); returns (listed, in range). ``rank(f, ib,
    ctx, j, d2)`` orders them: ``by_distance``, the K nearest; a rank that adds to d2 moves some
    points behind others (kernels.claim_first), with ``ctx`` what it needs besides (b, i)."""
    rp = padded(ti.sqrt(r2))
    span_y = rows(py, rp, h)
    kept, in_range = 0, 0
    for qy in range(span_y[0], span_y[1] + 1):
        span_x = columns(px, py, rp, qy, h)
        run = row_run(ib, span_x, qy, G, S)
        for t in range(run[1]):
            j = run_item(ib, run, t, span_x, qy, I, CELL)
            if j >= 0 and j != skip:
                dx, dy = f[P + 2 * j] - px, f[P + 2 * j + 1] - py
                d2 = dx * dx + dy * dy
                if d2 <= r2:
                    in_range += 1
                    kept = insert(f, ib, D2, IDX, kept, K, rank(f, ib, ctx, j, d2), j)
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
    rp = padded(ti.sqrt(reach2))
    span_y = rows(py, rp, h)
    best = none
    for qy in range(span_y[0], span_y[1] + 1):
        span_x = columns(px, py, rp, qy, h)
        run = row_run(ib, span_x, qy, G, S)
        for t in range(run[1]):
            j = run_item(ib, run, t, span_x, qy, I, CELL)
            if j >= 0 and j > last and j < best and j != i:
                dx, dy = f[P + 2 * j] - px, f[P + 2 * j + 1] - py
                d2 = dx * dx + dy * dy
                if d2 > 0.0 and d2 < reach2:
                    best = j
    return best
