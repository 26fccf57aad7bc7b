"""taichi_swarm: batched multi-agent particle teams in Taichi kernels.

    env = taichi_swarm.make("coverage", num_envs=1024, num_agents=3)
    obs = env.reset(seed=0)
    obs, reward, done, info = env.step(actions)  # actions: int64 [B, M] in 0..4

    # the paper's five and four quarter-strength pushes (actions 5..8): int64 [B, M] in 0..8
    env = taichi_swarm.make("formation", 1024, 3, action_space="fine")

    # MPE's continuous mode: actions float32 [B, M, 2], force 5 clip(u, -1, 1) per axis
    env = taichi_swarm.make("coverage", 1024, 3, action_space="continuous")

Taichi is initialised by the first ``make`` (or ``taichi_swarm.init``), never
at import.
"""

from .env import ARRAYS, COMMS, NaNActionsError, SwarmEnv, make
from .physics import ACTION_DIM, ACTION_MEANINGS, ACTION_SPACES, NUM_ACTIONS, num_actions
from .runtime import init
from .setting import TaskSetting
from .tasks import TASK_SPECS, TASKS

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
    "TaskSetting",
    "SwarmEnv",
    "init",
    "make",
    "num_actions",
]
