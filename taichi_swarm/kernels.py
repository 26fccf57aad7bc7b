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
communication graph.

Compile-time arguments: ``task`` (the task id, tasks/), ``cap`` (work-array size of the
large-M assignment), ``sm`` (M itself for M <= layout.STATIC_M_MAX, so the
loops over agents unroll; else 0 and M is read from the header) and
``parallel`` (serial env loop for small batches, see env.py).
"""

import taichi as ti

from . import assignment, physics, tasks
from .layout import (
    H_B,
    H_COMM_RC,
    H_MAX_STEPS,
    O_ACTIONS,
    O_ADJ,
    O_DONE,
    O_EP_DIST,
    O_EP_LEN,
    O_EP_MATCHED,
    O_EP_RETURN,
    O_EP_SUCCESS,
    O_EP_TRUNC,
    O_LMK,
    O_MATCHED,
    O_OBS_ENT,
    O_OBS_SELF,
    O_POS,
    O_RET_ACC,
    O_REWARD,
    O_STEP,
    O_TERM_ADJ,
    O_TERM_ENT,
    O_TERM_SELF,
    O_TGT,
    O_VEL,
    P_AGENT_RADIUS,
    P_COMM_RADIUS,
    P_SUCCESS,
    agent_at,
    env_at,
    team_size,
)

F32 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)
U8 = ti.types.ndarray(dtype=ti.u8, ndim=1)


@ti.func
def match(task: ti.template(), cap: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32):
    """Targets, optimal assignment and matched distances d*_i of env b."""
    tasks.place_targets(task, sm, f, ib, b)
    assignment.solve(cap, sm, f, ib, b)


@ti.func
def write_team_obs(
    task: ti.template(),
    sm: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    self_off: ti.i32,
    ent_off: ti.i32,
    adj_off: ti.i32,
):
    """Every agent's observation, into the blocks starting at the given offsets:
    self [M, 4] = (vel, pos), entities [M, L, 2] = landmark - pos, adjacency
    [M, M] = who agent i hears (itself always; "rc": those within comm radius)."""
    M, L = team_size(sm, ib), tasks.landmark_count(task, sm, ib)
    P0, V0, LM = ib[O_POS] + b * M * 2, ib[O_VEL] + b * M * 2, ib[O_LMK] + b * L * 2
    S, E, A = self_off + b * M * 4, ent_off + b * M * L * 2, adj_off + b * M * M
    restricted = ib[H_COMM_RC] != 0
    radius = f[P_COMM_RADIUS]
    r2 = radius * radius
    for i in range(M):
        px, py = f[P0 + 2 * i], f[P0 + 2 * i + 1]
        f[S + 4 * i + 0] = f[V0 + 2 * i]
        f[S + 4 * i + 1] = f[V0 + 2 * i + 1]
        f[S + 4 * i + 2] = px
        f[S + 4 * i + 3] = py
        for l in range(L):
            f[E + (i * L + l) * 2] = f[LM + 2 * l] - px
            f[E + (i * L + l) * 2 + 1] = f[LM + 2 * l + 1] - py
    for i in range(M):  # the graph is symmetric: each pair once
        u8[A + i * M + i] = ti.u8(1)
        px, py = f[P0 + 2 * i], f[P0 + 2 * i + 1]
        for j in range(i + 1, M):
            dx, dy = f[P0 + 2 * j] - px, f[P0 + 2 * j + 1] - py
            hears = ti.cast((not restricted) or dx * dx + dy * dy <= r2, ti.u8)
            u8[A + i * M + j] = hears
            u8[A + j * M + i] = hears


@ti.func
def target_dist(sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32) -> ti.f32:
    """DIST: mean over targets of the distance to the closest agent."""
    M = team_size(sm, ib)
    P0, T0 = ib[O_POS] + b * M * 2, ib[O_TGT] + b * M * 2
    total = 0.0
    for t in range(M):
        tp = ti.math.vec2(f[T0 + 2 * t], f[T0 + 2 * t + 1])
        best = 1e30
        for i in range(M):
            best = ti.min(best, (ti.math.vec2(f[P0 + 2 * i], f[P0 + 2 * i + 1]) - tp).norm())
        total += best
    return total / M


@ti.func
def start_episode(
    task: ti.template(), cap: ti.template(), sm: ti.template(), f: ti.template(), ib: ti.template(), b: ti.i32
):
    tasks.spawn(task, sm, f, ib, b)
    ib[env_at(ib, O_STEP, b)] = 0
    f[env_at(ib, O_RET_ACC, b)] = 0.0
    match(task, cap, sm, f, ib, b)


@ti.kernel
def reset_kernel(
    f: F32, ib: I32, u8: U8, task: ti.template(), cap: ti.template(), sm: ti.template(), parallel: ti.template()
):
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):  # the only parallel loop: one environment per thread
        start_episode(task, cap, sm, f, ib, b)
        f[env_at(ib, O_REWARD, b)] = 0.0
        u8[env_at(ib, O_DONE, b)] = ti.u8(0)
        write_team_obs(task, sm, f, ib, u8, b, ib[O_OBS_SELF], ib[O_OBS_ENT], ib[O_ADJ])


@ti.kernel
def refresh_kernel(
    f: F32, ib: I32, u8: U8, task: ti.template(), cap: ti.template(), sm: ti.template(), parallel: ti.template()
):
    """Recompute targets, assignment and observations after ``set_state``."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):
        match(task, cap, sm, f, ib, b)
        write_team_obs(task, sm, f, ib, u8, b, ib[O_OBS_SELF], ib[O_OBS_ENT], ib[O_ADJ])


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

    Discrete (``continuous`` False): the actions are ib[O_ACTIONS] and ``u`` is not read.
    Continuous: u is the float32 [B * M * 2] array of force commands (clipped to [-1, 1])."""
    M = team_size(sm, ib)
    dist_min = 2.0 * f[P_AGENT_RADIUS]
    P0, V0, A0 = ib[O_POS] + b * M * 2, ib[O_VEL] + b * M * 2, ib[O_ACTIONS] + b * M
    force = ti.Vector.zero(ti.f32, 2 * cap)  # [M, 2], on the thread's stack
    for i in range(M):
        if ti.static(continuous):
            c = physics.continuous_force(ti.math.vec2(u[(b * M + i) * 2], u[(b * M + i) * 2 + 1]))
            force[2 * i] = c[0]
            force[2 * i + 1] = c[1]
        else:
            a = physics.action_force(ib[A0 + i])
            force[2 * i] = a[0]
            force[2 * i + 1] = a[1]
    for i in range(M):  # contact forces from the old positions, each pair once (equal and
        # opposite; every agent still sums its contacts in increasing j, as MPE does)
        p = ti.math.vec2(f[P0 + 2 * i], f[P0 + 2 * i + 1])
        for j in range(i + 1, M):
            fc = physics.contact_force(p, ti.math.vec2(f[P0 + 2 * j], f[P0 + 2 * j + 1]), dist_min)
            force[2 * i] += fc[0]
            force[2 * i + 1] += fc[1]
            force[2 * j] -= fc[0]
            force[2 * j + 1] -= fc[1]
    for i in range(M):
        v = physics.integrate_velocity(
            ti.math.vec2(f[V0 + 2 * i], f[V0 + 2 * i + 1]), ti.math.vec2(force[2 * i], force[2 * i + 1])
        )
        f[V0 + 2 * i] = v[0]
        f[V0 + 2 * i + 1] = v[1]
        # plain read-modify-write: ``+=`` on an ndarray element compiles to an atomic add
        # (a lock cmpxchg loop), needless here as each env belongs to one thread
        f[P0 + 2 * i] = f[P0 + 2 * i] + v[0] * physics.DT
        f[P0 + 2 * i + 1] = f[P0 + 2 * i + 1] + v[1] * physics.DT


@ti.func
def step_env(
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    f: ti.template(),
    ib: ti.template(),
    u8: ti.template(),
    b: ti.i32,
    u: ti.template(),
    continuous: ti.template(),
):
    """One step of env b: physics, targets, assignment, reward, done, auto-reset, observations."""
    M = team_size(sm, ib)
    physics_step(cap, sm, f, ib, b, u, continuous)
    t = ib[env_at(ib, O_STEP, b)] + 1
    ib[env_at(ib, O_STEP, b)] = t
    match(task, cap, sm, f, ib, b)
    sum_d, sum_clipped, success = 0.0, 0.0, True
    for i in range(M):
        d = f[agent_at(ib, O_MATCHED, b, M, i, 1)]
        sum_d += d
        sum_clipped += ti.math.clamp(d, 0.0, 2.0)
        success = success and d < f[P_SUCCESS]
    r = tasks.reward(task, sum_d / M, sum_clipped / M)
    f[env_at(ib, O_REWARD, b)] = r
    ret = f[env_at(ib, O_RET_ACC, b)] + r
    f[env_at(ib, O_RET_ACC, b)] = ret
    done = success or t >= ib[H_MAX_STEPS]
    u8[env_at(ib, O_DONE, b)] = ti.cast(done, ti.u8)
    if done:
        u8[env_at(ib, O_EP_SUCCESS, b)] = ti.cast(success, ti.u8)
        u8[env_at(ib, O_EP_TRUNC, b)] = ti.cast(not success, ti.u8)
        ib[env_at(ib, O_EP_LEN, b)] = t
        f[env_at(ib, O_EP_RETURN, b)] = ret
        f[env_at(ib, O_EP_DIST, b)] = target_dist(sm, f, ib, b)
        for i in range(M):
            f[agent_at(ib, O_EP_MATCHED, b, M, i, 1)] = f[agent_at(ib, O_MATCHED, b, M, i, 1)]
        write_team_obs(task, sm, f, ib, u8, b, ib[O_TERM_SELF], ib[O_TERM_ENT], ib[O_TERM_ADJ])
        start_episode(task, cap, sm, f, ib, b)
    write_team_obs(task, sm, f, ib, u8, b, ib[O_OBS_SELF], ib[O_OBS_ENT], ib[O_ADJ])


@ti.kernel
def step_kernel(
    f: F32, ib: I32, u8: U8, task: ti.template(), cap: ti.template(), sm: ti.template(), parallel: ti.template()
):
    """One step of every environment, with the discrete actions already in ib[O_ACTIONS]."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):  # the only parallel loop: one environment per thread
        step_env(task, cap, sm, f, ib, u8, b, f, False)  # ``u`` unused (discrete): any array will do


@ti.kernel
def step_continuous_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    u: F32,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    parallel: ti.template(),
):
    """One step of every environment with continuous actions u: float32 [B * M * 2] (a
    kernel of its own, so that the discrete step keeps its three arguments)."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):
        step_env(task, cap, sm, f, ib, u8, b, u, True)


@ti.kernel
def reset_masked_kernel(
    f: F32,
    ib: I32,
    u8: U8,
    mask: U8,
    task: ti.template(),
    cap: ti.template(),
    sm: ti.template(),
    parallel: ti.template(),
):
    """A fresh episode in the environments b with mask[b] != 0 (their random streams go on);
    the others are left as they are."""
    ti.loop_config(serialize=ti.static(not parallel))
    for b in range(ib[H_B]):
        if mask[b] != 0:
            start_episode(task, cap, sm, f, ib, b)
            f[env_at(ib, O_REWARD, b)] = 0.0
            u8[env_at(ib, O_DONE, b)] = ti.u8(0)
            write_team_obs(task, sm, f, ib, u8, b, ib[O_OBS_SELF], ib[O_OBS_ENT], ib[O_ADJ])
