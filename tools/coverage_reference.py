"""Hand-written controllers for density-scaled coverage, as references for the learned policies
(docs/SWARM.md, "What a hand-written controller reaches"). Same setting as the swarm spec's
policies: rc within 1, lists of K = 4 teammates and KL = 5 landmarks within 1, scale="density",
the 50-step limit, the exact assignment's S%, covered and DIST. ``--task formation``: formation's
lattice with its points sensed as landmarks (the 12 nearest within 1.5, as its policies sense
them), every agent on one point, success within 0.05. ``--task line``: line's rows, their
targets sensed the same way (the 24 nearest within 1.5, as the line policies sense them).

- planned: the min-sum matching of agents to landmarks at the episode's start (scipy), known to
  every agent (a central plan, not decentralised); each agent then drives to its landmark.
  What the dynamics allow in 50 steps: the ceiling.
- nearest-first: central too, re-planned every step: the greedy matching of the current
  positions (the nearest agent-landmark pair first, then the nearest pair left, and so on),
  known to every agent. It is the best any rule can do that never gives a landmark to an agent
  other than the nearest one left, with every agent seeing everything: a bound for the local
  rules below, which approximate it from their lists.
- greedy: decentralised, from what the agent's lists hold and 3 rounds of messages. It drives
  to the nearest landmark it senses that no teammate it hears heads for from nearer; when it
  has given up every landmark it senses (or senses none), it moves away from the teammates it
  hears, to find others.
- claim: greedy on claim lists (8 teammates heard, the 16 nearest landmarks within 6 sensed, the
  free ones first, each with its claim reading: ``landmark_order="claim"``), the setting of the
  zoo's ``coverage-rc-m100-claim``. A landmark that reads held (a teammate the threshold matching
  gives it, within the threshold: a reading below it) is never a goal; of the rest, the agent
  drives to the nearest that no teammate it hears heads for from nearer (3 rounds, as greedy).
  An agent the matching holds reads its own landmark free and nearest, so it stays on it.
- window: each agent solves the min-sum matching of the agents and landmarks within
  ``--window-radius`` of it (all positions known exactly, every landmark within it, a privileged
  view no list gives), re-planned every step, and drives to its own landmark (to its nearest
  where the matching leaves it none). It asks how far a local plan must see: the network's 3
  rounds of messages over teammates within 1 reach agents up to 3 away.

    python tools/coverage_reference.py --sizes 10 100 1000 --episodes 100 --save
    python tools/coverage_reference.py --task formation --sizes 10 100 --episodes 100
    python tools/coverage_reference.py --task line --controllers nearest-first --sizes 50 100 --episodes 100
    python tools/coverage_reference.py --controllers window --window-radius 3 --sizes 100 --episodes 100

--save merges the rows into results/swarm/reference-<controller>.json (a size run again
replaces its row; reference-<controller>-nearest.json with --assignment nearest;
reference-<task>-<controller>.json for formation and line; window-r<R> for window's radius R), which
tools/swarm_curves.py draws beside the policies' zero-shot curves.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
RESULTS = os.path.join(ROOT, "results", "swarm")
sys.path.insert(0, ROOT)

import taichi_swarm  # noqa: E402
from taichi_swarm.physics import DAMPING, DT, FINE, MASS, SENSITIVITY  # noqa: E402

CONTROLLERS = ("planned", "nearest-first", "greedy", "claim", "window")
# the landmarks each task's policies sense (formation's are the points of its lattice)
SENSED = {
    "coverage": dict(landmark_neighbours=5, sense_radius=1.0),
    "formation": dict(landmark_neighbours=12, sense_radius=1.5),
    "line": dict(landmark_neighbours=24, sense_radius=1.5),
}
# what the claim controller senses: the zoo's coverage-rc-m100-claim's lists
CLAIM = dict(neighbours=8, landmark_neighbours=16, sense_radius=6.0, landmark_occupancy=True, landmark_order="claim")
# unit force direction of each discrete action: no-op, -x, +x, -y, +y; "fine" adds the four at FINE
DIRECTIONS = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], np.float32)
FORCES = {"discrete": DIRECTIONS, "fine": np.concatenate([DIRECTIONS, FINE * DIRECTIONS[1:]])}


def steer_costs(pos: np.ndarray, vel: np.ndarray, goal: np.ndarray, action_space: str = "discrete") -> np.ndarray:
    """[N, 2] each -> [N, A]: for each first action, the least cost of a two-action sequence
    that starts with it, the cost being how far the next two positions and the stopping point
    after them (where the agent comes to rest if it coasts from there on) lie from its goal
    (squared distances, summed). ``steer`` takes the action of least cost.
    From rest an agent's stopping points lie on a lattice of side 0.2 (each impulse adds
    SENSITIVITY / MASS * DT * DT / DAMPING = 0.2 to it), wider than the 0.1 of success, so a
    controller that only parks misses a goal between lattice points (up to 0.141 away); this
    one alternates impulses and hovers there: within 0.056 of 4000 random goals over the last
    10 of 50 steps (one step of lookahead: 6% of them out of 0.1). ``action_space="fine"`` picks
    from the nine actions of that space (the quarter pushes too)."""
    forces = FORCES[action_space]
    accel = forces * (SENSITIVITY / MASS) * DT  # [A, 2] velocity change of each action
    v1 = vel[:, None, :] * (1.0 - DAMPING) + accel[None]  # [N, A, 2]
    p1 = pos[:, None, :] + v1 * DT
    v2 = v1[:, :, None, :] * (1.0 - DAMPING) + accel[None, None]  # [N, A, A, 2]
    p2 = p1[:, :, None, :] + v2 * DT
    stop = p2 + v2 * DT * (1.0 - DAMPING) / DAMPING
    g = goal[:, None, None, :]
    cost = ((p1[:, :, None] - g) ** 2).sum(-1) + ((p2 - g) ** 2).sum(-1) + ((stop - g) ** 2).sum(-1)  # [N, A, A]
    return cost.min(axis=2)


def steer(pos: np.ndarray, vel: np.ndarray, goal: np.ndarray, action_space: str = "discrete") -> np.ndarray:
    """[N, 2] each -> int64 [N]: the action of least ``steer_costs``."""
    return np.argmin(steer_costs(pos, vel, goal, action_space), axis=1).astype(np.int64)


def matched_goals(state: dict, match) -> np.ndarray:
    """[B, M, 2]: every agent's landmark in ``match`` ([M, M] distances -> each row's column)
    of the current positions, env by env."""
    pos, lmk = state["pos"], state["landmarks"]
    goals = np.empty_like(pos)
    for b in range(pos.shape[0]):
        goals[b] = lmk[b, match(np.linalg.norm(pos[b][:, None, :] - lmk[b][None, :, :], axis=-1))]
    return goals


def planned_goals(state: dict) -> np.ndarray:
    """[B, M, 2]: every agent's landmark in the min-sum matching of the current positions."""
    from scipy.optimize import linear_sum_assignment

    return matched_goals(state, lambda cost: linear_sum_assignment(cost)[1])  # rows come in order


