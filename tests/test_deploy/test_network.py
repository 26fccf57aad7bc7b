"""The team as processes over Zenoh (deploy/net): parity with the in-process executor at
zero faults, an agent killed mid-episode, faults, and bad packets refused without a crash.

Everything stays on 127.0.0.1 (the world listens there, agents connect there and listen on
a free port there, multicast scouting off); every agent process a test starts is stopped by
the test, with its own timeout.
"""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("zenoh")

import taichi_swarm  # noqa: E402
from deploy.executor import DeployError, Executor, ExportedModel, resolve_settings  # noqa: E402
from deploy.export import export  # noqa: E402
from deploy.net import protocol as P  # noqa: E402
from deploy.net.agent import NetAgent  # noqa: E402
from deploy.net.faults import FaultError, FaultSpec, LinkFaults  # noqa: E402
from deploy.net.transport import Endpoint, TransportError, check_endpoint, open_session  # noqa: E402
from deploy.net.world import AgentProcesses, NetSettings, World  # noqa: E402
from deploy.radio import Table  # noqa: E402
from taichi_swarm.metrics import run_first_episodes  # noqa: E402
from trainer import checkpoint  # noqa: E402
from trainer.model import ModelConfig, SwarmPolicy  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _export(d, cfg: ModelConfig, task: str, agents: int, seed: int) -> str:
    torch.manual_seed(seed)
    policy = SwarmPolicy(cfg).eval()
    path = str(d / "ckpt.pt")
    checkpoint.save(
        path,
        {
            "model_config": policy.config.to_dict(),
            "model": policy.state_dict(),
            "task": {"task": task, "agents": agents, "comm": "rc", "comm_radius": 0.8},
        },
    )
    export(path, str(d / "onnx"))
    return str(d / "onnx")


