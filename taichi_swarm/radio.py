"""The radio auction (``landmark_order="radio"``): agents agree on who takes which landmark only
through messages exchanged with the teammates they hear.

No price or holder is kept per landmark (a beacon at each landmark, which a team of radios does
not have). Each agent keeps its own bounded table, one entry per landmark it senses (its KL
nearest within sense_radius, ``candidates``), keyed by landmark id: (epoch, price, holder), and the landmark
it believes it holds (``radio_won``; -1: none). That is all an agent knows of the auction; it
learns the rest by merging the tables of the agents on its neighbour list (obs nbr / nbr_mask).

A step (``rebuild`` per agent, then ``rounds``):
 1. Rebuild the table from this step's candidates: a landmark still sensed keeps its entry, a
    new one starts at (0, 0, none), one no longer sensed is dropped (the table stays bounded).
    The agent lets its landmark go if it no longer senses it or another option (staying out
    included) is cheaper by more than HOLD_SLACK increments (cost: distance + price); a release
    is written as (epoch + 1, 0, none).
 2. R rounds (auction_rounds), each synchronous: every agent reads the tables of the round
    before (the ``radio_next_*`` blocks are the double buffer), so the order in which agents are
    visited does not matter and both step kernels give the same results bit for bit.
    a. bid: an agent holding nothing bids for its cheapest entry, if it beats staying out
       (OUT sense radii), at price + (second cheapest - cheapest) + increment;
    b. exchange: for each landmark in its own table, it takes the greatest entry among its own
       and its heard teammates' (epoch, then price; on a tie the lower holder, none lowest);
    c. outbid: if its landmark's entry now names another holder, it holds nothing (and bids in
       the next round); an entry naming it for another landmark (a stale claim heard back) it
       releases.
    Within a step a table only grows in the order merging takes the max by (bids raise a price,
    a release raises the epoch, a merge takes the greater entry), so a teammate's table that has
    not changed since the round before is already within the agent's: merging it again changes
    nothing and is skipped (``radio_changed``). The results are those of merging every table
    every round, bit for bit, and the messages counted are still every heard table every round.
 3. The observation (kernels.agent_landmarks): a holder lists its landmark alone, read free; an
    agent holding nothing lists the landmarks its own table says another agent holds last,
    reading 0.

Why max-consensus with epochs: within an epoch a landmark's price only rises, so "greatest
(price, holder) wins" is a lattice join — idempotent, commutative, associative — and the
tables converge over any connected graph of agents that sense the landmark in at most its
diameter rounds, whatever the order messages arrive in (the consensus-based auctions of
Zavlanos, Spesivtsev and Pappas 2008 and CBBA, Choi, Brunet and How 2009). A release must undo
a price, which a max cannot; the epoch counter makes the release the greater entry, so it
spreads like a bid. Each bid raises a price by at least the increment, and no price passes the
staying-out cost, so with agents still the bidding ends, and the winners hold landmarks within
the increment of their best (eps-complementary slackness): the matching is then within M
increments of the optimum over what each senses (Bertsekas' eps-complementary slackness).

Locality: an agent's step reads its own position, the landmarks it senses, its own table and
won, and in 2b the tables of the agents on its list — nothing else, and no per-landmark shared
state (the layout has none). News thus moves
one hop per round: with R rounds, an agent at hop distance h > R from a change cannot see it at
that step (tests/test_taichi_swarm/test_radio_auction.py checks this).

Messages: every round each agent receives the table of every teammate on its list: one message
of ENTRY_BYTES per entry (u16 id, u16 epoch, f32 price, u16 holder). ``rounds`` writes the
step's messages and bytes received per agent (radio_messages, radio_bytes [B];
``info["radio"]``).
"""

import taichi as ti

from .constants import DEFAULT_ROUNDS, MAX_ROUNDS  # noqa: F401 - radio.DEFAULT_ROUNDS, as before
from .layout import H_GL, H_K, H_KL, H_ROUNDS, P_BID_EPS, P_LCELL, P_SENSE, blocks
from .neighbours import by_distance, nearest_in_grid

