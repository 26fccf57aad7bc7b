"""Where a coverage policy's misses are (or a formation policy's on its sensed lattice, whose
landmarks are its M targets): at the last step of each episode, every agent that the
maximum matching within the success threshold leaves without a landmark is a

- duplicate: within the threshold of a landmark another agent covers (the matching is maximum,
  so every landmark within its reach is taken);
- near miss: its nearest landmark lies within 2.5 thresholds (it parked or hovers next to one);
- far: farther still (it never found a free landmark).

An unmatched agent means an uncovered landmark (as many agents as landmarks), so the three
fractions add up to 1 - covered. For the duplicates it also reports how far the nearest
uncovered landmark is (the median) and how many of them sense one (among the KL nearest within
the sensing radius, the policy's lists, or ``--sense KL R``; on free-first lists, any within the
radius): a duplicate with none in sight has nowhere it can see to go. Over the last ``--window``
steps before it, it reports how many agents held a landmark of their own at every step (*held*),
at some steps only (*hover*: they pass in and out of the threshold), and the most landmarks
covered at any one of those steps (*best*): success needs them all at once. With ``--jostle`` it
adds, over the same window, how often the nearer agent of each duplicate's pair changes
(*swaps*, per pair: the agent the duplicate shares its landmark with) and the share of full
pushes (actions 1-4) among the pairs' actions (*pair_push*) and the lone holders' (*lone_push*,
agents alone within the threshold of the landmark the matching gives them). Run in the swarm
policies' setting (rc within 1, lists K = 4 and KL = 5 within 1, density-scaled; the lists and
options a policy trained on take precedence, landmark occupancy among them), greedy actions,
fresh episodes at the seed:

    python tools/coverage_misses.py coverage-rc-m50-swarm --agents 100 --episodes 20
    python tools/coverage_misses.py formation-rc-m50-lattice --agents 50 100 --steps 100 --window 20
    python tools/coverage_misses.py coverage-rc-m100-free-far --agents 100 --window 15 --jostle
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

NEAR = 2.5  # a near miss: the nearest landmark within this many thresholds


def matching(pos: np.ndarray, landmarks: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """pos [M, 2], landmarks [M, 2] -> (distances [agents, landmarks], each agent's landmark in the
    maximum matching over |p - l| < threshold, -1 where unmatched)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    d = np.linalg.norm(pos[:, None] - landmarks[None], axis=-1)
    return d, maximum_bipartite_matching(csr_matrix(d < threshold), perm_type="column")


def classify(pos: np.ndarray, landmarks: np.ndarray, threshold: float) -> dict:
    """pos [M, 2], landmarks [M, 2] of one environment -> the fractions of agents covered (in the
    maximum matching of agents to landmarks over |p - l| < threshold), duplicate, near and far."""
    d, match = matching(pos, landmarks, threshold)
    free = match < 0
    nearest = d.min(1)
    M = len(pos)
    return {
        "covered": float((~free).sum() / M),
        "duplicate": float((free & (nearest < threshold)).sum() / M),
        "near": float((free & (nearest >= threshold) & (nearest < NEAR * threshold)).sum() / M),
        "far": float((free & (nearest >= NEAR * threshold)).sum() / M),
    }


def duplicates_reach(
    pos: np.ndarray, landmarks: np.ndarray, threshold: float, kl: int, radius: float, free_first: bool = False
):
    """pos, landmarks [M, 2] of one environment -> for each duplicate agent (as ``classify``
    counts them): (distance to the nearest landmark the maximum matching leaves uncovered,
    whether one is among its ``kl`` nearest landmarks within ``radius``), as two arrays. With
    ``free_first`` (the lists of ``landmark_order`` "free", "open" and the claim ones, which hold the
    landmarks no other agent holds before the held ones) any uncovered landmark within ``radius``
    is in sight, however many held ones lie nearer."""
    d, match = matching(pos, landmarks, threshold)
    uncovered = np.ones(len(landmarks), bool)
    uncovered[match[match >= 0]] = False
    dup = np.where((match < 0) & (d.min(1) < threshold))[0]
    if not uncovered.any() or not len(dup):
        return np.zeros(0), np.zeros(0, bool)
    dist = d[dup][:, uncovered].min(1)
    if free_first:
        return dist, dist < radius
    sensed = np.argsort(d[dup], axis=1)[:, :kl]  # each duplicate's kl nearest landmarks
    rows = np.arange(len(dup))[:, None]
    in_sight = (uncovered[sensed] & (d[dup][rows, sensed] < radius)).any(1)
    return dist, in_sight


def hovering(inside: np.ndarray) -> dict:
    """inside [W, M] bool, whether each agent held a landmark of its own (the maximum matching)
    at each of W steps -> the fractions of agents inside at all W (held) and at some but not all
    (hover), and the largest fraction covered at one step (best)."""
    always, ever = inside.all(0), inside.any(0)
    return {"held": float(always.mean()), "hover": float((ever & ~always).mean()), "best": float(inside.mean(1).max())}


