"""PettingZoo ``ParallelEnv`` over ONE environment of the simulator (``taichi_swarm.make(..., num_envs=1)``).

    env = SwarmParallelEnv("coverage", num_agents=3, obs_mode="full")
    obs, infos = env.reset(seed=0)
    while env.agents:
        actions = {a: env.action_space(a).sample() for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)

Agents ``agent_0 .. agent_{M-1}``; actions ``Discrete(5)`` (0 no-op, -x, +x, -y, +y) or, with
``action_space="continuous"``, ``Box(-1, 1, (2,))`` (force 5 clip(u, -1, 1) per axis); observations
``Box`` float32 [D] (baselines/observations.py: "local" or "full").

Episode semantics are PettingZoo's, not the simulator's: the simulator restarts a finished
episode inside ``step``, the adapter instead returns the episode's last observation, sets
``terminations`` (success) or ``truncations`` (time limit) for every agent, and empties
``agents`` until ``reset()``. Every agent gets the team reward.

Infos, per agent: ``success`` (the episode ended in success at this step); in "local" mode
``adj`` bool [M], who this agent hears (the communication graph's row, PAPER.md s.3); at the
episode's end ``episode``: success, truncated, length, return, dist (DIST, coverage's metric)
and matched_dist (the agent's final d*_i).
"""

from __future__ import annotations

import numbers

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

import taichi_swarm

from .observations import agent_names, check_obs_mode, flat_observation, obs_dim


