"""Greedy, decentralised evaluation: S%, T and DIST on fresh seeds (s.5)."""

from __future__ import annotations

import numbers

import torch

import taichi_swarm
from taichi_swarm.env import ASSIGNMENTS, LANDMARK_ORDERS
from taichi_swarm.metrics import format_results, result_header, run_first_episodes
from trainer.model import lists_to_dense, neighbour_slots, policy_inputs

ACTION_MODES = ("greedy", "sampled")
SWARM_KEYS = (
    "neighbours", "landmark_neighbours", "sense_radius", "scale", "assignment", "landmark_occupancy", "action_space",
    "landmark_order", "auction_rounds",
)  # fmt: skip
# the simulator's discrete action spaces, those a policy (a head of logits) can be trained on
ACTION_SETS = tuple(space for space in taichi_swarm.ACTION_SPACES if taichi_swarm.num_actions(space))


def swarm_options(
    neighbours=None, landmark_neighbours=None, sense_radius=None, scale=None, assignment=None, landmark_occupancy=None,
    action_space=None, landmark_order=None, auction_rounds=None,
) -> dict:  # fmt: skip
    """The simulator's neighbour-list, scaling, assignment, occupancy, landmark-order, radio-round
    and action-set options that are set, as ``make()`` keywords (none set: the dense layout, the
    paper's geometry, the exact assignment, the paper's 5 actions)."""
    given = dict(
        neighbours=neighbours, landmark_neighbours=landmark_neighbours, sense_radius=sense_radius, scale=scale,
        assignment=assignment, landmark_occupancy=landmark_occupancy, action_space=action_space,
        landmark_order=landmark_order, auction_rounds=auction_rounds,
    )  # fmt: skip
    for key in ("neighbours", "landmark_neighbours"):
        v = given[key]
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ValueError(f"{key} must be an integer >= 1, got {v!r}")
    r = given["sense_radius"]
    if r is not None and not (isinstance(r, int | float) and 0 < r < float("inf")):
        raise ValueError(f"sense_radius must be a positive finite number, got {r!r}")
    if scale is not None and scale != "density":
        raise ValueError(f"scale must be 'density' (or unset: the paper's geometry), got {scale!r}")
    if assignment is not None and assignment not in ASSIGNMENTS:
        raise ValueError(f"assignment must be one of {ASSIGNMENTS}, got {assignment!r}")
    if assignment == "free" and neighbours is None:
        raise ValueError(f"assignment {assignment!r} needs neighbour lists: set neighbours (--neighbours K)")
    if assignment == "exact":  # the default: recorded as unset, so the exact runs' records stay as they were
        given["assignment"] = None
    if landmark_occupancy not in (None, False, True):
        raise ValueError(f"landmark_occupancy must be true or false, got {landmark_occupancy!r}")
    if landmark_occupancy and (neighbours is None or landmark_neighbours is None):
        raise ValueError(
            "landmark_occupancy needs neighbour and landmark lists: set neighbours and landmark_neighbours"
        )
    if not landmark_occupancy:  # off: recorded as unset, like the exact assignment
        given["landmark_occupancy"] = None
    if landmark_order is not None and landmark_order not in LANDMARK_ORDERS:
        raise ValueError(f"landmark_order must be one of {LANDMARK_ORDERS}, got {landmark_order!r}")
    if landmark_order not in (None, "nearest") and not landmark_occupancy:
        raise ValueError(
            f"landmark_order {landmark_order!r} needs landmark occupancy: a policy trained with landmark_occupancy "
            "(--landmark-occupancy)"
        )
    if auction_rounds is not None:
        if isinstance(auction_rounds, bool) or not isinstance(auction_rounds, numbers.Integral) or auction_rounds < 1:
            raise ValueError(f"auction_rounds must be an integer >= 1, got {auction_rounds!r}")
        if landmark_order != "radio":
            raise ValueError(
                f"auction_rounds is the radio auction's message rounds a step: it needs landmark_order 'radio' "
                f"(--landmark-order), got {landmark_order!r}"
            )
    if landmark_order == "nearest":  # the default: recorded as unset
        given["landmark_order"] = None
    if action_space is not None and action_space not in ACTION_SETS:
        raise ValueError(f"action_space must be one of {ACTION_SETS}, got {action_space!r}")
    if action_space == "discrete":  # the paper's: recorded as unset
        given["action_space"] = None
    return {k: v for k, v in given.items() if v is not None}


