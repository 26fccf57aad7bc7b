"""Paired A/B timing of two versions of the simulator, in one process.

    git worktree add /tmp/old <commit>          # the version to compare against
    python tools/bench_sim_ab.py /tmp/old . --cells 8192x3 1024x10

Each directory must hold a ``taichi_swarm`` package. Both are copied under fresh
names and imported side by side (one Taichi runtime), then timed in alternating
chunks: a slow spell of a shared machine hits both alike, so the per-round time
ratio is far steadier than comparing two separate runs (on this 2-core VM, the
same step varies by 30-50% between runs, but the paired ratio by a few percent).
Prints, per cell, both medians and the median of the per-round ratios A/B
(> 1: B is faster). ``--threads 1`` (default) times one core, which removes the
thread pool's wake-up jitter; ``--threads 0`` uses every core.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import statistics
import sys
import tempfile

from swarm_cli.bench_sim import paired_ratio, time_chunk


def _cell(text: str) -> tuple[int, int]:
    try:
        b, m = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"cell must look like 8192x3 (B x M), got {text!r}") from None
    if b < 1 or m < 1:
        raise argparse.ArgumentTypeError(f"B and M must be >= 1, got {text!r}")
    return b, m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="directory holding version A's taichi_swarm/")
    ap.add_argument("b", help="directory holding version B's taichi_swarm/")
    ap.add_argument("--cells", type=_cell, nargs="+", default=[(8192, 3), (1024, 10)], help="B x M cells")
    ap.add_argument("--task", default="coverage")
    ap.add_argument("--comm", default="rc", choices=("rc", "uc"))
    ap.add_argument("--rounds", type=int, default=16)
    ap.add_argument("--chunk-seconds", type=float, default=0.1)
    ap.add_argument("--threads", type=int, default=1, help="Taichi CPU threads (0 = every core)")
    args = ap.parse_args(argv)
    for d in (args.a, args.b):
        if not os.path.isfile(os.path.join(d, "taichi_swarm", "__init__.py")):
            ap.error(f"{d!r} holds no taichi_swarm package")
    if args.threads:
        os.environ["TAICHI_SWARM_THREADS"] = str(args.threads)  # read by runtime.init
    import torch

    torch.set_num_threads(1)
    root = tempfile.mkdtemp(prefix="bench_sim_ab_")
    try:
        for name, src in (("ab_version_a", args.a), ("ab_version_b", args.b)):
            shutil.copytree(os.path.join(src, "taichi_swarm"), os.path.join(root, name))
        sys.path.insert(0, root)
        versions = [importlib.import_module(n) for n in ("ab_version_a", "ab_version_b")]
        versions[0].runtime.init("cpu")
        versions[1].runtime._state["arch"] = "cpu"  # one Taichi runtime: B must not re-init it
        print(f"A = {args.a}, B = {args.b}; {args.task}, comm={args.comm}, threads={args.threads or 'all'}")
        for B, M in args.cells:
            runs = []
            gen = torch.Generator().manual_seed(0)
            actions = [torch.randint(0, 5, (B, M), generator=gen) for _ in range(16)]
            for mod in versions:
                env = mod.make(args.task, B, M, comm=args.comm, seed=0)
                env.reset()
                for k in range(3):  # compile and warm up
                    env.step(actions[k])
                runs.append(env)
            steps = [lambda k, env=env, acts=actions: env.step(acts[k % len(acts)]) for env in runs]
            chunk_ms: list[list[float]] = [[], []]
            for r in range(args.rounds):
                for v in (0, 1) if r % 2 == 0 else (1, 0):
                    n, elapsed = time_chunk(steps[v], 0, args.chunk_seconds, None)
                    chunk_ms[v].append(1e3 * elapsed / n)
            a, b = ({"chunk_ms": ms} for ms in chunk_ms)
            ratios = [x / y for x, y in zip(*chunk_ms, strict=True)]
            print(
                f"B={B:<6} M={M:<3} A {statistics.median(chunk_ms[0]):8.3f} ms  "
                f"B {statistics.median(chunk_ms[1]):8.3f} ms  A/B {paired_ratio(b, a):.3f} "
                f"(rounds {min(ratios):.3f}..{max(ratios):.3f})",
                flush=True,
            )
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