@pytest.fixture(scope="module")
def emp_dir(tmp_path_factory):
    """A random-init EMP policy (K = 2) for coverage RC, exported."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _export(tmp_path_factory.mktemp("net-emp"), ModelConfig(hidden=32, rounds=2), "coverage", 3, 0)
    finally:
        torch.set_num_threads(threads)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _reference_actions(model, s) -> list[np.ndarray]:
    """The in-process executor's actions [B, M] at every step (``swarm execute``'s loop)."""
    env = taichi_swarm.make(
        s.task, s.episodes, s.agents, comm=s.comm, comm_radius=s.comm_radius, arch="cpu", seed=s.seed, array="numpy"
    )
    executor = Executor(model, s.episodes, s.agents, seed=s.seed)
    history = []

    def decide(obs):
        _, actions, attention = executor.decide(obs["self"], obs["entities"], obs["adj"])
        history.append(actions.copy())
        return actions, attention

    tally = run_first_episodes(env, decide)
    return history, tally.summary(s.task)


def _run_world(export_dir, s, net, faults=None, kill=None, absent=(), inject=None):
    """A world in this process and its agents as `swarm agent` processes; returns (world, row)."""
    model = ExportedModel(export_dir)
    port, ns = _free_port(), f"test{secrets.token_hex(4)}"
    endpoint = Endpoint(open_session("router", [f"tcp/127.0.0.1:{port}"], []), ns)
    world = World(model, s, net, endpoint, quiet=True)
    procs = AgentProcesses(export_dir, s.agents, f"tcp/127.0.0.1:{port}", ns, net.round_deadline, faults)
    try:
        present = sorted(set(range(s.agents)) - set(absent))
        for i in present:
            procs.start(i)

        def hook(step):
            if kill is not None and step == kill[1]:
                procs.kill(kill[0])
            if inject is not None:
                inject(step, endpoint, world)

        world.step_hook = hook
        heard = world.wait_for_agents(present)
        assert heard == set(present), f"agents {sorted(set(present) - heard)} never said hello"
        row = world.run_episodes()
    finally:
        world.stop_agents()
        procs.stop(timeout=15)
        endpoint.close()
    return world, row


def test_networked_team_matches_execute_action_for_action(emp_dir):
    """M = 3 agent processes on 127.0.0.1, 4 episodes side by side: every action of every step
    equals the in-process executor's; bad packets sent into the run mid-episode are dropped and
    counted by the agents, and change nothing."""
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", 3, "rc", 0.8, episodes=4, seed=7)
    reference, ref_summary = _reference_actions(model, s)

    def inject(step, endpoint, world):
        if step == 3:
            endpoint.publish(b"garbage", "msg", 1)  # malformed
            endpoint.publish(b"TSWM" + bytes([9]) + bytes(40), "msg", 2)  # another schema version
            foreign = P.msg_packet(world.run ^ 1, step, 0, 0, np.zeros((4, 2, 32), np.float32))
            endpoint.publish(foreign, "msg", 0)  # another run's (foreign)

    net = NetSettings(period=0.0, round_deadline=5.0, action_deadline=30.0, start_timeout=60.0)
    world, row = _run_world(emp_dir, s, net, inject=inject)
    # a lost or late message first: it would show as a differing action, for another reason
    assert row["missing_actions"] == 0
    reports = row["agents_report"]
    assert all(r["missed"] == 0 and r["late"] == 0 for r in reports), [(r["missed"], r["late"]) for r in reports]
    assert len(world.history) == len(reference)
    for t, (got, want) in enumerate(zip(world.history, reference, strict=True)):
        np.testing.assert_array_equal(got, want, err_msg=f"step {t}")
    assert row["success_rate"] == ref_summary["success_rate"]
    assert sum(r["malformed"] for r in reports) >= 1
    assert sum(r["version"] for r in reports) >= 1
    assert sum(r["foreign"] for r in reports) >= 1


def test_killed_agent_the_others_carry_on(emp_dir):
    """Agent 1 is killed at step 4: the world keeps stepping to the end, its actions become
    no-ops, the other two go on without its messages after each round deadline."""
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", 3, "uc", 1.0, episodes=2, seed=3)
    # the world waits for the dead agent's action until the deadline every step: keep it short
    net = NetSettings(period=0.0, round_deadline=0.05, action_deadline=0.5, start_timeout=60.0)
    world, row = _run_world(emp_dir, s, net, kill=(1, 4))
    steps = row["steps"]
    assert steps > 8 and len(world.history) == steps
    r0, r1, r2 = row["agents_report"]
    assert r1["missing_actions"] >= steps - 4
    assert r0["missing_actions"] <= 2 and r2["missing_actions"] <= 2  # a busy machine may miss one or two
    # in uc each hears agent 1 in every world; its messages stop at step 4
    assert r0["missed"] >= (steps - 4) * s.episodes * model.rounds - 2
    assert r2["missed"] >= (steps - 4) * s.episodes * model.rounds - 2
    assert (world.history[-1][:, 1] == 0).all()


def test_absent_agent_and_injected_loss_keep_the_world_stepping(emp_dir):
    """An agent that never starts plus 50% independent loss on every link: the world finishes,
    the absent agent's actions are no-ops, the others report about half their messages missed."""
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", 3, "uc", 1.0, episodes=2, seed=5)
    net = NetSettings(period=0.0, round_deadline=0.03, action_deadline=0.5, start_timeout=60.0)
    world, row = _run_world(emp_dir, s, net, faults=FaultSpec(drop=0.5, seed=1), absent=(2,))
    r0, r1, r2 = row["agents_report"]
    assert r2["missing_actions"] == row["steps"]
    expected = row["steps"] * s.episodes * model.rounds  # messages from the one live neighbour
    for r in (r0, r1):
        assert r["missing_actions"] <= 2  # a busy machine may miss a deadline or two
        # the live neighbour's messages: about half are lost; the absent one's all missed
        assert 0.25 * expected < r["msgs_heard"] < 0.75 * expected


# ----------------------------------------------------------------------------- faults
def test_gilbert_elliott_loss_rate_and_bursts():
    spec = FaultSpec(burst_loss=0.3, burst_len=4.0, seed=2)
    link = LinkFaults(spec, receiver=0, round_deadline=0.03)
    lost = np.array([link.fate(0, 1, 0) is None for _ in range(40000)])
    assert abs(lost.mean() - 0.3) < 0.02
    starts = np.flatnonzero(np.diff(lost.astype(int)) == 1)
    assert abs(lost.sum() / max(len(starts), 1) - 4.0) < 0.4  # mean burst length
    indep = LinkFaults(FaultSpec(drop=0.3, seed=2), 0, 0.03)
    lost_i = np.array([indep.fate(0, 1, 0) is None for _ in range(40000)])
    runs_i = lost_i.sum() / max(len(np.flatnonzero(np.diff(lost_i.astype(int)) == 1)), 1)
    assert runs_i < 1.6  # independent losses come one or two at a time: 1 / (1 - 0.3)


