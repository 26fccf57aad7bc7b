"""Where a coverage policy's misses are: at the last step of each episode, every agent that the
maximum matching within the success threshold leaves without a landmark is a

- duplicate: within the threshold of a landmark another agent covers (the matching is maximum,
  so every landmark within its reach is taken);
- near miss: its nearest landmark lies within 2.5 thresholds (it parked or hovers next to one);
- far: farther still (it never found a free landmark).

An unmatched agent means an uncovered landmark (as many agents as landmarks), so the three
fractions add up to 1 - covered. Run in the swarm policies' setting (rc within 1, lists K = 4
and KL = 5 within 1, density-scaled; the lists and options a policy trained on take
precedence, landmark occupancy among them), greedy actions, fresh episodes at the seed:

    python tools/coverage_misses.py coverage-rc-m50-swarm --agents 100 --episodes 20
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

NEAR = 2.5  # a near miss: the nearest landmark within this many thresholds


def classify(pos: np.ndarray, landmarks: np.ndarray, threshold: float) -> dict:
    """pos [M, 2], landmarks [M, 2] of one environment -> the fractions of agents covered (in the
    maximum matching of agents to landmarks over |p - l| < threshold), duplicate, near and far."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    d = np.linalg.norm(pos[:, None] - landmarks[None], axis=-1)  # [agents, landmarks]
    match = maximum_bipartite_matching(csr_matrix(d < threshold), perm_type="column")  # agent -> landmark or -1
    free = match < 0
    nearest = d.min(1)
    M = len(pos)
    return {
        "covered": float((~free).sum() / M),
        "duplicate": float((free & (nearest < threshold)).sum() / M),
        "near": float((free & (nearest >= threshold) & (nearest < NEAR * threshold)).sum() / M),
        "far": float((free & (nearest >= NEAR * threshold)).sum() / M),
    }


def run(policy_name: str, agents: int, episodes: int, seed: int) -> dict:
    """The mean fractions over ``episodes`` episodes (one environment each) that run their 50 steps;
    episodes that succeed before the last step are counted apart (every landmark covered)."""
    import torch

    import taichi_swarm
    from taichi_swarm.tasks.coverage import CoverageParams
    from trainer.checkpoint import load_policy
    from trainer.model import policy_inputs

    torch.set_num_threads(1)
    policy, payload = load_policy(policy_name)
    fused = policy.fused_weights()
    # the swarm policies' setting, with the lists and options the policy trained on over it
    swarm = {"neighbours": 4, "landmark_neighbours": 5, "sense_radius": 1.0, "scale": "density"}
    swarm.update(payload.get("swarm") or {})
    env = taichi_swarm.make("coverage", episodes, agents, comm="rc", comm_radius=1.0, seed=seed, **swarm)
    obs = env.reset()
    finished = np.zeros(episodes, bool)
    for _ in range(env.params["max_steps"] - 1):  # stop before the last step: its auto-reset would clear the state
        with torch.no_grad():
            logits, _ = policy(**policy_inputs(obs, "cpu"), fused=fused)
        obs, _, done, _ = env.step(logits.argmax(-1).contiguous())
        finished |= np.asarray(done, bool)
    state = {k: np.asarray(v) for k, v in env.get_state().items()}
    threshold = CoverageParams().success_threshold
    rows = [classify(state["pos"][b], state["landmarks"][b], threshold) for b in range(episodes) if not finished[b]]
    out = {k: float(np.mean([r[k] for r in rows])) if rows else None for k in ("covered", "duplicate", "near", "far")}
    return {"agents": agents, "episodes": episodes, "succeeded_early": int(finished.sum()), **out}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("policy", help="a zoo name, policy.pt or run directory")
    ap.add_argument("--agents", type=int, nargs="+", default=[100], help="team sizes (default: 100)")
    ap.add_argument("--episodes", type=int, default=20, help="episodes per size (default: 20)")
    ap.add_argument("--seed", type=int, default=777, help="evaluation seed (default: 777)")
    args = ap.parse_args(argv)
    if args.episodes < 1 or any(m < 1 for m in args.agents):
        ap.error("--episodes and --agents must be >= 1")
    print(f"{'M':>5} {'episodes':>8} {'covered':>8} {'duplicate':>9} {'near':>6} {'far':>6}")
    for m in args.agents:
        r = run(args.policy, m, args.episodes, args.seed)
        if r["covered"] is None:
            print(f"{m:>5} {args.episodes:>8}  every episode succeeded before its last step")
            continue
        fractions = f"{r['covered']:>8.3f} {r['duplicate']:>9.3f} {r['near']:>6.3f} {r['far']:>6.3f}"
        print(f"{m:>5} {args.episodes:>8} {fractions}")


if __name__ == "__main__":
    main()
