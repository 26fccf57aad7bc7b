"""Standard doors into the simulator: PettingZoo, TorchRL and BenchMARL adapters.

    from baselines.pettingzoo_env import SwarmParallelEnv   # one environment, PettingZoo ParallelEnv
    from baselines.torchrl_env import SwarmTorchRLEnv       # the whole batch, TorchRL EnvBase
    from baselines.benchmarl_tasks import SwarmTask         # coverage / formation / line for BenchMARL

Depends only on ``taichi_swarm`` (and the optional ``baselines`` extra:
pettingzoo, torchrl, tensordict, benchmarl), never on ``trainer`` or ``deploy``.
Importing this package imports none of the optional libraries.
"""
