"""The bounds every networked option is checked against, before anything is allocated or a
session opened (``swarm agent`` and ``swarm world`` at parse, ``NetAgent`` and ``World`` again
for callers of the API). Imports nothing heavy, so the command line can use it."""

from __future__ import annotations

import math

MAX_SECONDS = 3600.0  # any deadline, period or delay: one hour (longer ones overflow the waits or never fire)
MAX_AGENT_ID = 0xFFFF  # the header's sender field is a u16
MAX_AGENTS = 0xFFFF  # the OBS and ACT packets' team size is a u16
MAX_EPISODES = 10_000  # as `swarm execute`: one environment per episode, in one batch
MAX_CELLS = 1 << 28  # B x M x M: the graph and the attention the world holds each step (1 GiB as float32)


class LimitError(ValueError):
    """An option out of its bounds (the message names the option)."""


def check_seconds(value: float, option: str, zero_ok: bool = False, scale: float = 1.0, unit: str = "s") -> None:
    """``value`` > 0 (>= 0 with ``zero_ok``), finite and at most an hour (in ``unit``: ``scale`` per second)."""
    low_ok = value >= 0 if zero_ok else value > 0
    if not (low_ok and value <= MAX_SECONDS * scale):  # (False for nan)
        raise LimitError(
            f"{option} must be {'>= 0' if zero_ok else '> 0'} and <= {MAX_SECONDS * scale:g} {unit} (an hour), "
            f"got {value}"
        )


def check_agent_id(agent_id: int, option: str = "--id") -> None:
    if not 0 <= agent_id <= MAX_AGENT_ID:
        raise LimitError(f"{option} must be in 0..{MAX_AGENT_ID} (the wire's agent id is a u16), got {agent_id}")


def check_team(agents: int | None, episodes: int) -> None:
    """The sizes the world allocates by (``agents`` None: not known yet, the manifest's)."""
    if not 1 <= episodes <= MAX_EPISODES:
        raise LimitError(f"--episodes must be in 1..{MAX_EPISODES} (they run as one batch), got {episodes}")
    if agents is None:
        return
    if not 1 <= agents <= MAX_AGENTS:
        raise LimitError(f"--agents must be in 1..{MAX_AGENTS} (the wire's team size is a u16), got {agents}")
    if episodes * agents * agents > MAX_CELLS:
        raise LimitError(
            f"--agents {agents} with --episodes {episodes}: the world holds a [B, M, M] graph and attention "
            f"each step, and B x M x M must be <= 2^{int(math.log2(MAX_CELLS))}, got {episodes * agents * agents}"
        )