FULL_PUSHES = (1, 2, 3, 4)  # the paper's four pushes, at full force in either action set


def jostling(pos: np.ndarray, actions: np.ndarray, landmarks: np.ndarray, threshold: float) -> dict:
    """pos [W, M, 2] and actions [W, M] of one environment over a window, landmarks [M, 2] -> for
    the duplicates at the window's last step (as ``classify`` counts them) and the agent each
    shares its landmark with: the changes of which of the two is nearer the landmark over the
    window (summed over pairs, with their count), their full pushes and actions counted, and the
    same counts for the lone holders (alone within the threshold of their matched landmark)."""
    d, match = matching(pos[-1], landmarks, threshold)
    full = np.isin(actions, FULL_PUSHES)
    out = {"pairs": 0, "swaps": 0, "pair_full": 0, "pair_actions": 0, "lone_full": 0, "lone_actions": 0}
    within = d < threshold
    for i in np.flatnonzero((match < 0) & (d.min(1) < threshold)):
        lm = int(d[i].argmin())
        others = [j for j in np.flatnonzero(within[:, lm]) if j != i]
        if not others:
            continue
        h = min(others, key=lambda j: d[j, lm])
        di = np.linalg.norm(pos[:, i] - landmarks[lm], axis=-1)
        dh = np.linalg.norm(pos[:, h] - landmarks[lm], axis=-1)
        nearer = di < dh
        out["pairs"] += 1
        out["swaps"] += int((nearer[1:] != nearer[:-1]).sum())
        out["pair_full"] += int(full[:, [i, h]].sum())
        out["pair_actions"] += 2 * len(actions)
    for i in np.flatnonzero(match >= 0):
        if within[:, match[i]].sum() == 1:
            out["lone_full"] += int(full[:, i].sum())
            out["lone_actions"] += len(actions)
    return out


