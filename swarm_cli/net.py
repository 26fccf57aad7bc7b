"""``swarm agent`` and ``swarm world``: the team as processes over Zenoh (deploy/net/).

    swarm agent DIR --id 3 [--connect tcp/HOST:7447]         one agent, as on a robot
    swarm world --export DIR [--spawn-agents] [faults...]    the simulator; prints S% / T like `swarm execute`

Neither imports torch.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Annotated

import tyro

from deploy.net.faults import FaultSpec
from deploy.net.limits import check_agent_id, check_seconds, check_team
from swarm_cli.options import (
    Default,
    OptionError,
    OutputOptions,
    Positional,
    SettingOptions,
    at_least,
    fail,
    parse,
)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(kw_only=True)
class FaultOptions:
    faults: Annotated[FaultSpec, tyro.conf.OmitArgPrefixes] = FaultSpec()
    """Faults injected at each agent's radio (between processes); all off by default."""


@dataclass(kw_only=True)
class AgentOptions(FaultOptions):
    """Run one agent of an exported policy as its own process: it subscribes to its observation,
    exchanges the K rounds of messages with whoever it hears (a radio policy first its R auction
    rounds) and publishes its action."""

    directory: Annotated[str, Positional, tyro.conf.arg(metavar="DIRECTORY")]
    """directory written by `swarm export`"""
    id: int
    """this agent's index in the team (0..M-1)"""
    connect: str = DEFAULT_ENDPOINT
    """the world's Zenoh endpoint"""
    listen: str = "tcp/127.0.0.1:0"
    """this agent's own endpoint, where the other agents reach it (port 0: any free port)"""
    ns: str = "swarm"
    """key namespace of the team (one per team on a shared network)"""
    round_deadline: float = 0.03
    """seconds each communication round waits for the neighbours' messages"""
    slow_ms: float = 0.0
    """sleep this long before each decision (a slow agent)"""
    idle_timeout: Annotated[float | None, Default("never")] = None
    """leave after this many seconds without an observation"""
    threads: int = 1
    """onnxruntime intra-op threads per session"""
    hold: int = 0
    """a neighbour's lost message is replaced by its last one heard, if at most N steps old (0: off)"""
    quiet: bool = False
    """no line on stderr for dropped packets (they are still counted)"""

    def __post_init__(self):
        check_agent_id(self.id)
        at_least(self.threads, 1, "threads")
        cores = os.cpu_count() or 1
        if self.threads > cores:  # (before onnxruntime allocates them; more than the cores only wait on each other)
            raise OptionError(f"--threads must be <= {cores}, this machine's cores, got {self.threads}")
        at_least(self.hold, 0, "hold")
        check_seconds(self.round_deadline, "--round-deadline")
        check_seconds(self.slow_ms, "--slow-ms", zero_ok=True, scale=1e3, unit="ms")
        if self.idle_timeout is not None and not self.idle_timeout > 0:
            raise OptionError(f"--idle-timeout must be > 0 seconds, got {self.idle_timeout}")


@dataclass(kw_only=True)
class WorldOptions(SettingOptions, OutputOptions, FaultOptions):
    """Run the simulator as the world of a team of agent processes: publishes each agent's
    observation, waits for the actions until a deadline (a missing one is a no-op), steps at a
    fixed control period; prints S%, T, DIST like `swarm execute` and the network's numbers."""

    export: str
    """directory written by `swarm export` (the policy the agents run: checked against the task)"""
    agents: Annotated[int | None, Default("the manifest's")] = None
    """team size M"""
    episodes: int = 10
    """episodes, run side by side (B parallel worlds, as `swarm execute` does)"""
    seed: int = 777
    """seed of the episodes (777, as `swarm execute` and `swarm eval`: one training never uses)"""
    listen: str = DEFAULT_ENDPOINT
    """this world's Zenoh endpoint (the agents connect to it)"""
    ns: str = "swarm"
    """key namespace of the team"""
    period: float = 0.1
    """control period in seconds (0: step as soon as every action is in)"""
    round_deadline: float = 0.03
    """communication round deadline given to the agents it spawns, s"""
    action_deadline: Annotated[float | None, Default("K round deadlines + 0.1 s")] = None
    """seconds after publishing the observations that a missing action becomes a no-op"""
    start_timeout: float = 60.0
    """seconds to wait for the agents before the first step"""
    spawn_agents: bool = False
    """start the M agent processes on this machine too (and stop them at the end)"""
    absent: tuple[int, ...] | None = None
    """with --spawn-agents: agents never started"""
    kill: tuple[str, ...] | None = None
    """with --spawn-agents: I@STEP kills agent I at that step, I@STEP+S restarts it S seconds later"""
    slow: tuple[str, ...] | None = None
    """with --spawn-agents: I:MS makes agent I sleep MS ms before each decision"""
    agent_logs: str | None = None
    """with --spawn-agents: write each agent's output to DIR/agent-I.log"""
    hold: int = 0
    """with --spawn-agents: the agents' --hold (a lost message replaced by the last one heard, up to N steps old)"""
    json: str | None = None
    """also write the result row to this JSON file"""

    def __post_init__(self):
        SettingOptions.__post_init__(self)
        OutputOptions.__post_init__(self)
        check_team(self.agents, self.episodes)  # (again once the manifest gives an unset --agents)
        at_least(self.seed, 0, "seed")
        at_least(self.hold, 0, "hold")
        check_seconds(self.period, "--period", zero_ok=True)
        check_seconds(self.round_deadline, "--round-deadline")
        if self.action_deadline is not None:
            check_seconds(self.action_deadline, "--action-deadline")
        check_seconds(self.start_timeout, "--start-timeout")
        for i in self.absent or ():
            check_agent_id(i, "--absent")
        if not self.spawn_agents and (self.absent or self.kill or self.slow or self.agent_logs or self.hold):
            raise OptionError("--absent, --kill, --slow, --agent-logs and --hold need --spawn-agents")
        self.kill_plan = [_kill(k) for k in self.kill or ()]
        self.slow_plan = dict(_slow(x) for x in self.slow or ())


