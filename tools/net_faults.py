"""The fault table of a team of agent processes (``swarm world --spawn-agents``), beside the
in-process executor (``swarm execute``) at the same drop rate.

    python tools/net_faults.py --export runs/net/coverage-rc-m5 --episodes 20 --out runs/net/faults-m5.json
    python tools/net_faults.py --export runs/net/line-rc-m10 --hold 3 --cells none "bursty 0.3 (len 4)"
    python tools/net_faults.py --plot docs/media/net-faults.png "M = 5=runs/net/faults-m5.json"

Each cell starts the M agents as `swarm agent` processes on 127.0.0.1 with one fault, runs
the episodes side by side at the control period, and reports S% / T with the agents' decision
latency (p50 / p99 over agents and steps), messages and bytes sent per second per agent, CPU
per agent process (fraction of one core) and the actions that missed their deadline. With
``--hold N`` the agents (``swarm agent --hold``) and the in-process reference hold lost
messages up to N steps.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from deploy.executor import ExportedModel, resolve_settings, run_episodes  # noqa: E402
from deploy.net.faults import FaultSpec  # noqa: E402
from deploy.net.transport import Endpoint, open_session  # noqa: E402
from deploy.net.world import AgentProcesses, NetSettings, World  # noqa: E402

# name -> (fault spec kwargs, launcher faults {"kill": (agent, step, restart_s), "absent": agent, "slow": (agent, ms)},
#          the in-process executor's faults for the reference column or None)
CELLS = {
    "none": ({}, {}, {}),
    "drop 0.1": ({"drop": 0.1}, {}, {"drop": 0.1}),
    "drop 0.3": ({"drop": 0.3}, {}, {"drop": 0.3}),
    "bursty 0.3 (len 4)": ({"burst_loss": 0.3, "burst_len": 4.0}, {}, {"burst_loss": 0.3, "burst_len": 4.0}),
    "latency 10 ms +- 5": ({"latency_ms": 10.0, "jitter_ms": 5.0}, {}, None),
    "latency 25 ms +- 10": ({"latency_ms": 25.0, "jitter_ms": 10.0}, {}, None),
    "late round 0": ({"late_round": 0}, {}, None),
    "reorder 0.3": ({"reorder": 0.3}, {}, None),
    "slow agent (+60 ms)": ({}, {"slow": (1, 60.0)}, None),
    "killed at 10, back 1 s later": ({}, {"kill": (1, 10, 1.0)}, None),
    "one never starts": ({}, {"absent": 1}, None),
}


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_cell(export_dir, settings, net, fault_kwargs, launcher, seed, hold=0) -> dict:
    model = ExportedModel(export_dir)
    port = _port()
    endpoint = Endpoint(open_session("router", [f"tcp/127.0.0.1:{port}"], []), f"faults{port}")
    world = World(model, settings, net, endpoint, quiet=True)
    spec = FaultSpec(**fault_kwargs, seed=seed)
    slow = dict([launcher["slow"]]) if "slow" in launcher else None
    procs = AgentProcesses(
        export_dir, settings.agents, f"tcp/127.0.0.1:{port}", endpoint.ns, net.round_deadline, spec, slow, hold=hold
    )
    present = [i for i in range(settings.agents) if i != launcher.get("absent")]
    restart = []

    def hook(step):
        if "kill" in launcher and step == launcher["kill"][1]:
            procs.kill(launcher["kill"][0])
            restart.append(time.monotonic() + launcher["kill"][2])
        if restart and time.monotonic() >= restart[0]:
            restart.pop()
            procs.start(launcher["kill"][0])

    try:
        for i in present:
            procs.start(i)
        world.step_hook = hook
        world.wait_for_agents(present)
        row = world.run_episodes()
    finally:
        world.stop_agents()
        procs.stop(timeout=15)
        endpoint.close()
    reps = [r for r in row["agents_report"] if r.get("msgs_per_s") is not None]
    dec = np.concatenate([np.asarray(r.decision_s) for r in world.reports if r.decision_s]) * 1e3
    return {
        "success": row["success_rate"],
        "T": row["mean_length"],
        "steps": row["steps"],
        "wall_s": row["wall_s"],
        "decision_ms_p50": float(np.percentile(dec, 50)),
        "decision_ms_p99": float(np.percentile(dec, 99)),
        "msgs_per_s": float(np.mean([r["msgs_per_s"] for r in reps])),
        "kbytes_per_s": float(np.mean([r["bytes_per_s"] for r in reps])) / 1e3,
        "cpu_per_agent": float(np.mean([r["cpu_frac"] for r in reps])),
        "missing_actions": row["missing_actions"],
        "missed_messages": int(sum(r["missed"] for r in reps)),
        "late_messages": int(sum(r["late"] for r in reps)),
        "row": row,
    }


def markdown(rows: dict, M: int, episodes: int) -> str:
    head = (
        f"| fault (M = {M}, {episodes} episodes) | S% processes | S% in-process | T | decision p50 / p99 ms "
        "| msg/s per agent | kB/s per agent | CPU per agent | missed actions |"
    )
    lines = [head, "|" + "---|" * 9]
    for name, r in rows.items():
        ref = "-" if r["executor"] is None else f"{100 * r['executor']:.0f}"
        lines.append(
            f"| {name} | {100 * r['success']:.0f} | {ref} | {r['T']:.1f} | {r['decision_ms_p50']:.1f} / "
            f"{r['decision_ms_p99']:.1f} | {r['msgs_per_s']:.0f} | {r['kbytes_per_s']:.1f} | "
            f"{100 * r['cpu_per_agent']:.0f}% | {r['missing_actions']} |"
        )
    return "\n".join(lines)


def plot(tables: list[tuple[str, dict]], path: str) -> None:
    """S% per fault, a bar per table (e.g. M = 5 and M = 10), the in-process executor's as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(n for _, rows in tables for n in rows))
    fig, ax = plt.subplots(figsize=(9, 3.6))
    width = 0.8 / len(tables)
    for k, (label, rows) in enumerate(tables):
        x = [i + (k - (len(tables) - 1) / 2) * width for i, n in enumerate(names) if n in rows]
        ys = [100 * rows[n]["success"] for n in names if n in rows]
        ax.bar(x, ys, width, label=f"{label}: processes")
        present = [n for n in names if n in rows]
        ref = [
            (xi, 100 * rows[n]["executor"]) for xi, n in zip(x, present, strict=True) if rows[n]["executor"] is not None
        ]
        if ref:
            label_ref = f"{label}: in-process"
            ax.plot(*zip(*ref, strict=True), "k_", markersize=14, mew=2, label=label_ref)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("S%")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--export", help="directory written by `swarm export`")
    p.add_argument("--agents", type=int, default=None, help="team size M (default: the manifest's)")
    p.add_argument("--episodes", type=int, default=20, help="episodes per cell, side by side")
    p.add_argument("--seed", type=int, default=4242, help="seed of the episodes and of the faults")
    p.add_argument("--period", type=float, default=0.1, help="control period, s")
    p.add_argument("--round-deadline", type=float, default=0.03, help="communication round deadline, s")
    p.add_argument("--hold", type=int, default=0, help="the agents hold lost messages up to N steps (0: off)")
    p.add_argument("--cells", nargs="+", default=None, help=f"a subset of the cells: {', '.join(CELLS)}")
    p.add_argument("--out", default=None, help="write the rows to this JSON file")
    p.add_argument(
        "--plot", nargs="+", default=None, metavar="ARG", help="draw instead of running: OUT.png LABEL=ROWS.json ..."
    )
    args = p.parse_args(argv)
    if args.plot:
        tables = []
        for item in args.plot[1:]:
            label, _, path = item.rpartition("=")
            with open(path) as f:
                tables.append((label, json.load(f)["rows"]))
        plot(tables, args.plot[0])
        print(f"wrote {args.plot[0]}")
        return 0
    if not args.export:
        p.error("--export DIR is needed (or --plot)")
    cells = args.cells or list(CELLS)
    unknown = [c for c in cells if c not in CELLS]
    if unknown:
        p.error(f"unknown cells {unknown}; choose from {list(CELLS)}")
    model = ExportedModel(args.export)
    s = resolve_settings(model, None, args.agents, None, None, episodes=args.episodes, seed=args.seed)
    net = NetSettings(period=args.period, round_deadline=args.round_deadline)
    rows = {}
    for name in cells:
        fault_kwargs, launcher, reference = CELLS[name]
        t0 = time.perf_counter()
        r = run_cell(args.export, s, net, fault_kwargs, launcher, args.seed, args.hold)
        r["executor"] = None
        if reference is not None:
            held = {"hold": args.hold} if args.hold else {}
            ref = resolve_settings(
                model, None, args.agents, None, None, episodes=args.episodes, seed=args.seed, **reference, **held
            )
            r["executor"] = run_episodes(model, ref)["success_rate"]
        rows[name] = r
        print(f"{name}: S% {100 * r['success']:.0f} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    print(markdown(rows, s.agents, s.episodes))
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"export": args.export, "settings": vars(args), "rows": rows}, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
