"""The networked team's life cycle (deploy/net): who is agent i (a stray hello, a second agent
on a taken id, a world started again), the children a world spawns, the bounds on what is
buffered, and every size or time option refused in one line before anything is allocated.

The team tests share one team of three `swarm agent` processes on 127.0.0.1 and step it with
made-up observations (no simulator: the world's network side is what they exercise); each
wait has its own timeout, and every process a test starts is stopped by it.
"""

from __future__ import annotations

import secrets
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest

pytest.importorskip("zenoh")

from test_network import _FakeEndpoint, _free_port, emp_dir  # noqa: E402, F401 - emp_dir: the export fixture

import deploy.net.world as world_module  # noqa: E402
from deploy.executor import ExportedModel, resolve_settings  # noqa: E402
from deploy.net import agent as agent_module  # noqa: E402
from deploy.net import protocol as P  # noqa: E402
from deploy.net import transport  # noqa: E402
from deploy.net.agent import NetAgent  # noqa: E402
from deploy.net.transport import Endpoint, open_session  # noqa: E402
from deploy.net.world import AgentProcesses, NetSettings, SpawnError, World, error_line  # noqa: E402
from swarm_cli.net import AgentOptions, WorldOptions, agent_main, world_main  # noqa: E402
from swarm_cli.options import parse  # noqa: E402

M = 3


def _obs(B: int = 1) -> dict:
    """A made-up observation of a team of M in coverage (L = M landmarks), everyone hearing everyone."""
    rng = np.random.default_rng(0)
    return {
        "self": (0.1 * rng.standard_normal((B, M, 4))).astype(np.float32),
        "entities": rng.standard_normal((B, M, M, 2)).astype(np.float32),
        "adj": np.ones((B, M, M), bool),
    }


def _world(model, listen: str, ns: str, quiet=True) -> World:
    s = resolve_settings(model, "coverage", M, "uc", 1.0, episodes=1, seed=0)
    # the world steps as soon as every action is in; the deadline only bounds a test that fails
    net = NetSettings(period=0.0, round_deadline=0.5, action_deadline=5.0, start_timeout=60.0)
    return World(model, s, net, Endpoint(open_session("router", [listen], []), ns), quiet=quiet)


@dataclass
class Team:
    model: ExportedModel
    world: World
    procs: AgentProcesses
    listen: str
    ns: str


@pytest.fixture(scope="module")
def team(emp_dir):  # noqa: F811
    """Three agent processes and a world that has bound them all."""
    model = ExportedModel(emp_dir)
    listen, ns = f"tcp/127.0.0.1:{_free_port()}", f"test{secrets.token_hex(4)}"
    procs = AgentProcesses(emp_dir, M, listen, ns, round_deadline=0.5, idle_timeout=120)
    t = Team(model, _world(model, listen, ns), procs, listen, ns)
    try:
        for i in range(M):
            procs.start(i)
        t.world.watch = procs.check
        assert t.world.wait_for_agents(range(M)) == set(range(M))
        yield t
    finally:
        t.world.stop_agents()
        procs.stop(timeout=15)
        t.world.ep.close()


def _steps(world: World, n: int) -> None:
    for _ in range(n):
        world.decide(_obs())


# ----------------------------------------------------------------------------- identity
def test_a_stray_hello_does_not_silence_agent_1(team):
    """A hello for agent 1 of another export, and one of this export from another instance,
    sent from a session of their own mid-run: agent 1 keeps its binding and acts every step."""
    world = team.world
    _steps(world, 2)
    bound, missing = world.bound[1], world.reports[1].missing
    stray = Endpoint(open_session("peer", ["tcp/127.0.0.1:0"], [team.listen]), team.ns)
    try:
        refused = world.dropped["refused"]
        for _ in range(100):  # until the world has read both (each step reads what came)
            stray.publish(P.hello_packet(0, 1, "0" * 64, nonce=12345), "hello", 1)
            stray.publish(P.hello_packet(0, 1, world.sha, nonce=67890), "hello", 1)
            _steps(world, 1)
            if world.dropped["refused"] >= refused + 2:
                break
    finally:
        stray.close()
    assert world.dropped["refused"] >= refused + 2
    _steps(world, 3)
    assert world.bound[1] == bound and 1 not in world.refused
    assert world.reports[1].missing == missing  # not one of agent 1's actions was lost
    assert all(proc.poll() is None for proc in team.procs.procs.values())  # no one was told to leave


