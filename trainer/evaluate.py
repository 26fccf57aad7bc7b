"""Greedy, decentralised evaluation: S%, T and DIST on fresh seeds (s.5)."""

from __future__ import annotations

import torch

import taichi_swarm
from taichi_swarm.metrics import FirstEpisodes, format_results


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
) -> dict:
    """Run ``episodes`` episodes in parallel, one per environment, with argmax actions.

    Each agent's action depends only on its own observation and the messages of the
    agents it hears (the network's masked attention), so this is decentralised
    execution. Returns success_rate, mean_length (T; 50 for failures), dist (DIST,
    coverage), and per-episode arrays.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batched forwards: more threads stall on a busy 2-core machine
    try:
        return _evaluate(policy, task, agents, comm, comm_radius, episodes, seed, arch, device, recorder)
    finally:
        torch.set_num_threads(threads)


def _evaluate(policy, task, agents, comm, comm_radius, episodes, seed, arch, device, recorder) -> dict:
    env = taichi_swarm.make(task, episodes, agents, comm=comm, comm_radius=comm_radius, arch=arch, seed=seed)
    obs = env.reset()
    tally = FirstEpisodes(episodes)
    fused = policy.fused_weights()  # computed once: the weights do not change here
    step = 0
    while not tally.all_done():
        inputs = (obs["self"].to(device), obs["entities"].to(device), obs["adj"].to(device))
        if recorder is None:
            logits, _ = policy(*inputs, fused=fused)
        else:  # the last round's attention weights are drawn on the communication edges
            logits, _, attention = policy(*inputs, fused=fused, return_attention=True)
        actions = logits.argmax(-1).to(env.device)
        if recorder is not None:
            recorder.log_step(step, env, actions, attention=attention[-1] if attention else None)
        obs, _, done, info = env.step(actions)
        step += 1
        new = tally.add(done, info["episode"])
        if recorder is not None and new.any():
            recorder.log_episode_ends(step, new, info["episode"])
    return {
        "task": task,
        "agents": agents,
        "comm": comm,
        "comm_radius": comm_radius,
        "episodes": episodes,
        "seed": seed,
        **tally.summary(task),
    }


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


__all__ = ["evaluate", "format_table", "parse_sizes"]
