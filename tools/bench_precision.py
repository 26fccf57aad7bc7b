"""One PPO minibatch step (forward + loss + backward + fused Adam, torch.compile'd, 1 thread)
in fp32 against the same step under CPU bf16 autocast, timed in alternation.

The measurement behind `swarm train --precision bf16` (TrainConfig.precision): bf16 changes the
numerics; docs/RESULTS.md checks the learning.

    python tools/bench_precision.py --agents 3 10
"""

from __future__ import annotations

import argparse
import statistics
import time
from types import SimpleNamespace

import torch

from trainer.model import ModelConfig, SwarmPolicy
from trainer.ppo import make_loss_fn


def time_step(agents: int, teams: int, rounds: int, steps: int) -> tuple[float, float]:
    """Median ms per minibatch step: (fp32, bf16 autocast), coverage-shaped (L = M)."""
    torch.manual_seed(0)
    M, N = agents, teams
    policy = SwarmPolicy(ModelConfig())
    ppo = SimpleNamespace(clip=0.2, value_coef=0.5, entropy_coef=0.01)
    loss_fns = {bf16: make_loss_fn(policy, ppo, compile=True, precision="bf16" if bf16 else "fp32") for bf16 in (0, 1)}
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-4, fused=True)
    batch = (
        torch.randn(N, M, 4),  # self observation
        torch.randn(N, M, M, 2),  # landmark offsets
        torch.ones(N, M, M, dtype=torch.bool),  # comm graph
        torch.randint(0, 5, (N, M)),  # actions
        -torch.rand(N, M),  # old log-probs
        torch.randn(N, M),  # old values
        torch.randn(N, M),  # advantages
        torch.randn(N, M),  # returns
    )

    def step(bf16: bool) -> None:
        loss, _ = loss_fns[bf16](*batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    for bf16 in (False, True):  # compile both variants
        for _ in range(5):
            step(bf16)
    ms: dict[bool, list[float]] = {False: [], True: []}
    for r in range(rounds):
        for bf16 in (False, True) if r % 2 == 0 else (True, False):
            start = time.perf_counter()
            for _ in range(steps):
                step(bf16)
            ms[bf16].append((time.perf_counter() - start) / steps * 1e3)
    return statistics.median(ms[False]), statistics.median(ms[True])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, nargs="+", default=[3, 10], help="team sizes M (L = M)")
    ap.add_argument("--teams", type=int, default=128, help="teams per minibatch (paper preset: 128)")
    ap.add_argument("--rounds", type=int, default=6, help="alternating timing rounds")
    ap.add_argument("--steps", type=int, default=20, help="minibatch steps per round")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"{'M':>3} {'fp32 ms':>8} {'bf16 ms':>8} {'fp32/bf16':>9}")
    for M in args.agents:
        fp32, bf16 = time_step(M, args.teams, args.rounds, args.steps)
        print(f"{M:>3} {fp32:>8.1f} {bf16:>8.1f} {fp32 / bf16:>8.2f}x")


if __name__ == "__main__":
    main()