def nearest_first(cost: np.ndarray) -> np.ndarray:
    """[N, N] -> int [N]: each row's column in the greedy matching (the smallest entry first, then
    the smallest left in the rows and columns not yet matched, ...). It is built as rounds of
    mutual nearest pairs, O(N^2) a round instead of a sorted scan of N^2 pairs: for distinct
    entries the scan matches every such pair too (no smaller entry left shares its row or column,
    so both ends are still free when the scan reaches it), so the rounds give its matching."""
    n = cost.shape[0]
    match = np.full(n, -1, np.int64)
    rows, cols = np.arange(n), np.arange(n)
    while len(rows):
        sub = cost[np.ix_(rows, cols)]
        best_col, best_row = sub.argmin(1), sub.argmin(0)
        mutual = best_row[best_col] == np.arange(len(rows))
        if not mutual.any():  # only ties can do this: take the smallest entry left
            mutual = np.zeros(len(rows), bool)
            mutual[np.unravel_index(sub.argmin(), sub.shape)[0]] = True
        match[rows[mutual]] = cols[best_col[mutual]]
        keep_cols = np.ones(len(cols), bool)
        keep_cols[best_col[mutual]] = False
        rows, cols = rows[~mutual], cols[keep_cols]
    return match


def nearest_first_goals(state: dict) -> np.ndarray:
    """[B, M, 2]: every agent's landmark in the greedy matching of the current positions."""
    return matched_goals(state, nearest_first)


