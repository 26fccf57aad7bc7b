"""How a coverage policy fails at a team size: where its agents are one step before the
episodes that will time out end.

    python tools/transfer_diagnosis.py POLICY.pt [POLICY.pt ...] --sizes 3 5 --episodes 200

For each policy and team size M it runs ``episodes`` greedy episodes (one per environment,
fresh seed ``--seed``) for 49 steps (an episode times out at 50) and, over the environments
still running then (the failures), reports:

- ``covered``: landmarks with an agent within the success distance 0.1, out of M;
- ``claimed``: distinct landmarks that are some agent's nearest, out of M (agents that
  share a nearest landmark leave another without one);
- ``stacked``: agents within 0.1 of a landmark another agent is nearer to (a pile-up);
- ``far``: agents more than 0.3 from every landmark (wandering or stopped between them).

A policy that carries to M but is slow shows failures with most landmarks covered; one
that assigns badly shows ``claimed`` < M with ``stacked`` agents. Evaluation only (no
training); one core is enough.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

SUCCESS_DIST = 0.1  # coverage: every landmark within 0.1 of its matched agent (spec s.3)
FAR = 0.3
STEPS_BEFORE_TIMEOUT = 49


def diagnose(policy, agents: int, episodes: int, seed: int, comm: str) -> dict:
    import taichi_swarm

    env = taichi_swarm.make("coverage", episodes, agents, comm=comm, arch="cpu", seed=seed)
    fused = policy.fused_weights()
    obs = env.reset()
    running = np.ones(episodes, bool)  # still in its first episode
    with torch.no_grad():
        for _ in range(STEPS_BEFORE_TIMEOUT):
            logits, _ = policy(obs["self"], obs["entities"], obs["adj"], fused=fused)
            obs, _, done, _ = env.step(logits.argmax(-1))
            running &= ~np.asarray(done, bool)
    state = env.get_state()
    pos = np.asarray(state["pos"])[running]  # [F, M, 2]
    marks = np.asarray(state["landmarks"])[running]  # [F, M, 2]
    if not len(pos):
        return {"agents": agents, "failures": 0}
    d = np.linalg.norm(pos[:, :, None, :] - marks[:, None, :, :], axis=-1)  # [F, agents, landmarks]
    nearest = d.argmin(-1)  # [F, M]
    nearest_d = d.min(-1)
    covered = (d.min(1) < SUCCESS_DIST).sum(-1)  # [F]
    claimed = np.array([len(set(row)) for row in nearest])
    # an agent near a landmark that another agent is nearer to
    closest_agent = d.argmin(1)  # [F, L]
    own = np.take_along_axis(closest_agent, nearest, axis=1)  # closest agent of each agent's nearest landmark
    stacked = ((own != np.arange(agents)) & (nearest_d < SUCCESS_DIST)).sum(-1)
    far = (nearest_d > FAR).sum(-1)
    return {
        "agents": agents,
        "failures": int(len(pos)),
        "covered": float(covered.mean()),
        "claimed": float(claimed.mean()),
        "stacked": float(stacked.mean()),
        "far": float(far.mean()),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("policies", nargs="+", help="policy.pt / checkpoint.pt files (coverage)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[3, 5])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=777)
    parser.add_argument("--comm", default=None, help="uc | rc (default: the policy's own)")
    args = parser.parse_args(argv)
    if args.episodes < 1 or any(m < 2 for m in args.sizes):
        parser.error("--episodes must be >= 1 and --sizes team sizes >= 2")
    from taichi_swarm import runtime
    from trainer.checkpoint import load_policy

    runtime.init("cpu")
    torch.set_num_threads(1)
    print(f"{'policy':60s} {'M':>3s} {'failures':>9s} {'covered':>8s} {'claimed':>8s} {'stacked':>8s} {'far':>6s}")
    for path in args.policies:
        policy, payload = load_policy(path)
        policy.eval()
        task = (payload.get("task") or {}).get("task", "coverage")
        if task != "coverage":
            print(f"{path}: a {task} policy; this diagnosis is for coverage", file=sys.stderr)
            return 2
        comm = args.comm or (payload.get("task") or {}).get("comm", "uc")
        for M in args.sizes:
            r = diagnose(policy, M, args.episodes, args.seed, comm)
            if not r["failures"]:
                print(f"{path[-60:]:60s} {M:3d} {0:9d}")
                continue
            print(
                f"{path[-60:]:60s} {M:3d} {r['failures']:9d} {r['covered']:8.2f} {r['claimed']:8.2f} "
                f"{r['stacked']:8.2f} {r['far']:6.2f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
