"""Paired A/B timing of two versions of the trainer: PPO updates timed in alternation.

    git worktree add /tmp/old <commit>          # the version to compare against
    python benchmarks/train_ab.py /tmp/old . --cells paper:3 paper:10 fast:3 fast:10

Each directory must hold the ``trainer`` and ``taichi_swarm`` packages. One worker
process per version imports its own tree and runs ``train`` with a callback that
blocks after every update; this script lets the two workers take turns, one update
each (the order alternating every round), so a slow spell of a shared machine hits
both alike. Prints per cell: env steps/s of both (median over rounds), the median of
the per-round ratios B/A (> 1: B is faster), and the share of the update in B.

``--threads-a`` / ``--threads-b`` set each worker's torch threads for the update; by
default each version uses its own default (its ``TrainConfig.torch_threads``).
Each worker is started with the other core idle (they take turns), so this measures
a quiet machine; run a load beside it for the loaded case.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys


def _cell(text: str) -> tuple[str, int]:
    try:
        preset, m = text.split(":")
        agents = int(m)
    except ValueError:
        raise argparse.ArgumentTypeError(f"cell must look like paper:3 (preset:agents), got {text!r}") from None
    if agents < 1:
        raise argparse.ArgumentTypeError(f"agents must be >= 1, got {text!r}")
    return preset, agents


def _override(text: str) -> tuple[str, object]:
    """FIELD=VALUE, the value read as JSON where it is (numbers, true/false), else a string."""
    field, sep, value = text.partition("=")
    if not sep or not field:
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
    try:
        return field, json.loads(value)
    except json.JSONDecodeError:
        return field, value


def worker(tree: str, preset: str, agents: int, task: str, threads: int | None, overrides: dict) -> None:
    """Runs inside the worker process: trains, reporting each update on stdout and
    waiting for a line on stdin before the next one."""
    out = os.fdopen(os.dup(1), "w")  # the protocol channel
    os.dup2(2, 1)  # anything else written to stdout (Taichi's banner, prints) goes to stderr
    sys.path.insert(0, tree)
    import copy
    import tempfile

    from trainer.config import PRESETS, TrainConfig
    from trainer.train import train

    def on_update(record: dict) -> None:
        out.write(json.dumps(record) + "\n")
        out.flush()
        if not sys.stdin.readline():
            raise SystemExit(0)

    kwargs = ({} if threads is None else {"torch_threads": threads}) | overrides
    with tempfile.TemporaryDirectory(prefix="bench-train-ab-") as tmp:
        cfg = TrainConfig(
            task=task,
            agents=agents,
            preset=preset,
            ppo=copy.deepcopy(PRESETS[preset]),
            updates=10**6,
            eval_every=10**6,
            eval_episodes=1,
            checkpoint_every=10**6,
            run_dir=os.path.join(tmp, "run"),
            progress=False,
            **kwargs,
        )
        sys.stdin.readline()  # wait for the first turn
        train(cfg, on_update=on_update)


class Worker:
    def __init__(self, tree: str, preset: str, agents: int, task: str, threads: int | None, overrides: dict):
        cmd = [sys.executable, os.path.abspath(__file__), "--worker", tree, preset, str(agents), task]
        cmd += ["default" if threads is None else str(threads), json.dumps(overrides)]
        env = dict(os.environ, PYTHONPATH=tree)
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env
        )

    def one_update(self) -> dict:
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {self.proc.args[3]} ended (run it alone to see why)")
        try:
            return json.loads(line)
        except json.JSONDecodeError:
            raise RuntimeError(f"worker wrote {line!r}, not a record") from None

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        tree, preset, agents, task, threads, overrides = argv[1:7]
        worker(tree, preset, int(agents), task, None if threads == "default" else int(threads), json.loads(overrides))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="directory holding version A's trainer/ and taichi_swarm/")
    ap.add_argument("b", help="directory holding version B's trainer/ and taichi_swarm/")
    ap.add_argument("--cells", type=_cell, nargs="+", default=[("paper", 3), ("paper", 10)], help="preset:agents")
    ap.add_argument("--task", default="coverage")
    ap.add_argument("--rounds", type=int, default=4, help="timed updates per version and cell (after 1 warm-up)")
    ap.add_argument("--threads-a", type=int, default=None, help="A's torch threads (default: A's own default)")
    ap.add_argument("--threads-b", type=int, default=None, help="B's torch threads (default: B's own default)")
    for v in ("a", "b"):
        ap.add_argument(
            f"--set-{v}",
            type=_override,
            action="append",
            default=[],
            metavar="FIELD=VALUE",
            help=f"a TrainConfig field of {v.upper()}'s runs, e.g. precision=bf16 (repeatable)",
        )
    args = ap.parse_args(argv)
    for d in (args.a, args.b):
        if not os.path.isfile(os.path.join(d, "trainer", "train.py")):
            ap.error(f"{d!r} holds no trainer package")
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    sets = "".join(f"; {v} sets {dict(o)}" for v, o in (("A", args.set_a), ("B", args.set_b)) if o)
    print(f"A = {args.a}, B = {args.b}; {args.task}; {args.rounds} paired updates per cell{sets}", flush=True)
    head = f"{'cell':<10} {'A env steps/s':>13} {'B env steps/s':>13} {'B/A':>6} {'rounds':>13} {'B update':>9}"
    print(head + "\n" + "-" * len(head), flush=True)
    for preset, agents in args.cells:
        workers = [
            Worker(os.path.abspath(args.a), preset, agents, args.task, args.threads_a, dict(args.set_a)),
            Worker(os.path.abspath(args.b), preset, agents, args.task, args.threads_b, dict(args.set_b)),
        ]
        try:
            for w in workers:  # warm-up: kernel compilation, first allocations
                w.one_update()
            sps: list[list[float]] = [[], []]
            share_update: list[float] = []
            for r in range(args.rounds):
                for v in (0, 1) if r % 2 == 0 else (1, 0):
                    rec = workers[v].one_update()
                    sps[v].append(rec["sps"])
                    if v == 1:
                        per_update = rec["env_steps"] / rec["update"]
                        share_update.append(rec["time_update"] * rec["sps"] / per_update)
        finally:
            for w in workers:
                w.close()
        ratios = [b / a for a, b in zip(*sps, strict=True)]
        print(
            f"{preset}:{agents:<4} {statistics.median(sps[0]):>13.0f} {statistics.median(sps[1]):>13.0f} "
            f"{statistics.median(ratios):>5.2f}x {min(ratios):>5.2f}..{max(ratios):<5.2f} "
            f"{100 * statistics.median(share_update):>8.0f}%",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
