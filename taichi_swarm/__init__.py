"""taichi_swarm: batched multi-agent particle teams in Taichi kernels.

    env = taichi_swarm.make("coverage", num_envs=1024, num_agents=3)
    # or from the setting's one declaration (sim.py), as every layer above passes it
    env = taichi_swarm.make(taichi_swarm.Sim("coverage", 3, comm="rc"), num_envs=1024)
    obs = env.reset(seed=0)
    obs, reward, done, info = env.step(actions)  # actions: int64 [B, M] in 0..4

    # the paper's five and four quarter-strength pushes (actions 5..8): int64 [B, M] in 0..8
    env = taichi_swarm.make("formation", 1024, 3, action_space="fine")

    # MPE's continuous mode: actions float32 [B, M, 2], force 5 clip(u, -1, 1) per axis
    env = taichi_swarm.make("coverage", 1024, 3, action_space="continuous")

Taichi is initialised by the first ``make`` (or ``taichi_swarm.init``), never
at import.
"""

import importlib

# Taichi is imported with the first name that needs it, not with the package: an agent process
# (deploy/net/agent.py) reads taichi_swarm.files and nothing that compiles kernels, and stays
# small without it
_NAMES = {
    **dict.fromkeys(("ARRAYS", "NaNActionsError", "SwarmEnv", "make"), "env"),
    "COMMS": "constants",
    **dict.fromkeys(("ACTION_DIM", "ACTION_MEANINGS", "ACTION_SPACES", "NUM_ACTIONS", "num_actions"), "physics"),
    "init": "runtime",
    **dict.fromkeys(("ConfigError", "Sim"), "sim"),
    **dict.fromkeys(("TASK_SPECS", "TASKS"), "tasks"),
}


def __getattr__(name: str):
    if name in _NAMES:
        return getattr(importlib.import_module(f".{_NAMES[name]}", __name__), name)
    try:  # a submodule (taichi_swarm.physics), as when the package imported them all
        return importlib.import_module(f".{name}", __name__)
    except ModuleNotFoundError as exc:
        if exc.name != f"{__name__}.{name}":
            raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ACTION_DIM",
    "ACTION_MEANINGS",
    "ACTION_SPACES",
    "ARRAYS",
    "COMMS",
    "NUM_ACTIONS",
    "NaNActionsError",
    "TASKS",
    "TASK_SPECS",
    "ConfigError",
    "Sim",
    "SwarmEnv",
    "init",
    "make",
    "num_actions",
]