def window_goals(state: dict, radius: float) -> np.ndarray:
    """[B, M, 2]: each agent's landmark in the min-sum matching of the agents and the landmarks
    within ``radius`` of it (its nearest landmark where that matching leaves it none, or none lie
    within the radius). One matching per agent: the plan an agent could make from a window."""
    from scipy.optimize import linear_sum_assignment

    pos, lmk = state["pos"], state["landmarks"]
    goals = np.empty_like(pos)
    for b in range(pos.shape[0]):
        to_agents = np.linalg.norm(pos[b][:, None] - pos[b][None], axis=-1)  # [M, M]
        to_landmarks = np.linalg.norm(pos[b][:, None] - lmk[b][None], axis=-1)  # [M, L]
        nearest = to_landmarks.argmin(1)
        for i in range(pos.shape[1]):
            goals[b, i] = lmk[b, nearest[i]]
            agents = np.flatnonzero(to_agents[i] <= radius)  # i among them
            landmarks = np.flatnonzero(to_landmarks[i] <= radius)
            if len(landmarks) == 0:
                continue
            rows, cols = linear_sum_assignment(to_landmarks[np.ix_(agents, landmarks)])
            mine = cols[agents[rows] == i]
            if len(mine):
                goals[b, i] = lmk[b, landmarks[mine[0]]]
    return goals


def greedy_goals(state: dict, obs: dict, rounds: int = 3, taken: np.ndarray | None = None) -> np.ndarray:
    """[B, M, 2] from each agent's own lists and 3 rounds of messages, as the network has:
    obs["entities"] (offsets to its KL nearest sensed landmarks, nearest first), obs["nbr"] /
    obs["nbr_mask"] (the teammates it hears). Each round every agent tells the teammates that
    hear it which landmark it is heading for and how far it is; an agent gives a landmark up to
    a teammate that heads for it and is nearer, and takes its next nearest. (Landmarks are
    compared by position here, which a message would carry as an offset.) ``taken`` [B, M, KL]:
    listed landmarks never to head for (claim's held ones)."""
    pos = state["pos"]  # [B, M, 2]
    ent, emask = np.asarray(obs["entities"]), np.asarray(obs["entity_mask"])  # [B, M, KL, 2], [B, M, KL]
    nbr, nmask = np.asarray(obs["nbr"]), np.asarray(obs["nbr_mask"])  # [B, M, K]
    b_idx = np.arange(pos.shape[0])[:, None, None]
    lmk = pos[:, :, None, :] + ent  # [B, M, KL, 2]
    mine = np.where(emask, np.linalg.norm(ent, axis=-1), np.inf)  # [B, M, KL]

    def heading(given_up):  # each agent's nearest landmark not given up: (goal [B, M, 2], its distance, any left)
        free = ~given_up
        choice = np.argmax(free, axis=-1)[..., None]  # the lists are nearest first
        goal = np.take_along_axis(lmk, choice[..., None].repeat(2, -1), axis=2)[:, :, 0]
        has = free.any(-1)
        return goal, np.where(has, np.take_along_axis(mine, choice, axis=2)[..., 0], np.inf), has

    given_up = ~emask if taken is None else ~emask | taken
    for _ in range(rounds):
        goal, dist, _ = heading(given_up)
        # what each heard teammate heads for, and how far it is from it
        their_goal, their_dist = goal[b_idx, nbr], dist[b_idx, nbr]  # [B, M, K, 2], [B, M, K]
        same = (np.abs(their_goal[:, :, None] - lmk[:, :, :, None]).max(-1) < 1e-5) & nmask[:, :, None, :]
        given_up = given_up | (same & (their_dist[:, :, None, :] < mine[..., None])).any(-1)  # beaten
    goal_free, _, has = heading(given_up)
    # nothing left: one unit away from the centroid of the teammates heard (stay if none heard)
    mates = pos[b_idx, nbr]
    n_heard = nmask.sum(-1, keepdims=True)
    centroid = (mates * nmask[..., None]).sum(2) / np.maximum(n_heard, 1)
    away = pos - centroid
    away = away / np.maximum(np.linalg.norm(away, axis=-1, keepdims=True), 1e-6)
    goal_explore = np.where(n_heard > 0, pos + away, pos)
    return np.where(has[..., None], goal_free, goal_explore)


