"""One agent as a process (``swarm agent``): the ONNX pieces in its own sessions, its own
observation, its messages over Zenoh.

Per control step t (the world's OBS packet for this agent starts it), for each of the B
worlds the packet covers (B = 1 on a robot):

    a radio policy first: its table rebuilt from its sensing (the OBS packet's), then R auction
        rounds: bid, publish TABLE(t, r), merge the tables of the agents it hears by the round
        deadline (deploy/radio.py); its landmark rows from its table
    encode(own obs) -> h, message; publish MSG(t, round 0)
    round r = 0..K-1: wait until every agent it hears this step (the OBS packet's heard list,
        nothing more) has sent its MSG(t, r), or until the round deadline; then
        round(h, heard, their offsets) -> h, message and publish MSG(t, r + 1)   (the last
        round: round_heads -> logits, action = argmax)
    publish ACT(t): actions [B], attention [B, M], this agent's counters

With ``hold`` A >= 1 (``swarm agent --hold A``), a neighbour the OBS packet says it hears but
whose round-r message did not come by the deadline is attended over with the last round-r
message this agent did get from it, if at most A steps old: the in-process executor's
``MessageBus`` hold (deploy/executor.py), so a lost message counts as a late one.

What arrives after its round closed, of an older step, or of another run is dropped and
counted (late, foreign); a packet that does not decode is dropped and counted (malformed,
version), with one line on stderr the first time, and never stops the agent. A newer OBS
that arrives mid-step (this agent fell behind) abandons the step: the world has moved on.
The heard messages are stacked in the OBS packet's heard order (the executor's: ascending ids
on the dense graph, list order on neighbour lists), so at zero faults the actions are the
executor's bit for bit. What is kept for later is bounded, the rest
dropped and counted (overflow): messages of at most STEPS_AHEAD steps ahead, EARLY_KEPT
messages (EARLY_BYTES) before the run's observation, PENDING_KEPT delayed by injected faults.

Identity: the process draws a random nonce at start and sends it in every packet; the world
binds this id to it at the first hello of the right export and addresses its observations to
it. An observation for another instance of this id is not acted on; the world's REFUSE for
this instance (another holds the id, or the world runs another export) ends the agent with
one line. The hello repeats every HELLO_EVERY_S until the first observation and every
ALIVE_EVERY_S after it, so a world started again after a crash hears the team at once.
"""

from __future__ import annotations

import heapq
import math
import os
import secrets
import sys
import time
from collections import deque

import numpy as np

from deploy.net import protocol as P
from deploy.net.faults import FaultSpec, LinkFaults
from deploy.net.limits import check_agent_id, check_seconds
from deploy.net.transport import Endpoint
from deploy.policy import DeployError, ExportedModel, Pieces
from deploy.radio import AgentAuction, Sensing

HELLO_EVERY_S = 0.25
ALIVE_EVERY_S = 1.0  # the hello's period once the agent is in a run (the world's liveness of a binding)
EARLY_KEPT = 4096  # messages of a run not yet observed, kept at most (the oldest go first)
EARLY_BYTES = 64 << 20  # and their bytes at most
STEPS_AHEAD = 2  # a teammate that got its observation first is one step ahead: more is not the team's
PENDING_KEPT = 65536  # messages held back by injected latency or reordering, at most


def check_faults(spec: FaultSpec, model: ExportedModel) -> None:
    """What a fault spec can only be checked against: the policy's K rounds."""
    if spec.late_round is not None and spec.late_round >= max(model.rounds, 1):
        raise DeployError(
            f"--late-round {spec.late_round} is not a round of this policy (K = {model.rounds}: rounds 0.."
            f"{max(model.rounds - 1, 0)})"
        )


