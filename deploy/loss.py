"""Bursty message loss, the one model every radio here uses: `swarm execute --burst-loss`
(deploy/executor.py's MessageBus) and the networked agents' `--burst-loss` (deploy/net/faults.py).

Gilbert-Elliott: a two-state chain per link, good (delivers) and bad (loses), stepping once per
message. Its stationary loss is ``loss`` and a loss burst lasts ``burst_len`` messages on average:
P(bad -> good) = 1 / burst_len, P(good -> bad) = loss / (burst_len (1 - loss)). A chain starts in
its stationary law (bad with probability ``loss``), so the first message already sees the mean loss.
"""

from __future__ import annotations

import math

import numpy as np

# A mean burst longer than this is a link that never recovers within any episode (at most
# max_steps x 64 rounds of messages on a link); inf would make the return probability 0
MAX_BURST_LEN = 1e6


class GilbertElliott:
    """The chain's two transition probabilities; ``start`` and ``step`` take uniform draws ``u``
    (a float or an array, one per link) and the links' states ``bad`` (True: in a burst)."""

    def __init__(self, loss: float, burst_len: float, error=ValueError):
        check(loss, burst_len, error)
        self.loss = float(loss)
        self.to_good = 1.0 / burst_len
        self.to_bad = self.loss * self.to_good / (1.0 - self.loss)

    def start(self, u):
        return u < self.loss

    def step(self, bad, u):
        return np.where(bad, u >= self.to_good, u < self.to_bad)


def check(loss: float, burst_len: float, error=ValueError) -> None:
    """--burst-loss in [0, 1) and --burst-len in [1, MAX_BURST_LEN] messages (NaN and inf refused)."""
    if not 0.0 <= loss < 1.0:
        raise error(f"--burst-loss must be in [0, 1), got {loss}")
    if not (math.isfinite(burst_len) and 1.0 <= burst_len <= MAX_BURST_LEN):
        raise error(f"--burst-len must be in [1, {MAX_BURST_LEN:g}] messages, got {burst_len}")
