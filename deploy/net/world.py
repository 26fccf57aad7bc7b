"""The world as a process (``swarm world``): the Taichi simulator at a fixed control rate,
talking to the agent processes over Zenoh.

Per control step: publish each agent's own observation (its state, the landmarks it senses
and the row of the communication graph that says whom it hears this step), wait for the
actions until the action deadline (a missing one is a no-op, counted), step the simulator,
then sleep out the rest of the control period. Episodes run B at a time side by side, as
``swarm execute`` runs them (B parallel worlds; agent process i is agent i in each), with
the same seed, so at zero faults the two give the same actions step for step.

Who is agent i: the world binds id i to the instance (protocol.py: the nonce of the agent
process) whose hello of this export it hears first, takes i's actions from that instance only
and addresses i's observations to it. A hello of another export never displaces it: counted
(refused), named in one line, and that instance is told (REFUSE) so it can leave. Nor does a
second instance of a bound id: it is refused the same way once the bound one is heard after
it appeared (both live), and bound in its place only once the bound one has been silent for
``live_s`` (it died and was restarted); the launcher's own kills release the binding at once.
Every agent repeats its hello, so a world started again after a crash binds the team within
about a second.

With --spawn-agents, the world watches its children (``AgentProcesses.check``): one that
exits by itself ends the run with its first error line.
"""

from __future__ import annotations

import os
import re
import secrets
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from deploy.executor import DeployError, ExecuteSettings, ExportedModel, make_env
from deploy.net import protocol as P
from deploy.net.agent import ALIVE_EVERY_S, radio_settings
from deploy.net.faults import FaultSpec
from deploy.net.limits import LimitError, check_seconds, check_team
from deploy.net.transport import Endpoint
from deploy.radio import sense
from taichi_swarm.metrics import format_results, result_header, run_first_episodes

NOOP = 0  # ACTION_MEANINGS[0]
REFUSE_EVERY_S = 0.1  # a refused instance is told at most this often (a flood of hellos is not answered in kind)


class SpawnError(DeployError):
    """An agent process the world started left by itself."""


@dataclass
class NetSettings:
    period: float = 0.1  # control period, s (0: step as soon as every action is in)
    round_deadline: float = 0.03  # per communication round, s (passed to spawned agents)
    action_deadline: float | None = None  # from publishing the observations, s; None: K rounds + 0.1 s
    start_timeout: float = 60.0  # for the agents' hello before the first step, s

    def __post_init__(self):
        for name in ("period", "round_deadline", "action_deadline", "start_timeout"):
            v = getattr(self, name)
            if v is not None:
                try:
                    check_seconds(v, f"--{name.replace('_', '-')}", zero_ok=name == "period")
                except LimitError as exc:
                    raise DeployError(str(exc)) from None

    def deadline(self, rounds: int) -> float:
        return self.action_deadline if self.action_deadline is not None else rounds * self.round_deadline + 0.1

    def live_s(self, rounds: int) -> float:
        """How long a bound agent may go unheard and still hold its id: two of its hellos and a
        step's decision."""
        return 2 * ALIVE_EVERY_S + self.deadline(rounds) + 0.5


@dataclass
class AgentReport:
    """What the world knows of one agent: from its actions' packets only."""

    missing: int = 0  # steps without its action by the deadline
    late: int = 0  # actions of an older step
    decision_s: list = field(default_factory=list)
    first: dict | None = None  # stats at its first and last action (counters are cumulative)
    last: dict | None = None
    t_first: float = 0.0
    t_last: float = 0.0

    def summary(self) -> dict:
        d = np.asarray(self.decision_s) * 1e3
        out = {
            "missing_actions": self.missing,
            "late_actions": self.late,
            "decision_ms_p50": float(np.percentile(d, 50)) if d.size else None,
            "decision_ms_p99": float(np.percentile(d, 99)) if d.size else None,
        }
        if self.last is not None:
            span = max(self.t_last - self.t_first, 1e-9)
            a, z = self.first, self.last
            out.update(
                msgs_per_s=(z["msgs_sent"] - a["msgs_sent"]) / span if z["msgs_sent"] >= a["msgs_sent"] else None,
                bytes_per_s=(z["bytes_sent"] - a["bytes_sent"]) / span if z["bytes_sent"] >= a["bytes_sent"] else None,
                cpu_frac=(z["cpu_s"] - a["cpu_s"]) / span if z["cpu_s"] >= a["cpu_s"] else None,
                **{
                    k: int(z[k])
                    for k in ("msgs_heard", "missed", "late", "malformed", "foreign", "version", "overflow")
                },
            )
        return out


