"""Simulator cost per agent-step as the team grows, at a fixed total of agents (one process).

B x M = 10,000 agents (B = 1000 x M = 10, 100 x 100, 10 x 1000), coverage under "rc" with
the density-scaled arena (scale="density": the agents per unit area of M = 10), random
actions; the dense layout against neighbour lists (K = 16), with the exact assignment and the
local rewards (assignment="free"), and the zoo's radio lists (the agents' auction by
messages, 8 rounds a step); then M = 10,000 in one environment (the layouts with "free" or
radio: the dense layout and the exact solver need M x M blocks); ``--layouts`` picks some.
Prints ns per agent-step, the ratio to M = 10 of the same layout, and the first call (make +
reset + one step: compiling, unless cached; ``--cold`` compiles into a fresh cache directory);
``--policy NAME`` also the policy's forward per agent at each size.

    python benchmarks/swarm.py            # about 2-5 minutes on 2 CPU cores
    python benchmarks/swarm.py --cold --seconds 1
    python benchmarks/swarm.py --arch cuda       # the GPU (torch tensors on the device)
    python benchmarks/swarm.py --layouts "lists K=16" "lists K=16 free" "lists KL=16 free"
    python benchmarks/swarm.py --layouts "lists KL=16 free" --skip-10k --vmas 10 100   # pip install vmas
    python benchmarks/swarm.py --arch cuda --layouts "lists KL=16 free" "lists KL=16 free wide"
    python benchmarks/swarm.py --layouts "radio lists R=8" --policy coverage-rc-m100-radio   # the radio's cost

A layout ending in "wide" steps every agent in parallel (``agent_parallel=True``, the default
on CUDA); the others pin one thread per environment, so a pair of them is an A/B in one run
and its time ratio is printed.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

# run from the checkout: its root ahead of benchmarks/ (whose deploy.py would hide the deploy package)
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np

SIZES = ((1000, 10), (100, 100), (10, 1000))
# the lists and the agents' auction by messages (radio.py) as the zoo's coverage-rc-m100-radio runs
# them: 8 message rounds a step, tables of the 64 nearest landmarks within the sense radius
RADIO_LISTS = {
    "neighbours": 12,
    "landmark_neighbours": 64,
    "sense_radius": 6.0,
    "landmark_occupancy": True,
    "landmark_order": "radio",
    "auction_rounds": 8,
    "assignment": "free",
}
LAYOUTS = (
    ("dense", {}),
    ("lists K=16", {"neighbours": 16}),
    ("lists K=16 free", {"neighbours": 16, "assignment": "free"}),
    # landmark lists too: no [M, L] entities block, every observation O(K) per agent
    (
        "lists KL=16 free",
        {"neighbours": 16, "landmark_neighbours": 16, "sense_radius": 1.0, "assignment": "free"},
    ),
    ("radio lists R=8", RADIO_LISTS),
    # the same stepped agent by agent in parallel (agent_parallel, the default on CUDA; the rows
    # above pin one thread per environment on every arch, so each pair is an A/B in one run)
    ("lists K=16 free wide", {"neighbours": 16, "assignment": "free", "agent_parallel": True}),
    (
        "lists KL=16 free wide",
        {
            "neighbours": 16,
            "landmark_neighbours": 16,
            "sense_radius": 1.0,
            "assignment": "free",
            "agent_parallel": True,
        },
    ),  # fmt: skip
)


def measure(
    B: int, M: int, options: dict, seconds: float, comm_radius: float, arch: str = "cpu", min_steps: int = 3
) -> dict:
    import taichi_swarm

    t0 = time.perf_counter()
    array = "numpy" if arch == "cpu" else "torch"
    if "neighbours" in options:
        options = {"agent_parallel": False, **options}
    env = taichi_swarm.make(
        "coverage", B, M, comm="rc", comm_radius=comm_radius, scale="density", seed=0, arch=arch, array=array,
        **options,
    )  # fmt: skip
    env.reset()
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 5, size=(8, B, M))
    if arch != "cpu":
        import torch

        actions = torch.from_numpy(actions).to("cuda")
    env.step(actions[0])
    first = time.perf_counter() - t0
    env.step(actions[1])  # one more outside the clock
    steps, t1 = 0, time.perf_counter()
    while steps < min_steps or time.perf_counter() - t1 < seconds:
        env.step(actions[steps % len(actions)])
        steps += 1
    if arch != "cpu":
        import torch

        torch.cuda.synchronize()
    per_step = (time.perf_counter() - t1) / steps
    dropped = int(env.info["neighbours"]["dropped"].sum()) if "neighbours" in env.info else None
    return {
        "first_s": first,
        "step_ms": 1e3 * per_step,
        "ns": 1e9 * per_step / (B * M),
        "steps": steps,
        "dropped": dropped,
    }


def measure_policy(name: str, B: int, M: int, seconds: float, comm_radius: float) -> dict:
    """ns per agent of the policy's batched forward (torch on 1 thread) on observations of its own
    trained setting at B x M, after a few random steps: with lists the network attends over K
    teammates and KL landmarks, so the cost per agent should not grow with M."""
    import torch

    import taichi_swarm
    from trainer.checkpoint import load_policy
    from trainer.model import policy_inputs

    torch.set_num_threads(1)
    policy, _ = load_policy(name)
    env = taichi_swarm.make(policy.sim.override(agents=M, comm="rc", comm_radius=comm_radius), B, seed=0)
    obs = env.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        obs = env.step(rng.integers(0, 5, size=(B, M)))[0]
    inputs, fused = policy_inputs(obs, "cpu"), policy.fused_weights()
    with torch.no_grad():
        policy(**inputs, fused=fused)  # warm-up outside the clock
        calls, t = 0, time.perf_counter()
        while calls < 3 or time.perf_counter() - t < seconds:
            policy(**inputs, fused=fused)
            calls += 1
    per_call = (time.perf_counter() - t) / calls
    return {"ms": 1e3 * per_call, "ns": 1e9 * per_call / (B * M)}


def measure_vmas(B: int, M: int) -> float:
    """ns per agent-step of VMAS's simple_spread (random discrete actions, torch on 1 thread):
    one step untimed, one timed (its step is seconds at M = 100: its reward and collision
    penalty loop over agent pairs in Python)."""
    import torch
    import vmas

    torch.set_num_threads(1)
    env = vmas.make_env(
        scenario="simple_spread", num_envs=B, device="cpu", continuous_actions=False, n_agents=M, seed=0
    )
    env.reset()
    gen = torch.Generator().manual_seed(0)
    actions = [torch.randint(0, env.action_space[0].n, (B, 1), generator=gen) for _ in range(M)]
    env.step(actions)
    t = time.perf_counter()
    env.step(actions)
    return 1e9 * (time.perf_counter() - t) / (B * M)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="timed stepping per configuration")
    parser.add_argument("--comm-radius", type=float, default=1.0)
    parser.add_argument("--cold", action="store_true", help="compile into a fresh kernel cache (compile times)")
    parser.add_argument("--skip-dense-large", action="store_true", help="no dense layout at M = 1000")
    parser.add_argument("--skip-10k", action="store_true", help="no M = 10,000 run")
    parser.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    names = [name for name, _ in LAYOUTS]
    parser.add_argument("--layouts", nargs="+", choices=names, default=names, metavar="NAME", help=f"of {names}")
    parser.add_argument(
        "--vmas", type=int, nargs="*", metavar="M", default=None,
        help="also time VMAS simple_spread at these team sizes of the table (default with the flag: 10 100; "
        "1000 takes minutes a step) and print the first layout's speed-up over it",
    )  # fmt: skip
    parser.add_argument(
        "--policy", metavar="NAME",
        help="also time this policy's forward per agent at each size, on its own trained setting "
        "(a zoo name, e.g. coverage-rc-m100-radio)",
    )  # fmt: skip
    args = parser.parse_args()
    if args.vmas == []:
        args.vmas = [10, 100]
    if args.vmas and set(args.vmas) - {M for _, M in SIZES}:
        parser.error(f"--vmas sizes must be among {[M for _, M in SIZES]}, got {args.vmas}")
    if args.seconds <= 0 or args.comm_radius <= 0:
        parser.error("--seconds and --comm-radius must be > 0")
    if args.cold:
        os.environ["TAICHI_SWARM_CACHE"] = tempfile.mkdtemp(prefix="bench_swarm_cache_")

    rows = []
    print(
        f"coverage, rc (radius {args.comm_radius}), scale='density', random actions, {args.arch}; B x M = 10,000 agents"
    )
    head = f"{'layout':<20} {'B':>5} {'M':>6} {'first call s':>12} {'ms/step':>9} {'ns/agent-step':>14} {'x M=10':>7}"
    print(head)
    print("-" * len(head))
    for name, options in LAYOUTS:
        if name not in args.layouts:
            continue
        base = None
        for B, M in SIZES:
            if name == "dense" and M >= 1000 and args.skip_dense_large:
                continue
            r = measure(B, M, options, args.seconds, args.comm_radius, args.arch)
            base = base or r["ns"]
            rows.append((name, B, M, r))
            print(
                f"{name:<20} {B:>5} {M:>6} {r['first_s']:>12.1f} {r['step_ms']:>9.2f} {r['ns']:>14.0f} "
                f"{r['ns'] / base:>7.2f}",
                flush=True,
            )
    if args.vmas:
        first = next(r for r in rows)[0]
        print(f"\nVMAS simple_spread (1 timed step, torch 1 thread) against {first!r}:")
        for B, M in SIZES:
            if M not in args.vmas:
                continue
            ns = measure_vmas(B, M)
            ours = next(r["ns"] for name, b, m, r in rows if name == first and m == M)
            print(f"vmas {B:>5} x {M:>5}: {ns:>12.0f} ns/agent-step; {first} is {ns / ours:.0f}x faster", flush=True)
    if args.policy:
        print(f"\npolicy forward of {args.policy} (torch 1 thread, B x M = 10,000 agents):")
        base = None
        for B, M in SIZES:
            r = measure_policy(args.policy, B, M, args.seconds, args.comm_radius)
            base = base or r["ns"]
            ratio = r["ns"] / base
            print(f"{'policy':<20} {B:>5} {M:>6} {r['ms']:>9.1f} ms/call {r['ns']:>10.0f} ns/agent {ratio:>7.2f}")
    paired = [(n, n + " wide") for n, _ in LAYOUTS if n + " wide" in args.layouts and n in args.layouts]
    if paired:
        print("\nagent-parallel step against one thread per environment (time ratio, < 1: faster):")
        for one, wide in paired:
            ns = {(name, M): r["ns"] for name, B, M, r in rows}
            ratios = "  ".join(f"M = {M}: {ns[wide, M] / ns[one, M]:.2f}" for _, M in SIZES if (one, M) in ns)
            print(f"{wide:<26} {ratios}", flush=True)
    for name, options in LAYOUTS[2:]:  # no M x M block: "free" and the radio
        if args.skip_10k or name not in args.layouts:
            continue
        r = measure(1, 10_000, options, args.seconds, args.comm_radius, args.arch, min_steps=3)
        print(
            f"{name:<20} {1:>5} {10_000:>6} {r['first_s']:>12.1f} {r['step_ms']:>9.2f} {r['ns']:>14.0f}"
            f"  ({r['steps']} steps timed; dropped {r['dropped']})",
            flush=True,
        )


if __name__ == "__main__":
    main()
