"""Training throughput: env steps/s of the whole PPO cycle and where the time goes.

    python benchmarks/train.py [options]      # --help: the options

Runs a few updates of each preset side by side (same task, team size and
machine, one process) and prints env steps/s, the share of wall time spent in
simulation, policy forward (rollout) and the update (forward + backward), and
the effect of the torch thread count on the update.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass
from typing import Annotated, Literal

# run from the checkout: its root ahead of benchmarks/ (whose deploy.py would hide the deploy package)
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")  # as `swarm` does: the output is the benchmark's

from swarm_cli.options import Arch, Default, at_least, fail, parse
from trainer.config import PRESETS, TrainConfig
from trainer.train import train

CPU_MAX_ENVS = 256  # presets with more environments are for a GPU
PROG = "benchmarks/train.py"


@dataclass(kw_only=True)
class BenchTrainOptions:
    """env steps/s of the whole PPO cycle and where the time goes, for each preset and
    thread count side by side in one process."""

    task: str = "coverage"
    """task of the timed updates"""
    agents: int = 3
    """team size M"""
    updates: int = 3
    """timed updates per row (after one warm-up)"""
    presets: Annotated[tuple[str, ...] | None, Default("every preset of trainer.config.PRESETS")] = None
    """PPO presets, one row each"""
    threads: tuple[int, ...] = (1, 2)
    """torch threads of the update, one row each"""
    device: str = "cpu"
    """where the network runs: cpu | cuda | auto"""
    arch: Arch = "cpu"
    """where the simulator runs"""
    num_envs: int | None = None
    """override the preset's environments per rollout"""
    minibatches: int | None = None
    """override the preset's minibatches per epoch"""
    compile: bool = True
    """torch.compile the update (--no-compile: eager)"""
    precisions: tuple[Literal["fp32", "bf16"], ...] = ("fp32",)
    """arithmetic of the update, one row each (bf16: autocast, TrainConfig.precision)"""

    def __post_init__(self):
        for name in ("agents", "updates", "num_envs", "minibatches"):
            at_least(getattr(self, name), 1, name.replace("_", "-"))
        for t in self.threads:
            at_least(t, 1, "threads")


def default_presets(device: str) -> tuple[str, ...]:
    """The presets that fit the device: on a CPU, not the GPU ones (4096 environments there
    run for many minutes)."""
    return tuple(p for p in PRESETS if device.startswith("cuda") or PRESETS[p].num_envs <= CPU_MAX_ENVS)


def forward_flops(hidden: int, rounds: int, agents: int, landmarks: int, teams: int, emp: bool = True) -> float:
    """FLOPs (2 per multiply-add) of one ``SwarmPolicy.forward`` over ``teams`` teams, as
    the fused algebra computes it: per agent the encoder, EMP (entity encoder, query and
    update projections, L-long scores and weighted sum), K rounds (query and own-update
    projection [H, 2H], M-long scores and weighted sum, the heard projection [H, H]) and the
    heads; per call the weight products (3 H^3 per attention block). Elementwise ops not
    counted. A training step (forward + backward) is counted as 3x the forward."""
    H, M, L = hidden, agents, landmarks
    per_agent = 4 * H + 2 * H * H + 5 * H + H  # agent encoder, heads
    if emp:
        per_agent += L * 2 * H + 3 * H * H + 2 * L * H
    per_agent += rounds * (3 * H * H + 2 * M * H)
    per_call = (6 if emp else 3) * H**3
    return 2.0 * (teams * M * per_agent + per_call)


def sgemm_peak(threads: int = 1, size: int = 1024, seconds: float = 1.0, device: str = "cpu") -> float:
    """Measured fp32 GEMM GFLOP/s where the network runs: ``size``^3 matmuls on the CPU with
    ``threads`` threads, or on the GPU (``device="cuda"``, synchronised before reading the clock)."""
    import time

    import torch

    cuda = device.startswith("cuda")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        a, b = torch.randn(size, size, device=device), torch.randn(size, size, device=device)
        for _ in range(3):
            a @ b
        if cuda:
            torch.cuda.synchronize()
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            for _ in range(10 if cuda else 1):  # GPU: queue a few before each clock read
                a @ b
                n += 1
            if cuda:
                torch.cuda.synchronize()
        return 2 * size**3 * n / (time.perf_counter() - start) / 1e9
    finally:
        torch.set_num_threads(previous)