def check_agent(agent_id: int, round_deadline: float, slow_ms: float, hold: int, threads: int) -> None:
    """The agent's own options, each naming itself (``swarm agent`` checks them at parse too)."""
    check_agent_id(agent_id)
    if hold < 0:
        raise DeployError(f"--hold must be >= 0 steps, got {hold}")
    check_seconds(round_deadline, "--round-deadline")
    check_seconds(slow_ms, "--slow-ms", zero_ok=True, scale=1e3, unit="ms")
    cores = os.cpu_count() or 1
    if not 1 <= threads <= cores:  # (more onnxruntime threads than cores only wait on each other)
        raise DeployError(f"--threads must be in 1..{cores}, this machine's cores, got {threads}")


def _size(payload) -> int:
    """Bytes a kept message holds: messages [B, 2, H], or a table per world."""
    if isinstance(payload, np.ndarray):
        return payload.nbytes
    return sum(t.lid.nbytes + t.epoch.nbytes + t.price.nbytes + t.holder.nbytes for t in payload)


def radio_settings(model: ExportedModel) -> dict | None:
    """A radio policy's auction rules (landmark_order "radio": its manifest's ``contract["radio"]``,
    rounds R a step, table size, sense radius, ...); None for any other policy."""
    contract = model.manifest.get("contract") or {}
    if (contract.get("swarm") or {}).get("landmark_order") != "radio":
        return None
    if "radio" not in contract:
        raise DeployError(f"{model.directory} is a radio policy exported without its auction's rules: export it again")
    return contract["radio"]