@torch.no_grad()
def evaluate(
    policy,
    task: str,
    agents: int,
    comm: str = "uc",
    comm_radius: float = 1.0,
    episodes: int = 100,
    seed: int = 777,
    arch: str = "cpu",
    device="cpu",
    recorder=None,
    actions: str = "greedy",
    swarm: dict | None = None,
    progress: bool = False,
) -> dict:
    """Run ``episodes`` episodes in parallel, one per environment, with argmax actions
    (``actions="sampled"``: drawn from the policy's distribution instead, from a generator
    seeded with ``seed``; a diagnostic, the paper's numbers are greedy).

    Each agent's action depends only on its own observation and the messages of the
    agents it hears (the network's masked attention), so this is decentralised
    execution. Returns success_rate, mean_length (T; 50 for failures), dist (DIST,
    coverage), covered (the mean fraction of landmarks covered at the end, where the
    simulator reports it) and per-episode arrays.

    ``swarm``: ``swarm_options(...)``, the simulator's neighbour lists and density
    scaling; None: the setting the policy was trained on (``load_policy`` records it), else
    the dense layout; {}: the dense layout. ``progress``: a progress bar of the steps on stderr
    (the first use of a setting also compiles the simulator's kernels, which can take minutes).
    """
    if actions not in ACTION_MODES:
        raise ValueError(f"actions must be one of {ACTION_MODES}, got {actions!r}")
    if swarm is None:
        swarm = getattr(policy, "trained_swarm", None)
    swarm = swarm_options(**(swarm or {}))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batched forwards: more threads stall on a busy 2-core machine
    try:
        return _evaluate(
            policy, task, agents, comm, comm_radius, episodes, seed, arch, device, recorder, actions, swarm, progress
        )
    finally:
        torch.set_num_threads(threads)


def _evaluate(
    policy, task, agents, comm, comm_radius, episodes, seed, arch, device, recorder, actions, swarm, progress
) -> dict:
    from tqdm import tqdm

    env = taichi_swarm.make(task, episodes, agents, comm=comm, comm_radius=comm_radius, arch=arch, seed=seed, **swarm)
    desc = f"{task} M={agents} {comm}, {episodes} episodes (compiling on first use)"
    # (disable=None: tqdm draws only on a terminal, so a log file gets no bar)
    bar = tqdm(total=env.params["max_steps"], desc=desc, unit="step", leave=False, disable=None if progress else True)
    fused = policy.fused_weights()  # computed once: the weights do not change here
    generator = torch.Generator(device).manual_seed(seed) if actions == "sampled" else None

    def act(logits):  # [B, M, A] -> [B, M]
        if generator is None:
            return logits.argmax(-1)
        probs = torch.softmax(logits.float(), -1).reshape(-1, logits.shape[-1])
        return torch.multinomial(probs, 1, generator=generator).view(logits.shape[:-1])

    radio = []  # the agents' auction by messages: (messages, bytes) per agent-step, env means, per step

    def decide(obs):
        if "radio" in env.info:  # what the step before this decision cost on the air
            radio.append([float(v.mean()) for v in (env.info["radio"]["messages"], env.info["radio"]["bytes"])])
        inputs = policy_inputs(obs, device)
        if recorder is None:
            logits, _ = policy(**inputs, fused=fused)
            attention = None
        else:  # the last round's attention weights are drawn on the communication edges
            logits, _, rounds = policy(**inputs, fused=fused, return_attention=True)
            attention = rounds[-1] if rounds else None
            if attention is not None and "nbr" in inputs:  # [B, M, 1 + K] -> [D, M, M], drawn envs only
                D = getattr(recorder, "drawn", attention.shape[0])
                slots, mask = neighbour_slots(inputs["nbr"][:D], inputs["nbr_mask"][:D])
                attention = lists_to_dense(attention[:D], slots, mask)
        bar.update(1)
        return act(logits).to(env.device), attention

    try:
        tally = run_first_episodes(env, decide, recorder)
    finally:
        bar.close()
    header = result_header(task, agents, comm, comm_radius, episodes, seed)
    on_air = {}
    if radio:
        messages, nbytes = (sum(x) / len(radio) for x in zip(*radio, strict=True))
        on_air = {"messages_per_agent_step": messages, "bytes_per_agent_step": nbytes}
    return {**header, **swarm, "actions": actions, **tally.summary(task), **on_air}


def format_table(rows: list[dict]) -> str:
    """Rows of evaluate() results as an aligned text table (S% and T as in the paper; the
    fraction of landmarks covered, and the radio's messages per agent-step, beside them where
    every row has them)."""
    keys = ("covered", "messages_per_agent_step")
    extra = tuple(k for k in keys if rows and all(r.get(k) is not None for r in rows))
    return format_results(rows, extra)


MAX_SIZES = 1000  # team sizes in one --sizes list


def parse_sizes(spec: list[str]) -> list[int]:
    """["2-8"] or ["3", "5", "7"] -> [2, ..., 8] / [3, 5, 7]; clear error otherwise."""
    sizes: list[int] = []
    for item in spec:
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            try:
                if "-" in part:
                    lo, hi = (int(x) for x in part.split("-", 1))
                    if lo > hi:
                        raise ValueError
                    if hi - lo + 1 + len(sizes) > MAX_SIZES:  # checked before the list is made
                        raise OverflowError
                    sizes.extend(range(lo, hi + 1))
                else:
                    sizes.append(int(part))
            except OverflowError:
                raise ValueError(f"--sizes: {part!r} holds more than {MAX_SIZES} team sizes") from None
            except ValueError:
                raise ValueError(f"--sizes: cannot read {part!r}; use e.g. 2-8 or 3 5 7") from None
    if not sizes or min(sizes) < 1:
        raise ValueError("--sizes must list team sizes >= 1")
    return list(dict.fromkeys(sizes))


__all__ = ["ACTION_MODES", "ACTION_SETS", "SWARM_KEYS", "evaluate", "format_table", "parse_sizes", "swarm_options"]
