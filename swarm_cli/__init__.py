"""The application layer: the ``swarm`` command.

The only package that knows every subcommand; it sits on top of the libraries and
they never import it:

    swarm_cli/  (main: dispatch; train, deploy, reproduce, models, net: the subcommands)
        ├── trainer/   (policy, PPO, evaluation, curriculum, reproduce)
        ├── deploy/    (ONNX export, executor, recordings)
        └── baselines/ (PettingZoo / TorchRL / BenchMARL adapters)
              └── taichi_swarm/  (the simulator)
"""
