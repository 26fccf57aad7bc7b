"""Does a list policy go where its landmark attention points? Runs the policy greedily with its
landmark attention pinned each step to one listed landmark (its sensed-landmark mask cut to
that slot, so the attention's softmax is one-hot there) chosen by a rule the policy does not
have:

- none: the policy as it is (what `swarm eval` measures);
- first: the first listed slot, which on free-first and claim lists (``landmark_order``) is the
  nearest landmark no other agent holds;
- window: the agent's landmark in the min-sum matching of the agents and landmarks within
  ``--window-radius`` of it (tools/coverage_reference.py ``window_goals``: exact positions, a
  privileged view);
- planned: its landmark in the min-sum matching of everyone (``planned_goals``).

An agent whose pinned landmark is not among its sensed ones keeps its own attention (the
``listed`` column: the share of agent-steps pinned). S% that rises under a pin says the rest of
the network (the messages and the actor) reaches a landmark it is given, and the policy's gap
is in which landmark it attends to. The episodes are `swarm eval`'s (one environment each, the
policy's lists and options, fresh at the seed):

    python tools/pinned_attention.py results/reproduce-swarm/s-line-rc-rows-m50-k12-claim-zero/s0/stage-m50/policy.pt \\
        --agents 24 50 100 --pins none first window --episodes 100
    python tools/pinned_attention.py coverage-rc-m100-claim-zero --agents 100 --pins none planned --episodes 50
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from coverage_reference import planned_goals, window_goals  # noqa: E402
from imitate import goal_slots  # noqa: E402

import taichi_swarm  # noqa: E402
from taichi_swarm.files import atomic_write_json, ensure_writable  # noqa: E402
from trainer.model import policy_inputs  # noqa: E402

PINS = ("none", "first", "window", "planned")


def pinned_mask(inputs: dict, goals: np.ndarray | None, state: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """(entity_mask with every agent whose goal is listed cut to that slot, listed [B, M] bool);
    ``goals`` None pins the first slot (where it is sensed)."""
    sensed = inputs["entity_mask"]
    if goals is None:
        slot, listed = torch.zeros(sensed.shape[:-1], dtype=torch.long), sensed[..., 0].clone()
    else:
        offset = torch.from_numpy((goals - np.asarray(state["pos"])).astype(np.float32))  # [B, M, 2]
        slot, listed = goal_slots(inputs, offset)
    one = torch.nn.functional.one_hot(slot, sensed.shape[-1]).bool()
    return torch.where(listed.unsqueeze(-1), one, sensed), listed


def run(policy, payload: dict, agents: int, pin: str, episodes: int, seed: int, window_radius: float = 3.0) -> dict:
    """One pin at one team size: the policy's greedy first episodes with its attention pinned."""
    from taichi_swarm.metrics import run_first_episodes

    task = payload["task"]["task"]
    env = taichi_swarm.make(
        task, episodes, agents, comm="rc", comm_radius=payload["task"].get("comm_radius", 1.0), seed=seed,
        **payload["swarm"],
    )  # fmt: skip
    fused = policy.fused_weights()
    pinned = []

    def decide(obs):
        inputs = policy_inputs(obs)
        if pin != "none":
            state = {k: np.asarray(v) for k, v in env.get_state().items()}
            goals = None  # "first"
            if pin == "window":
                goals = window_goals(state, window_radius)
            elif pin == "planned":
                goals = planned_goals(state)
            mask, listed = pinned_mask(inputs, goals, state)
            inputs = dict(inputs, entity_mask=mask)
            pinned.append(float(listed.float().mean()))
        with torch.no_grad():
            logits, _ = policy(**inputs, fused=fused)
        return logits.argmax(-1).to(env.device), None

    summary = run_first_episodes(env, decide).summary(task)
    return {
        "task": task,
        "agents": agents,
        "pin": pin,
        **({"window_radius": window_radius} if pin == "window" else {}),
        "episodes": episodes,
        "seed": seed,
        "success_rate": summary["success_rate"],
        "covered": summary.get("covered"),
        "length": summary["mean_length"],
        "listed": float(np.mean(pinned)) if pinned else None,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("policy", help="a zoo name or policy.pt of a policy trained on landmark lists")
    ap.add_argument("--agents", type=int, nargs="+", default=[50], help="team sizes (default: 50)")
    ap.add_argument("--pins", nargs="+", choices=PINS, default=["none", "window"], help="default: none window")
    ap.add_argument("--episodes", type=int, default=100, help="episodes per size and pin (default: 100)")
    ap.add_argument("--seed", type=int, default=777, help="evaluation seed (default: 777)")
    ap.add_argument("--window-radius", type=float, default=3.0, help="window's radius (default: 3)")
    ap.add_argument("--json", help="also write the rows here (atomically)")
    args = ap.parse_args(argv)
    if args.episodes < 1 or any(m < 2 for m in args.agents):
        ap.error("--episodes must be >= 1 and every size >= 2")
    if args.window_radius <= 0:
        ap.error(f"--window-radius must be > 0, got {args.window_radius:g}")
    from trainer import checkpoint
    from trainer.zoo import get, looks_like_name

    if args.json:
        ensure_writable(args.json, "--json")

    taichi_swarm.init("cpu")
    path = get(args.policy).path if looks_like_name(args.policy) else args.policy
    policy, payload = checkpoint.load_policy(path)
    swarm = payload.get("swarm") or {}
    if swarm.get("landmark_neighbours") is None or policy.config.entity_mode != "emp":
        raise SystemExit(f"pinned_attention: {args.policy} has no landmark attention over lists to pin")
    torch.set_num_threads(1)
    rows = []
    print(f"{'M':>5} {'pin':>8} {'S%':>6} {'covered':>8} {'T':>6} {'listed':>7}")
    for m in args.agents:
        for pin in args.pins:
            r = run(policy, payload, m, pin, args.episodes, args.seed, args.window_radius)
            rows.append(r)
            listed = "" if r["listed"] is None else f"{r['listed']:.3f}"
            print(
                f"{m:>5} {pin:>8} {100 * r['success_rate']:>6.1f} {r['covered']:>8.3f} {r['length']:>6.1f} {listed:>7}"
            )
    if args.json:
        atomic_write_json(args.json, rows)


if __name__ == "__main__":
    main()