def test_latency_jitter_and_late_round():
    link = LinkFaults(FaultSpec(latency_ms=10, jitter_ms=4, late_round=1, seed=0), 0, round_deadline=0.02)
    delays = np.array([link.fate(0, 1, 0)[0] for _ in range(2000)])
    assert 0.006 <= delays.min() and delays.max() <= 0.014 and abs(delays.mean() - 0.010) < 5e-4
    assert link.fate(0, 1, 1)[0] > 0.02  # round 1 arrives after its deadline


@pytest.mark.parametrize(
    ("kwargs", "word"),
    [({"drop": 1.5}, "--drop"), ({"burst_loss": 1.0}, "--burst-loss"), ({"burst_len": 0.5}, "--burst-len"),
     ({"jitter_ms": -1}, "--jitter-ms"), ({"late_round": -1}, "--late-round")],
)  # fmt: skip
def test_bad_fault_parameters_are_refused(kwargs, word):
    with pytest.raises(FaultError, match=word):
        FaultSpec(**kwargs)


# ----------------------------------------------------------------------------- packets
def _obs(entities, heard, agents=3, **sensing):
    """An Observation of B worlds: landmark rows ``entities`` [B, L, F], ``heard`` [B, K] (-1: empty)."""
    B, L = entities.shape[:2]
    offsets = np.arange(B * heard.shape[1] * 2, dtype=np.float32).reshape(B, -1, 2)
    return P.Observation(
        np.zeros((B, 4), np.float32), entities.astype(np.float32), np.ones((B, L), bool), heard, offsets,
        np.zeros(B, bool), agents, **sensing,
    )  # fmt: skip


def test_packets_round_trip():
    rng = np.random.default_rng(0)
    o = _obs(rng.normal(size=(2, 3, 3)), np.array([[2, -1], [0, 2]]))
    o.self_obs = rng.normal(size=(2, 4)).astype(np.float32)
    o.entity_mask[1, 2] = False
    o.fresh[1] = True
    h, o2 = P.decode_obs(P.obs_packet(7, 11, 1, o))
    assert (h.run, h.step, h.envs, h.sender) == (7, 11, 2, 1) and o2.agents == 3 and o2.sensed is None
    for name in ("self_obs", "entities", "entity_mask", "heard", "offsets", "fresh"):
        np.testing.assert_array_equal(getattr(o2, name), getattr(o, name), err_msg=name)
    sensed_offsets = rng.normal(size=(1, 3, 2)).astype(np.float32)
    occupancy = np.ones((1, 3), np.float32)
    radio = _obs(np.zeros((1, 0, 3)), np.array([[1]]), sensed=np.array([[4, 0, -1]]), sensed_offsets=sensed_offsets,
                 occupancy=occupancy)  # fmt: skip
    _, r2 = P.decode_obs(P.obs_packet(7, 11, 0, radio))
    np.testing.assert_array_equal(r2.sensed, radio.sensed)
    np.testing.assert_array_equal(r2.sensed_offsets, radio.sensed_offsets)
    price = np.array([0.5, 2.0], np.float32)
    tables = [Table.empty(), Table(np.array([3, 9]), np.array([1, 0]), price, np.array([-1, 2]))]
    h, t2 = P.decode_table(P.table_packet(7, 11, 3, 2, tables))
    assert (h.round, h.sender, h.envs) == (3, 2, 2) and t2[0].lid.size == 0
    for name in ("lid", "epoch", "price", "holder"):
        np.testing.assert_array_equal(getattr(t2[1], name), getattr(tables[1], name), err_msg=name)
    unsorted = Table(np.array([9, 3]), np.array([1, 0]), price, np.array([-1, 2]))
    with pytest.raises(P.PacketError, match="not sorted"):
        P.decode_table(P.table_packet(7, 11, 3, 2, [unsorted]))
    msg = rng.normal(size=(2, 2, 8)).astype(np.float32)
    h, msg2 = P.decode_msg(P.msg_packet(7, 11, 1, 2, msg), 8)
    assert (h.round, h.sender) == (1, 2)
    np.testing.assert_array_equal(msg2, msg)
    stats = list(range(len(P.STATS)))
    h, a, att, st = P.decode_act(P.act_packet(7, 11, 2, np.array([0, 4]), np.ones((2, 3)), stats))
    assert a.tolist() == [0, 4] and st["cpu_s"] == 1.0


