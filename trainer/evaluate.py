"""Greedy, decentralised evaluation: S%, T and DIST on fresh seeds (s.5)."""

from __future__ import annotations

import torch

import taichi_swarm
from taichi_swarm.metrics import format_results, result_header, run_first_episodes
from taichi_swarm.sim import ConfigError, Sim
from trainer.model import lists_to_dense, neighbour_slots, policy_inputs

ACTION_MODES = ("greedy", "sampled")
# the simulator's discrete action spaces, those a policy (a head of logits) can be trained on
ACTION_SETS = tuple(space for space in taichi_swarm.ACTION_SPACES if taichi_swarm.num_actions(space))


def check_policy_actions(sim: Sim) -> None:
    """A policy (a head of logits) runs only a discrete action space (ACTION_SETS)."""
    if sim.action_space not in ACTION_SETS:
        raise ConfigError(
            "action_space", f"action_space must be one of {ACTION_SETS} for a policy, got {sim.action_space!r}"
        )


@torch.no_grad()
def evaluate(
    policy,
    sim: Sim | None = None,
    episodes: int = 100,
    seed: int = 777,
    arch: str = "cpu",
    device="cpu",
    recorder=None,
    actions: str = "greedy",
    progress: bool = False,
) -> dict:
    """Run ``episodes`` episodes of ``sim`` in parallel, one per environment, with argmax actions
    (``actions="sampled"``: drawn from the policy's distribution instead, from a generator
    seeded with ``seed``; a diagnostic, the paper's numbers are greedy).

    Each agent's action depends only on its own observation and the messages of the
    agents it hears (the network's masked attention), so this is decentralised
    execution. Returns success_rate, mean_length (T; 50 for failures), dist (DIST,
    coverage), covered (the mean fraction of landmarks covered at the end, where the
    simulator reports it) and per-episode arrays.

    ``sim``: the setting (None: the one the policy was trained on, ``policy.sim``, which
    ``load_policy`` records; ``policy.sim.override(agents=1000)`` runs it at another size).
    ``progress``: a progress bar of the steps on stderr (the first use of a setting also
    compiles the simulator's kernels, which can take minutes).
    """
    if actions not in ACTION_MODES:
        raise ValueError(f"actions must be one of {ACTION_MODES}, got {actions!r}")
    sim = sim if sim is not None else getattr(policy, "sim", None)
    if not isinstance(sim, Sim):
        raise ConfigError("sim", f"evaluate() needs a taichi_swarm.Sim (load_policy records the policy's), got {sim!r}")
    check_policy_actions(sim)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batched forwards: more threads stall on a busy 2-core machine
    try:
        return _evaluate(policy, sim, episodes, seed, arch, device, recorder, actions, progress)
    finally:
        torch.set_num_threads(threads)


def _evaluate(policy, sim, episodes, seed, arch, device, recorder, actions, progress) -> dict:
    from tqdm import tqdm

    env = taichi_swarm.make(sim, episodes, arch=arch, seed=seed)
    task, agents = sim.task, sim.agents
    desc = f"{task} M={agents} {sim.comm}, {episodes} episodes (compiling on first use)"
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
    header = result_header(task, agents, sim.comm, sim.comm_radius, episodes, seed)
    on_air = {}
    if radio:
        messages, nbytes = (sum(x) / len(radio) for x in zip(*radio, strict=True))
        on_air = {"messages_per_agent_step": messages, "bytes_per_agent_step": nbytes}
    return {**header, **sim.swarm_record(), "actions": actions, **tally.summary(task), **on_air}


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


__all__ = ["ACTION_MODES", "ACTION_SETS", "evaluate", "format_table", "parse_sizes"]