def measure(
    preset: str,
    task: str,
    agents: int,
    updates: int,
    threads: int,
    device: str = "cpu",
    arch: str = "cpu",
    num_envs: int | None = None,
    compile: bool = True,
    precision: str = "fp32",
    minibatches: int | None = None,
) -> dict:
    tmp = tempfile.mkdtemp(prefix="swarm-bench-")
    try:
        ppo = {k: v for k, v in (("num_envs", num_envs), ("minibatches", minibatches)) if v}
        cfg = TrainConfig.with_preset(
            preset,
            ppo,
            task=task,
            agents=agents,
            device=device,
            arch=arch,
            compile=compile,
            precision=precision,
            updates=updates + 1,
            eval_every=10**6,
            eval_episodes=1,
            checkpoint_every=10**6,
            run_dir=os.path.join(tmp, "run"),
            progress=False,
            torch_threads=threads,
        )
        records: list[dict] = []
        with contextlib.redirect_stdout(io.StringIO()):  # (a stopped run's resume hint names this temp dir)
            train(cfg, on_update=records.append)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rows = records[1:]  # the first update includes kernel compilation and warm-up
    per_update = cfg.ppo.num_envs * cfg.ppo.num_steps
    steps = per_update * len(rows)
    wall = sum(per_update / r["sps"] for r in rows)
    sim, pol, upd = (sum(r[k] for r in rows) for k in ("time_sim", "time_policy", "time_update"))
    import taichi_swarm

    p = cfg.ppo
    L = taichi_swarm.TASK_SPECS[task].num_landmarks(agents)
    teams_per_minibatch = p.num_envs * p.num_steps // p.minibatches
    step_flops = 3 * forward_flops(
        cfg.model.hidden, cfg.model.rounds, agents, L, teams_per_minibatch, cfg.model.entity_mode == "emp"
    )
    samples = p.epochs * p.num_envs * p.num_steps * agents * len(rows)  # agent-samples through fwd+bwd
    return {
        "agent_samples_per_s": samples / upd,
        "gflops": step_flops * p.epochs * p.minibatches * len(rows) / upd / 1e9,
        "preset": preset,
        "threads": threads,
        "precision": precision,
        "minibatches": p.minibatches,
        "env_steps_per_s": steps / wall,
        "agent_samples_per_update": cfg.ppo.num_envs * cfg.ppo.num_steps * agents,
        "share_sim": sim / wall,
        "share_policy": pol / wall,
        "share_update": upd / wall,
        "seconds_per_update": wall / len(rows),
    }


def main(argv: list[str] | None = None) -> int:
    args = parse(BenchTrainOptions, sys.argv[1:] if argv is None else argv, PROG, description=__doc__)
    from trainer.train import resolve_device

    try:
        device = resolve_device(args.device)
    except ValueError as exc:
        return fail(PROG, exc)
    presets = args.presets or default_presets(device)
    skipped = [p for p in PRESETS if p not in presets and not args.presets]
    import taichi_swarm

    problems = []
    if [p for p in presets if p not in PRESETS]:
        problems.append(f"--presets must be in {tuple(PRESETS)}, got {' '.join(presets)}")
    if args.task not in taichi_swarm.TASKS:
        problems.append(f"--task must be one of {taichi_swarm.TASKS}, got {args.task!r}")
    if problems:
        return fail(PROG, "; ".join(problems))
    if skipped:
        print(f"(not run on {device}: --presets {' '.join(skipped)}, the GPU presets; name them to run them)")
    combos = [(p, t, x) for p in presets for t in args.threads for x in args.precisions]
    rows = []
    for k, (p, t, x) in enumerate(combos, 1):
        print(f"[{k}/{len(combos)}] preset {p}, {t} thread(s), {x}: {args.updates + 1} updates ...", flush=True)
        try:
            rows.append(
                measure(
                    p, threads=t, precision=x, task=args.task, agents=args.agents, updates=args.updates,
                    device=args.device, arch=args.arch, num_envs=args.num_envs, compile=args.compile,
                    minibatches=args.minibatches,
                )
            )  # fmt: skip
        except KeyboardInterrupt:
            print(f"{PROG}: stopped (nothing to resume: a benchmark starts afresh)")
            raise
    if device.startswith("cuda"):  # one GPU peak; torch's CPU threads do not change it
        gpu_peak = sgemm_peak(1, 4096, device=device)
        peak = dict.fromkeys(args.threads, gpu_peak)
        peak_text = f"fp32 GEMM peak measured here (4096^3 on {device}): {gpu_peak:.0f} GFLOP/s"
    else:
        peak = {t: sgemm_peak(t) for t in sorted(set(args.threads))}
        peak_text = "fp32 GEMM peak measured here (1024^3 on cpu): " + ", ".join(
            f"{t} thread(s) {g:.0f} GFLOP/s" for t, g in peak.items()
        )
    print(f"\nPPO cycle, {args.task} M={args.agents}, {args.updates} timed updates per row")
    head = (
        f"{'preset':<7} {'threads':>7} {'prec':>5} {'env steps/s':>12} {'s/update':>9} {'sim':>6}"
        f" {'policy fwd':>10} {'update':>7}"
        f" {'agent-samples/s':>15} {'GFLOP/s':>8} {'of sgemm':>8}"
    )
    print(head + "\n" + "-" * len(head))
    for r in rows:
        print(
            f"{r['preset']:<7} {r['threads']:>7} {r['precision']:>5} {r['env_steps_per_s']:>12.0f}"
            f" {r['seconds_per_update']:>9.2f} "
            f"{100 * r['share_sim']:>5.1f}% {100 * r['share_policy']:>9.1f}% {100 * r['share_update']:>6.1f}%"
            f" {r['agent_samples_per_s']:>15.0f} {r['gflops']:>8.1f} {100 * r['gflops'] / peak[r['threads']]:>7.0f}%"
        )
    print(
        "agent-samples/s: agent samples through forward+backward in the update; GFLOP/s: the GEMM and "
        "attention FLOPs of the fused network (benchmarks/train.py: forward_flops, backward = 2x forward) per "
        "second of update; " + peak_text
    )
    base = {p: rows[[r["preset"] for r in rows].index(p)] for p in presets}  # fewest threads, first precision
    for r in rows:
        b = base[r["preset"]]
        if r is not b:
            print(
                f"{r['preset']}: {r['threads']} threads {r['precision']} / {b['threads']} thread {b['precision']}: "
                f"{r['env_steps_per_s'] / b['env_steps_per_s']:.2f}x env steps/s"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
