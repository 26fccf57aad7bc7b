"""Decentralised execution of exported policies (``swarm execute``); never imports torch.

Every agent sees only its own observation: own state [4] and landmark offsets [L, 2],
and the messages that reach it. The decentralisation is in that data flow, not in the
number of sessions: the ONNX pieces hold only weights, so one onnxruntime session per
piece (``Pieces``) runs every agent, each call on one agent's own arrays. Per simulator
step (K rounds, manifest "schedule"):

    encode(own obs)               -> h, message            (message = key [H], value [H])
    rounds 1..K-1: send message along the graph, round(h, heard) -> h, next message
    round K:       send message,  round_heads(h, heard)  -> logits [A]; action = argmax

Communication goes through ``MessageBus``, the in-process radio: it delivers a
message from j to i only along an edge of the simulator's communication graph
(``obs["adj"]``: everyone in "uc", within the radius in "rc") of the step the
message was sent in. With neighbour lists (``obs["nbr"]``, ``obs["nbr_mask"]``, the
simulator's ``neighbours=K``) the edges are each agent's K listed neighbours instead:
the same radio, O(K) per agent, with no M x M graph anywhere. With landmark lists
(``obs["entity_mask"]``) an agent encodes only the landmarks it senses ("emp"; the
same function as masking them) or zeroes the others' slots ("padded").

With relative edges (manifest edge_position "relative") each round also takes the offsets
p_j - p_i of the senders heard, which the executor computes from the observation's true
positions (self_obs[..., 2:4], whatever self_position zeroes in the encoder's input), as
the batched policy does (``SwarmPolicy.edge_offsets``), for exactly the messages delivered;
a delayed message gets the offset of the step it is used in (the receiver measures it).

An agent always hears itself: it adds its own current
message to what it heard (local memory, never dropped or delayed), so a round
gets n >= 1 messages even when the bus delivers none; the round graphs also
accept n = 0.

Imperfect communication (both seeded, both per env):
    drop p:  each message on each edge (j -> i, j != i) in each round is lost
             independently with probability p.
    delay k: a message sent in round r of step t arrives in round r of step t + k,
             along the edges of step t (that is when it was sent). In round r an
             agent therefore uses its neighbours' round-r messages from k steps
             ago, plus its own fresh one; in the first k steps of an episode it
             hears only itself. Messages in flight are discarded when an episode
             ends (they belong to the previous episode).

A receiver may hold what it last heard (``hold`` A >= 1, ``swarm execute --hold A``): when the
round-r message of a neighbour in the step's graph is lost, the agent attends over that
neighbour's last round-r message it did hear, if that is at most A steps old, as a robot keeps
its teammates' last broadcasts. It knows who is in range the way it measures their offsets
(relative edges): by sensing them, not from the lost message. A held message is a late one,
which the policies carry far better than a missing one (docs/DEPLOY.md's fault table). Hold
acts on losses only, so it is refused with a delay, where every message is late by design.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from deploy.loss import GilbertElliott
from deploy.loss import check as check_burst
from deploy.policy import DeployError, ExportedModel, Pieces
from taichi_swarm.constants import NUM_FINE_ACTIONS
from taichi_swarm.metrics import format_results, result_header, run_first_episodes

if TYPE_CHECKING:
    from taichi_swarm.sim import Sim


class MessageBus:
    """The radio between agents of B teams: delivers only along edges, with seeded drops and delays."""

    def __init__(
        self, num_envs: int, num_agents: int, rounds: int, drop: float = 0.0, delay: int = 0, seed: int = 0,
        burst_loss: float = 0.0, burst_len: float = 4.0, hold: int = 0,
    ):  # fmt: skip
        if not 0.0 <= drop <= 1.0:
            raise DeployError(f"drop probability must be in [0, 1], got {drop}")
        if delay < 0:
            raise DeployError(f"delay must be >= 0 steps, got {delay}")
        if hold < 0 or (hold and delay):
            raise DeployError(f"hold must be >= 0 steps and acts on lost messages only (no delay), got {hold}")
        self.drop, self.delay, self.hold = float(drop), int(delay), int(hold)
        self._rng = np.random.default_rng(seed)
        # bursty loss (deploy/loss.py): one chain per link (receiver i, sender j), one step per message
        self.burst_loss = float(burst_loss)
        self._burst = GilbertElliott(burst_loss, burst_len, DeployError)
        self._bad: np.ndarray | None = None  # [B, M, M]
        self._offdiag = ~np.eye(num_agents, dtype=bool)  # [M, M]; own messages never go through the bus
        # per round: queue of (messages [B, M, 2, H], edges [B, M, M]) in flight
        self._queues: list[deque] = [deque() for _ in range(rounds)]
        self.sent = 0
        self.delivered = 0
        self.held = 0  # lost messages replaced by the last one heard (hold)
        if self.hold:
            # per round: the last hold + 1 steps' messages by sender, in slot step % (hold + 1),
            # and the step at which i last heard j ([B, M, M]; far in the past: never)
            self._step = [0] * rounds
            self._ring: list[np.ndarray | None] = [None] * rounds
            self._heard_at = np.full((rounds, num_envs, num_agents, num_agents), -(1 << 30), np.int64)

    def exchange(self, r: int, messages: np.ndarray, adj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Send round-r ``messages`` [B, M, 2, H] along ``adj`` [B, M, M] (i hears j); return what
        arrives now: (messages [B, M, 2, H], edges [B, M, M] bool, edges[b, i, j]: i receives j's)."""
        edges = adj & self._offdiag
        arrived, arrived_edges, _ = self._send(r, messages, edges, None)
        return arrived, arrived_edges

    def exchange_lists(self, r: int, messages: np.ndarray, nbr: np.ndarray, nbr_mask: np.ndarray):
        """The same along neighbour lists ``nbr`` [B, M, K] (i hears nbr[b, i, k] where
        ``nbr_mask``): returns (messages [B, M, 2, H], edges [B, M, K] bool, senders [B, M, K]
        int: i receives senders[b, i, k]'s message where edges[b, i, k])."""
        M = nbr.shape[1]
        nbr = np.asarray(nbr, dtype=np.int64)
        edges = np.asarray(nbr_mask, dtype=bool) & (nbr != np.arange(M)[None, :, None]) & (nbr >= 0) & (nbr < M)
        return self._send(r, messages, edges, nbr)

    def gather(self, r: int, arrived: np.ndarray, b: int, i: int, senders: np.ndarray) -> np.ndarray:
        """What agent i of env b heard in round r from ``senders`` [n] (the senders of the edges an
        exchange returned): [n, 2, H], each sender's fresh message or, with hold, its held one."""
        if not self.hold:
            return arrived[b, senders]
        slot = self._heard_at[r, b, i, senders] % (self.hold + 1)
        return self._ring[r][slot, b, senders]

    def _send(self, r, messages, edges, senders):
        self.sent += int(edges.sum())
        graph = edges
        if self.drop > 0.0:
            edges = edges & (self._rng.random(edges.shape) >= self.drop)
        if self.burst_loss > 0.0:
            u = self._rng.random(edges.shape[:2] + edges.shape[1:2])  # [B, M, M]
            self._bad = self._burst.start(u) if self._bad is None else self._burst.step(self._bad, u)
            bad = self._bad if senders is None else np.take_along_axis(self._bad, np.clip(senders, 0, None), axis=2)
            edges = edges & ~bad
        if self.hold:
            return self._hold(r, messages, graph, edges, senders)
        queue = self._queues[r]
        queue.append((messages.copy() if self.delay else messages, edges, senders))
        if len(queue) <= self.delay:
            return messages, np.zeros_like(edges), senders
        arrived, arrived_edges, arrived_senders = queue.popleft()
        self.delivered += int(arrived_edges.sum())
        return arrived, arrived_edges, arrived_senders

    def _hold(self, r, messages, graph, edges, senders):
        """Deliver ``edges`` (what got through) and, for the other edges of ``graph``, the last
        message heard from that sender within ``hold`` steps (no delay here: refused with hold)."""
        t, A = self._step[r], self.hold
        self._step[r] += 1
        if self._ring[r] is None:
            self._ring[r] = np.zeros((A + 1, *messages.shape), np.float32)
        self._ring[r][t % (A + 1)] = messages
        heard_at = self._heard_at[r]  # [B, M, M]
        b, i, k = np.nonzero(edges)
        j = k if senders is None else senders[b, i, k]
        heard_at[b, i, j] = t
        last = heard_at if senders is None else np.take_along_axis(heard_at, np.clip(senders, 0, None), axis=2)
        kept = graph & (t - last <= A)
        self.delivered += int(edges.sum())
        self.held += int(kept.sum()) - int(edges.sum())
        return messages, kept, senders

    def reset_envs(self, mask: np.ndarray) -> None:
        """Discard messages in flight of the envs in ``mask`` [B] (their episode ended), and what
        their agents hold."""
        for queue in self._queues:
            for _, edges, _ in queue:
                edges[mask] = False
        if self.hold:
            self._heard_at[:, mask] = -(1 << 30)


