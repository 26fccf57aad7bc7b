"""The ``swarm`` command: one entry point, one subcommand per job.

Subcommands import their module lazily, so ``swarm execute`` (deploy) never
imports torch and ``swarm --help`` is instant.
"""

from __future__ import annotations

import sys

# name -> (module:function, one-line help)
COMMANDS = {
    "train": ("trainer.cli:train_main", "train a policy with PPO (one task, one team size)"),
    "eval": ("trainer.cli:eval_main", "evaluate a checkpoint: S%, T, DIST at any team size"),
    "curriculum": ("trainer.cli:curriculum_main", "train stage by stage over team sizes (3 5 7 10)"),
    "zero-shot": ("trainer.cli:zero_shot_main", "evaluate one checkpoint at many team sizes"),
    "plot": ("trainer.cli:plot_main", "draw the learning curves of a run directory"),
    "export": ("deploy.cli:export_main", "export a checkpoint to per-agent ONNX models"),
    "execute": ("deploy.cli:execute_main", "run exported models decentralised, one session per agent"),
    "replay": ("deploy.cli:replay_main", "play back or inspect a Rerun recording"),
    "bench": ("taichi_swarm.bench_cli:main", "benchmarks: sim | train | deploy"),
}


def _usage() -> str:
    lines = ["usage: swarm <command> [options]   (swarm <command> --help for its options)", "", "commands:"]
    lines += [f"  {name:<11} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"swarm: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    target, _ = COMMANDS[name]
    module_name, func_name = target.split(":")
    import importlib

    func = getattr(importlib.import_module(module_name), func_name)
    result = func(rest)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