ENTRY_BYTES = 10  # one table entry on the air: u16 landmark id + u16 epoch + f32 price + u16 holder
OUT = 2.0  # staying out costs this many sense radii: more than any sensed landmark's distance
# Each bid raises a price by at least the increment ROUND_EPS (header P_BID_EPS). A bidding war's
# rounds grow as the prices it must climb over the increment, and a policy needs its landmark
# within its first steps; the matching is then within the increment per agent of the optimum: at
# most that much more travel for an agent.
ROUND_EPS = 0.5
# A holder keeps its landmark until another option is better by HOLD_SLACK increments: more than
# a fresh winner's one (it won at its second best plus the increment), with room for a step's
# motion; each release reopens the bidding for the landmark at price 0.
HOLD_SLACK = 2.0


@ti.func
def candidates(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    """Agent i's landmarks this step, from its own sensing: its KL nearest within sense_radius,
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
def _consider(d: ti.f32, j: ti.i32, best: ti.math.vec3) -> ti.math.vec3:
    """best = (w1, w2, j1): fold in an option j of cost d."""
    out = best
    if d < best[0]:
        out = ti.math.vec3(d, best[0], ti.cast(j, ti.f32))
    elif d < best[1]:
        out[1] = d
    return out


@ti.func
def _rows(ib: ti.template(), b: ti.i32, i: ti.i32, nxt: ti.template()) -> ti.math.ivec4:
    """Agent i's table rows (lid, epoch, price, holder): its own, or with ``nxt`` the next round's."""
    lid = blocks.radio_next_lid if ti.static(nxt) else blocks.radio_lid
    ep = blocks.radio_next_epoch if ti.static(nxt) else blocks.radio_epoch
    pr = blocks.radio_next_price if ti.static(nxt) else blocks.radio_price
    ho = blocks.radio_next_holder if ti.static(nxt) else blocks.radio_holder
    return ti.math.ivec4(
        lid.row(ib, lid.env(ib, b), i), ep.row(ib, ep.env(ib, b), i), pr.row(ib, pr.env(ib, b), i),
        ho.row(ib, ho.env(ib, b), i),
    )  # fmt: skip


@ti.func
def _find(ib: ti.template(), LID: ti.i32, n: ti.i32, l: ti.i32) -> ti.i32:
    """The slot of landmark l in a table of n entries (-1: not in it). A table is sorted by id
    (``rebuild``), so a binary search: the observation asks this of every landmark an agent's
    search passes (about 280 within a sense radius of 6 from M = 400 on)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if ib[LID + mid] < l:
            lo = mid + 1
        else:
            hi = mid
    return lo if lo < n and ib[LID + lo] == l else -1


@ti.func
def _beats(e1: ti.i32, p1: ti.f32, h1: ti.i32, e2: ti.i32, p2: ti.f32, h2: ti.i32) -> ti.i32:
    """Entry 1 > entry 2: the later epoch, then the higher price, then the lower holder (-1, a
    release, lowest); a total order, so merging is a max whatever the order tables arrive in."""
    return e1 > e2 or (e1 == e2 and (p1 > p2 or (p1 == p2 and h1 < h2)))


@ti.func
def _cost(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, l: ti.i32) -> ti.f32:
    """Agent i's distance to landmark l (it senses l: its own sensing, no message)."""
    d = blocks.landmarks.load(f, ib, b, l) - blocks.pos.load(f, ib, b, i)
    return ti.sqrt(d[0] * d[0] + d[1] * d[1])


@ti.func
def _best(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, T: ti.math.ivec4, n: ti.i32) -> ti.math.vec3:
    """(w1, w2, s1) over agent i's table and staying out (OUT sense radii; s1 = -1 when best):
    the cheapest and second cheapest distance + price, s1 the cheapest's slot."""
    out = OUT * f[P_SENSE]
    best = ti.math.vec3(out, out, -1.0)
    for s in range(n):
        best = _consider(_cost(f, ib, b, i, ib[T[0] + s]) + f[T[2] + s], s, best)
    return best


@ti.func
def _release(f: ti.template(), ib: ti.template(), T: ti.math.ivec4, s: ti.i32):
    """Slot s let go: the next epoch, price 0, nobody; the new epoch beats every bid of the old."""
    ib[T[1] + s] = ib[T[1] + s] + 1
    f[T[2] + s] = 0.0
    ib[T[3] + s] = -1


@ti.func
def _settle(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, T: ti.math.ivec4, n: ti.i32) -> ti.i32:
    """2c: agent i outbid on its landmark holds nothing; an entry naming it for a landmark it does
    not hold (its own old claim, heard back from a teammate) it releases, else that landmark would
    read held by nobody that holds it. Returns whether it released any."""
    W = blocks.radio_won.env(ib, b) + i
    won = ib[W]
    if won >= 0:
        s = _find(ib, T[0], n, won)
        if s < 0 or ib[T[3] + s] != i:
            ib[W] = -1
            won = -1
    released = 0
    for s in range(n):
        if ib[T[3] + s] == i and ib[T[0] + s] != won:
            _release(f, ib, T, s)
            released = 1
    return released


@ti.func
def rebuild(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    """Step 1, agent i alone: its table rebuilt over this step's candidates (bid_cand, bid_count:
    ``candidates``, called first), entries kept for landmarks still sensed; a fresh episode
    (step 0) starts from an empty table. Then its landmark let go if no longer sensed or worse
    than another option by more than HOLD_SLACK increments."""
    T, N = _rows(ib, b, i, False), _rows(ib, b, i, True)
    C, W = blocks.radio_count.env(ib, b) + i, blocks.radio_won.env(ib, b) + i
    fresh = ib[blocks.step.env(ib, b)] == 0
    old = 0 if fresh else ib[C]
    won = -1 if fresh else ib[W]
    cand = blocks.bid_cand.row(ib, blocks.bid_cand.env(ib, b), i)
    n = ib[blocks.bid_count.env(ib, b) + i]
    for k in range(n):  # the candidates' ids, ascending (insertion sort: n <= KL)
        l = ib[cand + k]
        s = k
        while s > 0 and ib[N[0] + s - 1] > l:
            ib[N[0] + s] = ib[N[0] + s - 1]
            s -= 1
        ib[N[0] + s] = l
    for s in range(n):  # the entry last step's table holds, or a blank one
        o = _find(ib, T[0], old, ib[N[0] + s])
        e, p, h = 0, 0.0, -1
        if o >= 0:
            e, p, h = ib[T[1] + o], f[T[2] + o], ib[T[3] + o]
        ib[N[1] + s], f[N[2] + s], ib[N[3] + s] = e, p, h
    for s in range(n):
        ib[T[0] + s], ib[T[1] + s], f[T[2] + s], ib[T[3] + s] = ib[N[0] + s], ib[N[1] + s], f[N[2] + s], ib[N[3] + s]
    ib[C] = n
    if won >= 0:
        s = _find(ib, T[0], n, won)
        if s < 0:  # no longer sensed: its entry left with it
            won = -1
        elif _cost(f, ib, b, i, won) + f[T[2] + s] > _best(f, ib, b, i, T, n)[0] + HOLD_SLACK * f[P_BID_EPS]:
            _release(f, ib, T, s)
            won = -1
    ib[W] = won
    _settle(f, ib, b, i, T, n)


@ti.func
def _bid(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    """2a: agent i, holding nothing, bids for its cheapest entry unless staying out is cheaper:
    the price raised by (second cheapest - cheapest) + the increment, the holder itself."""
    W = blocks.radio_won.env(ib, b) + i
    if ib[W] < 0:
        T, n = _rows(ib, b, i, False), ib[blocks.radio_count.env(ib, b) + i]
        w = _best(f, ib, b, i, T, n)
        s = ti.cast(w[2], ti.i32)
        if s >= 0:
            f[T[2] + s] = f[T[2] + s] + (w[1] - w[0]) + f[P_BID_EPS]
            ib[T[3] + s] = i
            ib[W] = ib[T[0] + s]
            ib[blocks.radio_changed.env(ib, b) + i] = 1


@ti.func
def _merge(
    f: ti.template(), ib: ti.template(), u8: ti.template(), b: ti.i32, i: ti.i32, term: ti.template()
) -> ti.math.ivec2:
    """2b: agent i's next table, the max of its own entries and those of every teammate on its list
    (the round's tables, read only) for the landmarks in its own table; both are sorted by id, so
    one pass over each. Returns (messages, bytes) agent i received."""
    T, N = _rows(ib, b, i, False), _rows(ib, b, i, True)
    n = ib[blocks.radio_count.env(ib, b) + i]
    for s in range(n):
        ib[N[0] + s], ib[N[1] + s], f[N[2] + s], ib[N[3] + s] = ib[T[0] + s], ib[T[1] + s], f[T[2] + s], ib[T[3] + s]
    nbr = blocks.term_nbr if ti.static(term) else blocks.nbr
    mask = blocks.term_nbr_mask if ti.static(term) else blocks.nbr_mask
    row, row_mask = nbr.row(ib, nbr.env(ib, b), i), mask.row(ib, mask.env(ib, b), i)
    COUNT, CHANGED = blocks.radio_count.env(ib, b), blocks.radio_changed.env(ib, b)
    heard = ti.math.ivec2(0, 0)
    for k in range(ib[H_K]):
        if u8[row_mask + k] != 0:
            j = ib[row + k]
            J, m = _rows(ib, b, j, False), ib[COUNT + j]
            heard += ti.math.ivec2(1, ENTRY_BYTES * m)
            if ib[CHANGED + j] != 0:  # (unchanged since merged: nothing in it is news)
                t = 0
                for s in range(n):
                    l = ib[N[0] + s]
                    while t < m and ib[J[0] + t] < l:
                        t += 1
                    if t < m and ib[J[0] + t] == l:
                        e, p, h = ib[J[1] + t], f[J[2] + t], ib[J[3] + t]
                        if _beats(e, p, h, ib[N[1] + s], f[N[2] + s], ib[N[3] + s]):
                            ib[N[1] + s], f[N[2] + s], ib[N[3] + s] = e, p, h
    return heard


@ti.func
def _commit(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    """The merged table becomes agent i's own; then 2c. Whether it changed is kept for the next
    round's merges."""
    T, N = _rows(ib, b, i, False), _rows(ib, b, i, True)
    n = ib[blocks.radio_count.env(ib, b) + i]
    changed = 0
    for s in range(n):
        changed |= ti.cast(
            ib[T[1] + s] != ib[N[1] + s] or f[T[2] + s] != f[N[2] + s] or ib[T[3] + s] != ib[N[3] + s], ti.i32
        )
        ib[T[1] + s], f[T[2] + s], ib[T[3] + s] = ib[N[1] + s], f[N[2] + s], ib[N[3] + s]
    changed |= _settle(f, ib, b, i, T, n)
    ib[blocks.radio_changed.env(ib, b) + i] = changed


@ti.func
def rounds(f: ti.template(), ib: ti.template(), u8: ti.template(), b: ti.i32, M: ti.i32, term: ti.template()):
    """Step 2 for env b: auction_rounds synchronous rounds (each a pass of bids, one of merges
    reading only the round's tables, one of commits); then the step's messages and bytes
    received per agent. ``term``: the lists of the terminal observation being written."""
    heard = ti.math.ivec2(0, 0)
    for i in range(M):  # every table was rebuilt this step: the first round merges them all
        ib[blocks.radio_changed.env(ib, b) + i] = 1
    for _ in range(ib[H_ROUNDS]):
        for i in range(M):
            _bid(f, ib, b, i)
        for i in range(M):
            heard += _merge(f, ib, u8, b, i, term)
        for i in range(M):
            _commit(f, ib, b, i)
    f[blocks.radio_messages.env(ib, b)] = heard[0] / M
    f[blocks.radio_bytes.env(ib, b)] = heard[1] / M


@ti.func
def held_by_other(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, l: ti.i32) -> ti.i32:
    """Whether agent i's own table says another agent holds landmark l (not in it: no)."""
    T = _rows(ib, b, i, False)
    s = _find(ib, T[0], ib[blocks.radio_count.env(ib, b) + i], l)
    out = 0
    if s >= 0:
        h = ib[T[3] + s]
        out = ti.cast(h >= 0 and h != i, ti.i32)
    return out


@ti.func
def held_last(f: ti.template(), ib: ti.template(), ctx: ti.math.ivec2, l: ti.i32, d2: ti.f32) -> ti.f32:
    """The radio's rank of landmark l for agent ctx[1] of env ctx[0] (``nearest_in_grid``): its
    squared distance, plus more than any listed one has where its own table says another agent
    holds l, so the landmarks it believes free are listed first (kernels.claim_first's rule,
    from the agent's own table instead of the team-wide matching)."""
    held = held_by_other(f, ib, ctx[0], ctx[1], l)
    return d2 + ti.select(held, f[P_SENSE] * f[P_SENSE] + 1.0, 0.0)
