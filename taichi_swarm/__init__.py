"""taichi_swarm: batched multi-agent particle teams in Taichi kernels.

    env = taichi_swarm.make("coverage", num_envs=1024, num_agents=3)
    obs = env.reset(seed=0)
    obs, reward, done, info = env.step(actions)  # actions: int64 [B, M] in 0..4

Taichi is initialised by the first ``make`` (or ``taichi_swarm.init``), never
at import.
"""

from .env import ARRAYS, COMMS, SwarmEnv, make
from .physics import ACTION_MEANINGS, NUM_ACTIONS
from .runtime import init
from .tasks import TASK_SPECS, TASKS

__all__ = [
    "ACTION_MEANINGS",
    "ARRAYS",
    "COMMS",
    "NUM_ACTIONS",
    "TASKS",
    "TASK_SPECS",
    "SwarmEnv",
    "init",
    "make",
]