def claim_goals(state: dict, obs: dict, threshold: float) -> np.ndarray:
    """greedy over the landmarks that do not read held on claim lists: obs["entities"]
    [B, M, KL, 3], whose third feature is below ``threshold`` exactly where the threshold
    matching gives the landmark to another agent (kernels.claimed)."""
    ent = np.asarray(obs["entities"])
    return greedy_goals(state, {**obs, "entities": ent[..., :2]}, taken=ent[..., 2] < threshold)


def run(
    controller: str,
    agents: int,
    episodes: int,
    seed: int,
    batch: int = 10,
    assignment: str = "exact",
    task: str = "coverage",
    steps: int | None = None,
    window_radius: float = 3.0,
) -> dict:
    """One controller at one team size: S%, covered and DIST over ``episodes`` episodes; covered
    and S% by the min-sum matching (``assignment="exact"``) or by the maximum matching within
    the threshold ("nearest", never below the min-sum one's: docs/SWARM.md)."""
    from taichi_swarm.metrics import run_first_episodes

    tallies = []
    for first in range(0, episodes, batch):
        # one env per batch, seeded as reset(seed=seed + first) would: make's seed starts the first reset
        sensed = CLAIM if controller == "claim" else dict(neighbours=4, **SENSED[task])
        env = taichi_swarm.make(
            task,
            num_envs=min(batch, episodes - first),
            num_agents=agents,
            comm="rc",
            comm_radius=1.0,
            seed=seed + first,
            scale="density",
            assignment=assignment,
            array="numpy",
            **({"max_steps": steps} if steps else {}),
            **sensed,
        )
        plan = {}

        def decide(obs, env=env, plan=plan):
            state = env.get_state()
            if controller == "planned":  # the plan of the first episode's start (only first episodes count)
                goals = plan.setdefault("goals", planned_goals(state))
            elif controller == "nearest-first":
                goals = nearest_first_goals(state)
            elif controller == "claim":
                goals = claim_goals(state, obs, env.params["success_threshold"])
            elif controller == "window":
                goals = window_goals(state, window_radius)
            else:
                goals = greedy_goals(state, obs)
            actions = steer(state["pos"].reshape(-1, 2), state["vel"].reshape(-1, 2), goals.reshape(-1, 2))
            return actions.reshape(env.num_envs, agents), None

        tallies.append(run_first_episodes(env, decide).summary(task)["per_episode"])
    per = {k: np.concatenate([t[k] for t in tallies]) for k in ("success", "covered", "dist", "length")}
    return {
        **({"task": task} if task != "coverage" else {}),
        "controller": controller,
        **({"window_radius": window_radius} if controller == "window" else {}),
        **({"assignment": assignment} if assignment != "exact" else {}),
        "agents": agents,
        "episodes": len(per["success"]),
        "success_rate": float(np.mean(per["success"])),
        "covered": float(np.mean(per["covered"])),
        "dist": float(np.mean(per["dist"])) if taichi_swarm.TASK_SPECS[task].reports_dist else None,
        "length": float(np.mean(per["length"])),
    }


