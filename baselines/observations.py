"""What the adapters share: agent names and flat per-agent observations (the paper's local one,
or the full one of its baselines).

Shapes: B environments, M agents, L landmarks; ``self_obs`` [B, M, 4] = (vx, vy, px, py) and
``entities`` [B, M, L, 2] = landmark - agent position, as ``SwarmEnv`` writes them.

    "local"  [B, M, 4 + 2L]                 the paper's (PAPER.md s.3): own velocity and absolute
                                            position, then every landmark relative to the agent;
                                            teammates come only through the communication graph
                                            (``obs["adj"]``), which the adapters pass alongside.
    "full"   [B, M, 4 + 2L + 4(M - 1)]      the paper's baselines (full observability, no
                                            communication), laid out like MPE's simple_spread:
                                            the local part, then the positions of the other agents
                                            relative to the agent, then their velocities relative
                                            to the agent's, others in index order (j != i).

Written once for numpy arrays and torch tensors (the same expressions): no loop over environments.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from .config import OBS_MODES

SELF_DIM = 4


def agent_names(num_agents: int) -> list[str]:
    """["agent_0", ..., "agent_{M-1}"] (the names VMAS and PettingZoo use; BenchMARL groups them as "agents")."""
    return [f"agent_{i}" for i in range(num_agents)]


def check_obs_mode(obs_mode) -> str:
    """``obs_mode`` itself if it is one of OBS_MODES, else a ValueError naming it."""
    if not isinstance(obs_mode, str) or obs_mode not in OBS_MODES:
        raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {obs_mode!r}")
    return obs_mode


def obs_dim(obs_mode: str, num_agents: int, num_landmarks: int) -> int:
    """Length D of one agent's flat observation."""
    local = SELF_DIM + 2 * num_landmarks
    return local if check_obs_mode(obs_mode) == "local" else local + 4 * (num_agents - 1)


@cache
def _others(num_agents: int) -> np.ndarray:
    """int64 [M, M - 1]: row i lists j = 0..M-1 without i."""
    idx = np.arange(num_agents)
    return np.stack([np.delete(idx, i) for i in range(num_agents)]).reshape(num_agents, num_agents - 1)


def flat_observation(obs_mode: str, self_obs, entities):
    """[B, M, D] float32 observation (a new array/tensor) from self_obs [B, M, 4], entities [B, M, L, 2]."""
    B, M = self_obs.shape[0], self_obs.shape[1]
    parts = [self_obs, entities.reshape(B, M, 2 * entities.shape[2])]
    if check_obs_mode(obs_mode) == "full":
        vel, pos = self_obs[..., 0:2], self_obs[..., 2:4]  # [B, M, 2] each
        others = _others(M)  # [M, M - 1]
        if not isinstance(self_obs, np.ndarray):
            import torch

            others = torch.from_numpy(others).to(self_obs.device)
        rel_pos = pos[:, others] - pos[:, :, None]  # [B, M, M - 1, 2]: p_j - p_i
        rel_vel = vel[:, others] - vel[:, :, None]  # [B, M, M - 1, 2]: v_j - v_i
        parts += [rel_pos.reshape(B, M, 2 * (M - 1)), rel_vel.reshape(B, M, 2 * (M - 1))]  # (-1 fails at M = 1)
    if isinstance(self_obs, np.ndarray):
        return np.concatenate(parts, axis=-1)
    import torch

    return torch.cat(parts, dim=-1)
