"""Network cost per agent-sample as the team grows: forward + backward of SwarmPolicy
(the fast forward PPO trains with), the same number of agent-samples at every M.

    python tools/bench_swarm_net.py [--samples 2000] [--reps 5] [--threads 1]

Lists: K = 16 neighbour slots and KL = min(16, M) sensed landmark slots per agent (what a
swarm observes; a team of M <= 1 + K takes the dense rounds, the same function); dense:
the M x M graph and coverage's L = M landmarks. Prints ns per agent-sample and
the ratio to M = 10 of the same layout (issue 35's target: M = 100 within 2x of M = 10).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from trainer.model import ModelConfig, SwarmPolicy  # noqa: E402

K = KL = 16


def batch(layout: str, N: int, M: int, g: torch.Generator) -> dict:
    """Random observations of N teams of M agents in the given layout."""
    pos = torch.rand(N, M, 2, generator=g) * 2 - 1
    self_obs = torch.cat([torch.randn(N, M, 2, generator=g) * 0.3, pos], -1)
    if layout == "dense":
        lmk = torch.rand(N, M, 2, generator=g) * 2 - 1
        return dict(
            self_obs=self_obs, entities=lmk[:, None] - pos[:, :, None], adj=torch.rand(N, M, M, generator=g) < 0.5
        )
    k = min(K, M - 1)
    nbr = torch.randint(0, M, (N, M, K), generator=g, dtype=torch.int32)
    nbr_mask = torch.zeros(N, M, K, dtype=torch.bool)
    nbr_mask[..., :k] = True
    kl = min(KL, M)  # coverage has L = M landmarks: a small team senses them all
    entities = torch.rand(N, M, kl, 2, generator=g) * 0.6 - 0.3
    entity_mask = torch.rand(N, M, kl, generator=g) < 0.8
    return dict(self_obs=self_obs, entities=entities, nbr=nbr, nbr_mask=nbr_mask, entity_mask=entity_mask)


def time_fwd_bwd(policy: SwarmPolicy, inputs: dict, reps: int) -> float:
    """Median seconds of one forward + backward."""

    def once():
        policy.zero_grad(set_to_none=True)
        logits, value = policy(**inputs)
        (logits.square().mean() + value.mean()).backward()

    once()  # warm-up (allocator, first-call paths)
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        once()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000, help="agent-samples per forward (N x M)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if args.samples < 1000 or args.reps < 1 or args.threads < 1:
        print("bench_swarm_net: --samples must be >= 1000, --reps and --threads >= 1", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig())  # the paper's network: H = 128, 3 rounds, EMP
    g = torch.Generator().manual_seed(0)
    cases = [("lists", 10), ("lists", 100), ("lists", 1000), ("dense", 10), ("dense", 100)]
    print(f"forward + backward, {args.samples} agent-samples per call, H = 128, 3 rounds, {args.threads} thread(s)")
    print(f"{'layout':<6} {'M':>5} {'N':>5} {'ms/call':>9} {'ns/agent-sample':>16} {'x M=10':>7}")
    base = {}
    for layout, M in cases:
        N = max(1, args.samples // M)
        inputs = batch(layout, N, M, g)
        sec = time_fwd_bwd(policy, inputs, args.reps)
        ns = sec / (N * M) * 1e9
        base.setdefault(layout, ns)
        print(f"{layout:<6} {M:>5} {N:>5} {sec * 1e3:>9.2f} {ns:>16.0f} {ns / base[layout]:>7.2f}", flush=True)
    print(f"lists at M = 10 cost {base['lists'] / base['dense']:.2f}x dense at M = 10")
    return 0


if __name__ == "__main__":
    sys.exit(main())
