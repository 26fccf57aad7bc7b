"""Brute-force NumPy (float64) reference of the spec's formulas, written the
way MPE's multiagent/core.py loops: per agent, per pair, no vectorisation.
Only tests import it."""

import math

import numpy as np
from scipy.optimize import linear_sum_assignment

DT, DAMPING, MASS, SENS = 0.1, 0.25, 1.0, 5.0
CONTACT_FORCE, CONTACT_MARGIN = 100.0, 1e-3
ACTION_U = {0: (0, 0), 1: (-1, 0), 2: (1, 0), 3: (0, -1), 4: (0, 1)}


def mpe_step(pos, vel, actions, agent_radius):
    """One world step of one team: pos, vel [M, 2]; actions [M] -> new pos, vel."""
    return _world_step(pos, vel, [np.array(ACTION_U[int(a)], dtype=np.float64) * SENS for a in actions], agent_radius)


def mpe_step_continuous(pos, vel, u, agent_radius):
    """The same with continuous actions u [M, 2]: force = 5 clip(u, -1, 1) per axis."""
    return _world_step(pos, vel, [np.clip(np.asarray(a, dtype=np.float64), -1, 1) * SENS for a in u], agent_radius)


def _world_step(pos, vel, force, agent_radius):
    """Contact forces added to the action forces ``force`` (list of M [2]), then Euler."""
    pos, vel = pos.astype(np.float64), vel.astype(np.float64)
    M = len(pos)
    for a in range(M):  # MPE: for a, for b > a: equal and opposite contact forces
        for b in range(a + 1, M):
            delta = pos[a] - pos[b]
            dist = math.sqrt(float(np.sum(delta**2)))
            dist_min = 2 * agent_radius
            pen = np.logaddexp(0, -(dist - dist_min) / CONTACT_MARGIN) * CONTACT_MARGIN
            f = CONTACT_FORCE * delta / dist * pen
            force[a] = force[a] + f
            force[b] = force[b] - f
    new_vel = vel * (1 - DAMPING) + np.array(force) / MASS * DT
    return pos + new_vel * DT, new_vel


def matched_distances(pos, targets):
    """Optimal assignment (scipy) of agents to targets: d*_i [M] and total cost."""
    cost = np.linalg.norm(pos[:, None, :] - targets[None, :, :], axis=-1)
    rows, cols = linear_sum_assignment(cost)
    d = np.empty(len(pos))
    d[rows] = cost[rows, cols]
    return d, cost[rows, cols].sum()


def formation_targets(pos, landmark, radius=0.5):
    ang = np.mod(np.arctan2(pos[:, 1] - landmark[1], pos[:, 0] - landmark[0]), 2 * np.pi)
    theta0 = ang.min()
    k = np.arange(len(pos))
    a = theta0 + 2 * np.pi * k / len(pos)
    return landmark + radius * np.stack([np.cos(a), np.sin(a)], axis=-1)


def line_targets(l0, l1, M):
    k = np.arange(M)[:, None]
    return l0 + (l1 - l0) * k / (M - 1)
