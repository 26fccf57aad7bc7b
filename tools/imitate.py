"""Behaviour cloning of a hand-written controller (tools/coverage_reference.py) into a swarm
policy, by DAgger: roll out at several team sizes, each environment driven by the controller or
by the policy (the controller's share falling from 1 to 0), label every agent's step with the
controller's action, and fit the policy's logits to the labels (cross-entropy). The task, lists
and action space are the policy's own (``--init``). Teachers:

- greedy (coverage only): the local rule, which uses only what an agent's lists and 3 rounds of
  messages give, so the network (the same lists, 3 attention rounds) can represent it;
- window: each agent's own landmark in the min-sum matching of the agents and landmarks within
  ``--window-radius`` of it (a privileged teacher: exact positions, no lists), which a student
  approximates from its lists and messages.
- first: the first landmark of each agent's list, on free-first and claim lists the nearest
  one no other agent holds (the best choice an agent can make without its teammates).

With ``--goal`` the labels are the landmark the teacher heads for, not its action: the landmark
attention's scores are fitted to it and only its query and key weights train, so the messages
and the actor stay as they are (docs/SWARM.md, "The actor follows its attention"); with
``--goal-pass`` through a goal network whose embedding raises that attention's query
(ModelConfig.goal_pass).

The result is a policy that `swarm eval` and `swarm zero-shot` read, and a start for PPO
(`--init-from`).

    python tools/imitate.py --init coverage-rc-m10-swarm --sizes 10 20 50 100 --iterations 60 \
        --out runs/imitate/policy.pt
    python tools/imitate.py --init results/reproduce-swarm/s-line-rc-rows-m50-k12/s0/stage-m50/policy.pt \
        --teacher window --window-radius 3 --sizes 50 100 --iterations 40 --out runs/imitate-line/policy.pt
    python tools/imitate.py --init results/reproduce-swarm/s-line-rc-rows-m50-k12-claim-zero/s0/stage-m50/policy.pt \
        --teacher first --goal --sizes 24 50 --iterations 30 --expert-iterations 2 --lr 1e-3 \
        --out runs/goal-line-first/policy.pt
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import torch  # noqa: E402
from coverage_reference import DIRECTIONS, greedy_goals, steer_costs, window_goals  # noqa: E402

import taichi_swarm  # noqa: E402
from trainer import checkpoint  # noqa: E402
from trainer.model import SwarmPolicy, policy_inputs  # noqa: E402

AGENTS_PER_ROLLOUT = 1000  # B x M of each iteration's environments
STEPS = 50  # the episode's length: one rollout is one episode of every environment


TEACHERS = ("greedy", "window", "first")


def make_env(task: str, agents: int, swarm: dict, seed: int):
    return taichi_swarm.make(
        task, max(1, AGENTS_PER_ROLLOUT // agents), agents, comm="rc", comm_radius=1.0, seed=seed, **swarm
    )


def expert_actions(env, obs, teacher: str = "greedy", window_radius: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The teacher's steering costs for every agent and action of the env's action space,
    float32 [B, M, A] (tools/coverage_reference.py ``steer_costs``; its action is the argmin),
    and each agent's offset to the teacher's goal for it, float32 [B, M, 2]."""
    state = env.get_state()
    state = {k: np.asarray(v) for k, v in state.items()}
    if teacher == "window":
        goals = window_goals(state, window_radius)
    elif teacher == "first":  # the first listed landmark (an agent that senses none stays where it is)
        ent, sensed = np.asarray(obs["entities"])[..., 0, :2], np.asarray(obs["entity_mask"])[..., 0]
        goals = state["pos"] + np.where(sensed[..., None], ent, 0.0)
    else:
        goals = greedy_goals(state, {k: np.asarray(v) for k, v in obs.items()})
    c = steer_costs(state["pos"].reshape(-1, 2), state["vel"].reshape(-1, 2), goals.reshape(-1, 2), env.action_space)
    costs = torch.from_numpy(c.reshape(env.num_envs, env.num_agents, -1).astype(np.float32))
    return costs, torch.from_numpy((goals - state["pos"]).astype(np.float32))


# the push directions of actions 1-4 (-x, +x, -y, +y); in the fine space 5-8 push the same ways at a quarter
PUSHES = torch.from_numpy(DIRECTIONS[1:])


