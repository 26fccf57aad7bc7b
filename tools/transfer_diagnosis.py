"""How a coverage policy fails at a team size: where its agents are one step before the
episodes that will time out end.

    python tools/transfer_diagnosis.py POLICY.pt [POLICY.pt ...] --sizes 3 5 --episodes 200

For each policy and team size M it runs ``episodes`` greedy episodes (one per environment,
fresh seed ``--seed``, the episodes `swarm zero-shot` runs with that seed) to their end and,
over the failures (episodes that time out at step 50), reports where the agents were at step
49, one step before the end:

- ``covered``: landmarks with an agent within the success distance 0.1, out of M;
- ``claimed``: distinct landmarks that are some agent's nearest, out of M (agents that
  share a nearest landmark leave another without one);
- ``stacked``: agents within 0.2 of their nearest landmark while another agent is nearer to
  it (a pile-up; two touching agents of radius 0.05 are 0.1 apart);
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
STACK_DIST = 0.2
FAR = 0.3
EPISODE_STEPS = 50  # an episode times out after 50 steps (spec s.3)


def diagnose(policy, agents: int, episodes: int, seed: int, comm: str, comm_radius: float = 1.0) -> dict:
    import taichi_swarm
    from taichi_swarm.metrics import run_first_episodes

    env = taichi_swarm.make("coverage", episodes, agents, comm=comm, comm_radius=comm_radius, arch="cpu", seed=seed)
    fused = policy.fused_weights()
    seen = {"steps": 0, "state": None}

    def decide(obs):  # `swarm eval`'s greedy loop, keeping the state before the last step
        seen["steps"] += 1
        if seen["steps"] == EPISODE_STEPS:
            seen["state"] = env.get_state()  # after 49 steps: where a failure's agents end up
        with torch.no_grad():
            logits, _ = policy(obs["self"], obs["entities"], obs["adj"], fused=fused)
        return logits.argmax(-1), None

    tally = run_first_episodes(env, decide)
    failed = ~tally.success  # a failure runs all 50 steps, so the state above is its last but one
    if not failed.any():
        return {"agents": agents, "failures": 0, "success_rate": 1.0}
    pos = np.asarray(seen["state"]["pos"])[failed]  # [F, M, 2]
    marks = np.asarray(seen["state"]["landmarks"])[failed]  # [F, M, 2]
    d = np.linalg.norm(pos[:, :, None, :] - marks[:, None, :, :], axis=-1)  # [F, agents, landmarks]
    nearest = d.argmin(-1)  # [F, M]
    nearest_d = d.min(-1)
    covered = (d.min(1) < SUCCESS_DIST).sum(-1)  # [F]
    claimed = np.array([len(set(row)) for row in nearest])
    # an agent near a landmark that another agent is nearer to
    closest_agent = d.argmin(1)  # [F, L]
    own = np.take_along_axis(closest_agent, nearest, axis=1)  # closest agent of each agent's nearest landmark
    stacked = ((own != np.arange(agents)) & (nearest_d < STACK_DIST)).sum(-1)
    far = (nearest_d > FAR).sum(-1)
    return {
        "agents": agents,
        "failures": int(len(pos)),
        "success_rate": 1.0 - len(pos) / episodes,
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
    parser.add_argument("--comm", choices=("uc", "rc"), default=None, help="default: the policy's own")
    parser.add_argument("--comm-radius", type=float, default=None, help="default: the policy's own")
    args = parser.parse_args(argv)
    if args.episodes < 1 or any(m < 2 for m in args.sizes):
        parser.error("--episodes must be >= 1 and --sizes team sizes >= 2")
    from taichi_swarm import TaskSetting, runtime
    from trainer.checkpoint import load_policy

    runtime.init("cpu")
    torch.set_num_threads(1)
    loaded = []
    for path in args.policies:  # every policy checked before any is evaluated
        policy, payload = load_policy(path)
        setting = TaskSetting.from_dict(payload.get("task"), path)
        if setting.task != "coverage":
            print(f"{path}: a {setting.task} policy; this diagnosis is for coverage", file=sys.stderr)
            return 2
        radius = args.comm_radius if args.comm_radius is not None else setting.comm_radius
        loaded.append((path, policy.eval(), args.comm or setting.comm, radius))
    width = max(len("policy"), *(len(path) for path, *_ in loaded))  # every path whole
    head = f"{'M':>3s} {'S%':>6s} {'failures':>9s} {'covered':>8s} {'claimed':>8s} {'stacked':>8s} {'far':>6s}"
    print(f"{'policy':{width}s} {head}")
    for path, policy, comm, radius in loaded:
        for M in args.sizes:
            r = diagnose(policy, M, args.episodes, args.seed, comm, radius)
            line = f"{path:{width}s} {M:3d} {100 * r['success_rate']:6.1f} {r['failures']:9d}"
            if r["failures"]:
                line += f" {r['covered']:8.2f} {r['claimed']:8.2f} {r['stacked']:8.2f} {r['far']:6.2f}"
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