def run(
    policy_name: str,
    agents: int,
    episodes: int,
    seed: int,
    sense: tuple[int, float] | None = None,
    steps: int = 50,
    window: int = 10,
    jostle: bool = False,
) -> dict:
    """The mean fractions over ``episodes`` episodes (one environment each) that run their ``steps``,
    and where the duplicates' free landmarks are (``sense``: (KL, radius) counted as in sight;
    default the policy's lists); episodes that succeed before the last step are counted apart
    (every landmark covered). ``steps``: the episode length (the task's is 50); ``window``: the
    steps before the last that ``hovering`` reads."""
    import torch

    import taichi_swarm
    from trainer.checkpoint import load_policy
    from trainer.model import policy_inputs

    torch.set_num_threads(1)
    policy, payload = load_policy(policy_name)
    fused = policy.fused_weights()
    # the swarm policies' setting, with the lists and options the policy trained on over it
    swarm = {"neighbours": 4, "landmark_neighbours": 5, "sense_radius": 1.0, "scale": "density"}
    swarm.update(payload.get("swarm") or {})
    task = (payload.get("task") or {}).get("task", "coverage")
    env = taichi_swarm.make(task, episodes, agents, comm="rc", comm_radius=1.0, seed=seed, max_steps=steps, **swarm)
    if env.num_landmarks != agents:  # formation's sensed lattice: its landmarks are its M targets
        raise SystemExit(f"coverage_misses: {task}'s landmarks are not its {agents} targets here ({env.num_landmarks})")
    obs = env.reset()
    finished = np.zeros(episodes, bool)
    threshold = env.params["success_threshold"]
    last = env.params["max_steps"] - 1  # stop before the last step: its auto-reset would clear the state
    inside = np.zeros((min(window, last), episodes, agents), bool)
    pos_w, act_w = np.zeros((len(inside), episodes, agents, 2)), np.zeros((len(inside), episodes, agents), int)
    for t in range(last):
        with torch.no_grad():
            logits, _ = policy(**policy_inputs(obs, "cpu"), fused=fused)
        action = logits.argmax(-1).contiguous()
        obs, _, done, _ = env.step(action)
        finished |= np.asarray(done, bool)
        if t >= last - len(inside):
            state = {k: np.asarray(v) for k, v in env.get_state().items()}
            # the action that led to this step's positions
            pos_w[t - last + len(inside)], act_w[t - last + len(inside)] = state["pos"], action.numpy()
            for b in np.flatnonzero(~finished):
                inside[t - last + len(inside), b] = matching(state["pos"][b], state["landmarks"][b], threshold)[1] >= 0
    # (state: read at the window's last step, the one before the episode's last)
    kept = [b for b in range(episodes) if not finished[b]]
    rows = [{**classify(state["pos"][b], state["landmarks"][b], threshold), **hovering(inside[:, b])} for b in kept]
    names = ("covered", "duplicate", "near", "far", "held", "hover", "best")
    out = {k: float(np.mean([r[k] for r in rows])) if rows else None for k in names}
    kl, radius = sense or (swarm["landmark_neighbours"], swarm["sense_radius"])
    free_first = swarm.get("landmark_order") not in (None, "nearest")  # env's FREE_FIRST rule
    reach = [duplicates_reach(state["pos"][b], state["landmarks"][b], threshold, kl, radius, free_first) for b in kept]
    dist = np.concatenate([r[0] for r in reach]) if reach else np.zeros(0)
    sight = np.concatenate([r[1] for r in reach]) if reach else np.zeros(0, bool)
    out["free_distance"] = float(np.median(dist)) if len(dist) else None
    out["free_in_sight"] = float(sight.mean()) if len(sight) else None
    if swarm.get("landmark_order") == "auction":  # a winner lists its own landmark alone: no sight to count
        out["free_in_sight"] = None
    if jostle:
        j = [jostling(pos_w[:, b], act_w[:, b], state["landmarks"][b], threshold) for b in kept]
        total = {
            k: sum(r[k] for r in j)
            for k in ("pairs", "swaps", "pair_full", "pair_actions", "lone_full", "lone_actions")
        }
        out["swaps"] = total["swaps"] / total["pairs"] if total["pairs"] else None
        out["pair_push"] = total["pair_full"] / total["pair_actions"] if total["pair_actions"] else None
        out["lone_push"] = total["lone_full"] / total["lone_actions"] if total["lone_actions"] else None
    return {"agents": agents, "episodes": episodes, "succeeded_early": int(finished.sum()), **out}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("policy", help="a zoo name, policy.pt or run directory")
    ap.add_argument("--agents", type=int, nargs="+", default=[100], help="team sizes (default: 100)")
    ap.add_argument("--episodes", type=int, default=20, help="episodes per size (default: 20)")
    ap.add_argument("--seed", type=int, default=777, help="evaluation seed (default: 777)")
    ap.add_argument("--steps", type=int, default=50, help="episode length (default: the task's 50)")
    ap.add_argument(
        "--window", type=int, default=10, help="steps before the last that held, hover, best read (default: 10)"
    )
    ap.add_argument(
        "--sense", nargs=2, metavar=("KL", "R"), help="count a free landmark in sight among the KL nearest within R "
        "(default: the policy's landmark lists)",
    )  # fmt: skip
    ap.add_argument(
        "--jostle", action="store_true", help="add swaps, pair_push and lone_push over the window (the docstring)"
    )
    args = ap.parse_args(argv)
    if args.episodes < 1 or any(m < 1 for m in args.agents):
        ap.error("--episodes and --agents must be >= 1")
    if args.window < 1:
        ap.error(f"--window must be >= 1, got {args.window}")
    if args.steps < 2:
        ap.error(f"--steps must be >= 2 (the state is read before the last step), got {args.steps}")
    sense = None
    if args.sense:
        try:
            sense = (int(args.sense[0]), float(args.sense[1]))
        except ValueError:
            ap.error(f"--sense takes an integer KL and a radius, got {' '.join(args.sense)}")
        if sense[0] < 1 or not sense[1] > 0:
            ap.error(f"--sense takes KL >= 1 and a radius > 0, got {' '.join(args.sense)}")
    # succeeded: episodes that covered everything before the last step (the fractions are over the others)
    head = f"{'M':>5} {'episodes':>8} {'succeeded':>9} {'covered':>8} {'duplicate':>9} {'near':>6} {'far':>6}"
    head += f" {'held':>6} {'hover':>6} {'best':>6} {'free_distance':>13} {'free_in_sight':>13}"
    print(head + (f" {'swaps':>6} {'pair_push':>9} {'lone_push':>9}" if args.jostle else ""))
    for m in args.agents:
        r = run(args.policy, m, args.episodes, args.seed, sense, args.steps, args.window, args.jostle)
        if r["covered"] is None:
            print(f"{m:>5} {args.episodes:>8} {r['succeeded_early']:>9}  every episode succeeded before its last step")
            continue
        fractions = f"{r['covered']:>8.3f} {r['duplicate']:>9.3f} {r['near']:>6.3f} {r['far']:>6.3f}"
        fractions += f" {r['held']:>6.3f} {r['hover']:>6.3f} {r['best']:>6.3f}"
        reach = " ".join(  # (None: no duplicate)
            "-".rjust(13) if r[k] is None else f"{r[k]:>13.2f}" for k in ("free_distance", "free_in_sight")
        )
        if args.jostle:
            reach += " " + " ".join(
                "-".rjust(w) if r[k] is None else f"{r[k]:>{w}.{p}f}"
                for k, w, p in (("swaps", 6, 2), ("pair_push", 9, 3), ("lone_push", 9, 3))
            )
        print(f"{m:>5} {args.episodes:>8} {r['succeeded_early']:>9} {fractions} {reach}")


if __name__ == "__main__":
    main()