class Executor:
    """B teams of M agents and their message bus; ``decide`` is one decision step.

    The agents share one ``Pieces`` (one session per ONNX piece) and keep their state in
    per-agent rows of arrays: h [B, M, H], messages [B, M, 2, H]. Every call runs one agent's
    piece on its own row: its own observation, the messages the bus delivered to it."""

    def __init__(
        self,
        model: ExportedModel,
        num_envs: int,
        num_agents: int,
        drop: float = 0.0,
        delay: int = 0,
        seed: int = 0,
        threads: int = 1,
        burst: tuple[float, float] = (0.0, 4.0),
        hold: int = 0,
    ):
        if num_agents < 1:
            raise DeployError(f"agents must be >= 1, got {num_agents}")
        if num_envs < 1:
            raise DeployError(f"episodes must be >= 1, got {num_envs}")
        self.model = model
        self.B, self.M, self.K = num_envs, num_agents, model.rounds
        self.pieces = Pieces(model, threads)
        self.bus = MessageBus(num_envs, num_agents, self.K, drop, delay, seed, *burst, hold)

    def decide(
        self,
        self_obs: np.ndarray,
        entities: np.ndarray,
        adj: np.ndarray | None = None,
        *,
        nbr: np.ndarray | None = None,
        nbr_mask: np.ndarray | None = None,
        entity_mask: np.ndarray | None = None,
    ):
        """self_obs [B, M, 4], entities [B, M, L, 2] and the graph: adj [B, M, M] bool, or the
        lists nbr, nbr_mask [B, M, K] (``entity_mask`` [B, M, L]: the sensed landmark slots) ->
        (logits [B, M, A], actions int64 [B, M], attention of the last round: [B, M, M] dense,
        [B, M, 1 + K] on [self; listed] with lists)."""
        if (adj is None) == (nbr is None) or (nbr is not None and nbr_mask is None):
            raise DeployError("decide takes the graph either dense (adj) or as lists (nbr with nbr_mask)")
        B, M, H = self.B, self.M, self.model.hidden
        pieces = self.pieces
        self_obs = np.ascontiguousarray(self_obs, dtype=np.float32)
        entities = np.ascontiguousarray(entities, dtype=np.float32)
        lists = nbr is not None
        if lists:
            nbr, nbr_mask = np.asarray(nbr), np.asarray(nbr_mask, dtype=bool)
        else:
            adj = np.asarray(adj, dtype=bool)
        sensed = None if entity_mask is None else np.asarray(entity_mask, dtype=bool)
        if sensed is not None and self.model.entity_mode == "padded":  # an unsensed slot is a zero slot
            entities, sensed = entities * sensed[..., None], None
        h = np.empty((B, M, H), np.float32)
        messages = np.empty((B, M, 2, H), np.float32)
        for b in range(B):
            for i in range(M):
                own = entities[b, i] if sensed is None else np.ascontiguousarray(entities[b, i][sensed[b, i]])
                h[b, i], messages[b, i] = pieces.encode(self_obs[b, i], own)
        pos = self_obs[..., 2:4] if self.model.edge_position == "relative" else None  # true positions [B, M, 2]
        logits = np.empty((B, M, self.model.manifest["num_actions"]), np.float32)
        K = nbr.shape[-1] if lists else 0
        # lists: slot 0 is the agent itself, slot 1 + k its k-th listed neighbour
        attention = np.zeros((B, M, 1 + K) if lists else (B, M, M), np.float32)
        if self.K == 0:
            for b in range(B):
                for i in range(M):
                    logits[b, i], _ = pieces.decide(h[b, i], None)
                    attention[b, i, 0 if lists else i] = 1.0
        for r in range(self.K):
            if lists:
                arrived, edges, listed = self.bus.exchange_lists(r, messages, nbr, nbr_mask)
            else:
                arrived, edges = self.bus.exchange(r, messages, adj)
            last = r == self.K - 1
            nxt = messages if last else np.empty_like(messages)
            for b in range(B):
                for i in range(M):
                    slots = np.flatnonzero(edges[b, i])
                    senders = listed[b, i, slots] if lists else slots
                    heard = self.bus.gather(r, arrived, b, i, senders)  # [n, 2, H]: only what reached agent i
                    # p_j - p_i of exactly the senders heard; for a delayed message, at this step (receive
                    # time): E_k r_ij is what the receiver measures of j when it attends over j's message
                    # (ModelConfig.edge_position), as a range sensor would, not where j was when it sent
                    offsets = None if pos is None else pos[b, senders] - pos[b, i]
                    if last:
                        logits[b, i], w = pieces.decide(h[b, i], heard, offsets)
                        if lists:
                            attention[b, i, 0] = w[0]
                            attention[b, i, 1 + slots] = w[1:]
                        else:
                            attention[b, i, i] = w[0]
                            attention[b, i, senders] = w[1:]
                    else:
                        h[b, i], nxt[b, i] = pieces.round(h[b, i], heard, offsets)
            messages = nxt
        return logits, logits.argmax(-1).astype(np.int64), attention


