"""The fused kernels: one launch per ``reset`` and one per ``step``.

Every kernel takes the three packed buffers (see layout.py) and, for the
discrete step, nothing else (the actions are copied into the int32 buffer
first); the continuous step also takes the float32 actions, the masked reset
its mask. Each
kernel has exactly one parallel loop, over environments (only the outermost
loop is parallel, and every extra pass costs a thread-pool dispatch, which
dominated at small B). Per environment, a step is: forces -> velocities ->
positions, targets, optimal assignment, reward, success and done, episode
statistics, terminal observation and auto-reset, then the observations and
communication graph. ``step_wide_kernel`` is the exception, for GPUs: the same
step as several passes, each per-agent part parallel over (environment, agent).

Compile-time arguments: ``task`` (the task id, tasks/), ``cap`` (size of the dense
physics' per-thread force array and of the small-M assignment's work arrays; 0 with
neighbour lists: no per-M stack arrays), ``lists`` (AGENT_LISTS | LANDMARK_LISTS: neighbour
and landmark lists through cell grids instead of the dense adjacency, neighbours.py; OCCUPANCY:
each listed landmark's occupancy beside its offset; FREE: the local assignment, nearest.py;
RADIO: the agents' auction by messages, radio.py),
``sm`` (M itself for M <= layout.STATIC_M_MAX, so the loops over agents unroll; else 0
and M is read from the header) and ``parallel`` (serial env loop for small batches, see
env.py).
"""

import taichi as ti

from . import assignment, nearest, neighbours, physics, radio, tasks
from .layout import (
    H_B,
    H_COMM_RC,
    H_G,
    H_GL,
    H_K,
    H_KL,
    H_MAX_STEPS,
    P_AGENT_RADIUS,
    P_CELL,
    P_COMM_RADIUS,
    P_LCELL,
    P_SENSE,
    P_SUCCESS,
    blocks,
    team_size,
)

# bits of the compile-time ``lists`` argument: neighbour lists, landmark lists, the local
# assignment (assignment="free": nearest-agent team reward, a threshold matching, each agent paid by
# its matched or nearest free target; nearest.py; needs AGENT_LISTS), landmark occupancy (needs
# AGENT_LISTS and LANDMARK_LISTS: it reads the agents' grid), and the radio auction, agents
# coordinating through their neighbour lists' messages alone (RADIO: landmark_order="radio",
# radio.py; needs AGENT_LISTS, LANDMARK_LISTS and OCCUPANCY)
AGENT_LISTS, LANDMARK_LISTS, FREE, OCCUPANCY, RADIO = 1, 2, 8, 16, 2048
CONTACT_SLOTS = 8  # contacts an agent sums without a second pass (discs of radius r: at most 6 touch without overlap)

F32 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)
U8 = ti.types.ndarray(dtype=ti.u8, ndim=1)


@ti.func
def match(
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    b: ti.i32,
):
    """Targets, optimal assignment and matched distances d*_i of env b;
    with FREE, each target's nearest-agent distance d_t, the maximum threshold matching and each
    agent's matched or nearest free target's distance (nearest.py), the agents' grid built here for them (and for the
    observations and the next step's contacts: every caller writes the observations next)."""
    if ti.static(lists & FREE):
        nearest_setup(task, sm, f, ib, b)
        nearest.solve(f, ib, b)
    else:
        tasks.place_targets(task, sm, f, ib, b)
        assignment.solve(cap, sm, f, ib, b)