@pytest.mark.parametrize(
    ("data", "error", "words"),
    [
        (b"", P.PacketError, "shorter than"),
        (b"XXXX" + bytes(30), P.PacketError, "does not start with"),
        (
            P.header_bytes(P.MSG, 1, 0, 1, 0, 0)[:4] + bytes([P.SCHEMA_VERSION + 1]) + bytes(15),
            P.VersionError,
            f"schema version {P.SCHEMA_VERSION + 1}",
        ),
        (P.msg_packet(1, 0, 0, 0, np.zeros((1, 2, 8), np.float32))[:-4], P.PacketError, "truncated"),
        (P.msg_packet(1, 0, 0, 0, np.zeros((1, 2, 9), np.float32)), P.PacketError, "bytes after"),
        (P.msg_packet(1, 0, 0, 0, np.full((1, 2, 8), np.nan, np.float32)), P.PacketError, "non-finite"),
    ],
)
def test_bad_packets_raise_one_clear_error(data, error, words):
    with pytest.raises(error, match=words) as info:
        P.decode_msg(data, 8)
    assert "\n" not in str(info.value)


class _FakeEndpoint:
    ns = "swarm"

    def __init__(self):
        self.published = []

    def subscribe(self, *parts):
        pass

    def publish(self, data, *parts):
        self.published.append(("/".join(map(str, parts)), data))

    unrouted: tuple = ()

    def matched(self, *parts):  # (a route to every subscriber but the agents named unrouted)
        return not (parts[0] == "obs" and parts[1] in self.unrouted)

    sent = sent_bytes = 0

    def get(self, timeout):
        return None


def test_agent_drops_and_counts_what_it_cannot_use(emp_dir, capsys):
    agent = NetAgent(ExportedModel(emp_dir), 0, _FakeEndpoint(), round_deadline=0.01)
    agent.run, agent.step, agent.B, agent.M = 5, 3, 1, 3
    good = np.zeros((1, 2, 32), np.float32)
    ones = np.array([[1, 2]])  # agent 0 hears 1 and 2
    cases = [
        ("swarm/msg/1", b"\x00" * 3, "malformed"),
        ("swarm/msg/1", P.header_bytes(P.MSG, 5, 3, 1, 0, 1)[:4] + bytes([7]) + bytes(40), "version"),
        ("swarm/msg/1", P.msg_packet(5, 3, 0, 9, good), "foreign"),  # a sender outside the team
        ("swarm/msg/1", P.msg_packet(5, 2, 0, 1, good), "late"),  # an older step
        ("swarm/msg/1", P.msg_packet(5, 3, 0, 1, np.zeros((1, 2, 16), np.float32)), "malformed"),  # other H
        ("swarm/obs/0", P.obs_packet(5, 2, 0, _obs(np.zeros((1, 3, 2)), ones), agent.nonce), "late"),
        ("swarm/obs/0", P.obs_packet(5, 4, 0, _obs(np.zeros((1, 3, 2)), ones), agent.nonce ^ 1), "foreign"),
    ]
    for key, data, counter in cases:
        before = agent.stats[counter]
        agent._on_packet(key, data, 0.0)
        assert agent.stats[counter] > before, (key, counter)
    agent._on_packet("swarm/msg/1", P.msg_packet(5, 3, 1, 1, good), 0.0)  # a future round: kept
    assert 1 in agent.box[(3, 1)][0]
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 4 and all(line.startswith("swarm agent 0: dropped a packet") for line in lines)
    assert agent.next_obs is None  # neither the stale observation nor another instance's is acted on