@dataclass
class ExecuteSettings:
    sim: Sim
    """the setting the team runs in: the policy's own (its manifest), with the command's options over it"""
    episodes: int = 10
    drop: float = 0.0
    delay: int = 0
    seed: int = 777
    burst_loss: float = 0.0
    """Gilbert-Elliott loss on every link: the mean loss (MessageBus)"""
    burst_len: float = 4.0
    """its mean burst length, in messages"""
    hold: int = 0
    """a lost message is replaced by the sender's last one heard, up to this many steps old (MessageBus)"""

    def __post_init__(self):
        """Every setting checked here, once (``swarm execute`` and ``run_episodes`` alike)."""
        self.sim.team_size("the manifest")
        for name, low in (("episodes", 1), ("delay", 0), ("hold", 0)):
            if getattr(self, name) < low:
                raise DeployError(f"--{name} must be >= {low}, got {getattr(self, name)}")
        if not 0.0 <= self.drop <= 1.0:
            raise DeployError(f"--drop values must be probabilities in [0, 1], got {self.drop}")
        check_burst(self.burst_loss, self.burst_len, DeployError)
        if self.hold and self.delay:
            raise DeployError("--hold replaces lost messages; with --delay every message is late already: not both")
        steps = episode_length(self.task)
        if self.delay >= steps:  # a message would arrive after its episode ended: none would be heard
            raise DeployError(f"--delay must be < the episode length ({steps} steps), got {self.delay}")
        if self.hold > steps:  # (the bus keeps hold + 1 steps of messages per agent pair)
            raise DeployError(f"--hold must be at most the episode length ({steps} steps), got {self.hold}")

    # the setting's parts every reader of a result names
    task = property(lambda self: self.sim.task)
    agents = property(lambda self: self.sim.agents)
    comm = property(lambda self: self.sim.comm)
    comm_radius = property(lambda self: self.sim.comm_radius)