def test_a_second_agent_on_a_taken_id_is_refused_and_named(team, emp_dir, capsys):  # noqa: F811
    """A second `swarm agent --id 1` while the first is live: the world names id 1 in one line
    and refuses it; that process leaves with one error line naming --id 1; agent 1 acts on."""
    world = team.world
    world.quiet = False
    bound, missing = world.bound[1], world.reports[1].missing
    second = subprocess.Popen(
        [sys.executable, "-m", "swarm_cli", "agent", emp_dir, "--id", "1", "--connect", team.listen,
         "--ns", team.ns, "--idle-timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        for _ in range(600):  # (each step listens at least 0.1 s: a minute at most)
            if second.poll() is not None:
                break
            _steps(world, 1)
            world._sleep_listening(0.1)
        out, err = second.communicate(timeout=30)
    finally:
        if second.poll() is None:
            second.kill()
            second.wait(timeout=10)
        world.quiet = True
    assert second.returncode == 2, (out, err)
    lines = [line for line in err.strip().splitlines() if not line.startswith("[Taichi]")]
    assert len(lines) == 1 and lines[0].startswith("swarm agent: error:") and "--id 1" in lines[0], err
    said = [line for line in capsys.readouterr().err.splitlines() if "--id 1" in line]
    assert len(said) == 1 and said[0].startswith("swarm world:")
    _steps(world, 2)
    assert world.bound[1] == bound and world.reports[1].missing == missing


def test_a_world_started_again_hears_the_team_at_once(team):
    """The world's session goes away mid-run (as under kill -9) and a new world, with a new run
    id, opens on the same endpoint: the agents, already in a run, say hello again and the new
    world binds all three and steps with them."""
    team.world.ep.close()
    world = team.world = _world(team.model, team.listen, team.ns)
    world.watch = team.procs.check
    assert world.wait_for_agents(range(M)) == set(range(M))
    _steps(world, 3)
    assert [r.missing for r in world.reports] == [0, 0, 0]


def test_a_claim_on_a_bound_id_waits_for_evidence(emp_dir):  # noqa: F811
    """Another instance's hello for a bound id: refused once the bound one is heard after it
    (both live), bound in its place once the bound one has been silent for live_s (a restart)."""
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", M, "uc", 1.0, episodes=1, seed=0)
    ep = _FakeEndpoint()
    world = World(model, s, NetSettings(), ep, quiet=True)
    sha = world.sha

    def hello(nonce, t):
        world._on_packet("swarm/hello/1", P.hello_packet(0, 1, sha, nonce=nonce), t)

    hello(11, 0.0)
    hello(22, 1.0)  # the bound one may have just died: no verdict yet
    assert world.bound == {1: 11} and not ep.published
    hello(11, 1.5)  # it has not
    hello(22, 2.0)
    assert world.bound == {1: 11} and world.duplicates == {1}
    ((key, data),) = ep.published
    h, reason, _ = P.decode_refuse(data)
    assert key == "refuse/1" and (h.nonce, reason) == (22, P.REFUSED_ID)
    hello(33, 3.0)  # a restart: 11 falls silent, 33 keeps saying hello
    hello(33, 1.5 + world.live_s + 0.1)
    assert world.bound == {1: 33} and len(ep.published) == 1


# ----------------------------------------------------------------------------- spawned agents
_DIE = "import sys; print('[Taichi] version'); print('swarm agent: error: --fault-seed must be >= 0, got -1', file=sys.stderr); sys.exit(2)"  # noqa: E501


def test_a_spawned_team_that_dies_fails_the_world_naming_why(emp_dir, monkeypatch, capsys):  # noqa: F811
    """Every agent the world spawns dies at start: `swarm world` does not wait out its start
    timeout and report a result, it exits nonzero with one line naming the first child's error."""

    class Dying(AgentProcesses):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs, command=[sys.executable, "-c", _DIE])

    monkeypatch.setattr(world_module, "AgentProcesses", Dying)
    listen = f"tcp/127.0.0.1:{_free_port()}"
    status = world_main(["--export", emp_dir, "--spawn-agents", "--listen", listen, "--ns", "dying"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status != 0
    assert [line for line in err if "error" in line] == [err[-1]]
    assert err[-1].startswith("swarm world: error: agent 0 exited with status 2") and "--fault-seed" in err[-1]


def test_error_line_takes_the_reason():
    assert error_line("[Taichi] x\nswarm agent: error: --id taken\nmore") == "swarm agent: error: --id taken"
    assert error_line("Traceback (most recent call last):\n  File x\nKeyError: 'a'\n") == "KeyError: 'a'"
    assert error_line("") == "(it wrote nothing)"


def test_world_watch_stops_the_wait_at_a_dead_child(emp_dir):  # noqa: F811
    model = ExportedModel(emp_dir)
    s = resolve_settings(model, "coverage", M, "uc", 1.0, episodes=1, seed=0)
    world = World(model, s, NetSettings(start_timeout=60.0), _FakeEndpoint(), quiet=True)
    procs = AgentProcesses(emp_dir, M, "tcp/127.0.0.1:1", "x", 0.03, command=[sys.executable, "-c", _DIE])
    try:
        procs.start(1)
        world.watch = procs.check
        with pytest.raises(SpawnError, match="agent 1 exited with status 2: swarm agent: error: --fault-seed"):
            world.wait_for_agents({1})
    finally:
        procs.stop(timeout=10)


# ----------------------------------------------------------------------------- bounded buffers
def test_messages_far_ahead_or_before_a_run_are_bounded(emp_dir, monkeypatch):  # noqa: F811
    """30,000 messages for steps far ahead are dropped and counted, none kept; messages before
    any observation are kept up to EARLY_KEPT, the oldest going first."""
    agent = NetAgent(ExportedModel(emp_dir), 0, _FakeEndpoint(), round_deadline=0.01, quiet=True)
    agent.run, agent.step, agent.B, agent.M = 5, 3, 1, M
    msg = np.zeros((1, 2, 32), np.float32)
    for step in range(10, 30_010):
        agent._on_packet("swarm/msg/1", P.msg_packet(5, step, 0, 1, msg), 0.0)
    assert agent.stats["overflow"] == 30_000 and not agent.box
    agent._on_packet("swarm/msg/1", P.msg_packet(5, 3 + agent_module.STEPS_AHEAD, 0, 1, msg), 0.0)
    assert agent.box  # within the window: kept
    monkeypatch.setattr(agent_module, "EARLY_KEPT", 10)
    for step in range(50):
        agent._on_packet("swarm/msg/2", P.msg_packet(6, step, 0, 2, msg), 0.0)  # a run not yet observed
    assert len(agent._early) == 10 and agent._early[0][0].step == 40
    assert agent.stats["overflow"] == 30_040


def test_the_inbox_is_bounded(monkeypatch):
    monkeypatch.setattr(transport, "INBOX_PACKETS", 5)
    ep = Endpoint(None, "swarm")
    for _ in range(8):
        ep._arrive("swarm/msg/1", b"x" * 10)
    assert ep.inbox.qsize() == 5 and ep.overflow == 3
    monkeypatch.setattr(transport, "INBOX_BYTES", 60)
    while ep.get(0) is not None:
        pass
    ep._arrive("swarm/msg/1", b"x" * 50)
    ep._arrive("swarm/msg/1", b"x" * 50)  # 100 bytes queued would pass the bound
    assert ep.inbox.qsize() == 1 and ep.overflow == 4


# ----------------------------------------------------------------------------- refused options
@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["D", "--id", "65536"], "--id"),
        (["D", "--id", "0", "--threads", "100000000"], "--threads"),
        (["D", "--id", "0", "--slow-ms", "inf"], "--slow-ms"),
        (["D", "--id", "0", "--slow-ms", "nan"], "--slow-ms"),
        (["D", "--id", "0", "--round-deadline", "inf"], "--round-deadline"),
        (["D", "--id", "0", "--round-deadline", "1e8"], "--round-deadline"),
        (["D", "--id", "0", "--fault-seed", "-1"], "--fault-seed"),
        (["D", "--id", "0", "--latency-ms", "1e12"], "--latency-ms"),
    ],
)
def test_agent_sizes_and_times_are_refused_in_one_line(argv, option, capsys):
    with pytest.raises(SystemExit) as info:
        parse(AgentOptions, argv, "swarm agent")
    err = capsys.readouterr().err.strip()
    assert info.value.code == 2 and len(err.splitlines()) == 1 and option in err, err


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["--agents", "100000000"], "--agents"),
        (["--agents", "5000", "--episodes", "100"], "--agents"),  # B x M x M
        (["--episodes", "100000000"], "--episodes"),
        (["--seed", "-1"], "--seed"),
        (["--period", "1e12"], "--period"),
        (["--period", "1e8"], "--period"),
        (["--round-deadline", "1e12"], "--round-deadline"),
        (["--action-deadline", "1e12"], "--action-deadline"),
        (["--start-timeout", "inf"], "--start-timeout"),
        (["--spawn-agents", "--slow", "0:inf"], "--slow"),
        (["--spawn-agents", "--absent", "-1"], "--absent"),
        (["--spawn-agents", "--kill", "0@3+inf"], "--kill"),
        (["--spawn-agents", "--fault-seed", "-1"], "--fault-seed"),
    ],
)
def test_world_sizes_and_times_are_refused_in_one_line(argv, option, capsys):
    with pytest.raises(SystemExit) as info:
        parse(WorldOptions, ["--export", "D", *argv], "swarm world")
    err = capsys.readouterr().err.strip()
    assert info.value.code == 2 and len(err.splitlines()) == 1 and option in err, err


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["--spawn-agents", "--late-round", "2"], "--late-round"),  # K = 2: rounds 0 and 1
        (["--spawn-agents", "--kill", "0@100000"], "--kill"),  # past the episode
    ],
)
def test_world_options_that_would_do_nothing_are_refused(emp_dir, argv, option, capsys):  # noqa: F811
    status = world_main(["--export", emp_dir, "--listen", f"tcp/127.0.0.1:{_free_port()}", *argv])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1 and option in err, err


def test_agent_late_round_past_its_rounds_is_refused(emp_dir, capsys):  # noqa: F811
    status = agent_main([emp_dir, "--id", "0", "--late-round", "100000000", "--connect", "tcp/127.0.0.1:1"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1 and "--late-round" in err, err