def test_agent_uses_what_came_before_its_observation_and_drops_other_runs(emp_dir):
    """A teammate that got its OBS first has sent round 0 before this agent knows the run: that
    message is kept and used once the OBS comes; a message of another run is counted as foreign
    then (until the OBS, it could have been of the run about to start)."""
    agent = NetAgent(ExportedModel(emp_dir), 0, _FakeEndpoint(), round_deadline=0.01, quiet=True)
    good = np.zeros((1, 2, 32), np.float32)
    agent._on_packet("swarm/msg/1", P.msg_packet(5, 0, 0, 1, good), 0.0)  # before any OBS
    agent._on_packet("swarm/msg/2", P.msg_packet(6, 0, 0, 2, good), 0.0)  # of another run
    assert agent.stats["foreign"] == 0
    obs = P.decode_obs(P.obs_packet(5, 0, 0, _obs(np.zeros((1, 3, 2)), np.array([[1, -1]])), agent.nonce))  # hears 1
    agent._decide((*obs, 0.0))
    assert agent.stats["msgs_heard"] == 1 and agent.stats["missed"] == agent.K - 1  # round 0 heard
    assert agent.stats["foreign"] == 1


def test_agent_hold_attends_over_a_lost_neighbours_last_message(emp_dir):
    """--hold A: a neighbour the OBS row names whose message is missing is replaced by its last
    message of that round, if at most A steps old (the in-process MessageBus hold)."""
    agent = NetAgent(ExportedModel(emp_dir), 0, _FakeEndpoint(), round_deadline=0.01, hold=2)
    m = {j: np.full((2, 32), j, np.float32) for j in (1, 2)}
    assert sorted(agent._hold(0, 1, 10, {1, 2}, m)) == [1, 2]
    got = agent._hold(0, 1, 12, {1, 2}, {2: m[2] + 10})  # 1 lost: its message of step 10 is held
    assert float(got[1][0, 0]) == 1.0 and float(got[2][0, 0]) == 12.0
    assert sorted(agent._hold(0, 1, 13, {1, 2}, {})) == [2]  # 1's is 3 steps old now
    assert agent._hold(0, 0, 13, {1, 2}, {}) == {}  # another round holds its own messages
    with pytest.raises(DeployError, match="--hold must be >= 0"):
        NetAgent(ExportedModel(emp_dir), 0, _FakeEndpoint(), hold=-1)


def test_world_refuses_an_agent_of_another_export(emp_dir):
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", 3, "rc", 0.8, episodes=1, seed=0)
    ep = _FakeEndpoint()
    world = World(model, s, NetSettings(), ep, quiet=True)
    world._on_packet("swarm/hello/1", P.hello_packet(0, 1, "0" * 64, nonce=11), 0.0)
    world._on_packet("swarm/hello/2", P.hello_packet(0, 2, model.manifest["manifest_sha256"], nonce=12), 0.0)
    assert world.refused == {1} and world.heard == {2} and world.bound == {2: 12}
    # the refused instance is told why (it leaves with one line: swarm agent)
    ((key, data),) = ep.published
    h, reason, _ = P.decode_refuse(data)
    assert key == "refuse/1" and (h.sender, h.nonce, reason) == (1, 11, P.REFUSED_EXPORT)


class _QueuedEndpoint(_FakeEndpoint):
    """Hands out the given packets one per get(), then nothing."""

    def __init__(self, packets):
        super().__init__()
        self.queue = list(packets)

    def get(self, timeout):
        return self.queue.pop(0) if self.queue else None


def test_world_starts_once_every_agent_has_heard_every_other(emp_dir, capsys):
    """The start barrier: hellos alone are not enough; the world waits until each agent says it
    has heard the others' hellos (their routes to it exist), and names the gaps when it gives up."""
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", 3, "rc", 0.8, episodes=1, seed=0)
    sha = model.manifest["manifest_sha256"]
    heard = [(0, ()), (1, (0,)), (2, (0, 1)), (0, (1,)), (1, (0, 2)), (0, (1, 2))]
    packets = [(f"swarm/hello/{i}", P.hello_packet(0, i, sha, peers, i + 1), 0.0) for i, peers in heard]
    ep = _QueuedEndpoint(packets + [("swarm/hello/2", P.hello_packet(0, 2, sha, (0,), 3), 0.0)])
    world = World(model, s, NetSettings(start_timeout=5.0), ep, quiet=True)
    assert world.wait_for_agents({0, 1, 2}) == {0, 1, 2}
    assert len(ep.queue) == 1  # it returned at the sixth hello, the first at which all heard all
    # an agent that never hears agent 2: the world gives up at the timeout and says so
    ep = _QueuedEndpoint([(f"swarm/hello/{i}", P.hello_packet(0, i, sha, p, i + 1), 0.0) for i, p in heard[:3]])
    world = World(model, s, NetSettings(start_timeout=0.2), ep)
    assert world.wait_for_agents({0, 1, 2}) == {0, 1, 2}
    err = capsys.readouterr().err
    assert "agent 0 has not heard agents [1, 2]" in err and "agent 1 has not heard agents [2]" in err
    # every hello heard, but agent 1's subscription to its observations not routed yet: the world
    # waits for the route (a first OBS put before it would be dropped), and names it at the timeout
    ep = _QueuedEndpoint(packets)
    ep.unrouted = (1,)
    world = World(model, s, NetSettings(start_timeout=0.3), ep)
    assert world.wait_for_agents({0, 1, 2}) == {0, 1, 2}
    assert not ep.queue and "no route to the observations of agents [1] yet" in capsys.readouterr().err


