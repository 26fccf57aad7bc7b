"""The in-process fault table of docs/DEPLOY.md: policies under the faults the fault-trained ones
are judged on, with `swarm execute`'s executor (deploy.executor.run_episodes), 500 episodes per
cell at seed 4242, one JSON per policy under results/faults/.

    python tools/fault_table.py coverage-rc-m5 coverage-rc-m5-rounds   # run (or reuse) and print
    python tools/fault_table.py --hold 3 line-rc-m10                    # its agents holding lost messages
    python tools/fault_table.py --render                                # the table from the files

A policy is a zoo name or a policy.pt; a cell already in its file is not run again. With
``--hold N`` (``swarm execute --hold``) a lost message is replaced by the sender's last one heard
up to N steps old; the row is ``NAME hold N``. Hold acts on losses only, so its delay cell is
run without it (the policy's own, as in its plain row).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
OUT = os.path.join(ROOT, "results", "faults")
# cell -> ExecuteSettings' fault fields: the issue's targets are 30% bursty loss and one step late
CELLS = {
    "none": {},
    "drop 0.3": {"drop": 0.3},
    "bursty 0.3 (len 4)": {"burst_loss": 0.3, "burst_len": 4.0},
    "delay 1": {"delay": 1},
}


def measure(policy: str, episodes: int, seed: int, hold: int = 0) -> dict:
    from deploy.executor import ExportedModel, resolve_settings, run_episodes
    from deploy.export import export
    from taichi_swarm.files import atomic_write_json

    name = os.path.basename(os.path.dirname(os.path.dirname(policy))) if policy.endswith(".pt") else policy
    name += f" hold {hold}" if hold else ""
    path = os.path.join(OUT, f"{name.replace(' ', '-')}.json")
    data = {"policy": policy, "episodes": episodes, "seed": seed, "cells": {}, **({"hold": hold} if hold else {})}
    if os.path.exists(path):
        with open(path) as f:
            old = json.load(f)
        if (old["policy"], old["episodes"], old["seed"], old.get("hold", 0)) == (policy, episodes, seed, hold):
            data = old
    with tempfile.TemporaryDirectory() as tmp:
        for cell, faults in CELLS.items():
            if cell in data["cells"]:
                continue
            if not os.path.exists(os.path.join(tmp, "manifest.json")):
                export(policy, tmp)
            model = ExportedModel(tmp)
            held = {"hold": hold} if hold and "delay" not in faults else {}
            row = run_episodes(model, resolve_settings(model, episodes=episodes, seed=seed, **faults, **held))
            data["cells"][cell] = {k: row[k] for k in ("success_rate", "mean_length", "dist", "covered")}
            print(f"{name}: {cell}: S% {100 * row['success_rate']:.1f}", flush=True)
            os.makedirs(OUT, exist_ok=True)
            atomic_write_json(path, data)
    return data


def render() -> str:
    lines = ["| policy | " + " | ".join(CELLS) + " |", "|---|" + "---|" * len(CELLS)]
    for path in sorted(glob.glob(os.path.join(OUT, "*.json"))):
        with open(path) as f:
            data = json.load(f)
        cells = [data["cells"].get(c) for c in CELLS]
        base = cells[0]["success_rate"] if cells[0] else None
        shown = []
        for c in cells:
            if c is None:
                shown.append("-")
            elif c is cells[0] or base is None:
                shown.append(f"{100 * c['success_rate']:.1f}")
            else:
                shown.append(f"{100 * c['success_rate']:.1f} ({100 * (c['success_rate'] - base):+.1f})")
        name, hold = os.path.basename(path)[:-5], data.get("hold", 0)
        label = f"`{name.removesuffix(f'-hold-{hold}')}` hold {hold}" if hold else f"`{name}`"
        lines.append(f"| {label} | " + " | ".join(shown) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("policies", nargs="*", help="zoo names or policy.pt files")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=4242)
    parser.add_argument("--hold", type=int, default=0, help="the agents hold lost messages up to N steps (0: off)")
    parser.add_argument("--render", action="store_true", help="print the table from results/faults/ only")
    args = parser.parse_args(argv)
    if not args.render:
        from taichi_swarm import runtime

        runtime.init("cpu")
        for policy in args.policies:
            measure(policy, args.episodes, args.seed, args.hold)
    print(render())
    return 0


if __name__ == "__main__":
    sys.exit(main())
