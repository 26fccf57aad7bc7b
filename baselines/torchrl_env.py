"""TorchRL ``EnvBase`` over the whole batch of the simulator, keyed like TorchRL's VMAS wrapper.

    env = SwarmTorchRLEnv("coverage", num_envs=32, num_agents=3, obs_mode="full")
    td = env.rollout(50, break_when_any_done=False)

Keys (batch_size [B]; one group "agents", agents agent_0..agent_{M-1}):
    ("agents", "observation")  float32 [B, M, D]     baselines/observations.py ("local" / "full")
    ("agents", "adj")          bool    [B, M, M]     "local" only: adj[b, i, j], agent i hears agent j
    ("agents", "action")       int64   [B, M]        discrete: 0..4 (categorical, like VMAS's
                                                     categorical_actions=True)
                               float32 [B, M, 2]     continuous: in [-1, 1], force 5 u per axis
    ("agents", "reward")       float32 [B, M, 1]     the team reward, the same for every agent
    "done", "terminated", "truncated"            bool [B, 1]     episode end; success; time limit
    ("agents", "done" / "terminated" / "truncated") bool [B, M, 1]  the same per agent
    ("episode", "success" / "length" / "return" / "dist" / "covered")  [B, 1]  statistics of the episode that
                                                     ended at this step (where "done"; 0 elsewhere)

Auto-reset: the simulator restarts a finished environment inside its own step. Here a step
returns the episode's last observation (the simulator's ``info["terminal_obs"]``) where
"done", and remembers that these environments already hold their next episode's first
observation: TorchRL's partial ``_reset`` of them (the ``"_reset"`` mask a rollout or collector
sends) then just returns that observation, without touching the simulator, so trajectories
equal stepping ``SwarmEnv`` directly. A ``_reset`` of environments that are still running
(a collector truncating a trajectory, or a reset without a mask) starts fresh episodes in just
those (``SwarmEnv.reset_envs``); an environment whose fresh episode has not been stepped yet
counts as reset already, so ``reset(); reset()`` gives the same first observation twice.

Memory: actions go to the simulator as they come (discrete ones are copied once into its int32
action block, a CPU tensor read through numpy; continuous float32 ones go straight into the
kernel). Outputs are read from the simulator's torch buffers, each written once into a new
tensor (no numpy round trip): they cannot be views, since the next step overwrites the
buffers while TorchRL keeps every step's tensordict.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

import taichi_swarm

from .observations import agent_names, check_obs_mode, flat_observation, obs_dim

GROUP = "agents"


class SwarmTorchRLEnv(EnvBase):
    """``num_envs`` teams of ``num_agents`` agents on ``task`` as one batched TorchRL env.

    task: coverage, formation or line. obs_mode: "local" (the paper's, with the comm graph
    under ("agents", "adj")) or "full" (its baselines'). continuous_actions: MPE's continuous
    mode instead of the 5 discrete actions. comm, comm_radius: the communication graph.
    seed: the first reset's seed. device: "cpu" or "cuda" (Taichi then runs on that device).
    task_params: ``max_steps`` (50) and the task's parameters, as for ``taichi_swarm.make``.
    """

    batch_locked = True

    def __init__(
        self,
        task: str = "coverage",
        num_envs: int = 32,
        num_agents: int = 3,
        obs_mode: str = "local",
        continuous_actions: bool = False,
        comm: str = "uc",
        comm_radius: float = 1.0,
        seed: int | None = None,
        device: str | torch.device = "cpu",
        **task_params,
    ):
        self.obs_mode = check_obs_mode(obs_mode)
        if not isinstance(continuous_actions, bool):
            raise ValueError(f"continuous_actions must be a bool, got {continuous_actions!r}")
        device = torch.device(device)
        if device.type not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {str(device)!r}")
        self.sim = taichi_swarm.make(
            task,
            num_envs,
            num_agents,
            comm=comm,
            comm_radius=comm_radius,
            arch="cuda" if device.type == "cuda" else "cpu",
            seed=seed,
            array="torch",
            action_space="continuous" if continuous_actions else "discrete",
            **task_params,
        )
        super().__init__(device=device, batch_size=torch.Size([self.sim.num_envs]))
        self.task = task
        self.num_envs = self.sim.num_envs
        self.n_agents = self.sim.num_agents
        self.continuous_actions = continuous_actions
        self.max_steps = self.sim.params["max_steps"]
        self.agent_names = agent_names(self.n_agents)
        self.group_map = {GROUP: list(self.agent_names)}
        self._obs_dim = obs_dim(self.obs_mode, self.n_agents, self.sim.num_landmarks)
        # [B] True where the simulator already holds a fresh, never stepped episode
        self._fresh = torch.zeros(self.num_envs, dtype=torch.bool, device=device)
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B, M, dev = self.num_envs, self.n_agents, self.device
        flag = Categorical(n=2, shape=(B, M, 1), dtype=torch.bool, device=dev)
        obs = {"observation": Unbounded(shape=(B, M, self._obs_dim), dtype=torch.float32, device=dev)}
        if self.obs_mode == "local":
            obs["adj"] = Categorical(n=2, shape=(B, M, M), dtype=torch.bool, device=dev)
        env_flag = Categorical(n=2, shape=(B, 1), dtype=torch.bool, device=dev)
        episode = Composite(
            success=env_flag.clone(),
            length=Unbounded(shape=(B, 1), dtype=torch.int64, device=dev),
            dist=Unbounded(shape=(B, 1), dtype=torch.float32, device=dev),
            covered=Unbounded(shape=(B, 1), dtype=torch.float32, device=dev),
            shape=(B,),
            device=dev,
        )
        episode["return"] = Unbounded(shape=(B, 1), dtype=torch.float32, device=dev)
        self.full_observation_spec = Composite(
            {GROUP: Composite(obs, shape=(B, M), device=dev), "episode": episode}, shape=(B,), device=dev
        )
        if self.continuous_actions:
            action = Bounded(low=-1.0, high=1.0, shape=(B, M, 2), dtype=torch.float32, device=dev)
        else:
            action = Categorical(n=self.sim.num_actions, shape=(B, M), dtype=torch.int64, device=dev)
        self.full_action_spec = Composite(
            {GROUP: Composite(action=action, shape=(B, M), device=dev)}, shape=(B,), device=dev
        )
        self.full_reward_spec = Composite(
            {GROUP: Composite(reward=Unbounded(shape=(B, M, 1), device=dev), shape=(B, M), device=dev)},
            shape=(B,),
            device=dev,
        )
        self.full_done_spec = Composite(
            done=env_flag.clone(),
            terminated=env_flag.clone(),
            truncated=env_flag.clone(),
            **{GROUP: Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=(B, M), device=dev)},
            shape=(B,),
            device=dev,
        )

    # ------------------------------------------------------------------ EnvBase
    def _set_seed(self, seed: int | None) -> None:
        """Restart every environment's random stream from ``seed``, with a fresh episode each:
        ``set_seed(s)`` then ``reset()`` starts like ``SwarmEnv.reset(seed=s)``."""
        self.sim.reset(seed=seed)
        self._fresh.fill_(True)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = self._reset_mask(tensordict)  # [B] bool; all True without a "_reset" entry
        # Environments whose episode has just started (auto-reset inside the simulator's step,
        # or a reset never stepped since) are already reset; restart only the others.
        stale = mask & ~self._fresh
        if bool(stale.all()):
            self.sim.reset()  # the first call seeds the streams (make's seed), later ones go on
        elif bool(stale.any()):
            self.sim.reset_envs(stale)
        self._fresh |= mask
        obs = self.sim.obs
        zeros = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        return self._output(obs["self"], obs["entities"], obs["adj"].clone(), None, zeros, zeros, zeros, None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get((GROUP, "action"))
        obs, reward, done, info = self.sim.step(self._check_action(action))
        done = done.clone()  # [B]
        self._fresh = done
        ep = info["episode"]
        terminated = done & ep["success"]
        truncated = done & ep["truncated"]
        term = info["terminal_obs"]
        d3, d4 = done[:, None, None], done[:, None, None, None]
        self_obs = torch.where(d3, term["self"], obs["self"])  # [B, M, 4]: the ended episode's last
        entities = torch.where(d4, term["entities"], obs["entities"])  # [B, M, L, 2]
        adj = torch.where(d3, term["adj"], obs["adj"])  # [B, M, M]
        return self._output(self_obs, entities, adj, reward, done, terminated, truncated, ep)

    def _check_action(self, action: torch.Tensor) -> torch.Tensor:
        """The action tensor as the simulator takes it, or a ValueError naming ("agents", "action")."""
        B, M = self.num_envs, self.n_agents
        shape, dtype = ((B, M, 2), torch.float32) if self.continuous_actions else ((B, M), torch.int64)
        if not isinstance(action, torch.Tensor) or tuple(action.shape) != shape:
            got = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
            kind = "continuous: num_envs, num_agents, 2" if self.continuous_actions else "num_envs, num_agents"
            raise ValueError(f"('agents', 'action') must have shape {shape} ({kind}), got {got}")
        if action.dtype != dtype:
            if self.continuous_actions and action.is_floating_point():
                action = action.to(dtype)
            elif not self.continuous_actions and not action.is_floating_point() and action.dtype != torch.bool:
                action = action.to(dtype)
            else:
                raise ValueError(f"('agents', 'action') must have dtype {dtype}, got {action.dtype}")
        return action.contiguous()

    def _output(self, self_obs, entities, adj, reward, done, terminated, truncated, episode) -> TensorDict:
        """The step's (or reset's) tensordict: every entry a new tensor (see module doc); ``adj``
        must already be one (the other inputs are only read)."""
        B, M, dev = self.num_envs, self.n_agents, self.device
        group = {"observation": flat_observation(self.obs_mode, self_obs, entities)}
        if self.obs_mode == "local":
            group["adj"] = adj
        per_agent = {"done": done, "terminated": terminated, "truncated": truncated}
        for k, v in per_agent.items():
            group[k] = v[:, None, None].expand(B, M, 1).clone()
        if reward is not None:
            group["reward"] = reward[:, None, None].expand(B, M, 1).clone()
        if episode is None:
            stats = {
                "success": torch.zeros(B, 1, dtype=torch.bool, device=dev),
                "length": torch.zeros(B, 1, dtype=torch.int64, device=dev),
                "return": torch.zeros(B, 1, dtype=torch.float32, device=dev),
                "dist": torch.zeros(B, 1, dtype=torch.float32, device=dev),
                "covered": torch.zeros(B, 1, dtype=torch.float32, device=dev),
            }
        else:  # the simulator keeps the last statistics of every env: keep those that just ended
            stats = {
                "success": (done & episode["success"])[:, None],
                "length": torch.where(done, episode["length"], 0)[:, None].to(torch.int64),
                "return": torch.where(done, episode["return"], 0.0)[:, None],
                "dist": torch.where(done, episode["dist"], 0.0)[:, None],
                "covered": torch.where(done, episode["covered"], 0.0)[:, None],
            }
        out = {
            GROUP: TensorDict(group, batch_size=(B, M), device=dev),
            "episode": TensorDict(stats, batch_size=(B,), device=dev),
            "done": done[:, None].clone(),
            "terminated": terminated[:, None].clone(),
            "truncated": truncated[:, None].clone(),
        }
        return TensorDict(out, batch_size=(B,), device=dev)

    def _reset_mask(self, tensordict: TensorDictBase | None) -> torch.Tensor:
        """[B] bool from the "_reset" entries (root, else per agent); all True without one."""
        if tensordict is not None:
            root = tensordict.get("_reset", None)
            if root is not None:
                return root.reshape(self.num_envs).to(torch.bool)
            nested = tensordict.get((GROUP, "_reset"), None)
            if nested is not None:
                return nested.reshape(self.num_envs, -1).any(-1)
        return torch.ones(self.num_envs, dtype=torch.bool, device=self.device)

    def to(self, device) -> SwarmTorchRLEnv:
        """The simulator's buffers live where Taichi runs: the device is fixed at construction."""
        if torch.device(device) != torch.device(self.device):
            raise ValueError(
                f"device: this env was built on {self.device} and cannot move to {device}; "
                f"build it with device={str(device)!r}"
            )
        return self

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(task={self.task!r}, num_envs={self.num_envs}, n_agents={self.n_agents}, "
            f"obs_mode={self.obs_mode!r}, continuous_actions={self.continuous_actions}, device={self.device})"
        )


__all__ = ["GROUP", "SwarmTorchRLEnv"]