def direction_loss(logits: torch.Tensor, offset: torch.Tensor, beyond: float) -> tuple[torch.Tensor, int, int]:
    """-log P(a push towards the goal) for the agents farther than ``beyond`` from the teacher's
    goal: the push whose direction is nearest the offset's, full or quarter (their probabilities
    summed). Nearer agents carry no label, so the policy keeps its own way of parking. Returns
    (loss, hits, labelled): hits where the policy's most likely push group is the label's."""
    far = offset.norm(dim=-1) > beyond
    want = (offset @ PUSHES.T).argmax(-1)  # [..]: 0-3
    logp = torch.log_softmax(logits, -1)
    groups = [
        logp[..., 1 + k] if logits.shape[-1] <= 5 else torch.logaddexp(logp[..., 1 + k], logp[..., 5 + k])
        for k in range(4)
    ]
    groups = torch.stack([logp[..., 0]] + groups, -1)  # [.., 5]: no-op and the four directions
    picked = groups.gather(-1, (want + 1)[..., None])[..., 0]
    n = int(far.sum())
    loss = -(picked * far).sum() / max(n, 1)
    return loss, int(((groups.argmax(-1) == want + 1) & far).sum()), n


def targets(costs: torch.Tensor, soft: float) -> torch.Tensor:
    """The labels' distribution over actions [..., A]: all on the teacher's action (``soft`` 0),
    or softmax(-(cost - least) / soft), which spreads it over the actions that steer nearly as
    well (a hover between two pushes) and keeps it on the one action far from the goal."""
    if soft <= 0:
        return torch.nn.functional.one_hot(costs.argmin(-1), costs.shape[-1]).float()
    return torch.softmax(-(costs - costs.min(-1, keepdim=True).values) / soft, dim=-1)


def rollout(env, policy, expert_share: float, seed: int, teacher: str = "greedy", window_radius: float = 3.0):
    """One episode of every environment; the first round(expert_share * B) follow the teacher,
    the rest the policy's argmax. Returns (inputs per step, the teacher's labels per step, covered,
    success), the last two over the episodes that ended in the environments the policy drove (all
    of them while the teacher drives every one)."""
    obs = env.reset(seed=seed)
    n_expert = int(round(expert_share * env.num_envs))
    inputs, labels = [], []
    covered, success = [], []
    for _ in range(STEPS):
        x = {k: v.clone() for k, v in policy_inputs(obs).items()}  # the env's views are overwritten
        label = expert_actions(env, obs, teacher, window_radius)
        with torch.no_grad():
            mine = policy(**x)[0].argmax(-1)
        action = mine.clone()
        action[:n_expert] = label[0][:n_expert].argmin(-1)
        inputs.append(x)
        labels.append(label)
        obs, _, done, info = env.step(action.contiguous())
        ended = np.asarray(done).copy()
        if n_expert < env.num_envs:
            ended[:n_expert] = False
        covered.extend(np.asarray(info["episode"]["covered"])[ended].tolist())
        success.extend(np.asarray(info["episode"]["success"])[ended].tolist())
    return inputs, labels, float(np.mean(covered)) if covered else 0.0, float(np.mean(success)) if success else 0.0


GOAL_MATCH = 1e-3  # a listed landmark is the teacher's goal where its offset is this near the goal's


