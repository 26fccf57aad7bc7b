"""Wall-clock of one small table through `swarm reproduce` with 1 and 2 (or more) Ray
workers, each into a fresh root, side by side in one run; prints the ratios.

    python tools/bench_reproduce.py --spec quick --workers 1 2

Run it on an otherwise idle machine: the workers share its cores with anything else.
The per-cell training times it prints are what docs/BENCHMARKS.md scales to N machines.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spec", default="quick")
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--keep", default=None, help="keep the roots under this directory (default: a temp dir)")
    args = ap.parse_args()
    base = args.keep or tempfile.mkdtemp(prefix="bench-reproduce-")
    rows = []
    for w in args.workers:
        root = os.path.join(base, f"workers-{w}")
        cmd = [sys.executable, "-m", "swarm_cli", "reproduce", "--spec", args.spec, "--root", root]
        start = time.perf_counter()
        proc = subprocess.run([*cmd, "--workers", str(w), "--progress-every", "600"], capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            print(proc.stdout[-3000:], proc.stderr[-3000:], file=sys.stderr)
            return 1
        cells = []
        for cell in sorted(os.listdir(root)):
            path = os.path.join(root, cell, "s0", "result.json")
            if os.path.exists(path):
                with open(path) as f:
                    r = json.load(f)
                cells.append((cell, r["wall_time_last_attempt"], sum(x.get("wall_time", 0.0) for x in r["rows"])))
        rows.append((w, wall, cells))
        print(f"{w} worker(s): {wall / 60:.2f} min for {len(cells)} cells", flush=True)
    print(f"\n{'workers':>7} {'wall (min)':>11} {'speed-up':>9} {'sum of cell times (min)':>24}")
    for w, wall, cells in rows:
        cell_sum = sum(c[1] for c in cells) / 60
        print(f"{w:>7} {wall / 60:>11.2f} {rows[0][1] / wall:>8.2f}x {cell_sum:>24.2f}")
    print("\nper cell (the last run): cell, whole task incl. final evaluation (s), training (s)")
    for cell, task_s, train_s in rows[-1][2]:
        print(f"  {cell:<24} {task_s:>7.1f} {train_s:>7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
