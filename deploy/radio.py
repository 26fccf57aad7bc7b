"""The radio auction as one agent runs it: taichi_swarm/radio.py in numpy, for the agent
processes (``swarm agent``) of a ``landmark_order="radio"`` policy.

The simulator runs every agent's table in one kernel; an agent process runs only its own,
from what it senses (``Sensing``: the landmarks within its sense radius, nearest first, their
offsets and occupancy readings) and the tables its teammates send it. The rules, the order of
the float32 operations and the tie-breaks are radio.py's line for line, so with every table
delivered the agents hold what the simulator's agents hold, and observe what they observe
(tests/test_deploy/test_radio_agents.py holds both to the kernel). A lost table is news that
comes a round later: the merge is a max, so nothing else changes.

Per world b of the B an agent process steps side by side (its agent is the same id in each):
    rebuild(b, fresh, sensing)     the table over this step's KL nearest landmarks
    R rounds: bid(b); send table(b); merge(b, the tables heard); settle
    landmarks(b, sensing)          the observation's landmark rows [n, 3]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AgentAuction", "Sensing", "Table", "sense"]

f32 = np.float32


@dataclass
class Sensing:
    """What agent i senses of the landmarks in one world: those within its sense radius, nearest
    first, at most 2 KL (the observation lists KL of them, the table holds the KL nearest)."""

    ids: np.ndarray  # int [n]
    offsets: np.ndarray  # float32 [n, 2]: landmark - own position
    occupancy: np.ndarray  # float32 [n]: the landmark's nearest other agent's distance, capped at the sense radius


@dataclass
class Table:
    """One agent's auction table in one world, sorted by landmark id (what a round's message carries)."""

    lid: np.ndarray  # int32 [n]
    epoch: np.ndarray  # int32 [n]
    price: np.ndarray  # float32 [n]
    holder: np.ndarray  # int32 [n]; -1: nobody

    @staticmethod
    def empty() -> Table:
        return Table(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, f32), np.zeros(0, np.int32))


def sense(pos: np.ndarray, landmarks: np.ndarray, sense_radius: float, slots: int) -> list[Sensing]:
    """The world's sensors for the M agents of one world: pos [M, 2], landmarks [L, 2] float32 ->
    each agent's ``Sensing`` of at most ``slots`` landmarks (the simulator's cell-grid searches,
    by brute force: squared distances <= the sense radius squared, nearest first, the lower id first
    on a tie; the occupancy from each landmark's two nearest agents within the radius)."""
    pos, landmarks = np.asarray(pos, f32), np.asarray(landmarks, f32)
    radius = f32(sense_radius)
    r2 = radius * radius
    d = landmarks[None, :, :] - pos[:, None, :]  # [M, L, 2]
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
    inside = d2 <= r2
    # each landmark's nearest and second nearest agent within the radius
    M = pos.shape[0]
    by_agent = np.where(inside, d2, np.inf).T  # [L, M]
    order = np.argsort(by_agent, axis=1, kind="stable")[:, :2]
    near = np.take_along_axis(by_agent, order, axis=1)  # [L, 2]
    out = []
    for i in range(M):
        ids = np.flatnonzero(inside[i])
        ids = ids[np.argsort(d2[i, ids], kind="stable")][:slots]
        first_is_me = order[ids, 0] == i
        other = np.where(first_is_me, near[ids, 1] if M > 1 else np.inf, near[ids, 0])
        out.append(Sensing(ids, d[i, ids], np.minimum(np.sqrt(other), radius).astype(f32)))  # (none: inf -> radius)
    return out