# claimants of a bound id named in the log, each once, up to this many per id (a launcher gone wrong
# can start a flood of them; every one is refused all the same)
NAMED_CLAIMANTS = 8


class World:
    """B parallel worlds of M agents whose decisions come over the network."""

    def __init__(self, model: ExportedModel, s: ExecuteSettings, net: NetSettings, endpoint: Endpoint, quiet=False):
        check_team(s.agents, s.episodes)  # (before the [M] reports, the [B, M, M] arrays of each step)
        self.model, self.s, self.net, self.ep = model, s, net, endpoint
        self.M, self.B = s.agents, s.episodes
        self.run = secrets.randbits(32) or 1  # (0: an agent's hello before its first observation)
        self.sha = model.manifest["manifest_sha256"]
        self.quiet = quiet
        self.reports = [AgentReport() for _ in range(self.M)]
        self.bound: dict[int, int] = {}  # agent id -> the nonce of the instance taken as that agent
        self.last_heard: dict[int, float] = {}  # agent id -> arrival time of its bound instance's last packet
        self.radio = radio_settings(model)
        # a step's rounds: the radio policy's R auction rounds, then the network's K
        self.rounds = model.rounds + (self.radio["rounds"] if self.radio else 0)
        self.live_s = net.live_s(self.rounds)
        self.env = None
        self.refused: set[int] = set()  # ids only heard from agents of another export
        self.duplicates: set[int] = set()  # ids a second instance claimed while the first was live
        self._named: dict[int, set[int]] = {}  # id -> the claimants (nonces) named, up to NAMED_CLAIMANTS
        self._claims: dict[int, tuple[int, float]] = {}  # id -> (another instance claiming it, since when)
        self._told: dict[int, float] = {}  # id -> when a refused instance of it was last told
        self.heard: set[int] = set()  # the ids bound
        self.peers: dict[int, frozenset] = {}  # agent -> the agents whose hellos it has heard
        self.dropped = dict.fromkeys(("malformed", "version", "foreign", "refused"), 0)
        self._warned: set = set()
        self.watch = None  # called while waiting (the launcher's check that its agents are alive)
        self.step = 0
        self.history: list[np.ndarray] = []  # actions [B, M] of every step
        self.overruns = 0  # steps that took longer than the period
        self.step_hook = None  # called with the step number before each step (the launcher's faults)
        endpoint.subscribe("act", "*")
        endpoint.subscribe("hello", "*")
        trained = model.manifest.get("contract", {}).get("control_period_s")
        if trained and net.period > 0 and abs(net.period - trained) > 1e-9:
            self._say(f"control period {net.period:g} s differs from the {trained:g} s the policy was trained at")

    def _say(self, text: str) -> None:
        if not self.quiet:
            print(f"swarm world: {text}", file=sys.stderr, flush=True)

    def _drop(self, counter: str, why: str) -> None:
        self.dropped[counter] += 1
        if counter not in self._warned:
            self._warned.add(counter)
            self._say(f"dropped a packet ({counter}): {why}")

    def _on_packet(self, key: str, data: bytes, t: float, actions=None, attention=None, got=None):
        topic = key[len(self.ep.ns) + 1 :].split("/")[0]
        try:
            if topic == "hello":
                self._on_hello(*P.decode_hello(data), t)
            elif topic == "act":
                h, a, att, stats = P.decode_act(data)
                if (a >= self.model.manifest["num_actions"]).any():
                    raise P.PacketError(f"an action {int(a.max())} of a policy of {self.model.manifest['num_actions']}")
                if h.run != self.run or h.sender >= self.M or h.envs != self.B or att.shape[1] != self.M:
                    return self._drop("foreign", f"an action of run {h.run:08x} from agent {h.sender}")
                if self.bound.get(h.sender) != h.nonce:
                    self.dropped["refused"] += 1  # not the instance taken as this agent
                    return
                self.last_heard[h.sender] = t
                rep = self.reports[h.sender]
                if h.step != self.step or got is None:
                    rep.late += 1
                    return
                actions[:, h.sender] = a
                attention[:, h.sender] = att
                got.add(h.sender)
                rep.decision_s.append(stats["decision_s"])
                if rep.first is None:
                    rep.first, rep.t_first = stats, t
                rep.last, rep.t_last = stats, t
        except P.VersionError as exc:
            self._drop("version", str(exc))
        except P.PacketError as exc:
            self._drop("malformed", f"{topic} on {key}: {exc}")

    def _on_hello(self, h: P.Header, sha: str, peers: frozenset, t: float) -> None:
        i = h.sender
        if i >= self.M:
            return self._drop("foreign", f"agent {i} announced itself in a team of {self.M}")
        if h.nonce == 0:
            return self._drop("malformed", f"a hello of agent {i} without its instance nonce")
        if sha != self.sha:
            self.dropped["refused"] += 1
            if i not in self.bound:
                self.refused.add(i)
            if ("export", i) not in self._warned:
                self._warned.add(("export", i))
                self._say(
                    f"agent {i} runs another export (manifest {sha[:12]}, this world's is {self.sha[:12]}): "
                    "its actions are refused"
                )
            if h.nonce != self.bound.get(i):  # (never the instance taken as agent i: a stray packet)
                self._tell(i, h.nonce, P.REFUSED_EXPORT)
            return
        bound = self.bound.get(i)
        if bound == h.nonce:
            self.last_heard[i] = t
            self.peers[i] = peers
            return
        if bound is not None:
            # Another instance claims a bound id. It waits: refused once the bound one is heard
            # after the claim began (both live: two agents with one id, or a stray hello), bound in
            # its place once the bound one has been silent for live_s (it died: a restart).
            claim = self._claims.get(i)
            if claim is None or claim[0] != h.nonce:
                claim = self._claims[i] = (h.nonce, t)
            if self.last_heard[i] > claim[1]:
                self.dropped["refused"] += 1
                self.duplicates.add(i)
                named = self._named.setdefault(i, set())
                if h.nonce not in named and len(named) < NAMED_CLAIMANTS:  # (each claimant once; a flood, a few)
                    named.add(h.nonce)
                    self._say(f"a second agent claims --id {i}, which a live agent holds: the second is refused")
                return self._tell(i, h.nonce, P.REFUSED_ID)
            silent = t - self.last_heard[i]
            if silent <= self.live_s:
                return None
            self._say(f"agent {i} is another instance now (the last one silent for {silent:.1f} s)")
        self._claims.pop(i, None)  # (bound now)
        self.bound[i] = h.nonce
        self.last_heard[i] = t
        self.refused.discard(i)
        self.heard.add(i)
        self.peers[i] = peers

    def _tell(self, i: int, nonce: int, reason: int) -> None:
        now = time.monotonic()
        if now - self._told.get(i, -np.inf) >= REFUSE_EVERY_S:
            self._told[i] = now
            self.ep.publish(P.refuse_packet(self.run, i, nonce, reason, self.sha), "refuse", i)

    def release(self, i: int) -> None:
        """Agent i's instance is gone (the launcher killed it): the next to say hello is agent i."""
        self.bound.pop(i, None)
        self.heard.discard(i)

    def _check(self) -> None:
        if self.watch is not None:
            self.watch()

    def wait_for_agents(self, expected) -> set[int]:
        """Wait up to start_timeout for the hello of every agent in ``expected``, each saying it has
        heard every other's, and for a route to each one's observations (its subscription known
        here): a first step sent before the routes exist would be dropped, and the team would
        wait out its deadlines (a busy machine takes seconds). Returns who was heard."""
        expected = set(expected)

        def deaf() -> dict[int, list[int]]:  # agent -> the expected ones it has not heard yet
            gaps = {i: sorted(expected - {i} - self.peers.get(i, frozenset())) for i in expected & self.heard}
            return {i: g for i, g in gaps.items() if g}

        def unrouted() -> list[int]:  # heard, but its subscription to its observations not yet routed here
            return [i for i in sorted(expected & self.heard) if not self.ep.matched("obs", i)]

        until = time.perf_counter() + self.net.start_timeout
        while not (expected <= self.heard and not deaf() and not unrouted()) and time.perf_counter() < until:
            self._check()
            item = self.ep.get(min(until - time.perf_counter(), 0.25))
            if item is not None:
                self._on_packet(*item)
        missing = sorted(expected - self.heard)
        if missing:
            self._say(f"agents {missing} not heard within {self.net.start_timeout:g} s: their actions are no-ops")
        for i, gap in deaf().items():
            self._say(
                f"agent {i} has not heard agents {gap} within {self.net.start_timeout:g} s: it starts without them"
            )
        unreached = unrouted()
        if unreached:
            self._say(f"no route to the observations of agents {unreached} yet: they may miss the first steps")
        return set(self.heard)

    def decide(self, obs):
        """One control step over the network -> (actions [B, M], attention [B, M, M])."""
        t0 = time.perf_counter()
        if self.step_hook is not None:
            self.step_hook(self.step)
        for i, o in enumerate(self.observations(obs)):
            nonce = self.bound.get(i, 0)  # (0: nobody acts on it yet)
            self.ep.publish(P.obs_packet(self.run, self.step, i, o, nonce), "obs", i)
        actions = np.full((self.B, self.M), NOOP, np.int64)
        attention = np.zeros((self.B, self.M, self.M), np.float32)
        got: set[int] = set()
        until = t0 + self.net.deadline(self.rounds)
        wanted = set(self.bound)
        while not wanted <= got:
            now = time.perf_counter()
            if now >= until:
                break
            item = self.ep.get(until - now)
            if item is not None:
                self._on_packet(*item, actions=actions, attention=attention, got=got)
        self._check()
        for i in set(range(self.M)) - got:
            self.reports[i].missing += 1
        self.history.append(actions.copy())
        self.step += 1
        if self.net.period > 0:
            rest = self.net.period - (time.perf_counter() - t0)
            if rest > 0:
                self._sleep_listening(rest)
            else:
                self.overruns += 1
        return actions, attention

    def observations(self, obs) -> list[P.Observation]:
        """Each agent's own observation in the B worlds: its state, its landmark rows (a radio
        policy: its sensing instead, deploy/radio.py), whom it hears this step and their offsets."""
        B, M = self.B, self.M
        self_obs = np.asarray(obs["self"], np.float32)
        pos = self_obs[..., 2:4]
        me = np.arange(M)
        if "nbr" in obs:  # neighbour lists: the heard in list order (the executor's slots)
            nbr = np.asarray(obs["nbr"], np.int64)
            ok = np.asarray(obs["nbr_mask"], bool) & (nbr != me[None, :, None]) & (nbr >= 0) & (nbr < M)
        else:  # the dense graph: ascending ids
            nbr = np.broadcast_to(me, (B, M, M))
            ok = np.asarray(obs["adj"], bool) & (nbr != me[None, :, None])
        heard = np.where(ok, nbr, -1)
        others = pos[np.arange(B)[:, None, None], np.clip(heard, 0, None)]  # [B, M, K, 2]
        offsets = np.where(ok[..., None], others - pos[:, :, None], 0)
        # which worlds start an episode (without the simulator, a caller's own loop: the first step)
        state = self.env.get_state() if self.env is not None else None
        fresh = np.asarray(state["step"]) == 0 if state is not None else np.full(B, self.step == 0)
        radio = self.radio
        if radio:
            S = 2 * radio["table"]
            sensed = np.full((B, M, S), -1, np.int64)
            sensed_off = np.zeros((B, M, S, 2), np.float32)
            occ = np.zeros((B, M, S), np.float32)
            for b in range(B):
                for i, x in enumerate(sense(state["pos"][b], state["landmarks"][b], radio["sense_radius"], S)):
                    n = x.ids.size
                    sensed[b, i, :n], sensed_off[b, i, :n], occ[b, i, :n] = x.ids, x.offsets, x.occupancy
            entities = np.zeros((B, M, 0, 3), np.float32)
            mask = np.zeros((B, M, 0), bool)
        else:
            entities = np.asarray(obs["entities"], np.float32)
            mask = np.asarray(obs["entity_mask"], bool) if "entity_mask" in obs else np.ones(entities.shape[:3], bool)
        out = []
        for i in range(M):
            o = P.Observation(
                self_obs[:, i], entities[:, i], mask[:, i], heard[:, i], offsets[:, i].astype(np.float32), fresh, M
            )
            if radio:
                o.sensed, o.sensed_offsets, o.occupancy = sensed[:, i], sensed_off[:, i], occ[:, i]
            out.append(o)
        return out

    def _sleep_listening(self, seconds: float) -> None:
        """Sleep out the control period while still reading (late actions, hellos)."""
        until = time.perf_counter() + seconds
        while (now := time.perf_counter()) < until:
            self._check()
            item = self.ep.get(min(until - now, 0.25))
            if item is not None:
                self._on_packet(*item)

    def run_episodes(self, recorder=None, env=None) -> dict:
        """``env``: the simulator ``make_env`` built (None: built here)."""
        s = self.s
        env = self.env = env if env is not None else make_env(self.model, s)
        t0 = time.perf_counter()
        tally = run_first_episodes(env, self.decide, recorder)
        wall = time.perf_counter() - t0
        return {
            **result_header(s.task, s.agents, s.comm, s.comm_radius, s.episodes, s.seed),
            **tally.summary(s.task),
            "steps": self.step,
            "wall_s": wall,
            "period_s": self.net.period,
            "round_deadline_s": self.net.round_deadline,
            "action_deadline_s": self.net.deadline(self.rounds),
            "overruns": self.overruns,
            "missing_actions": sum(r.missing for r in self.reports),
            "dropped_at_world": {**self.dropped, "overflow": getattr(self.ep, "overflow", 0)},
            "agents_report": [r.summary() for r in self.reports],
        }

    def stop_agents(self) -> None:
        for _ in range(3):  # a few times: a stop is one small packet, and nothing answers it
            self.ep.publish(P.stop_packet(self.run), "stop")
            time.sleep(0.02)


