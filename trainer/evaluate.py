"""Greedy, decentralised evaluation: S%, T and DIST on fresh seeds (s.5)."""

from __future__ import annotations

import torch

import taichi_swarm
from taichi_swarm.metrics import format_results, result_header, run_first_episodes

ACTION_MODES = ("greedy", "sampled")


@torch.no_grad()
def evaluate(
    policy,
    task: str,
    agents: int,
    comm: str = "uc",
    comm_radius: float = 1.0,
    episodes: int = 100,
    seed: int = 12345,
    arch: str = "cpu",
    device="cpu",
    recorder=None,
    actions: str = "greedy",
) -> dict:
    """Run ``episodes`` episodes in parallel, one per environment, with argmax actions
    (``actions="sampled"``: drawn from the policy's distribution instead, from a generator
    seeded with ``seed``; a diagnostic, the paper's numbers are greedy).

    Each agent's action depends only on its own observation and the messages of the
    agents it hears (the network's masked attention), so this is decentralised
    execution. Returns success_rate, mean_length (T; 50 for failures), dist (DIST,
    coverage), and per-episode arrays.
    """
    if actions not in ACTION_MODES:
        raise ValueError(f"actions must be one of {ACTION_MODES}, got {actions!r}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batched forwards: more threads stall on a busy 2-core machine
    try:
        return _evaluate(policy, task, agents, comm, comm_radius, episodes, seed, arch, device, recorder, actions)
    finally:
        torch.set_num_threads(threads)


def _evaluate(policy, task, agents, comm, comm_radius, episodes, seed, arch, device, recorder, actions) -> dict:
    env = taichi_swarm.make(task, episodes, agents, comm=comm, comm_radius=comm_radius, arch=arch, seed=seed)
    fused = policy.fused_weights()  # computed once: the weights do not change here
    generator = torch.Generator(device).manual_seed(seed) if actions == "sampled" else None

    def act(logits):  # [B, M, A] -> [B, M]
        if generator is None:
            return logits.argmax(-1)
        probs = torch.softmax(logits.float(), -1).reshape(-1, logits.shape[-1])
        return torch.multinomial(probs, 1, generator=generator).view(logits.shape[:-1])

    def decide(obs):
        inputs = (obs["self"].to(device), obs["entities"].to(device), obs["adj"].to(device))
        if recorder is None:
            logits, _ = policy(*inputs, fused=fused)
            attention = None
        else:  # the last round's attention weights are drawn on the communication edges
            logits, _, rounds = policy(*inputs, fused=fused, return_attention=True)
            attention = rounds[-1] if rounds else None
        return act(logits).to(env.device), attention

    tally = run_first_episodes(env, decide, recorder)
    header = result_header(task, agents, comm, comm_radius, episodes, seed)
    return {**header, "actions": actions, **tally.summary(task)}


def format_table(rows: list[dict]) -> str:
    """Rows of evaluate() results as an aligned text table (S% and T as in the paper)."""
    return format_results(rows)


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
                    sizes.extend(range(lo, hi + 1))
                else:
                    sizes.append(int(part))
            except ValueError:
                raise ValueError(f"--sizes: cannot read {part!r}; use e.g. 2-8 or 3 5 7") from None
    if not sizes or min(sizes) < 1:
        raise ValueError("--sizes must list team sizes >= 1")
    return list(dict.fromkeys(sizes))


__all__ = ["ACTION_MODES", "evaluate", "format_table", "parse_sizes"]
