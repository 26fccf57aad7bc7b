"""How many bid rounds the agents' own auction (landmark_order="auction") takes to settle from an
episode's start: the radio cost behind ``auction_rounds``. For each policy, in the lists and
options it trained on, B fresh episodes at the seed; the agents are held where they spawned, and
the auction runs one round at a time (``auction_rounds=1``, a step each with zero velocity) until
a round places no bid (no landmark's price moves). It prints, over the episodes, the rounds that
took (median, 90th percentile, most) and the share of agents holding a landmark after R rounds,
for the budgets R that ``swarm eval NAME --auction-rounds R`` is measured at in docs/SWARM.md:

    python tools/auction_rounds.py coverage-rc-m100-auction line-rc-m100-auction formation-rc-m100-auction
    python tools/auction_rounds.py coverage-rc-m100-auction line-rc-m100-auction formation-rc-m100-auction --eps 0.01

Rounds here are those of the budgeted auction (each agent without a landmark bids once a round,
in index order, at the prices the landmarks hold then: auction._bid_rounds).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

BUDGETS = (4, 16, 64, 256)


def settle(env, max_rounds: int, budgets=BUDGETS) -> tuple[np.ndarray, dict]:
    """Rounds until a round places no bid, per environment (max_rounds + 1: not settled), and the
    share of agents holding a landmark after each budget's rounds."""
    env.reset()
    state = env.get_state()
    pos, lmk = state["pos"], state["landmarks"]
    B, M = pos.shape[:2]
    rounds = np.full(B, max_rounds + 1)
    held = {}
    last = np.asarray(env._view("bid_price")).copy()
    for r in range(1, max_rounds + 1):
        # step r - 1 (0: an episode's start, the auction reset) keeps the rounds' state; a round each
        env.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=lmk, step=np.full(B, r - 1, dtype=np.int64))
        price = np.asarray(env._view("bid_price")).copy()
        moved = (price != last).any(-1) if r > 1 else np.ones(B, bool)
        rounds[(rounds > max_rounds) & ~moved] = r - 1  # round r placed no bid: r - 1 settled it
        last = price
        if r in budgets:
            held[r] = float((np.asarray(env._view("bid_won")) >= 0).mean())
        if (rounds <= max_rounds).all() and r >= max(budgets):
            break
    final = float((np.asarray(env._view("bid_won")) >= 0).mean())
    for r in budgets:  # settled before a budget's rounds: it holds what the settled auction holds
        held.setdefault(r, final if (rounds < r).all() else float("nan"))
    return rounds, held


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("policies", nargs="+", help="zoo names or policy.pt paths trained on auction lists")
    ap.add_argument("--agents", type=int, default=100, help="team size M")
    ap.add_argument("--episodes", type=int, default=20, help="fresh episode starts (environments)")
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--max-rounds", type=int, default=3000, help="stop counting here")
    ap.add_argument("--eps", type=float, default=None, help="the bid increment (auction_eps; default: the simulator's)")
    args = ap.parse_args(argv)
    for name, value in (("agents", args.agents), ("episodes", args.episodes), ("max-rounds", args.max_rounds)):
        if value < 1:
            ap.error(f"--{name} must be >= 1, got {value}")

    import taichi_swarm
    from trainer.checkpoint import load

    print(f"M = {args.agents}, {args.episodes} episode starts at seed {args.seed}, agents held where they spawned")
    head = f"{'policy':32} {'increment':>9} {'rounds: median':>15} {'p90':>6} {'most':>6}  "
    print(head + "  ".join(f"held@{r:<4}" for r in BUDGETS))
    for name in args.policies:
        payload = load(name)  # a zoo name, a checkpoint file or a run directory
        swarm = dict(payload.get("swarm") or {})
        if swarm.get("landmark_order") != "auction":
            print(
                f"auction_rounds.py: {name} was not trained on auction lists (landmark_order 'auction')",
                file=sys.stderr,
            )
            return 2
        swarm["auction_rounds"] = 1
        if args.eps is not None:
            swarm["auction_eps"] = args.eps
        setting = payload["task"]  # the task it trained on: {"task", "agents", "comm", "comm_radius"}
        env = taichi_swarm.make(
            setting["task"], args.episodes, args.agents, comm=setting["comm"], comm_radius=setting["comm_radius"],
            seed=args.seed, array="numpy", **swarm,
        )  # fmt: skip
        rounds, held = settle(env, args.max_rounds)
        more = ">" if (rounds > args.max_rounds).any() else ""
        stats = f"{np.median(rounds):>15.0f} {np.percentile(rounds, 90):>6.0f} {more}{rounds.max():>5d}"
        print(f"{name:32} {env.auction_eps:>9g} {stats}  " + "  ".join(f"{held[r]:<9.3f}" for r in BUDGETS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