class SwarmParallelEnv(ParallelEnv):
    """One team of ``num_agents`` agents on ``task`` as a PettingZoo ParallelEnv.

    task: coverage, formation or line. obs_mode: "local" (the paper's) or "full" (its
    baselines'). action_space: "discrete", "fine" (9 actions) or "continuous". comm, comm_radius: the
    communication graph reported in infos (local mode). seed: the first reset's seed
    (``reset(seed=...)`` overrides). task_params: ``max_steps`` (50) and the task's
    parameters, as for ``taichi_swarm.make``.
    """

    metadata = {"name": "taichi_swarm_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(
        self,
        task: str = "coverage",
        num_agents: int = 3,
        obs_mode: str = "local",
        action_space: str = "discrete",
        comm: str = "uc",
        comm_radius: float = 1.0,
        seed: int | None = None,
        **task_params,
    ):
        self.obs_mode = check_obs_mode(obs_mode)
        # numpy buffers, CPU: PettingZoo speaks numpy, and one env gains nothing from a GPU
        self.sim = taichi_swarm.make(
            task,
            1,
            num_agents,
            comm=comm,
            comm_radius=comm_radius,
            seed=seed,
            array="numpy",
            action_space=action_space,
            **task_params,
        )
        self.task = task
        self.team_size = M = self.sim.num_agents
        self.continuous = self.sim.continuous
        self.max_steps = self.sim.params["max_steps"]
        self.possible_agents = agent_names(M)
        self.agents: list[str] = []
        self._index = {name: i for i, name in enumerate(self.possible_agents)}
        D = obs_dim(self.obs_mode, M, self.sim.num_landmarks)
        self._obs_spaces = {a: spaces.Box(-np.inf, np.inf, (D,), np.float32) for a in self.possible_agents}
        if self.continuous:
            act = {a: spaces.Box(-1.0, 1.0, (2,), np.float32) for a in self.possible_agents}
        else:
            act = {a: spaces.Discrete(self.sim.num_actions) for a in self.possible_agents}
        self._act_spaces = act
        n_state = 4 * M + 2 * self.sim.num_landmarks
        self.state_space = spaces.Box(-np.inf, np.inf, (n_state,), np.float32)
        self.render_mode = None
        # the step's actions, written in place: int64 [1, M] or float32 [1, M, 2]
        self._actions = np.zeros((1, M, 2), np.float32) if self.continuous else np.zeros((1, M), np.int64)

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> spaces.Space:
        return self._act_spaces[self._check_agent(agent)]

    def _check_agent(self, agent) -> str:
        if agent not in self._index:
            raise ValueError(f"agent must be one of {self.possible_agents}, got {agent!r}")
        return agent

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        """A fresh episode; returns ``(observations, infos)``. ``seed`` restarts the random stream."""
        self.sim.reset(seed=seed)
        self.agents = self.possible_agents[:]
        obs = self.sim.obs
        return self._split(obs["self"], obs["entities"]), self._infos(obs["adj"], None, False)

    def step(self, actions: dict):
        """Advance one step; returns ``(observations, rewards, terminations, truncations, infos)``."""
        if not self.agents:
            raise RuntimeError("the episode has ended (or never started): call reset() before step()")
        self._read_actions(actions)
        obs, reward, done, info = self.sim.step(self._actions)
        ended = bool(done[0])
        if ended:  # the simulator already started the next episode: report the one that ended
            src, ep = info["terminal_obs"], info["episode"]
            success, truncated = bool(ep["success"][0]), bool(ep["truncated"][0])
        else:
            src, ep, success, truncated = obs, None, False, False
        observations = self._split(src["self"], src["entities"])
        infos = self._infos(src["adj"], ep, success)
        r = float(reward[0])
        rewards = dict.fromkeys(self.agents, r)
        terminations = dict.fromkeys(self.agents, success)
        truncations = dict.fromkeys(self.agents, truncated)
        if ended:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """float32 [4M + 2L]: positions [M, 2], velocities [M, 2] and landmarks [L, 2], flattened."""
        s = self.sim.get_state()
        return np.concatenate([s["pos"][0].ravel(), s["vel"][0].ravel(), s["landmarks"][0].ravel()])

    def close(self) -> None:
        self.agents = []

    # ------------------------------------------------------------------ helpers
    def _read_actions(self, actions: dict) -> None:
        """Check ``actions`` (one per live agent) and write them into self._actions."""
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict agent name -> action, got {type(actions).__name__}")
        unknown = sorted(set(actions) - set(self.agents), key=str)
        if unknown:
            raise ValueError(f"actions has unknown or finished agent(s) {unknown}; live agents: {self.agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions is missing agent(s) {missing}")
        for name, a in actions.items():
            i = self._index[name]
            if self.continuous:
                u = np.asarray(a, dtype=np.float32)
                if u.shape != (2,):
                    raise ValueError(f"actions[{name!r}] must have shape (2,) (continuous), got {u.shape}")
                if np.isnan(u).any():
                    raise taichi_swarm.NaNActionsError(f"actions[{name!r}] must not contain NaN, got {u.tolist()}")
                self._actions[0, i] = u
            else:
                if isinstance(a, np.ndarray) and a.shape == ():
                    a = a.item()
                if isinstance(a, bool) or not isinstance(a, numbers.Integral) or not 0 <= a < self.sim.num_actions:
                    raise ValueError(
                        f"actions[{name!r}] must be an integer in 0..{self.sim.num_actions - 1} (discrete), got {a!r}"
                    )
                self._actions[0, i] = a

    def _split(self, self_obs, entities) -> dict:
        """Per-agent copies of the flat observation of env 0."""
        flat = flat_observation(self.obs_mode, self_obs, entities)[0]  # [M, D], a new array
        return {a: flat[i] for i, a in enumerate(self.possible_agents)}

    def _infos(self, adj, episode: dict | None, success: bool) -> dict:
        infos = {}
        for i, a in enumerate(self.possible_agents):
            d = {"success": success}
            if self.obs_mode == "local":
                d["adj"] = adj[0, i].copy()
            if episode is not None:
                d["episode"] = {
                    "success": bool(episode["success"][0]),
                    "truncated": bool(episode["truncated"][0]),
                    "length": int(episode["length"][0]),
                    "return": float(episode["return"][0]),
                    "dist": float(episode["dist"][0]),
                    "covered": float(episode["covered"][0]),
                    "matched_dist": float(episode["matched_dist"][0, i]),
                }
            infos[a] = d
        return infos


def parallel_env(**kwargs) -> SwarmParallelEnv:
    """PettingZoo's conventional constructor name; the arguments of SwarmParallelEnv."""
    return SwarmParallelEnv(**kwargs)


__all__ = ["SwarmParallelEnv", "parallel_env"]