@ti.func
def agents_grid(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """The cell grid of env b's agents at their current positions."""
    GS, GI, GC = blocks.grid_start.env(ib, b), blocks.grid_items.env(ib, b), blocks.grid_cell.env(ib, b)
    neighbours.build(f, ib, team_size(sm, ib), blocks.pos.env(ib, b), f[P_CELL], ib[H_G], GS, GI, GC)


@ti.func
def nearest_setup(task: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """What nearest.py's searches read: env b's targets, the agents' grid and the targets' grid."""
    tasks.place_targets(task, sm, f, ib, b)
    agents_grid(sm, f, ib, b)
    nearest.targets_grid(f, ib, b)


@ti.func
def write_team_obs(
    task: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    term: ti.template(),
):
    """Every agent's observation of env b, into the current (``term`` False) or the
    terminal observation blocks: self [M, 4] = (vel, pos); entities [M, L, 2] = landmark
    - pos (with landmark lists: agent_landmarks); and who agent i hears: the adjacency
    [M, M] (dense: itself always; "rc": those within comm radius) or, with neighbour lists,
    its K nearest heard agents. ``step_wide_kernel`` writes the same, agent by agent in parallel."""
    M, L = team_size(sm, ib), tasks.landmark_count(task, sm, ib)
    for i in range(M):
        self_obs(f, ib, b, i, term)
    obs_grids(task, sm, lists, f, ib, b)
    if ti.static(lists & AGENT_LISTS):
        dropped = 0
        for i in range(M):
            dropped += agent_list(lists, f, ib, u8, b, i, M, term)
        ib[blocks.dropped.env(ib, b)] = dropped
    else:
        pos, adj = blocks.pos, blocks.term_adj if ti.static(term) else blocks.adj
        P0, A = pos.env(ib, b), adj.env(ib, b)
        restricted = ib[H_COMM_RC] != 0
        radius = f[P_COMM_RADIUS]
        r2 = radius * radius
        width = adj.row_width(ib)  # M: adjacency row i is u8[A + i * M : A + (i + 1) * M]
        for i in range(M):  # the graph is symmetric: each pair once
            u8[A + i * width + i] = ti.u8(1)
            p = pos.get2(f, ib, P0, i)
            for j in range(i + 1, M):
                d = pos.get2(f, ib, P0, j) - p
                hears = ti.cast((not restricted) or d[0] * d[0] + d[1] * d[1] <= r2, ti.u8)
                u8[A + i * width + j] = hears
                u8[A + j * width + i] = hears
    # after the graph: landmark occupancy reads the agents' grid (obs_grids)
    if ti.static(lists & OCCUPANCY):
        for l in range(L):
            landmark_occupants(f, ib, b, l)
    if ti.static(lists & RADIO):  # after the lists: the radio's messages go to the agents listed
        for i in range(M):
            radio.candidates(f, ib, b, i)
            radio.rebuild(f, ib, b, i)
        radio.rounds(f, ib, u8, b, M, term)
    for i in range(M):
        if ti.static(lists & LANDMARK_LISTS):
            agent_landmarks(lists, f, ib, u8, b, i, term)
        else:
            entity_offsets(L, f, ib, b, i, term)


@ti.func
def self_obs(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, term: ti.template()):
    """Agent i's own (vx, vy, px, py): SELF_DIM."""
    obs_self = blocks.term_self if ti.static(term) else blocks.obs_self
    s = obs_self.row(ib, obs_self.env(ib, b), i)
    v, p = blocks.vel.get2(f, ib, blocks.vel.env(ib, b), i), blocks.pos.get2(f, ib, blocks.pos.env(ib, b), i)
    f[s + 0], f[s + 1], f[s + 2], f[s + 3] = v[0], v[1], p[0], p[1]


@ti.func
def entity_offsets(L: ti.i32, f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, term: ti.template()):
    """Agent i's [L, 2] offsets to every landmark (no landmark lists)."""
    ent = blocks.term_entities if ti.static(term) else blocks.obs_entities
    p, e = blocks.pos.get2(f, ib, blocks.pos.env(ib, b), i), ent.row(ib, ent.env(ib, b), i)
    LM = blocks.landmarks.env(ib, b)
    for l in range(L):
        d = blocks.landmarks.get2(f, ib, LM, l) - p
        f[e + 2 * l], f[e + 2 * l + 1] = d[0], d[1]


@ti.func
def obs_grids(
    task: ti.template(), sm: ti.template(), lists: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32
):
    """The cell grids of env b the observation's queries read: the agents' (kept for the next
    step's contacts; with FREE ``match`` has just built it) and, with landmark lists, the
    landmarks'."""
    if ti.static((lists & AGENT_LISTS) and not (lists & FREE)):
        agents_grid(sm, f, ib, b)
    if ti.static(lists & LANDMARK_LISTS):
        GS, GI, GC = blocks.lgrid_start.env(ib, b), blocks.lgrid_items.env(ib, b), blocks.lgrid_cell.env(ib, b)
        L = tasks.landmark_count(task, sm, ib)
        neighbours.build(f, ib, L, blocks.landmarks.env(ib, b), f[P_LCELL], ib[H_GL], GS, GI, GC)


@ti.func
def agent_list(
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    i: ti.i32,
    M: ti.i32,
    term: ti.template(),
) -> ti.i32:
    """Agent i's K nearest heard agents (itself excluded), nearest first, through the agents'
    grid: its rows of nbr [M, K] (padded with its own index), nbr_mask [M, K], in_range [M];
    returns how many it heard but could not list (the env's ``dropped`` sums them)."""
    K, G = ib[H_K], ib[H_G]
    nbr = blocks.term_nbr if ti.static(term) else blocks.nbr
    mask = blocks.term_nbr_mask if ti.static(term) else blocks.nbr_mask
    P0 = blocks.pos.env(ib, b)
    GS, GI, GC = blocks.grid_start.env(ib, b), blocks.grid_items.env(ib, b), blocks.grid_cell.env(ib, b)
    h = f[P_CELL]
    NB, MK, D2 = nbr.env(ib, b), mask.env(ib, b), blocks.nbr_d2.env(ib, b)
    p = blocks.pos.get2(f, ib, P0, i)
    row, row_d2, row_mask = nbr.row(ib, NB, i), blocks.nbr_d2.row(ib, D2, i), mask.row(ib, MK, i)
    found = ti.math.ivec2(0, 0)  # (listed, in range)
    if ib[H_COMM_RC] != 0:
        r2 = f[P_COMM_RADIUS] * f[P_COMM_RADIUS]
        found = neighbours.nearest_in_grid(
            f, ib, p[0], p[1], i, P0, r2, h, G, GS, GI, GC, row_d2, row, K, neighbours.by_distance, ti.math.ivec2(0, 0)
        )
    else:  # "uc": everyone is heard; the K nearest of all
        kept = 0
        for j in range(M):
            if j != i:
                d = blocks.pos.get2(f, ib, P0, j) - p
                kept = neighbours.insert(f, ib, row_d2, row, kept, K, d[0] * d[0] + d[1] * d[1], j)
        found = ti.math.ivec2(kept, M - 1)
    for k in range(K):
        listed = k < found[0]
        u8[row_mask + k] = ti.cast(listed, ti.u8)
        if not listed:
            ib[row + k] = i
    ib[blocks.in_range.env(ib, b) + i] = found[1]
    return found[1] - found[0]


@ti.func
def agent_landmarks(
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    i: ti.i32,
    term: ti.template(),
):
    """Agent i's KL nearest landmarks within sense_radius, nearest first, through the
    landmarks' cell grid: its rows of entities [M, KL, 2] (landmark - pos, zeros where none)
    and entity_mask [M, KL]. With OCCUPANCY, entities [M, KL, 3]: the third feature is the
    landmark's distance to its nearest agent other than this one, capped at sense_radius
    (sense_radius where none is nearer; 0 where none is listed), from each landmark's two
    nearest agents (``landmark_occupants``). With RADIO, an agent lists the landmark it believes
    it holds (radio_won) alone, its reading floored at the success threshold; an agent holding
    none lists the landmarks its own table says another agent holds last, reading 0
    (radio.held_last), the others their occupancy floored at the success threshold."""
    KL, G = ib[H_KL], ib[H_GL]
    EF = 3 if ti.static(lists & OCCUPANCY) else 2
    ent = blocks.term_entities if ti.static(term) else blocks.obs_entities
    mask = blocks.term_entity_mask if ti.static(term) else blocks.entity_mask
    P0, LM = blocks.pos.env(ib, b), blocks.landmarks.env(ib, b)
    GS, GI, GC = blocks.lgrid_start.env(ib, b), blocks.lgrid_items.env(ib, b), blocks.lgrid_cell.env(ib, b)
    E, MK, D2, IDX = ent.env(ib, b), mask.env(ib, b), blocks.ent_d2.env(ib, b), blocks.ent_idx.env(ib, b)
    s2 = f[P_SENSE] * f[P_SENSE]
    p = blocks.pos.get2(f, ib, P0, i)
    row_d2, row_mask, row = blocks.ent_d2.row(ib, D2, i), mask.row(ib, MK, i), ent.row(ib, E, i)
    # the search's indices go in row i of ent_idx (one row per agent: agents may search at once)
    idx = blocks.ent_idx.row(ib, IDX, i)
    rank = ti.static(radio.held_last if lists & RADIO else neighbours.by_distance)
    ctx = ti.math.ivec2(b, i)
    won = -1
    if ti.static(lists & RADIO):
        won = ib[blocks.radio_won.env(ib, b) + i]
    found = ti.math.ivec2(1, 1)
    if won >= 0:  # the landmark it holds, alone
        ib[idx] = won
    else:
        found = neighbours.nearest_in_grid(
            f, ib, p[0], p[1], -1, LM, s2, f[P_LCELL], G, GS, GI, GC, row_d2, idx, KL, rank, ctx
        )
    for k in range(KL):
        listed = k < found[0]
        u8[row_mask + k] = ti.cast(listed, ti.u8)
        d = ti.math.vec2(0.0, 0.0)
        if listed:
            d = blocks.landmarks.get2(f, ib, LM, ib[idx + k]) - p
        f[row + EF * k], f[row + EF * k + 1] = d[0], d[1]
        if ti.static(lists & OCCUPANCY):
            occ = 0.0
            if listed:
                if won >= 0:  # free to the agent that holds it, whoever else is near
                    occ = ti.max(occupancy(f, ib, b, won, i), f[P_SUCCESS])
                else:
                    occ = reading(lists, f, ib, b, ib[idx + k], i)
            f[row + EF * k + 2] = occ


@ti.func
def reading(lists: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32, l: ti.i32, i: ti.i32) -> ti.f32:
    """Landmark l's occupancy reading for agent i: under RADIO 0 where its own table says another
    agent holds l, else ``occupancy`` floored at the success threshold (a held landmark reads
    nearer than any free one); else ``occupancy``."""
    out = 0.0
    if ti.static(lists & RADIO):
        if not radio.held_by_other(f, ib, b, i, l):
            out = ti.max(occupancy(f, ib, b, l, i), f[P_SUCCESS])
    else:
        out = occupancy(f, ib, b, l, i)
    return out


@ti.func
def landmark_occupants(f: ti.template(), ib: ti.template(), b: ti.i32, l: ti.i32):
    """Landmark l's two nearest agents within sense_radius (occ_idx, occ_d2, occ_found),
    through the agents' grid: with them every agent's occupancy of a landmark is a lookup."""
    P0, G = blocks.pos.env(ib, b), ib[H_G]
    GS, GI, GC = blocks.grid_start.env(ib, b), blocks.grid_items.env(ib, b), blocks.grid_cell.env(ib, b)
    LM, OD, OI, OF = (
        blocks.landmarks.env(ib, b), blocks.occ_d2.env(ib, b), blocks.occ_idx.env(ib, b), blocks.occ_found.env(ib, b)
    )  # fmt: skip
    s2 = f[P_SENSE] * f[P_SENSE]
    q = blocks.landmarks.get2(f, ib, LM, l)
    d2, idx = blocks.occ_d2.row(ib, OD, l), blocks.occ_idx.row(ib, OI, l)
    found = neighbours.nearest_in_grid(
        f, ib, q[0], q[1], -1, P0, s2, f[P_CELL], G, GS, GI, GC, d2, idx, 2, neighbours.by_distance, ti.math.ivec2(0, 0)
    )
    ib[OF + l] = found[0]


@ti.func
def occupancy(f: ti.template(), ib: ti.template(), b: ti.i32, l: ti.i32, i: ti.i32) -> ti.f32:
    """Landmark l's distance to its nearest agent other than agent i, capped at sense_radius."""
    OD, OI = blocks.occ_d2.env(ib, b), blocks.occ_idx.env(ib, b)
    d2, idx, n = blocks.occ_d2.row(ib, OD, l), blocks.occ_idx.row(ib, OI, l), ib[blocks.occ_found.env(ib, b) + l]
    k = 1 if n >= 1 and ib[idx] == i else 0  # the nearest is i itself: the next one
    out = f[P_SENSE]
    if k < n:
        out = ti.min(ti.sqrt(f[d2 + k]), f[P_SENSE])
    return out


@ti.func
def target_dist(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32) -> ti.f32:
    """DIST: mean over targets of the distance to the closest agent."""
    M = team_size(sm, ib)
    P0, T0 = blocks.pos.env(ib, b), blocks.targets.env(ib, b)
    total = 0.0
    for t in range(M):
        tp = blocks.targets.get2(f, ib, T0, t)
        best = 1e30
        for i in range(M):
            best = ti.min(best, (blocks.pos.get2(f, ib, P0, i) - tp).norm())
        total += best
    return total / M


@ti.func
def clear_agent_rewards(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """A reset's rewards are 0, the team's and each agent's."""
    M = team_size(sm, ib)
    RT = blocks.reward_terms.row_width(ib)
    for i in range(M):
        f[blocks.agent_reward.at(ib, b, i)] = 0.0
        row = blocks.reward_terms.at(ib, b, i)
        for k in range(RT):
            f[row + k] = 0.0


@ti.func
def start_episode(
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    b: ti.i32,
):
    tasks.spawn(task, sm, f, ib, b)
    ib[blocks.step.env(ib, b)] = 0
    f[blocks.return_acc.env(ib, b)] = 0.0
    match(task, cap, sm, lists, f, ib, b)


@ti.kernel
def reset_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    parallel: ti.template(),
):
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):  # the only parallel loop: one environment per thread
        start_episode(task, cap, sm, lists, f, ib, b)
        f[blocks.reward.env(ib, b)] = 0.0
        clear_agent_rewards(sm, f, ib, b)
        u8[blocks.done.env(ib, b)] = ti.u8(0)
        write_team_obs(task, sm, lists, f, ib, u8, b, False)


@ti.kernel
def refresh_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    parallel: ti.template(),
):
    """Recompute targets, assignment and observations after ``set_state``."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):
        match(task, cap, sm, lists, f, ib, b)
        write_team_obs(task, sm, lists, f, ib, u8, b, False)


@ti.func
def physics_step(
    cap: ti.template(),
    sm: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    b: ti.i32,
    u: ti.template(),
    continuous: ti.template(),
):
    """Action and contact forces -> velocities, then positions, for env b.

    Discrete (``continuous`` False): the actions are the actions block and ``u`` is not read.
    Continuous: u is the float32 [B * M * 2] array of force commands (clipped to [-1, 1])."""
    M = team_size(sm, ib)
    dist_min = 2.0 * f[P_AGENT_RADIUS]
    pos, vel = blocks.pos, blocks.vel
    P0, V0, A0 = pos.env(ib, b), vel.env(ib, b), blocks.actions.env(ib, b)
    force = ti.Vector.zero(ti.f32, 2 * cap)  # [M, 2], on the thread's stack
    for i in range(M):
        if ti.static(continuous):
            c = physics.continuous_force(ti.math.vec2(u[(b * M + i) * 2], u[(b * M + i) * 2 + 1]))
            force[2 * i] = c[0]
            force[2 * i + 1] = c[1]
        else:
            a = physics.action_force(ib[blocks.actions.row(ib, A0, i)])
            force[2 * i] = a[0]
            force[2 * i + 1] = a[1]
    C = blocks.contacts.env(ib, b)
    for i in range(M):
        f[C + i] = 0.0
    for i in range(M):  # contact forces from the old positions, each pair once (equal and
        # opposite; every agent still sums its contacts in increasing j, as MPE does)
        p = pos.get2(f, ib, P0, i)
        for j in range(i + 1, M):
            q = pos.get2(f, ib, P0, j)
            fc = physics.contact_force(p, q, dist_min)
            force[2 * i] += fc[0]
            force[2 * i + 1] += fc[1]
            force[2 * j] -= fc[0]
            force[2 * j + 1] -= fc[1]
            if (p - q).norm_sqr() < dist_min * dist_min:  # touching (the reward terms' contacts)
                f[C + i] = f[C + i] + 1.0
                f[C + j] = f[C + j] + 1.0
    for i in range(M):
        v = physics.integrate_velocity(vel.get2(f, ib, V0, i), ti.math.vec2(force[2 * i], force[2 * i + 1]))
        vel.set2(f, ib, V0, i, v)
        # a plain read-modify-write: ``+=`` on an ndarray element compiles to an atomic add
        # (a lock cmpxchg loop), needless here as each env belongs to one thread
        pos.set2(f, ib, P0, i, pos.get2(f, ib, P0, i) + v * physics.DT)


@ti.func
def grid_velocity(
    sm: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    b: ti.i32,
    i: ti.i32,
    u: ti.template(),
    continuous: ti.template(),
):
    """Agent i's action force and contacts, found through the cell grid of the current
    positions (built with the last observation), -> its new velocity. It sums its contacts
    in increasing j, as the dense loop does, so both give the same forces; it reads
    positions only, so every agent's velocity may be computed at once."""
    M = team_size(sm, ib)
    G = ib[H_G]
    pos, vel = blocks.pos, blocks.vel
    P0, V0, A0 = pos.env(ib, b), vel.env(ib, b), blocks.actions.env(ib, b)
    GS, GI, GC = blocks.grid_start.env(ib, b), blocks.grid_items.env(ib, b), blocks.grid_cell.env(ib, b)
    dist_min = 2.0 * f[P_AGENT_RADIUS]
    reach = (dist_min + physics.CUTOFF_MARGINS * physics.CONTACT_MARGIN) * 1.001  # a superset of the force's
    h = f[P_CELL]
    force = ti.math.vec2(0.0, 0.0)
    if ti.static(continuous):
        force = physics.continuous_force(ti.math.vec2(u[(b * M + i) * 2], u[(b * M + i) * 2 + 1]))
    else:
        force = physics.action_force(ib[blocks.actions.row(ib, A0, i)])
    p = pos.get2(f, ib, P0, i)
    # one pass over the cells that meet the reach's disc keeps the CONTACT_SLOTS smallest touching indices,
    # sorted; past that many (a pile-up) the rest are walked in increasing index
    touching = ti.Vector([M] * CONTACT_SLOTS, dt=ti.i32)
    count, touched = 0, 0.0
    rp = neighbours.padded(reach)
    span_y = neighbours.rows(p[1], rp, h)
    for qy in range(span_y[0], span_y[1] + 1):
        span_x = neighbours.columns(p[0], p[1], rp, qy, h)
        run = neighbours.row_run(ib, span_x, qy, G, GS)
        for t in range(run[1]):
            j = neighbours.run_item(ib, run, t, span_x, qy, GI, GC)
            if j >= 0 and j != i:
                d = pos.get2(f, ib, P0, j) - p
                d2 = d[0] * d[0] + d[1] * d[1]
                if d2 < dist_min * dist_min:  # touching (the reward terms' contacts; itself excluded)
                    touched += 1.0
                if d2 > 0.0 and d2 < reach * reach:
                    count += 1
                    if j < touching[CONTACT_SLOTS - 1]:
                        k = CONTACT_SLOTS - 1
                        while k > 0 and touching[k - 1] > j:
                            touching[k] = touching[k - 1]
                            k -= 1
                        touching[k] = j
    for k in range(ti.min(count, CONTACT_SLOTS)):
        j = touching[k]
        force += physics.contact_force(p, pos.get2(f, ib, P0, j), dist_min)
    if count > CONTACT_SLOTS:
        j = neighbours.next_contact(f, ib, i, touching[CONTACT_SLOTS - 1], P0, reach * reach, h, G, GS, GI, GC, M)
        while j < M:
            force += physics.contact_force(p, pos.get2(f, ib, P0, j), dist_min)
            j = neighbours.next_contact(f, ib, i, j, P0, reach * reach, h, G, GS, GI, GC, M)
    vel.set2(f, ib, V0, i, physics.integrate_velocity(vel.get2(f, ib, V0, i), force))
    f[blocks.contacts.at(ib, b, i)] = touched