class AgentAuction:
    """Agent ``me``'s side of the radio auction in each of B worlds (radio.py's per-agent blocks:
    its table, its cost to each entry, the landmark it holds). ``rules``: the export manifest's
    ``contract["radio"]`` (deploy/export.py writes radio.py's constants there)."""

    def __init__(self, me: int, worlds: int, rules: dict):
        self.me, self.kl = int(me), int(rules["table"])
        radius = f32(rules["sense_radius"])
        self.out = f32(rules["stay_out"]) * radius  # staying out: stay_out sense radii
        self.eps = f32(rules["increment"])
        self.slack = f32(rules["hold_slack"]) * self.eps
        self.s2 = radius * radius
        self.floor = f32(rules["success_threshold"])
        self.tables = [Table.empty() for _ in range(worlds)]
        self.cost = [np.zeros(0, f32) for _ in range(worlds)]
        self.won = np.full(worlds, -1, np.int64)

    # ------------------------------------------------------------------ radio.py's steps
    def rebuild(self, b: int, fresh: bool, sensing: Sensing) -> None:
        """Step 1: the table over this step's candidates (the KL nearest sensed), entries kept for
        landmarks still sensed; then the landmark let go if no longer sensed or worse than another
        option by more than HOLD_SLACK increments. ``fresh``: the episode's first step."""
        old = Table.empty() if fresh else self.tables[b]
        won = -1 if fresh else int(self.won[b])
        cand = np.asarray(sensing.ids[: self.kl], np.int32)
        order = np.argsort(cand, kind="stable")
        lid = cand[order]
        off = sensing.offsets[: self.kl][order]
        n = lid.size
        t = Table(lid, np.zeros(n, np.int32), np.zeros(n, f32), np.full(n, -1, np.int32))
        if old.lid.size:
            at = np.minimum(np.searchsorted(old.lid, lid), old.lid.size - 1)
            kept = old.lid[at] == lid
            at = at[kept]
            t.epoch[kept], t.price[kept], t.holder[kept] = old.epoch[at], old.price[at], old.holder[at]
        self.tables[b] = t
        self.cost[b] = np.sqrt(off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1]).astype(f32)
        if won >= 0:
            s = self._find(t, won)
            if s < 0:
                won = -1
            elif self.cost[b][s] + t.price[s] > self._best(b)[0] + self.slack:
                self._release(t, s)
                won = -1
        self.won[b] = won
        self._settle(b)

    def bid(self, b: int) -> None:
        """2a: holding nothing, bid for the cheapest entry unless staying out is cheaper."""
        if self.won[b] >= 0:
            return
        w0, w1, s = self._best(b)
        if s >= 0:
            t = self.tables[b]
            t.price[s] = (t.price[s] + (w1 - w0)) + self.eps
            t.holder[s] = self.me
            self.won[b] = int(t.lid[s])

    def merge(self, b: int, heard: list[Table]) -> None:
        """2b and 2c: the greatest entry of its own and the heard tables for each landmark in its own
        table (the later epoch, then the higher price, then the lower holder); then settle."""
        t = self.tables[b]
        if t.lid.size:
            for j in heard:
                if not j.lid.size:
                    continue
                at = np.minimum(np.searchsorted(j.lid, t.lid), j.lid.size - 1)
                e, p, h = j.epoch[at], j.price[at], j.holder[at]
                take = (j.lid[at] == t.lid) & (
                    (e > t.epoch) | ((e == t.epoch) & ((p > t.price) | ((p == t.price) & (h < t.holder))))
                )
                t.epoch[take], t.price[take], t.holder[take] = e[take], p[take], h[take]
        self._settle(b)

    def table(self, b: int) -> Table:
        return self.tables[b]

    def landmarks(self, b: int, sensing: Sensing) -> np.ndarray:
        """The observation's landmark rows [n, 3] (offset, reading): a holder its landmark alone,
        read free; else the KL sensed ranked by distance, those its table says another holds
        last, reading 0 (kernels.agent_landmarks)."""
        won = int(self.won[b])
        if won >= 0:
            k = int(np.flatnonzero(sensing.ids == won)[0])
            return np.array([[*sensing.offsets[k], max(sensing.occupancy[k], self.floor)]], f32)
        off = sensing.offsets
        d2 = off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1]
        held = self._held_by_other(b, sensing.ids)
        rank = d2 + np.where(held, self.s2 + f32(1.0), f32(0.0)).astype(f32)
        pick = np.argsort(rank, kind="stable")[: self.kl]
        reading = np.where(held[pick], f32(0.0), np.maximum(sensing.occupancy[pick], self.floor)).astype(f32)
        return np.concatenate([off[pick], reading[:, None]], axis=1).astype(f32)

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _find(t: Table, l: int) -> int:
        s = int(np.searchsorted(t.lid, l))
        return s if s < t.lid.size and t.lid[s] == l else -1

    def _best(self, b: int) -> tuple[np.float32, np.float32, int]:
        """(w1, w2, slot): the cheapest and second cheapest of distance + price and staying out."""
        t, out = self.tables[b], self.out
        if not t.lid.size:
            return out, out, -1
        d = (self.cost[b] + t.price).astype(f32)
        s = int(np.argmin(d))
        if not d[s] < out:
            return out, out, -1
        rest = np.delete(d, s)
        w1 = min(out, rest.min()) if rest.size else out
        return d[s], f32(w1), s

    @staticmethod
    def _release(t: Table, s: int) -> None:
        t.epoch[s] += 1
        t.price[s] = 0.0
        t.holder[s] = -1

    def _settle(self, b: int) -> None:
        """2c: outbid on its landmark it holds nothing; its own claim on a landmark it does not hold
        (heard back from a teammate) it releases."""
        t, won = self.tables[b], int(self.won[b])
        if won >= 0:
            s = self._find(t, won)
            if s < 0 or t.holder[s] != self.me:
                won = self.won[b] = -1
        for s in np.flatnonzero((t.holder == self.me) & (t.lid != won)):
            self._release(t, int(s))

    def _held_by_other(self, b: int, ids: np.ndarray) -> np.ndarray:
        """For each landmark in ``ids``: whether its own table says another agent holds it."""
        t = self.tables[b]
        if not t.lid.size:
            return np.zeros(ids.size, bool)
        at = np.minimum(np.searchsorted(t.lid, ids), t.lid.size - 1)
        who = t.holder[at]
        return (t.lid[at] == ids) & (who >= 0) & (who != self.me)