def _kill(text: str) -> tuple[int, int, float | None]:
    try:
        who, when = text.split("@")
        step, _, restart = when.partition("+")
        out = int(who), int(step), (float(restart) if restart else None)
    except ValueError:
        raise OptionError(f"--kill {text!r}: expected I@STEP or I@STEP+SECONDS (e.g. 2@10+1.5)") from None
    if out[0] < 0 or out[1] < 0 or (out[2] is not None and not out[2] >= 0):
        raise OptionError(f"--kill {text!r}: agent, step and seconds must be >= 0")
    check_agent_id(out[0], f"--kill {text!r}: the agent")
    if out[2] is not None:
        check_seconds(out[2], f"--kill {text!r}: the restart delay", zero_ok=True)
    return out


def _slow(text: str) -> tuple[int, float]:
    try:
        who, ms = text.split(":")
        out = int(who), float(ms)
    except ValueError:
        raise OptionError(f"--slow {text!r}: expected I:MS (e.g. 3:50)") from None
    if out[0] < 0 or not out[1] >= 0:
        raise OptionError(f"--slow {text!r}: agent and milliseconds must be >= 0")
    check_agent_id(out[0], f"--slow {text!r}: the agent")
    check_seconds(out[1], f"--slow {text!r}: the delay", zero_ok=True, scale=1e3, unit="ms")
    return out


# ----------------------------------------------------------------------------- agent
def agent_main(argv: list[str]) -> int:
    args = parse(AgentOptions, argv, "swarm agent")
    from deploy.net.agent import NetAgent, check_faults
    from deploy.net.transport import Endpoint, TransportError, open_session
    from deploy.policy import DeployError, ExportedModel

    try:
        spec = args.faults
        model = ExportedModel(args.directory)
        check_faults(spec, model)
        session = open_session("peer", [args.listen], [args.connect])
        endpoint = Endpoint(session, args.ns)
    except (DeployError, TransportError, ValueError) as exc:
        return fail("swarm agent", exc)
    try:
        agent = NetAgent(
            model, args.id, endpoint, args.round_deadline, spec, args.slow_ms, args.threads, args.quiet, args.hold
        )
        how = agent.serve(idle_timeout=args.idle_timeout)
    except (DeployError, ValueError) as exc:
        return fail("swarm agent", exc)
    finally:
        endpoint.close()
    if agent.refused is not None:  # (the world takes another instance as this id, or runs another export)
        return fail("swarm agent", agent.refused)
    if not args.quiet:
        s = agent.counters()
        print(
            f"swarm agent {args.id}: {how} after {agent.steps} steps; dropped late {int(s['late'])}, "
            f"malformed {int(s['malformed'])}, foreign {int(s['foreign'])}, version {int(s['version'])}, "
            f"overflow {int(s['overflow'])}; "
            f"missed {int(s['missed'])} neighbour messages"
        )
    return 0