def goal_slots(x: dict, offset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Which listed landmark is the teacher's goal: (slot [..], listed [..] bool) from the
    policy inputs' entities [.., KL, F] (offsets first) and the goal's offset [.., 2]; an agent
    whose goal is not among its sensed landmarks has no slot (listed False)."""
    d = (x["entities"][..., :2] - offset.unsqueeze(-2)).norm(dim=-1)
    d = d.masked_fill(~x["entity_mask"], float("inf"))
    near, slot = d.min(-1)
    return slot, near < GOAL_MATCH


def goal_loss(policy, x: dict, offset: torch.Tensor) -> tuple[torch.Tensor, int, int]:
    """Cross-entropy of the landmark attention's scores (``landmark_scores``) on the teacher's
    goal, over the agents whose goal is listed: what an agent heads for, not how it steers.
    Returns (loss, hits: the top score on the goal, labelled)."""
    slot, listed = goal_slots(x, offset)
    scores = policy.landmark_scores(**x)
    picked = torch.log_softmax(scores, -1).gather(-1, slot[..., None])[..., 0]
    n = int(listed.sum())
    loss = -(picked * listed).sum() / max(n, 1)
    return loss, int(((scores.argmax(-1) == slot) & listed).sum()), n


def fit(
    policy,
    optimizer,
    inputs,
    labels,
    rng,
    chunk: int = 10,
    soft: float = 0.0,
    beyond: float = 0.0,
    goal: bool = False,
) -> tuple[float, float]:
    """One pass over a rollout's steps in random chunks of ``chunk`` steps, the logits fitted to
    ``targets(costs, soft)`` (cross-entropy), or with ``beyond`` > 0 to ``direction_loss``, or
    with ``goal`` the landmark attention to ``goal_loss``; (loss, accuracy: the argmax on the
    teacher's action, its push direction or its landmark)."""
    order = rng.permutation(len(inputs))
    losses, hits, total = [], 0, 0
    for i in range(0, len(order), chunk):
        idx = order[i : i + chunk]
        x = {k: torch.cat([inputs[j][k] for j in idx]) for k in inputs[0]}
        if goal:
            loss, hit, n = goal_loss(policy, x, torch.cat([labels[j][1] for j in idx]))
        elif beyond > 0:
            loss, hit, n = direction_loss(policy(**x)[0], torch.cat([labels[j][1] for j in idx]), beyond)
        else:
            costs, logits = torch.cat([labels[j][0] for j in idx]), policy(**x)[0]
            loss = -(targets(costs, soft) * torch.log_softmax(logits, -1)).sum(-1).mean()
            hit, n = int((logits.argmax(-1) == costs.argmin(-1)).sum()), costs.shape[:-1].numel()
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
        optimizer.step()
        losses.append(loss.item())
        hits += hit
        total += n
    return float(np.mean(losses)), hits / max(total, 1)


def with_goal_pass(policy, payload: dict):
    """(policy, payload) with a goal network: the same network if it has one, else the same
    function with one (ModelConfig.goal_pass: W_g zero), the goal network a copy of the
    policy's own layers, so that it starts from what the policy makes of its lists and messages;
    the payload's model config to match."""
    if policy.config.goal_pass:
        return policy, payload
    config = dataclasses.replace(policy.config, goal_pass=True)
    out = SwarmPolicy(config)
    own = policy.state_dict()
    net = out.goal_net.state_dict()  # the policy's layers but its heads
    out.load_state_dict({**out.state_dict(), **own, **{f"goal_net.{k}": own[k] for k in net}})
    return out, dict(payload, model_config=config.to_dict())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--init", required=True, help="a zoo name or a checkpoint: the network, its lists and its start")
    ap.add_argument("--sizes", nargs="+", type=int, default=[10, 20, 50, 100])
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--expert-iterations", type=int, default=10, help="the controller's share falls to 0 over these")
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--passes", type=int, default=2, help="passes over the fitted rollouts each iteration")
    ap.add_argument(
        "--aggregate", type=int, default=1,
        help="fit each iteration over the last AGGREGATE rollouts of its team size, not the new one alone (DAgger's "
        "aggregated data, which steadies a fit that drifts between rollouts; default 1)",
    )  # fmt: skip
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--teacher", choices=TEACHERS, default="greedy", help="the controller whose actions label the steps"
    )
    ap.add_argument("--window-radius", type=float, default=3.0, help="window's radius (tools/coverage_reference.py)")
    ap.add_argument(
        "--soft", type=float, default=0.0,
        help="soft labels: softmax(-(steering cost - least) / SOFT) over the actions (default 0: the teacher's action)",
    )  # fmt: skip
    ap.add_argument(
        "--direction-beyond", type=float, default=0.0,
        help="label only the push towards the teacher's goal, for agents farther than this from it (default 0: "
        "the teacher's action for every agent)",
    )  # fmt: skip
    ap.add_argument(
        "--goal", action="store_true",
        help="fit the landmark attention to the landmark the teacher heads for, not the logits to its action: "
        "only the attention's query and key weights are trained (the messages and the actor are kept)",
    )  # fmt: skip
    ap.add_argument(
        "--goal-pass", action="store_true",
        help="with --goal: fit through a goal network (ModelConfig.goal_pass, added where the policy lacks it: a "
        "copy of its layers, joined by W_g at zero), whose weights alone are trained",
    )  # fmt: skip
    ap.add_argument(
        "--freeze-goal-net", action="store_true",
        help="with --goal-pass: train W_g alone, the goal network kept as it starts (a copy of the policy's layers)",
    )  # fmt: skip
    ap.add_argument("--out", required=True, help="the policy file to write (policy.pt format)")
    args = ap.parse_args(argv)
    if args.iterations < 1 or args.aggregate < 1 or any(m < 2 for m in args.sizes):
        ap.error("--iterations and --aggregate must be >= 1 and every size >= 2")
    if args.window_radius <= 0:
        ap.error(f"--window-radius must be > 0, got {args.window_radius:g}")
    if args.soft < 0 or args.direction_beyond < 0:
        ap.error(f"--soft and --direction-beyond must be >= 0, got {args.soft:g} and {args.direction_beyond:g}")
    if args.goal and (args.soft > 0 or args.direction_beyond > 0):
        ap.error("--goal fits the teacher's landmark: it takes neither --soft nor --direction-beyond")
    if args.goal_pass and not args.goal:
        ap.error("--goal-pass fits the landmark attention: add --goal")
    if args.freeze_goal_net and not args.goal_pass:
        ap.error("--freeze-goal-net keeps a goal network: add --goal-pass")
    taichi_swarm.init("cpu")
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    from trainer.zoo import get, looks_like_name

    path = get(args.init).path if looks_like_name(args.init) else args.init
    policy, payload = checkpoint.load_policy(path)
    task = payload["task"]["task"]
    if args.teacher == "greedy" and task != "coverage":
        raise SystemExit(f"imitate: the greedy teacher drives coverage, and {args.init} is a {task} policy")
    swarm = dict(payload.get("swarm") or {})
    swarm["assignment"] = "nearest"  # covered by the maximum matching, and a step cost flat in M
    for key in ("neighbours", "landmark_neighbours", "sense_radius"):
        if swarm.get(key) is None:
            raise SystemExit(f"imitate: {args.init} was not trained on lists ({key} unset)")
    params = policy.parameters()
    if args.goal:
        if policy.config.entity_mode != "emp":
            raise SystemExit(f"imitate: --goal fits the landmark attention, and {args.init} has none (entity_mode "
                             f"{policy.config.entity_mode!r})")  # fmt: skip
        if args.goal_pass:
            policy, payload = with_goal_pass(policy, payload)
            params = [*policy.goal_query.parameters()]
            if not args.freeze_goal_net:
                params += policy.goal_net.parameters()
        else:  # what scores the landmarks, not what the attention passes on (W_v, W_out) or the embeddings
            params = [policy.entity_attention.w_q.weight, policy.entity_attention.w_k.weight]
    policy.train()
    optimizer = torch.optim.Adam(params, lr=args.lr)
    envs = {m: make_env(task, m, swarm, args.seed) for m in args.sizes}
    log = []
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    kept = {m: [] for m in args.sizes}
    for it in range(args.iterations):
        m = args.sizes[it % len(args.sizes)]
        share = max(0.0, 1.0 - it / max(1, args.expert_iterations))
        t = time.time()
        inputs, labels, covered, success = rollout(
            envs[m], policy, share, args.seed * 100003 + it, args.teacher, args.window_radius
        )
        kept[m] = (kept[m] + [(inputs, labels)])[-args.aggregate :]  # DAgger's data: this size's last rollouts
        inputs = [x for rollout_inputs, _ in kept[m] for x in rollout_inputs]
        labels = [y for _, rollout_labels in kept[m] for y in rollout_labels]
        for _ in range(args.passes):
            loss, acc = fit(
                policy, optimizer, inputs, labels, rng, soft=args.soft, beyond=args.direction_beyond, goal=args.goal
            )
        row = dict(
            iteration=it,
            agents=m,
            expert_share=share,
            covered=covered,
            success=success,
            loss=loss,
            accuracy=acc,
            s=time.time() - t,
        )
        log.append(row)
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        payload = dict(payload, model={k: v.detach().clone() for k, v in policy.state_dict().items()})
        checkpoint.save_policy_only(payload, args.out)  # atomic: a stopped run keeps its last iteration
    with open(args.out + ".log.jsonl", "w") as f:
        f.writelines(json.dumps(r) + "\n" for r in log)


if __name__ == "__main__":
    main()