def format_net(row: dict) -> str:
    """S% / T like ``swarm execute``, then one line per agent."""
    lines = [format_results([row])]
    lines.append(
        f"{row['steps']} steps in {row['wall_s']:.1f} s (period {row['period_s']:g} s, {row['overruns']} overruns), "
        f"{row['missing_actions']} missing actions (no-ops)"
    )
    head = f"{'agent':>5} {'missing':>7} {'p50 ms':>7} {'p99 ms':>7} {'msg/s':>7} {'kB/s':>7} {'cpu':>5} " + (
        f"{'heard':>7} {'missed':>6} {'late':>5} {'bad':>4}"
    )
    decided = [r for r in row["agents_report"] if r["decision_ms_p50"] is not None]
    if decided:  # over the agents: the median of their p50s, the worst of their p99s
        p50 = np.median([r["decision_ms_p50"] for r in decided])
        p99 = max(r["decision_ms_p99"] for r in decided)
        lines.append(f"decision latency: p50 {p50:.0f} ms (median over agents), p99 {p99:.0f} ms (worst agent)")
    for key, what in (("agent_rss_mb", "peak RSS"), ("agent_pss_mb", "PSS at the end (shared pages split)")):
        if row.get(key):
            mb = list(row[key].values())
            spread = f"median {np.median(mb):.0f} MB, max {max(mb):.0f} MB"
            lines.append(f"agent process {what}: {spread} ({len(mb)} agents)")
    lines.append(head)
    for i, r in enumerate(row["agents_report"]):

        def f(v, fmt):
            return "-" if v is None else format(v, fmt)

        bad = None if "malformed" not in r else r["malformed"] + r["foreign"] + r["version"]
        lines.append(
            f"{i:>5} {r['missing_actions']:>7} {f(r['decision_ms_p50'], '.2f'):>7} {f(r['decision_ms_p99'], '.2f'):>7} "
            f"{f(r.get('msgs_per_s'), '.0f'):>7} {f(r.get('bytes_per_s') and r['bytes_per_s'] / 1e3, '.1f'):>7} "
            f"{f(r.get('cpu_frac'), '.2f'):>5} {f(r.get('msgs_heard'), 'd'):>7} {f(r.get('missed'), 'd'):>6} "
            f"{f(r.get('late'), 'd'):>5} {f(bad, 'd'):>4}"
        )
    return "\n".join(lines)