def episode_length(task: str) -> int:
    """The steps of an episode of ``task`` as execute runs it (the task's max_steps)."""
    from taichi_swarm import TASK_SPECS
    from taichi_swarm.tasks import COMMON_PARAMS

    return int({**COMMON_PARAMS, **TASK_SPECS[task].params}["max_steps"])


def resolve_settings(
    model: ExportedModel,
    task: str | None = None,
    agents: int | None = None,
    comm: str | None = None,
    comm_radius: float | None = None,
    swarm: dict | None = None,
    **rest,
) -> ExecuteSettings:
    """The manifest's training setting (``taichi_swarm.Sim``) with the command's options over it
    (``Sim.override``: ``swarm``, the list options), and the rest of ``ExecuteSettings``."""
    from taichi_swarm import TASK_SPECS
    from taichi_swarm.sim import Sim

    own = (model.manifest.get("contract") or {}).get("swarm", {})
    overrides = dict(task=task, agents=agents, comm=comm, comm_radius=comm_radius, **(swarm or {}))
    sim = Sim.resolve(model.task, own, "the manifest", **overrides)
    if model.manifest["num_actions"] == NUM_FINE_ACTIONS and sim.action_space != "fine":
        sim = sim.override(action_space="fine")  # a manifest's 9 actions are the fine set
    team_size = sim.team_size("the manifest")
    if sim.landmark_neighbours and model.entity_mode == "concat":
        raise DeployError("this model concatenates every landmark (entity_mode 'concat'): no --landmark-neighbours")
    L = sim.landmark_neighbours or TASK_SPECS[sim.task].num_landmarks(team_size)
    model.check_landmarks(sim.task, L)  # before any output opens
    return ExecuteSettings(sim=sim, **rest)


