"""BenchMARL tasks for coverage, formation and line, built like BenchMARL's VMAS tasks (BenchMARL 1.5).

    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig
    from baselines.benchmarl_tasks import SwarmTask

    task = SwarmTask.COVERAGE.get_task({"num_agents": 3, "obs_mode": "full"})  # the rest: defaults
    Experiment(task, MappoConfig.get_from_yaml(), MlpConfig.get_from_yaml(), seed=0,
               config=ExperimentConfig.get_from_yaml()).run()

``SwarmTask`` (the Enum, one member per task) gives a ``SwarmTaskClass``, whose ``get_env_fun``
returns a ``SwarmTorchRLEnv`` (baselines/torchrl_env.py) over the whole batch: BenchMARL steps
it as a vectorised environment, like VMAS. Task config (``SwarmTaskConfig``, every key optional):
team size, communication, observation mode, action space and episode length. There is no
BenchMARL yaml for these tasks: ``get_task()`` / ``get_from_yaml()`` without a path take the
dataclass defaults; ``get_from_yaml(path)`` reads a yaml of the same keys. Task parameters
(``task_params``) are checked when the first environment is built (``taichi_swarm.make``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import torch
from benchmarl.environments.common import Task, TaskClass
from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs import EnvBase

from taichi_swarm import COMMS, TASKS

from .config import ACTION_CHOICES
from .observations import check_obs_mode
from .torchrl_env import GROUP, SwarmTorchRLEnv


@dataclass
class SwarmTaskConfig:
    """Configuration of one of the simulator's tasks (the keys of a task config dict)."""

    num_agents: int = 3  # team size M
    comm: str = "uc"  # "uc": every agent hears every agent; "rc": within comm_radius
    comm_radius: float = 1.0  # the paper's restricted radius
    obs_mode: str = "full"  # "full": the paper's baselines (no communication); "local": the paper's own
    action_space: str = "any"  # "any": the algorithm (and prefer_continuous_actions) chooses; or force one
    max_steps: int = 50  # episode length limit (the paper's)
    task_params: dict = dataclasses.field(default_factory=dict)  # e.g. success_threshold (taichi_swarm.make)


def check_task_config(config: dict | None) -> dict:
    """The full config (defaults filled in) or a ValueError naming the bad key."""
    config = dict(config or {})
    fields = {f.name for f in dataclasses.fields(SwarmTaskConfig)}
    unknown = sorted(set(config) - fields)
    if unknown:
        raise ValueError(f"unknown task config key(s) {unknown}; known: {sorted(fields)}")
    full = dataclasses.asdict(SwarmTaskConfig(**config))
    check_obs_mode(full["obs_mode"])
    if full["action_space"] not in ACTION_CHOICES:
        raise ValueError(f"action_space must be one of {ACTION_CHOICES}, got {full['action_space']!r}")
    if full["comm"] not in COMMS:
        raise ValueError(f"comm must be one of {COMMS}, got {full['comm']!r}")
    if not isinstance(full["task_params"], dict) or "max_steps" in full["task_params"]:
        raise ValueError(f"task_params must be a dict of task parameters (not max_steps), got {full['task_params']!r}")
    return full


class SwarmTaskClass(TaskClass):
    """A task of the simulator with its config, as BenchMARL's experiment uses it."""

    def __init__(self, name: str, config: dict | None):
        if name.lower() not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {name!r}")
        super().__init__(name, check_task_config(config))

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: int | None, device) -> Callable[[], EnvBase]:
        if continuous_actions and not self.supports_continuous_actions():
            raise ValueError(f"continuous_actions: task {self.name} is configured with action_space='discrete'")
        if not continuous_actions and not self.supports_discrete_actions():
            raise ValueError(f"continuous_actions: task {self.name} is configured with action_space='continuous'")
        return lambda: self.make_env(num_envs, continuous_actions, seed, device)

    def make_env(self, num_envs: int, continuous_actions: bool, seed: int | None, device) -> SwarmTorchRLEnv:
        """The task's batch of ``num_envs`` environments as configured (training and evaluation)."""
        cfg = self.config
        return SwarmTorchRLEnv(
            self.name.lower(),
            num_envs=num_envs,
            num_agents=cfg["num_agents"],
            obs_mode=cfg["obs_mode"],
            continuous_actions=continuous_actions,
            comm=cfg["comm"],
            comm_radius=cfg["comm_radius"],
            seed=seed,
            device=device,
            max_steps=cfg["max_steps"],
            **cfg["task_params"],
        )

    def supports_continuous_actions(self) -> bool:
        return self.config["action_space"] in ("any", "continuous")

    def supports_discrete_actions(self) -> bool:
        return self.config["action_space"] in ("any", "discrete")

    def has_render(self, env: EnvBase) -> bool:
        return False

    def max_steps(self, env: EnvBase) -> int:
        return self.config["max_steps"]

    def group_map(self, env: EnvBase) -> dict[str, list[str]]:
        if hasattr(env, "group_map"):
            return env.group_map
        return {GROUP: [f"agent_{i}" for i in range(self.config["num_agents"])]}

    def observation_spec(self, env: EnvBase) -> Composite:
        """Only ("agents", "observation"): the models' input (the comm graph stays out)."""
        spec = env.full_observation_spec_unbatched
        return Composite({GROUP: Composite(observation=spec[GROUP, "observation"].clone(), shape=spec[GROUP].shape)})

    def info_spec(self, env: EnvBase) -> Composite | None:
        return None

    def state_spec(self, env: EnvBase) -> Composite | None:
        return None  # centralised critics see every agent's observation

    def action_mask_spec(self, env: EnvBase) -> Composite | None:
        return None

    def action_spec(self, env: EnvBase) -> Composite:
        return env.full_action_spec_unbatched

    @staticmethod
    def env_name() -> str:
        return "taichi_swarm"

    @staticmethod
    def log_info(batch: TensorDictBase) -> dict[str, float]:
        """Success rate and mean length of the episodes that ended in a collected batch."""
        done = batch.get(("next", "done")).squeeze(-1)  # [..., T]
        if not bool(done.any()):
            return {}
        ep = batch.get(("next", "episode"))
        success = ep.get("success").squeeze(-1)[done].to(torch.float32)
        length = ep.get("length").squeeze(-1)[done].to(torch.float32)
        return {"collection/success_rate": success.mean().item(), "collection/episode_length": length.mean().item()}


class SwarmTask(Task):
    """The simulator's tasks (docs/PAPER.md s.2)."""

    COVERAGE = None
    FORMATION = None
    LINE = None

    @staticmethod
    def associated_class():
        return SwarmTaskClass

    def get_from_yaml(self, path: str | None = None) -> TaskClass:
        """The task with the config in the yaml at ``path``, or the defaults without one."""
        if path is None:
            return self.get_task(config={})
        from benchmarl.utils import _read_yaml_config

        return self.get_task(config=_read_yaml_config(path))


def get_task(name: str, config: dict | None = None) -> SwarmTaskClass:
    """``SwarmTask[name.upper()].get_task(config)``, or a ValueError naming ``task``."""
    if not isinstance(name, str) or name.lower() not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {name!r}")
    return SwarmTask[name.upper()].get_task(config=config or {})


__all__ = ["ACTION_CHOICES", "SwarmTask", "SwarmTaskClass", "SwarmTaskConfig", "check_task_config", "get_task"]