def error_line(text: str) -> str:
    """The line of a process's output that says why it failed: its first ``error:`` line, else
    the last line (a traceback's exception, a summary)."""
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("[Taichi]")]
    for line in lines:
        if re.search(r"\berror:", line, re.IGNORECASE):
            return line[:400]
    return lines[-1][:400] if lines else "(it wrote nothing)"


class AgentProcesses:
    """The launcher: M ``swarm agent`` processes on this machine, each stopped by ``stop`` (or
    ``kill``). Each one's output goes to DIR/agent-I.log (``log_dir``) or a temporary file, so
    ``check`` can say why one that left by itself did."""

    def __init__(
        self,
        export_dir: str,
        agents: int,
        connect: str,
        ns: str,
        round_deadline: float,
        faults: FaultSpec | None = None,
        slow: dict[int, float] | None = None,
        log_dir: str | None = None,
        command: list[str] | None = None,
        hold: int = 0,
        idle_timeout: float = 30.0,
    ):
        self.hold = hold
        self.idle_timeout = idle_timeout
        self.export_dir, self.M, self.connect, self.ns = export_dir, agents, connect, ns
        self.round_deadline = round_deadline
        self.faults = faults or FaultSpec()
        self.slow = slow or {}
        self.log_dir = log_dir
        self.command = command or [sys.executable, "-m", "swarm_cli", "agent"]
        self.procs: dict[int, subprocess.Popen] = {}
        self._logs: list = []
        self._output: dict[int, tuple] = {}  # agent -> (its output file, where its present run's output starts)

    def start(self, i: int) -> None:
        argv = [
            *self.command, self.export_dir, "--id", str(i), "--connect", self.connect, "--ns", self.ns,
            "--round-deadline", str(self.round_deadline), "--idle-timeout", f"{self.idle_timeout:g}",
            *self.faults.to_args(),
        ]  # fmt: skip
        if self.slow.get(i):
            argv += ["--slow-ms", str(self.slow[i])]
        if self.hold:
            argv += ["--hold", str(self.hold)]
        if self.log_dir:
            os.makedirs(self.log_dir, exist_ok=True)
            out = open(os.path.join(self.log_dir, f"agent-{i}.log"), "a+b")  # noqa: SIM115 - closed in stop()
        else:
            out = tempfile.TemporaryFile()  # noqa: SIM115 - closed (and so removed) in stop()
        self._logs.append(out)
        self._output[i] = (out, out.seek(0, os.SEEK_END))
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        self.procs[i] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)

    def output(self, i: int) -> str:
        """What agent i's present (or last) process has written so far (its first 64 KiB)."""
        out, start = self._output[i]
        return os.pread(out.fileno(), 1 << 16, start).decode("utf-8", "replace")

    def check(self) -> None:
        """Raise ``SpawnError`` naming the first agent (by id) whose process has left by itself."""
        for i, p in sorted(self.procs.items()):
            status = p.poll()
            if status is not None:
                raise SpawnError(f"agent {i} exited with status {status}: {error_line(self.output(i))}")

    def kill(self, i: int) -> None:
        p = self.procs.pop(i, None)
        if p is not None:
            p.kill()
            p.wait(timeout=10)

    def memory_mb(self, file: str, key: str) -> dict[int, float]:
        """Each live agent process's ``key`` line of /proc/PID/``file`` in MB (Linux; {} elsewhere):
        "status", "VmHWM:" its peak resident memory; "smaps_rollup", "Pss:" its proportional share
        now, where a page that n processes map counts 1/n (the shared libraries of a team on one
        machine counted once, not M times)."""
        out = {}
        for i, p in self.procs.items():
            try:
                with open(f"/proc/{p.pid}/{file}") as f:
                    kb = next(int(line.split()[1]) for line in f if line.startswith(key))
            except (OSError, StopIteration, ValueError):
                continue
            out[i] = kb / 1024
        return out

    def stop(self, timeout: float = 10.0) -> None:
        """Wait for the agents to leave (after the world's stop), then kill what is left."""
        until = time.monotonic() + timeout
        for p in self.procs.values():
            try:
                p.wait(timeout=max(until - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)
        self.procs.clear()
        for f in self._logs:
            f.close()
        self._logs.clear()
