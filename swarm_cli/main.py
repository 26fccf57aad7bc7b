"""The ``swarm`` command: one entry point, one subcommand per job.

Subcommands import their module lazily, so ``swarm execute`` (deploy) never
imports torch and ``swarm --help`` is instant.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

# Taichi prints a version banner when imported; a command's output is the command's own
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

# name -> (module:function, one-line help)
COMMANDS = {
    "train": ("swarm_cli.train:train_main", "train a policy with PPO (one task, one team size)"),
    "eval": ("swarm_cli.train:eval_main", "evaluate a checkpoint: S%, T, DIST at any team size"),
    "curriculum": ("swarm_cli.train:curriculum_main", "train stage by stage over team sizes (3 5 7 10)"),
    "zero-shot": ("swarm_cli.train:zero_shot_main", "evaluate one checkpoint at many team sizes"),
    "models": ("swarm_cli.models:models_main", "the model zoo: list, show a card, re-evaluate (--check)"),
    "plot": ("swarm_cli.train:plot_main", "draw the learning curves of a run directory"),
    "reproduce": ("swarm_cli.reproduce:reproduce_main", "the paper's tables as one resumable run on Ray"),
    "import": ("swarm_cli.train:import_main", "convert a checkpoint of the paper authors' published format"),
    "export": ("swarm_cli.deploy:export_main", "export a checkpoint to per-agent ONNX models"),
    "execute": ("swarm_cli.deploy:execute_main", "run exported models decentralised, agent by agent"),
    "replay": ("swarm_cli.deploy:replay_main", "play back or inspect a Rerun recording"),
    "agent": ("swarm_cli.net:agent_main", "run one agent of an export as its own process, over Zenoh"),
    "world": ("swarm_cli.net:world_main", "run the simulator as the world of agent processes (--spawn-agents)"),
}


@contextlib.contextmanager
def sigterm_as_ctrl_c():
    """While inside, SIGTERM (``kill PID``, a scheduler's stop) takes the Ctrl-C path:
    training saves its checkpoint, says how to resume and exits. Yields a list that holds
    the signal once one arrived. A job started in the background by a non-interactive
    shell ignores Ctrl-C's SIGINT, so SIGTERM is how such a run is stopped cleanly."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
        yield received
        return

    def stop(signum, frame):
        received.append(signum)
        raise KeyboardInterrupt(f"stopped by {signal.Signals(signum).name}")

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, previous)


def dispatch(prog: str, commands: dict, argv: list[str]) -> int:
    """Run ``commands[argv[0]]`` ("module:function", imported only then) on the rest of argv."""
    usage = [f"usage: {prog} <command> [options]   ({prog} <command> --help for its options)", "", "commands:"]
    usage += [f"  {name:<11} {help_}" for name, (_, help_) in commands.items()]
    if not argv:
        print("\n".join(usage), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help", "help"):
        print("\n".join(usage))
        return 0
    name, rest = argv[0], argv[1:]
    if name not in commands:
        print(f"{prog}: unknown command {name!r}\n\n" + "\n".join(usage), file=sys.stderr)
        return 2
    module_name, func_name = commands[name][0].split(":")
    import importlib

    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        print(f"{prog} {name}: cannot import {module_name} ({exc})", file=sys.stderr)
        return 2
    with sigterm_as_ctrl_c() as received:
        try:
            code = int(getattr(module, func_name)(rest) or 0)
        except KeyboardInterrupt:
            code = 130
        except SystemExit as exc:  # an option parser refused the command line (and said why) or printed --help
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
        except OSError as exc:  # disk full, read-only file system, permissions: one line, no traceback
            where = f" ({exc.filename})" if exc.filename else ""
            print(f"{prog} {name}: error: {exc.strerror or exc}{where}", file=sys.stderr)
            code = 1
        except ValueError as exc:  # a refused input a command did not catch itself: one line too
            print(f"{prog} {name}: error: {exc}", file=sys.stderr)
            code = 2
    if received:  # the command took the Ctrl-C path because of SIGTERM: the shell's 128 + 15
        code = 128 + signal.SIGTERM
    return code


def main(argv: list[str] | None = None) -> int:
    return dispatch("swarm", COMMANDS, list(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
