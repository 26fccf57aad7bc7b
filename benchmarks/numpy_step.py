"""The coverage step in plain NumPy, batched over environments: the baseline of ``benchmarks/sim.py``.

The same step as the fused Taichi kernel (taichi_swarm/kernels.py; docs/PAPER.md
sections 1-3) for the coverage task, written as whole-batch array expressions:
action forces, MPE contact forces, semi-implicit Euler, the communication graph,
the observations, the team reward from an exact optimal assignment, success,
time limit and auto-reset. No Python loop over agents or pairs; the one loop over
environments is the assignment (scipy's ``linear_sum_assignment``, one call per
environment), which ``assign=False`` leaves out.

Shapes: B environments, M agents, L = M landmarks; float32 throughout like the kernels.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from taichi_swarm.physics import CONTACT_FORCE, CONTACT_MARGIN, DAMPING, DT, MASS, SENSITIVITY
from taichi_swarm.tasks import TASK_SPECS

# Unit direction of each discrete action (0 no-op, 1 -x, 2 +x, 3 -y, 4 +y): [5, 2]
ACTION_DIRS = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.float32)
AGENT_RADIUS = TASK_SPECS["coverage"].agent_radius
SUCCESS_THRESHOLD = TASK_SPECS["coverage"].params["success_threshold"]
MAX_STEPS = 50


def pairwise(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """delta [2, B, N, K] = a_n - b_k (coordinate first) and its norm [B, N, K], for a [B, N, 2], b [B, K, 2].

    Coordinate-first arrays broadcast over contiguous axes: ~2x faster than [B, N, K, 2].
    """
    a_t, b_t = np.ascontiguousarray(a.transpose(2, 0, 1)), np.ascontiguousarray(b.transpose(2, 0, 1))  # [2, B, *]
    delta = a_t[:, :, :, None] - b_t[:, :, None, :]
    return delta, np.sqrt(delta[0] * delta[0] + delta[1] * delta[1])


def physics(
    pos: np.ndarray, vel: np.ndarray, actions: np.ndarray, agent_radius: float = AGENT_RADIUS
) -> tuple[np.ndarray, np.ndarray]:
    """One MPE world step: pos, vel [B, M, 2] float32, actions int [B, M] -> new pos, vel."""
    force = SENSITIVITY * ACTION_DIRS[actions]  # [B, M, 2]
    delta, dist = pairwise(pos, pos)  # [2, B, M, M] p_i - p_j, [B, M, M]
    # pen = k softplus(-(d - dist_min) / k), softplus(x) = logaddexp(0, x) (stable)
    pen = CONTACT_MARGIN * np.logaddexp(np.float32(0.0), -(dist - 2 * agent_radius) / CONTACT_MARGIN)
    # F_ij = 100 (p_i - p_j) / d * pen; no force on itself (d = 0), nor between
    # coincident agents (NOTE: MPE divides by zero there, the kernels skip the pair too)
    scale = np.divide(CONTACT_FORCE * pen, dist, out=np.zeros_like(dist), where=dist > 0)  # [B, M, M]
    force += np.stack([(scale * delta[0]).sum(axis=-1), (scale * delta[1]).sum(axis=-1)], axis=-1)
    vel = vel * (1 - DAMPING) + (force / MASS) * DT
    return pos + vel * DT, vel


def comm_graph(pos: np.ndarray, comm_radius: float | None) -> np.ndarray:
    """adj [B, M, M] bool, adj[b, i, j]: i hears j (None: unrestricted; else |p_i - p_j| <= radius)."""
    B, M, _ = pos.shape
    if comm_radius is None:
        return np.ones((B, M, M), dtype=bool)
    _, dist = pairwise(pos, pos)
    return (dist <= comm_radius) | np.eye(M, dtype=bool)


def observe(pos: np.ndarray, vel: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """self [B, M, 4] = (vel, pos) and entities [B, M, L, 2] = landmark - agent position."""
    (B, M, _), L = pos.shape, landmarks.shape[1]
    entities = np.empty((B, M, L, 2), dtype=pos.dtype)
    for c in range(2):  # per coordinate (x, y): broadcasting over a trailing axis of 2 is slow
        np.subtract(landmarks[:, None, :, c], pos[:, :, None, c], out=entities[..., c])
    return np.concatenate([vel, pos], axis=-1), entities


def matched_distances(pos: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """d*_i [B, M] under the optimal agent-target assignment (a Python loop over B)."""
    _, cost = pairwise(pos, targets)  # [B, M, M]
    cols = np.stack([linear_sum_assignment(c)[1] for c in cost])  # [B, M] target of agent i
    return np.take_along_axis(cost, cols[..., None], axis=2)[..., 0]


class NumpyCoverage:
    """B coverage teams of M agents; ``step`` mirrors ``SwarmEnv.step`` of the Taichi env.

    ``assign=False`` skips the assignment, and with it the reward (0) and success:
    episodes then end at the time limit only.
    """

    def __init__(
        self, num_envs: int, num_agents: int, comm_radius: float | None = None, assign: bool = True, seed: int = 0
    ):
        self.B, self.M = num_envs, num_agents
        self.comm_radius, self.assign = comm_radius, assign
        self.rng = np.random.default_rng(seed)
        self.pos = self._uniform(self.B)  # [B, M, 2]
        self.vel = np.zeros_like(self.pos)  # [B, M, 2]
        self.landmarks = self._uniform(self.B)  # [B, L, 2]
        self.t = np.zeros(self.B, dtype=np.int32)  # [B] steps into the episode

    def _uniform(self, n: int) -> np.ndarray:
        """[n, M, 2] float32 uniform in [-1, 1]."""
        return self.rng.random((n, self.M, 2), dtype=np.float32) * 2 - 1

    def step(self, actions: np.ndarray):
        """actions int [B, M] -> obs (self, entities, adj), reward [B], done [B]."""
        self.pos, self.vel = physics(self.pos, self.vel, actions)
        self.t += 1
        if self.assign:
            d = matched_distances(self.pos, self.landmarks)  # [B, M]
            reward = np.clip(-d.mean(axis=1), -15, 15)
            success = (d < SUCCESS_THRESHOLD).all(axis=1)
        else:
            reward, success = np.zeros(self.B, dtype=np.float32), np.zeros(self.B, dtype=bool)
        done = success | (self.t >= MAX_STEPS)  # [B]
        n = int(done.sum())
        if n:  # auto-reset of the finished environments only
            self.pos[done], self.landmarks[done] = self._uniform(n), self._uniform(n)
            self.vel[done], self.t[done] = 0.0, 0
        obs_self, entities = observe(self.pos, self.vel, self.landmarks)
        return (obs_self, entities, comm_graph(self.pos, self.comm_radius)), reward, done