# ----------------------------------------------------------------------------- world
def world_main(argv: list[str]) -> int:
    from deploy.video import open_recorders

    args = parse(WorldOptions, argv, "swarm world")
    from deploy.executor import DeployError, ExportedModel, make_env, resolve_settings
    from deploy.net.agent import check_faults, radio_settings
    from deploy.net.transport import Endpoint, TransportError, check_endpoint, check_namespace, open_session
    from deploy.net.world import AgentProcesses, NetSettings, SpawnError, World, format_net
    from taichi_swarm.tasks.base import COMMON_PARAMS

    try:
        args.check_outputs()
        check_endpoint(args.listen, "--listen")
        check_namespace(args.ns)
        spec = args.faults
        model = ExportedModel(args.export)
        radio_settings(model)  # (a radio export without its auction's rules is refused here, in one line)
        s = resolve_settings(
            model, args.task, args.agents, args.comm, args.comm_radius, episodes=args.episodes, seed=args.seed
        )
        check_team(s.agents, s.episodes)  # (--agents unset: the manifest's)
        net = NetSettings(args.period, args.round_deadline, args.action_deadline, args.start_timeout)
        for i in [*(args.absent or ()), *(k[0] for k in args.kill_plan), *args.slow_plan]:
            if i >= s.agents:
                raise OptionError(f"agent {i} named by --absent/--kill/--slow is not in a team of {s.agents}")
        steps = COMMON_PARAMS["max_steps"]  # (the world runs the tasks' own episode length)
        for who, at, _ in args.kill_plan:
            if at >= steps:
                raise OptionError(
                    f"--kill {who}@{at}: the episodes end at step {steps - 1}, the kill would never happen"
                )
        if spec.any and not args.spawn_agents:
            raise OptionError("fault options go to the agents: give them to each `swarm agent`, or use --spawn-agents")
        if args.spawn_agents:
            check_faults(spec, model)  # (each agent would refuse it at start)
        env = make_env(model, s)  # (what the simulator refuses, before any agent starts)
        env.warm_up()  # its kernels compiled before the agents start: 50 of them starve a compile for minutes
        recorder = open_recorders(args, s.task, s.episodes, s.agents, s.comm, s.comm_radius)
        session = open_session("router", [args.listen], [])
    except (DeployError, TransportError, ValueError, OSError) as exc:
        return fail("swarm world", exc)
    endpoint = Endpoint(session, args.ns)
    world = World(model, s, net, endpoint)
    procs = None
    failed = None
    try:
        present = set(range(s.agents)) - set(args.absent or ())
        if args.spawn_agents:
            procs = AgentProcesses(
                args.export,
                s.agents,
                args.listen,
                args.ns,
                args.round_deadline,
                spec,
                args.slow_plan,
                args.agent_logs,
                hold=args.hold,
                # no observation before the start barrier, the first step's kernels and a period: not idle yet
                idle_timeout=60 + net.start_timeout + 2 * (net.period + net.deadline(world.rounds)),
            )
            for i in sorted(present):
                procs.start(i)
            world.step_hook = _kill_hook(procs, args.kill_plan, world)
            world.watch = procs.check  # an agent that leaves by itself ends the run, naming why
        world.wait_for_agents(present)
        row = world.run_episodes(recorder, env)
        if procs is not None:
            memory = {"agent_rss_mb": ("status", "VmHWM:"), "agent_pss_mb": ("smaps_rollup", "Pss:")}
            for key, (file, line) in memory.items():
                row[key] = {str(i): mb for i, mb in sorted(procs.memory_mb(file, line).items())}
    except SpawnError as exc:
        failed = exc
        if recorder is not None:
            recorder.close(ok=False)
    except BaseException:
        if recorder is not None:
            recorder.close(ok=False)
        raise
    finally:
        world.stop_agents()
        if procs is not None:
            procs.stop()
        endpoint.close()
    if failed is not None:
        print(f"swarm world: error: {failed}", file=sys.stderr)
        return 1  # (the command line was sound: the run failed)
    if recorder is not None:
        recorder.close()
        recorder.report()
    print(format_net(row))
    if args.json:
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(args.json, {"export": args.export, "faults": spec.to_dict(), "row": row})
    return 0


def _kill_hook(procs, plan, world):
    """The step hook that kills (and restarts) agents as ``--kill`` says."""
    restarts: list[tuple[float, int]] = []

    def hook(step: int) -> None:
        for who, at, restart in plan:
            if step == at:
                procs.kill(who)
                world.release(who)  # (its restart is another instance, to be bound at its hello)
                if restart is not None:
                    restarts.append((time.monotonic() + restart, who))
        for due in [r for r in restarts if r[0] <= time.monotonic()]:
            restarts.remove(due)
            procs.start(due[1])

    return hook