@ti.func
def move(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
    P0, V0 = blocks.pos.env(ib, b), blocks.vel.env(ib, b)
    blocks.pos.set2(f, ib, P0, i, blocks.pos.get2(f, ib, P0, i) + blocks.vel.get2(f, ib, V0, i) * physics.DT)


@ti.func
def physics_step_grid(
    sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32, u: ti.template(), continuous: ti.template()
):
    """``physics_step`` with the contacts found through the cell grid (``grid_velocity``):
    velocities first (forces read positions only), then positions."""
    M = team_size(sm, ib)
    for i in range(M):
        grid_velocity(sm, f, ib, b, i, u, continuous)
    for i in range(M):
        move(f, ib, b, i)


@ti.func
def step_env(
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    u: ti.template(),
    continuous: ti.template(),
):
    """One step of env b: physics, targets, assignment, reward, done, auto-reset, observations."""
    if ti.static(lists & AGENT_LISTS):
        physics_step_grid(sm, f, ib, b, u, continuous)
    else:
        physics_step(cap, sm, f, ib, b, u, continuous)
    settle(task, cap, sm, lists, f, ib, u8, b, False)
    write_team_obs(task, sm, lists, f, ib, u8, b, False)


@ti.func
def context(f: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, d: ti.f32) -> tasks.Context:
    """What agent i's reward terms see of it (tasks.Context)."""
    return tasks.Context(d=d, pos=blocks.pos.load(f, ib, b, i), contacts=f[blocks.contacts.at(ib, b, i)])


@ti.func
def settle(
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    searched: ti.template(),
):
    """Env b after its agents moved: targets, assignment, reward, done, episode statistics,
    terminal observation and auto-reset (all but the step's own observation). ``searched``
    (FREE): targets, grids and nearest distances are already there (step_wide_kernel's passes),
    only the matching is left."""
    M = team_size(sm, ib)
    t = ib[blocks.step.env(ib, b)] + 1
    ib[blocks.step.env(ib, b)] = t
    if ti.static(searched):
        nearest.matching(f, ib, b)
        for i in range(M):  # after the matching: the targets it leaves free
            nearest.agent_free(f, ib, b, i)
    else:
        match(task, cap, sm, lists, f, ib, b)
    # the team reward: the mean of the agents' own (each the sum of the task's named terms)
    sum_d, sum_r, success, covered = 0.0, 0.0, True, 0
    R = blocks.agent_reward.env(ib, b)
    if ti.static(lists & FREE):  # d_t per target; agent i's own d: its matched or nearest free target (lap_dist)
        MD, ND, A = blocks.matched_dist.env(ib, b), blocks.lap_dist.env(ib, b), blocks.assignment.env(ib, b)
        for i in range(M):
            tasks.agent_reward(task, f, ib, b, i, context(f, ib, b, i, f[ND + i]))
            sum_r += f[R + i]
            covered += ti.cast(ib[A + i] >= 0, ti.i32)  # the threshold matching's size
            sum_d += f[MD + i]
        success = covered == M
    else:
        for i in range(M):
            d = f[blocks.matched_dist.at(ib, b, i)]
            tasks.agent_reward(task, f, ib, b, i, context(f, ib, b, i, d))
            sum_r += f[R + i]
            within = d < f[P_SUCCESS]
            success = success and within
            covered += ti.cast(within, ti.i32)
    r = sum_r / M
    f[blocks.reward.env(ib, b)] = r
    ret = f[blocks.return_acc.env(ib, b)] + r
    f[blocks.return_acc.env(ib, b)] = ret
    done = success or t >= ib[H_MAX_STEPS]
    u8[blocks.done.env(ib, b)] = ti.cast(done, ti.u8)
    if done:
        u8[blocks.ep_success.env(ib, b)] = ti.cast(success, ti.u8)
        u8[blocks.ep_truncated.env(ib, b)] = ti.cast(not success, ti.u8)
        ib[blocks.ep_length.env(ib, b)] = t
        f[blocks.ep_return.env(ib, b)] = ret
        if ti.static(lists & FREE):  # DIST is the mean of the d_t just computed
            f[blocks.ep_dist.env(ib, b)] = sum_d / M
        else:
            f[blocks.ep_dist.env(ib, b)] = target_dist(sm, f, ib, b)
        f[blocks.ep_covered.env(ib, b)] = covered / M
        for i in range(M):
            f[blocks.ep_matched_dist.at(ib, b, i)] = f[blocks.matched_dist.at(ib, b, i)]
        write_team_obs(task, sm, lists, f, ib, u8, b, True)
        start_episode(task, cap, sm, lists, f, ib, b)


@ti.kernel
def step_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    parallel: ti.template(),
):
    """One step of every environment, with the discrete actions already in the actions block."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):  # one environment per thread (step_wide_kernel: per agent)
        step_env(task, cap, sm, lists, f, ib, u8, b, f, False)  # ``u`` unused (discrete): any array will do


@ti.kernel
def step_wide_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    u: F32,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    continuous: ti.template(),
):
    """``step_kernel`` (``continuous``: ``step_continuous_kernel``) with neighbour lists, its
    per-agent work parallel over (env, agent): a GPU given one thread per environment idles
    at B = 10 x M = 1000 (docs/SWARM.md). Each top-level loop is a parallel pass; what stays
    per environment is what the team shares: the assignment, reward, done, statistics, the
    auto-reset and the cell grids (counting sorts). Every agent computes exactly what it does
    in ``step_env``, so the two give the same results bit for bit."""
    B, M, L = ib[H_B], team_size(sm, ib), tasks.landmark_count(task, sm, ib)
    for b, i in ti.ndrange(B, M):  # velocities from the old positions (the grid of the last observation)
        grid_velocity(sm, f, ib, b, i, u, continuous)
    for b, i in ti.ndrange(B, M):
        move(f, ib, b, i)
    if ti.static(lists & FREE):  # ``match``'s searches, target by target (each agent's: in ``settle``)
        for b in range(B):
            nearest_setup(task, sm, f, ib, b)
        for b, t in ti.ndrange(B, M):
            nearest.target_nearest(f, ib, b, t)
    for b in range(B):
        settle(task, cap, sm, lists, f, ib, u8, b, ti.static((lists & FREE) != 0))
        obs_grids(task, sm, lists, f, ib, b)
        ib[blocks.dropped.env(ib, b)] = 0
    for b, i in ti.ndrange(B, M):
        self_obs(f, ib, b, i, False)
        ti.atomic_add(ib[blocks.dropped.env(ib, b)], agent_list(lists, f, ib, u8, b, i, M, False))
        if ti.static(not (lists & LANDMARK_LISTS)):
            entity_offsets(L, f, ib, b, i, False)
    if ti.static(lists & OCCUPANCY):
        for b, l in ti.ndrange(B, L):
            landmark_occupants(f, ib, b, l)
    if ti.static(lists & RADIO):  # each agent's own table in parallel; the rounds per env
        for b, i in ti.ndrange(B, M):
            radio.candidates(f, ib, b, i)
            radio.rebuild(f, ib, b, i)
        for b in range(B):
            radio.rounds(f, ib, u8, b, M, False)
    if ti.static(lists & LANDMARK_LISTS):
        for b, i in ti.ndrange(B, M):
            agent_landmarks(lists, f, ib, u8, b, i, False)


@ti.kernel
def step_continuous_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    u: F32,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    parallel: ti.template(),
):
    """One step of every environment with continuous actions u: float32 [B * M * 2] (a
    kernel of its own, so that the discrete step keeps its three arguments)."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):
        step_env(task, cap, sm, lists, f, ib, u8, b, u, True)


@ti.kernel
def reset_masked_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    mask: U8,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    lists: ti.template(),
    parallel: ti.template(),
):
    """A fresh episode in the environments b with mask[b] != 0 (their random streams go on);
    the others are left as they are."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):
        if mask[b] != 0:
            start_episode(task, cap, sm, lists, f, ib, b)
            f[blocks.reward.env(ib, b)] = 0.0
            clear_agent_rewards(sm, f, ib, b)
            u8[blocks.done.env(ib, b)] = ti.u8(0)
            write_team_obs(task, sm, lists, f, ib, u8, b, False)