class NetAgent:
    def __init__(
        self,
        model: ExportedModel,
        agent_id: int,
        endpoint: Endpoint,
        round_deadline: float = 0.03,
        faults: FaultSpec | None = None,
        slow_ms: float = 0.0,
        threads: int = 1,
        quiet: bool = False,
        hold: int = 0,
    ):
        check_agent(agent_id, round_deadline, slow_ms, hold, threads)
        check_faults(faults or FaultSpec(), model)
        self.id = agent_id
        self.nonce = secrets.randbits(64) or 1  # this instance (0 is the world's "none bound")
        self.refused: str | None = None  # why the world does not take this instance
        self.model = model
        self.pieces = Pieces(model, threads)
        self.H, self.K = model.hidden, model.rounds
        # a radio policy first runs R rounds of its auction (TABLE packets), then the network's K
        # (MSG): one numbering of a step's rounds, 0..R-1 the tables', R..R+K-1 the messages'
        self.radio = radio_settings(model)
        self.R = self.radio["rounds"] if self.radio else 0
        self.auction: AgentAuction | None = None
        self.sha = model.manifest["manifest_sha256"]
        self.ep = endpoint
        self.round_deadline = float(round_deadline)
        self.faults = LinkFaults(faults or FaultSpec(), agent_id, self.round_deadline)
        self.slow_s = slow_ms / 1e3
        self.quiet = quiet
        self.hold = int(hold)
        self._kept: dict[tuple[int, int, int], tuple[int, np.ndarray]] = {}  # (world, round, sender) -> (step, message)
        self.run: int | None = None
        # messages of a run this agent has no observation of yet: a teammate that got its OBS
        # first already sent round 0 (the world's OBS packets leave together, arrive apart)
        self._early: deque = deque()
        self._early_bytes = 0
        self.step = -1
        self.round = 0  # the round being collected; messages of earlier rounds of this step are late
        self.B = self.M = None
        self.box: dict[tuple[int, int], dict[int, dict[int, np.ndarray]]] = {}  # (step, round) -> world -> sender
        self._pending: list = []  # heap of (release time, (seq, run, step, round, world, sender, message [2, H]))
        self._held: dict[tuple[int, int], list] = {}  # reordered messages waiting for the next on their link
        self._seq = 0
        self._delivered: set[int] = set()
        self._need: dict[int, list[set[int]]] = {}  # step -> per world, the agents it hears
        self.next_obs = None
        self.stopped = False
        self.stats = dict.fromkeys(P.STATS, 0.0)
        self.steps = 0
        self._warned: set[str] = set()
        endpoint.subscribe("obs", agent_id)
        endpoint.subscribe("msg", "*")
        if self.radio:
            endpoint.subscribe("table", "*")
        # after msg, on the same session: hearing a teammate's hello shows the routes from it exist
        # (the world starts once every agent has heard every other, protocol.py HELLO)
        endpoint.subscribe("hello", "*")
        endpoint.subscribe("stop")
        endpoint.subscribe("refuse", agent_id)
        self.peers: set[int] = set()  # the agents whose hellos this one has heard

    # ------------------------------------------------------------------ receiving
    def _drop(self, counter: str, why: str, n: int = 1) -> None:
        self.stats[counter] += n
        if counter not in self._warned and not self.quiet:
            self._warned.add(counter)
            print(f"swarm agent {self.id}: dropped a packet ({counter}): {why}", file=sys.stderr, flush=True)

    def _on_packet(self, key: str, data: bytes, t: float) -> None:
        topic = key[len(self.ep.ns) + 1 :].split("/")[0]
        try:
            if topic == "stop":
                h = P.read_header(data)
                if h.kind == P.STOP and (self.run is None or h.run == self.run):
                    self.stopped = True
            elif topic == "obs":
                self._on_obs(P.decode_obs(data), t)
            elif topic in ("msg", "table"):
                if not self._wanted(P.read_header(data)):
                    return None  # a teammate this agent does not hear this step: no loss, not read
                self._on_msg(*(P.decode_msg(data, self.H) if topic == "msg" else P.decode_table(data)), t)
            elif topic == "hello":
                h = P.decode_hello(data)[0]
                if h.sender != self.id:
                    self.peers.add(h.sender)
            elif topic == "refuse":
                h, reason, sha = P.decode_refuse(data)
                if h.sender == self.id and h.nonce == self.nonce:
                    self.refused = (
                        f"--id {self.id} is taken: the world has another agent {self.id} (two agents with one --id?)"
                        if reason == P.REFUSED_ID
                        else f"the world runs another export (manifest {sha[:12]}, this agent's is {self.sha[:12]})"
                    )
        except P.VersionError as exc:
            self._drop("version", str(exc))
        except P.PacketError as exc:
            self._drop("malformed", f"{topic} on {key}: {exc}")

    def _on_obs(self, obs, t: float) -> None:
        h = obs[0]
        if h.sender != self.id:
            return self._drop("foreign", f"an observation addressed to agent {h.sender}")
        if h.nonce == 0:
            return None  # the world has not bound this id yet: it will at this agent's next hello
        if h.nonce != self.nonce:  # another process holds this id: counted, no line (the world's REFUSE says why)
            self.stats["foreign"] += 1
            return None
        if h.run == self.run and h.step <= self.step:
            return self._drop("late", f"observation of step {h.step}, this agent is at step {self.step}")
        if self.next_obs is not None:
            self.stats["late"] += 1  # an older one never got its turn
        self.next_obs = (*obs, t)

    def _wanted(self, h: P.Header) -> bool:
        """Whether a message may be of use: every one of a step whose hearers are not known yet
        (a step ahead, another run), and of this step only those from the agents it hears (in a
        team of 50 on one machine, reading only those cut the agents' work about fourfold)."""
        needs = self._need.get(h.step) if h.run == self.run else None
        return needs is None or any(h.sender in need for need in needs)

    def _late(self, step: int, round_: int) -> bool:
        return step < self.step or (step == self.step and round_ < self.round)

    def _on_msg(self, h: P.Header, payload, t: float) -> None:
        """A teammate's round: MSG (payload: messages [B, 2, H]) or TABLE (its auction table per world)."""
        if h.sender == self.id:
            return  # our own publication, delivered back by the session
        if h.run != self.run:
            return self._keep_early(h, payload, t)  # used, or dropped as foreign, at the next OBS
        if (self.M is not None and h.sender >= self.M) or (self.B is not None and h.envs != self.B):
            return self._drop("foreign", f"a message from agent {h.sender} for {h.envs} worlds")
        if h.step > self.step + STEPS_AHEAD:
            return self._drop("overflow", f"a message of step {h.step}, this agent is at step {self.step}")
        table = h.kind == P.TABLE
        if h.round >= (self.R if table else max(self.K, 1)):
            return self._drop(
                "malformed", f"a {P.KINDS[h.kind]} of round {h.round}; the policy has {self.R if table else self.K}"
            )
        round_ = h.round if table else self.R + h.round  # the step's rounds: the tables' first
        if self._late(h.step, round_):
            # only what this agent would have used counts as late (a non-neighbour's message is no loss)
            needs = self._need.get(h.step)
            n = h.envs if needs is None else sum(h.sender in need for need in needs)
            return self._drop("late", f"step {h.step} round {round_} arrived after its deadline", n) if n else None
        for b in range(h.envs):
            fate = self.faults.fate(b, h.sender, None if table else h.round)
            if fate is None:
                continue
            delay, held = fate
            self._seq += 1
            item = (self._seq, h.run, h.step, round_, b, h.sender, payload[b])
            if (held or delay > 0) and len(self._pending) >= PENDING_KEPT:
                self._drop("overflow", f"more than {PENDING_KEPT} messages held back by the injected faults")
                continue
            if held:  # delivered behind the next message on its link, or when its hold time is up
                self._held.setdefault((b, h.sender), []).append(item)
                heapq.heappush(self._pending, (t + max(delay, self.faults.spec.reorder_hold_ms / 1e3), item))
            elif delay > 0:
                heapq.heappush(self._pending, (t + delay, item))
            else:
                self._deliver(item)

    def _keep_early(self, h: P.Header, payload, t: float) -> None:
        """Keep a message of a run not yet observed, the oldest going first past the bounds."""
        size = _size(payload)
        self._early.append((h, payload, t, size))
        self._early_bytes += size
        while len(self._early) > EARLY_KEPT or self._early_bytes > EARLY_BYTES:
            self._early_bytes -= self._early.popleft()[3]
            self._drop("overflow", f"more than {EARLY_KEPT} messages ({EARLY_BYTES >> 20} MiB) before an observation")

    def _deliver(self, item) -> None:
        seq, run, step, round_, b, sender, vec = item
        if seq in self._delivered:
            return
        self._delivered.add(seq)
        held = self._held.get((b, sender))
        if held:  # a held one whose time is up leaves the queue of its link
            held[:] = [x for x in held if x[0] != seq]
        if run != self.run:
            return self._drop("foreign", f"a message of run {run:08x}")
        if self._late(step, round_):
            needs = self._need.get(step)
            if needs is None or sender in needs[b]:
                self._drop("late", f"step {step} round {round_} arrived after its deadline")
            return
        self.box.setdefault((step, round_), {}).setdefault(b, {})[sender] = vec
        while held:  # the reordered ones come after this one
            self._deliver(held.pop(0))

    def _release_due(self) -> None:
        now = time.perf_counter()
        while self._pending and self._pending[0][0] <= now:
            self._deliver(heapq.heappop(self._pending)[1])
        if len(self._delivered) > 100_000:  # only what is still queued can come again
            self._delivered &= {item[0] for _, item in self._pending}

    def pump(self, until: float, done) -> bool:
        """Handle packets and due messages until ``done()`` or the time ``until``; True if done."""
        while not self.stopped and self.refused is None:
            self._release_due()
            if done():
                return True
            now = time.perf_counter()
            if now >= until:
                return False
            timeout = until - now
            if self._pending:
                timeout = min(timeout, self._pending[0][0] - now)
            item = self.ep.get(timeout)
            if item is not None:
                self._on_packet(*item)
        return False

    # ------------------------------------------------------------------ deciding
    def _decide(self, obs) -> None:
        h, o, t0 = obs
        if self.run != h.run:
            self.box.clear()
            self._kept.clear()
        self.run, self.step, self.round = h.run, h.step, 0
        B, M = h.envs, o.agents
        if self.B != B:
            self.auction = None
        self.B, self.M = B, M
        while self._early:
            eh, payload, t, size = self._early.popleft()
            self._early_bytes -= size
            if eh.run != h.run:
                self._drop("foreign", f"a message of run {eh.run:08x}, this agent is in run {h.run:08x}")
            elif eh.step >= h.step:  # (a restarted agent's messages of earlier steps are no loss)
                self._on_msg(eh, payload, t)
        if (o.sensed is None) == bool(self.radio):
            return self._drop("foreign", "an observation without the sensing of a radio policy, or with it for another")
        if not self.radio:
            try:
                self.model.check_landmarks(self.model.task.get("task"), o.entities.shape[1])
            except DeployError as exc:
                return self._drop("foreign", f"an observation this export cannot take: {exc}")
        if self.slow_s:
            time.sleep(self.slow_s)
        # whom it hears in each world, in the order it stacks their messages, and their offsets
        slots = [np.flatnonzero(o.heard[b] >= 0) for b in range(B)]
        heard = [o.heard[b, k] for b, k in enumerate(slots)]
        need = [set(x.tolist()) for x in heard]
        self._need = {k: v for k, v in self._need.items() if k >= h.step - 1}
        self._need[h.step] = need
        if self.radio:
            entities = self._auction(h, o, need, heard)
            if entities is None:
                return
        else:
            padded = self.model.entity_mode == "padded"  # (an unsensed slot a zero one, as the executor)
            rows, sensed = o.entities, o.entity_mask
            entities = [rows[b] * sensed[b][:, None] if padded else rows[b][sensed[b]] for b in range(B)]
        pieces, H = self.pieces, self.H
        messages = np.empty((B, 2, H), np.float32)
        hs = np.empty((B, H), np.float32)  # this agent's state in each of the B worlds
        for b in range(B):
            hs[b], messages[b] = pieces.encode(o.self_obs[b], np.ascontiguousarray(entities[b], np.float32))
        actions = np.zeros(B, np.int64)
        attention = np.zeros((B, M), np.float32)
        if self.K == 0:
            for b in range(B):
                logits, _ = pieces.decide(hs[b], None)
                actions[b] = int(np.argmax(logits))
                attention[b, self.id] = 1.0
        for r in range(self.K):
            self.ep.publish(P.msg_packet(h.run, h.step, r, self.id, messages, self.nonce), "msg", self.id)
            box = self._collect(h.step, self.R + r, need)
            if box is None:
                return
            last = r == self.K - 1
            nxt = messages if last else np.empty_like(messages)
            for b in range(B):
                got = box.get(b, {})
                keep = np.array([j in got for j in heard[b].tolist()], bool)
                senders = heard[b][keep]
                self.stats["msgs_heard"] += len(senders)
                self.stats["missed"] += len(need[b]) - len(senders)
                offsets = o.offsets[b, slots[b][keep]]
                if self.hold:
                    got = self._hold(b, r, h.step, need[b], {j: got[j] for j in senders.tolist()})
                    keep = np.array([j in got for j in heard[b].tolist()], bool)
                    senders, offsets = heard[b][keep], o.offsets[b, slots[b][keep]]
                vec = np.stack([got[j] for j in senders.tolist()]) if len(senders) else np.zeros((0, 2, H), np.float32)
                offsets = np.ascontiguousarray(offsets, np.float32)
                if last:
                    logits, w = pieces.decide(hs[b], vec, offsets)
                    actions[b] = int(np.argmax(logits))
                    attention[b, self.id] = w[0]
                    attention[b, senders] = w[1:]
                else:
                    hs[b], nxt[b] = pieces.round(hs[b], vec, offsets)
            messages = nxt
        for key in [k for k in self.box if k[0] <= h.step]:
            del self.box[key]
        self.stats["decision_s"] = time.perf_counter() - t0
        self.stats["cpu_s"] = time.process_time()
        self.stats["msgs_sent"] = self.ep.sent + 1
        self.stats["bytes_sent"] = self.ep.sent_bytes
        stats = [self.counters()[k] for k in P.STATS]
        self.ep.publish(P.act_packet(h.run, h.step, self.id, actions, attention, stats, self.nonce), "act", self.id)
        self.steps += 1

    def _collect(self, step: int, round_: int, need: list[set[int]]):
        """Wait for round ``round_``'s messages from everyone in ``need`` (per world), or until the
        round deadline -> the round's box {world: {sender: payload}}; None if the world moved on."""
        self.round = round_
        box = self.box.setdefault((step, round_), {})

        def complete():
            return all(need[b] <= box.get(b, {}).keys() for b in range(len(need)))

        self.pump(time.perf_counter() + self.round_deadline, lambda: complete() or self.next_obs is not None)
        if self.stopped or self.refused is not None or self.next_obs is not None:
            self.stats["late"] += 1  # the world moved on: this step's action would be late
            return None
        self.round = round_ + 1  # this round is closed
        return box

    def _auction(self, h: P.Header, o: P.Observation, need: list[set[int]], heard: list[np.ndarray]):
        """The radio policy's R auction rounds (deploy/radio.py), its table to the teammates it hears
        each round -> its landmark rows in each world ([n, 3]); None if the world moved on."""
        B, cfg = h.envs, self.radio
        if self.auction is None:
            self.auction = AgentAuction(self.id, B, cfg)
        sensing = []
        for b in range(B):
            n = int((o.sensed[b] >= 0).sum())
            sensing.append(Sensing(o.sensed[b, :n], o.sensed_offsets[b, :n], o.occupancy[b, :n]))
            self.auction.rebuild(b, bool(o.fresh[b]), sensing[b])
        for r in range(self.R):
            for b in range(B):
                self.auction.bid(b)
            tables = [self.auction.table(b) for b in range(B)]
            self.ep.publish(P.table_packet(h.run, h.step, r, self.id, tables, self.nonce), "table", self.id)
            box = self._collect(h.step, r, need)
            if box is None:
                return None
            for b in range(B):
                got = box.get(b, {})
                senders = [j for j in heard[b].tolist() if j in got]
                self.stats["msgs_heard"] += len(senders)
                self.stats["missed"] += len(need[b]) - len(senders)
                self.auction.merge(b, [got[j] for j in senders])
        return [self.auction.landmarks(b, sensing[b]) for b in range(B)]

    def _hold(self, b: int, r: int, step: int, need: set[int], fresh: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """``fresh`` and, for each neighbour in ``need`` not in it, its last round-r message if at most
        ``hold`` steps old; remembers the fresh ones."""
        for j, vec in fresh.items():
            self._kept[(b, r, j)] = (step, vec)
        out = dict(fresh)
        for j in need - fresh.keys():
            kept = self._kept.get((b, r, j))
            if kept is not None and step - kept[0] <= self.hold:
                out[j] = kept[1]
        return out

    def counters(self) -> dict:
        """``stats`` with the packets the inbox had no room for (transport.py) in overflow."""
        return {**self.stats, "overflow": self.stats["overflow"] + getattr(self.ep, "overflow", 0)}

    def hello(self) -> None:
        self.ep.publish(P.hello_packet(self.run or 0, self.id, self.sha, self.peers, self.nonce), "hello", self.id)

    def serve(self, idle_timeout: float | None = None) -> str:
        """Run until the world says stop (-> "stopped"), refuses this instance (-> "refused", the
        reason in ``refused``) or sends no observation for ``idle_timeout`` s (-> "idle")."""
        last_seen = time.perf_counter()
        last_hello = -math.inf
        while not self.stopped and self.refused is None:
            now = time.perf_counter()
            # (also while stepping: the world's binding of this id stays live, a restarted world hears it)
            every = HELLO_EVERY_S if self.run is None else ALIVE_EVERY_S
            if now - last_hello >= every:
                self.hello()
                last_hello = now
            if self.next_obs is not None:
                obs, self.next_obs = self.next_obs, None
                self._decide(obs)
                last_seen = time.perf_counter()
                continue
            if idle_timeout is not None and now - last_seen > idle_timeout:
                return "idle"
            self.pump(last_hello + every, lambda: self.next_obs is not None)
        return "stopped" if self.refused is None else "refused"
