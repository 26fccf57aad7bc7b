"""Faults injected between processes, at the receiving agent's radio (before the policy sees
anything): every message of one world's link j -> i (j != i) goes through ``LinkFaults``.

    drop p                independent loss of each message with probability p
    burst_loss q, burst_len n
                          Gilbert-Elliott loss (deploy/loss.py): a two-state chain per link,
                          stationary loss q, mean length of a loss burst n messages
    latency_ms, jitter_ms each message arrives latency + U(-jitter, +jitter) ms late (at least 0)
    reorder p             a message is held back with probability p and delivered after the next
                          message on its link (or after reorder_hold_ms if none comes)
    late_round r          every message of round r arrives after that round's deadline
                          (counted late by the receiver, so the round goes on without it)

All draws are seeded (``seed``, the receiving agent's id, the world index and the sender), so
the same run loses the same messages. The agent-side faults (a slow agent, one that is killed,
restarted or never starts) are options of ``swarm agent`` and of the launcher.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Annotated

import numpy as np
import tyro

from deploy.loss import GilbertElliott
from deploy.loss import check as check_burst
from deploy.net.limits import MAX_SECONDS


class FaultError(ValueError):
    """A fault parameter out of range."""


@dataclass(frozen=True)
class FaultSpec:
    """The faults of every link into one agent; the docstrings are the options' --help texts
    (``swarm agent``, ``swarm world``)."""

    drop: float = 0.0
    """independent loss of each message, probability"""
    burst_loss: float = 0.0
    """Gilbert-Elliott bursty loss: the mean loss probability"""
    burst_len: float = 4.0
    """Gilbert-Elliott bursty loss: the mean length of a loss burst, in messages"""
    latency_ms: float = 0.0
    """latency added to every message, ms"""
    jitter_ms: float = 0.0
    """uniform jitter around the latency, +- ms"""
    reorder: float = 0.0
    """probability that a message is held back behind the next one on its link"""
    reorder_hold_ms: float = 20.0
    """how long a held-back message waits at most for the next one, ms"""
    late_round: int | None = None
    """every message of this round (0-based) arrives after the round's deadline"""
    seed: Annotated[int, tyro.conf.arg(name="fault-seed")] = 0  # (--seed is the world's episodes')
    """seed of the injected faults"""

    def __post_init__(self):
        for name in ("drop", "reorder"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise FaultError(
                    f"--{name.replace('_', '-')} must be a probability in [0, 1], got {getattr(self, name)}"
                )
        check_burst(self.burst_loss, self.burst_len, FaultError)
        for name in ("latency_ms", "jitter_ms", "reorder_hold_ms"):  # (an hour at most, as every wait: limits.py)
            if not 0.0 <= getattr(self, name) <= MAX_SECONDS * 1e3:
                option, value = f"--{name.replace('_', '-')}", getattr(self, name)
                raise FaultError(f"{option} must be >= 0 and <= {MAX_SECONDS * 1e3:g} ms, got {value}")
        if self.late_round is not None and self.late_round < 0:  # (its upper bound, K - 1: agent.check_faults)
            raise FaultError(f"--late-round must be >= 0, got {self.late_round}")
        if self.seed < 0:
            raise FaultError(f"--fault-seed must be >= 0, got {self.seed}")

    @property
    def any(self) -> bool:
        return self != FaultSpec(seed=self.seed)

    def to_args(self) -> list[str]:
        """The ``swarm agent`` options that give this spec."""
        out = []
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None and v != f.default:
                name = "fault-seed" if f.name == "seed" else f.name.replace("_", "-")
                out += [f"--{name}", str(v)]
        return out

    def to_dict(self) -> dict:
        return asdict(self)


class LinkFaults:
    """The fault state of every link into one agent: ``fate(world, sender, round)`` -> None (lost)
    or (delay in seconds, held back behind the next message)."""

    def __init__(self, spec: FaultSpec, receiver: int, round_deadline: float):
        self.spec = spec
        self.round_deadline = round_deadline
        self._rng = np.random.default_rng([spec.seed, receiver, 0x5EED])
        self._bad: dict[tuple[int, int], bool] = {}  # Gilbert-Elliott state per (world, sender)
        self._burst = GilbertElliott(spec.burst_loss, spec.burst_len, FaultError)
        self.injected_losses = 0

    def fate(self, world: int, sender: int, round_: int):
        s, rng = self.spec, self._rng
        lost = s.drop > 0 and rng.random() < s.drop
        if s.burst_loss > 0:
            link = (world, sender)
            bad = self._bad.get(link)
            u = rng.random()
            bad = bool(self._burst.start(u) if bad is None else self._burst.step(bad, u))
            self._bad[link] = bad
            lost = lost or bad
        if lost:
            self.injected_losses += 1
            return None
        delay = s.latency_ms / 1e3
        if s.jitter_ms > 0:
            delay += rng.uniform(-s.jitter_ms, s.jitter_ms) / 1e3
        if s.late_round is not None and round_ == s.late_round:
            delay = self.round_deadline * 1.5 + 0.005
        held = s.reorder > 0 and rng.random() < s.reorder
        return max(delay, 0.0), held