def run_episodes(model: ExportedModel, s: ExecuteSettings, recorder=None, threads: int = 1) -> dict:
    """One episode per environment, greedy actions, decided agent by agent; S%, T, DIST as ``swarm eval``
    (T is the episode length: the time limit, 50, for a failed episode)."""
    env = make_env(model, s)
    executor = Executor(
        model, s.episodes, s.agents, s.drop, s.delay, s.seed, threads, (s.burst_loss, s.burst_len), s.hold
    )
    drawn = getattr(recorder, "drawn", s.episodes)

    def decide(obs):
        graph = {k: obs[k] for k in ("adj", "nbr", "nbr_mask", "entity_mask") if k in obs}
        _, actions, attention = executor.decide(obs["self"], obs["entities"], **graph)
        if "nbr" in obs and recorder is not None:  # [B, M, 1 + K] -> [D, M, M] for the drawn envs
            attention = lists_to_dense(attention[:drawn], obs["nbr"][:drawn], obs["nbr_mask"][:drawn])
        elif "nbr" in obs:
            attention = None
        return actions, attention

    tally = run_first_episodes(env, decide, recorder, on_done=executor.bus.reset_envs)
    return {
        **result_header(s.task, s.agents, s.comm, s.comm_radius, s.episodes, s.seed),
        **s.sim.swarm_record(),
        "drop": s.drop,
        "delay": s.delay,
        **({"burst_loss": s.burst_loss, "burst_len": s.burst_len} if s.burst_loss else {}),
        **({"hold": s.hold, "messages_held": executor.bus.held} if s.hold else {}),
        "messages_sent": executor.bus.sent,
        "messages_delivered": executor.bus.delivered,
        **tally.summary(s.task),
    }


def make_env(model: ExportedModel, s: ExecuteSettings):
    """The B worlds a team acts in (``swarm execute``, ``swarm world``), on the policy's whole setting:
    its lists, sensing, landmark order and action space (``resolve_settings``)."""
    import taichi_swarm

    L = s.sim.landmark_neighbours or taichi_swarm.TASK_SPECS[s.task].num_landmarks(s.agents)
    model.check_landmarks(s.task, L)
    return taichi_swarm.make(s.sim, s.episodes, arch="cpu", seed=s.seed, array="numpy")


def lists_to_dense(attention: np.ndarray, nbr: np.ndarray, nbr_mask: np.ndarray) -> np.ndarray:
    """Attention on [self; listed] [D, M, 1 + K] -> the dense [D, M, M] (what recordings draw)."""
    D, M, _ = attention.shape
    dense = np.zeros((D, M, M), np.float32)
    rows = np.arange(M)
    dense[:, rows, rows] = attention[:, :, 0]
    nbr = np.asarray(nbr, dtype=np.int64)
    ok = np.asarray(nbr_mask, dtype=bool) & (nbr != rows[None, :, None]) & (nbr >= 0) & (nbr < M)
    d, i, k = np.nonzero(ok)
    np.add.at(dense, (d, i, nbr[d, i, k]), attention[d, i, 1 + k])
    return dense


def format_table(rows: list[dict]) -> str:
    """Rows of run_episodes() results: S% (and T, DIST) against drop rate and delay (and the
    fraction of landmarks covered, where every row has it)."""
    covered = ("covered",) if rows and all(r.get("covered") is not None for r in rows) else ()
    burst = ("burst_loss",) if any(r.get("burst_loss") for r in rows) else ()
    hold = ("hold",) if any(r.get("hold") for r in rows) else ()
    return format_results(rows, extra=("drop", "delay", *burst, *hold, *covered))
