"""``swarm bench train``: env steps/s of the whole PPO cycle and where the time goes.

Runs a few updates of each preset side by side (same task, team size and
machine, one process) and prints env steps/s, the share of wall time spent in
simulation, policy forward (rollout) and the update (forward + backward), and
the effect of the torch thread count on the update.
"""

from __future__ import annotations

import argparse
import copy
import os
import shutil
import tempfile

from trainer.config import PRESETS, TrainConfig
from trainer.train import train


def measure(preset: str, task: str, agents: int, updates: int, threads: int) -> dict:
    tmp = tempfile.mkdtemp(prefix="swarm-bench-")
    try:
        cfg = TrainConfig(
            task=task,
            agents=agents,
            preset=preset,
            ppo=copy.deepcopy(PRESETS[preset]),
            updates=updates + 1,
            eval_every=10**6,
            eval_episodes=1,
            checkpoint_every=10**6,
            run_dir=os.path.join(tmp, "run"),
            progress=False,
            torch_threads=threads,
        )
        records: list[dict] = []
        train(cfg, on_update=records.append)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rows = records[1:]  # the first update includes kernel compilation and warm-up
    per_update = cfg.ppo.num_envs * cfg.ppo.num_steps
    steps = per_update * len(rows)
    wall = sum(per_update / r["sps"] for r in rows)
    sim, pol, upd = (sum(r[k] for r in rows) for k in ("time_sim", "time_policy", "time_update"))
    return {
        "preset": preset,
        "threads": threads,
        "env_steps_per_s": steps / wall,
        "agent_samples_per_update": cfg.ppo.num_envs * cfg.ppo.num_steps * agents,
        "share_sim": sim / wall,
        "share_policy": pol / wall,
        "share_update": upd / wall,
        "seconds_per_update": wall / len(rows),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="swarm bench train", description=__doc__)
    ap.add_argument("--task", default="coverage")
    ap.add_argument("--agents", type=int, default=3)
    ap.add_argument("--updates", type=int, default=3, help="timed updates per row (after one warm-up)")
    ap.add_argument("--presets", nargs="+", default=list(PRESETS))
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2], help="torch threads of the update")
    args = ap.parse_args(argv)
    bad = [p for p in args.presets if p not in PRESETS]
    if bad or args.updates < 1 or min(args.threads) < 1:
        print(f"swarm bench train: error: presets must be in {tuple(PRESETS)}, updates and threads >= 1", flush=True)
        return 2
    rows = [measure(p, args.task, args.agents, args.updates, t) for p in args.presets for t in args.threads]
    print(f"\nPPO cycle, {args.task} M={args.agents}, {args.updates} timed updates per row")
    head = (
        f"{'preset':<7} {'threads':>7} {'env steps/s':>12} {'s/update':>9} {'sim':>6} {'policy fwd':>10} {'update':>7}"
    )
    print(head + "\n" + "-" * len(head))
    for r in rows:
        print(
            f"{r['preset']:<7} {r['threads']:>7} {r['env_steps_per_s']:>12.0f} {r['seconds_per_update']:>9.2f} "
            f"{100 * r['share_sim']:>5.1f}% {100 * r['share_policy']:>9.1f}% {100 * r['share_update']:>6.1f}%"
        )
    base = {p: min((r for r in rows if r["preset"] == p), key=lambda r: r["threads"]) for p in args.presets}
    for r in rows:
        b = base[r["preset"]]
        if r is not b:
            print(
                f"{r['preset']}: {r['threads']} threads / {b['threads']} thread: "
                f"{r['env_steps_per_s'] / b['env_steps_per_s']:.2f}x env steps/s"
            )
    return 0
