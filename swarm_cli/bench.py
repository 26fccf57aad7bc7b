"""``swarm bench {sim,train,deploy}``: the benchmarks, one subcommand each.

``sim`` lives here (bench_sim.py); ``train`` and ``deploy`` are imported lazily
from ``swarm_cli.bench_train`` and ``swarm_cli.bench_deploy`` and get the remaining arguments.
"""

from __future__ import annotations

import sys

from swarm_cli.options import BenchSimOptions, fail, parse

# name -> (module:function, one-line help); train and deploy import torch, so lazily
BENCHMARKS = {
    "sim": ("swarm_cli.bench:sim_main", "simulator throughput: taichi_swarm vs VMAS vs NumPy (agent-steps/s)"),
    "train": ("swarm_cli.bench_train:main", "training throughput (swarm_cli/bench_train.py)"),
    "deploy": ("swarm_cli.bench_deploy:main", "decentralised ONNX execution latency (swarm_cli/bench_deploy.py)"),
}
QUICK_SECONDS = 0.25


def sim_main(argv: list[str]) -> int:
    """``swarm bench sim``: parse, run, print; returns the exit code."""
    args = parse(BenchSimOptions, argv, "swarm bench sim")
    if args.json is not None:  # ('' too: refused, not skipped)
        from taichi_swarm.files import ensure_writable

        try:
            ensure_writable(args.json, "--json")  # before the benchmark, not after it
        except ValueError as exc:
            return fail("swarm bench sim", exc)
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
        include_vmas=args.vmas,
        include_numpy=args.numpy,
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
