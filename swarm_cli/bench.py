"""``swarm bench {sim,train,deploy}``: the benchmarks, one subcommand each.

``sim`` lives here (bench_sim.py); ``train`` and ``deploy`` are imported lazily
from ``swarm_cli.bench_train`` and ``swarm_cli.bench_deploy`` and get the remaining arguments.
"""

from __future__ import annotations

import argparse
import os
import sys

# name -> (module:function, one-line help); train and deploy import torch, so lazily
BENCHMARKS = {
    "sim": ("swarm_cli.bench:sim_main", "simulator throughput: taichi_swarm vs VMAS vs NumPy (agent-steps/s)"),
    "train": ("swarm_cli.bench_train:main", "training throughput (swarm_cli/bench_train.py)"),
    "deploy": ("swarm_cli.bench_deploy:main", "decentralised ONNX execution latency (swarm_cli/bench_deploy.py)"),
}
QUICK_SECONDS = 0.25


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text}")
    return value


def sim_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="swarm bench sim",
        description="Agent-steps/s of the taichi_swarm coverage step vs VMAS simple_spread vs plain NumPy, "
        "measured side by side in one process; prints a table and the target checks.",
    )
    p.add_argument(
        "--batch-sizes",
        type=_positive_int,
        nargs="+",
        default=[32, 1024, 8192],
        metavar="B",
        help="numbers of environments (default: 32 1024 8192)",
    )
    p.add_argument(
        "--agents", type=_positive_int, nargs="+", default=[3, 10], metavar="M", help="team sizes (default: 3 10)"
    )
    p.add_argument("--no-vmas", action="store_true", help="leave out VMAS (shown as skipped)")
    p.add_argument("--no-numpy", action="store_true", help="leave out the NumPy baselines (shown as skipped)")
    p.add_argument(
        "--torch-threads",
        type=_positive_int,
        default=1,
        metavar="N",
        help="torch.set_num_threads during the run (default 1: see docs/BENCHMARKS.md)",
    )
    p.add_argument(
        "--comm",
        choices=("rc", "uc"),
        default="rc",
        help="communication graph of taichi and numpy: rc = from distances every step (default), uc = all",
    )
    p.add_argument("--seconds", type=_positive_float, default=1.5, help="timed seconds per cell (default 1.5)")
    p.add_argument(
        "--steps", type=_positive_int, default=None, help="a fixed number of timed steps per cell instead (in 5 chunks)"
    )
    p.add_argument("--quick", action="store_true", help=f"{QUICK_SECONDS} s per cell instead of --seconds")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the rows and checks to PATH (JSON)")
    p.add_argument(
        "--serial-sweep",
        action="store_true",
        help="instead: time the Taichi step with a serial vs parallel env loop over small B",
    )
    return p


def sim_main(argv: list[str]) -> int:
    """``swarm bench sim``: parse, run, print; returns the exit code."""
    parser = sim_parser()
    args = parser.parse_args(argv)
    if args.json:
        folder = os.path.dirname(os.path.abspath(args.json))
        if not os.path.isdir(folder):
            parser.error(f"--json: directory {folder!r} does not exist")
    from swarm_cli import bench_sim

    seconds = QUICK_SECONDS if args.quick else args.seconds
    if args.serial_sweep:
        bench_sim.serial_sweep(tuple(args.agents), seconds=seconds, comm=args.comm)
        return 0
    bench_sim.run(
        batch_sizes=tuple(args.batch_sizes),
        team_sizes=tuple(args.agents),
        steps=args.steps,
        seconds=seconds,
        include_vmas=not args.no_vmas,
        include_numpy=not args.no_numpy,
        out_json=args.json,
        torch_threads=args.torch_threads,
        comm=args.comm,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``swarm bench``; returns the exit code."""
    from swarm_cli.main import dispatch

    return dispatch("swarm bench", BENCHMARKS, list(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