def test_hello_packet_round_trip_and_refusals():
    h, sha, peers = P.decode_hello(P.hello_packet(0, 4, "a" * 64, {3, 1, 900}))
    assert (h.sender, sha, peers) == (4, "a" * 64, frozenset({1, 3, 900}))
    good = P.hello_packet(0, 4, "a" * 64, (1,))
    for bad in (good[:-1], good + b"\x00", good[: P.HEADER_BYTES + 64]):
        with pytest.raises(P.PacketError):
            P.decode_hello(bad)


# ----------------------------------------------------------------------------- the commands
def _swarm(*argv, timeout=120):
    return subprocess.run(
        [sys.executable, "-m", "swarm_cli", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env={**os.environ, "COLUMNS": "400"},  # tyro's error box wraps at the terminal width
    )


def test_world_refuses_an_export_that_does_not_fit_its_task(tmp_path):
    concat = _export(tmp_path, ModelConfig(hidden=16, rounds=1, entity_mode="concat", num_landmarks=2), "line", 3, 1)
    out = _swarm("world", "--export", concat, "--task", "coverage", "--agents", "4")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert lines[-1].startswith("swarm world: error:") and "line" in lines[-1] and "coverage" in lines[-1]
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["agent", "{d}", "--id", "-1"], "--id must be in 0..65535"),
        (["agent", "{d}", "--id", "0", "--connect", "127.0.0.1"], "not a Zenoh endpoint"),
        (["agent", "{d}", "--id", "0", "--drop", "2"], "--drop must be a probability"),
        (["agent", "{d}", "--id", "0", "--hold", "-1"], "--hold must be >= 0"),
        (["world", "--export", "{d}", "--spawn-agents", "--kill", "1@x"], "expected I@STEP"),
        (["world", "--export", "{d}", "--kill", "1@3"], "need --spawn-agents"),
        (["world", "--export", "{d}", "--spawn-agents", "--absent", "7"], "not in a team of 3"),
        (["world", "--export", "{d}", "--ns", "a b"], "--ns"),
    ],
)
def test_bad_command_lines_are_refused_in_one_line(emp_dir, argv, words):
    out = _swarm(*[a.format(d=emp_dir) for a in argv], timeout=60)
    assert out.returncode == 2, out.stderr
    assert words in out.stderr and "Traceback" not in out.stderr


def test_endpoints_are_checked():
    assert check_endpoint("tcp/127.0.0.1:7447", "--listen")
    with pytest.raises(TransportError, match="not a Zenoh endpoint"):
        check_endpoint("localhost", "--listen")
    with pytest.raises(DeployError):
        NetSettings(period=-1)


def test_manifest_states_the_integrator_contract(emp_dir):
    """The export says the control period, K, the graph, the units and the message schema; a
    manifest made before the contract existed still loads."""
    from deploy.manifest import seal, validate

    manifest = ExportedModel(emp_dir).manifest
    c = manifest["contract"]
    assert c["control_period_s"] == taichi_swarm.physics.DT == 0.1
    assert (c["rounds"], c["comm"], c["comm_radius"]) == (2, "rc", 0.8)
    assert c["message_schema_version"] == P.SCHEMA_VERSION
    assert "vx, vy" in c["observation"]["self_obs"] and "[B, 2, 32]" in c["message"]
    old = {k: v for k, v in manifest.items() if k not in ("contract", "manifest_sha256")}
    validate(seal(old))
    with pytest.raises(ValueError, match="contract"):
        seal({**old, "contract": {**c, "control_period_s": 0}})