def _kind(row: dict) -> tuple[str, str, str]:
    """A row's (task, controller, assignment): one results file each (window's per radius)."""
    controller = row["controller"]
    if controller == "window":
        controller = f"window-r{row['window_radius']:g}"
    return row.get("task", "coverage"), controller, row.get("assignment", "exact")


def save(rows: list[dict], seed: int, directory: str = RESULTS) -> list[str]:
    """Merge ``rows`` into ``directory``/reference-<controller>.json, atomically; returns the paths."""
    paths = []
    for task, controller, assignment in sorted({_kind(r) for r in rows}):
        suffix = "" if assignment == "exact" else f"-{assignment}"
        name = controller if task == "coverage" else f"{task}-{controller}"
        path = os.path.join(directory, f"reference-{name}{suffix}.json")
        by_m = {}
        if os.path.exists(path):
            with open(path) as f:
                old = json.load(f)
            if old.get("seed") != seed:
                raise SystemExit(f"coverage_reference: {path} holds seed {old.get('seed')}, not {seed}: move it away")
            by_m = {r["agents"]: r for r in old["results"]}
        mine = [r for r in rows if _kind(r) == (task, controller, assignment)]
        by_m.update({r["agents"]: r for r in mine})
        data = {
            "checkpoint": f"reference: {name.replace('-', ' ')}",
            "controller": controller,
            "seed": seed,
            "results": [by_m[m] for m in sorted(by_m)],
        }
        os.makedirs(directory, exist_ok=True)
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, path)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", choices=tuple(SENSED), default="coverage")
    ap.add_argument(
        "--controllers", nargs="+", choices=CONTROLLERS, default=["planned", "greedy"],
        help="the controllers to run (default: planned greedy; claim needs --assignment nearest)",
    )  # fmt: skip
    ap.add_argument("--sizes", nargs="+", type=int, default=[10, 20, 50, 100, 1000])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument(
        "--assignment", choices=("exact", "nearest"), default="exact",
        help="covered and S%% by the min-sum matching (exact) or the maximum matching within the threshold (nearest)",
    )  # fmt: skip
    ap.add_argument("--steps", type=int, help="episode length (default: the task's 50); not with --save")
    ap.add_argument(
        "--window-radius", type=float, default=3.0, help="window's radius: the agents and landmarks it plans over"
    )
    ap.add_argument(
        "--save", action="store_true",
        help="merge the rows into results/swarm/reference-<controller>.json (-nearest.json with --assignment nearest; "
        "reference-<task>-<controller>.json for formation and line)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if args.episodes < 1 or any(m < 2 for m in args.sizes):
        ap.error("--episodes must be >= 1 and every size >= 2")
    if args.steps is not None and (args.steps < 1 or args.save):
        ap.error("--steps must be >= 1, and the saved rows are 50-step episodes: --steps goes without --save")
    if args.window_radius <= 0:
        ap.error(f"--window-radius must be > 0, got {args.window_radius:g}")
    if "claim" in args.controllers and args.assignment != "nearest":
        ap.error("--controllers claim reads claim lists, which the threshold matching builds: add --assignment nearest")
    taichi_swarm.init("cpu")
    rows = []
    print(f"{'controller':13} {'M':>5} {'episodes':>8} {'S%':>6} {'covered':>8} {'DIST':>7} {'T':>6}")
    for controller in args.controllers:
        for m in args.sizes:
            r = run(
                controller,
                m,
                args.episodes,
                args.seed,
                assignment=args.assignment,
                task=args.task,
                steps=args.steps,
                window_radius=args.window_radius,
            )
            rows.append(r)
            print(
                f"{controller:13} {m:5d} {r['episodes']:8d} {100 * r['success_rate']:6.1f} "
                f"{r['covered']:8.2f} {'-' if r['dist'] is None else format(r['dist'], '.3f'):>7} {r['length']:6.2f}",
                flush=True,
            )
            if args.save:  # after every size: a stopped run keeps what it measured
                save([r], args.seed)


if __name__ == "__main__":
    main()
