"""Zero-shot curves over team size: the `swarm zero-shot --json` files of results/swarm/ (and
the hand-written controllers' reference-*.json of tools/coverage_reference.py, dashed) as one
plot (log M axis: S% and the fraction of targets covered, per task) and as the markdown table
docs/SWARM.md shows.

    python tools/swarm_curves.py                       # table to stdout, plot to docs/media/
    python tools/swarm_curves.py results/swarm/*.json --out /tmp/curves.png
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
DEFAULT_GLOBS = [os.path.join(ROOT, "results", "swarm", f"{kind}-*.json") for kind in ("zero-shot", "reference")]
DEFAULT_OUT = os.path.join(ROOT, "docs", "media", "swarm-zero-shot.png")


def read(path: str) -> dict:
    """One zero-shot file -> {"name", "rows": [{"agents", "success_rate", "covered", ...}]}."""
    try:
        with open(path) as f:
            data = json.load(f)
        rows = sorted(data["results"], key=lambda r: r["agents"])
        for r in rows:
            r["agents"], r["success_rate"], r["covered"]  # noqa: B018 (the keys the curves need)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"swarm_curves: {path} is not a `swarm zero-shot --json` file ({exc!r})") from None
    name = data.get("checkpoint", os.path.basename(path))
    # a spec cell's policy (results/reproduce-<spec>/<cell>/s<seed>/stage-m<M>/policy.pt) by its cell id
    name = re.sub(r"^(?:.*/)?results/reproduce-[\w-]+/([\w-]+)/s\d+/.*$", r"\1", name)
    own = (data.get("trained_swarm") or {}).get("landmark_neighbours")
    sensed = {r.get("landmark_neighbours") for r in rows}
    if own is not None and sensed != {own}:  # the policy run on other landmark lists than its own
        name += " (KL = " + ", ".join(str(k) for k in sorted(sensed, key=str)) + ")"
    # covered by the maximum matching within the threshold
    if any(r.get("assignment") in ("nearest", "free") for r in rows):
        name += " (max matching)"
    return {"name": name, "rows": rows, "reference": "controller" in data}


def table(curves: list[dict]) -> str:
    sizes = sorted({r["agents"] for c in curves for r in c["rows"]})
    lines = ["| policy | | " + " | ".join(f"M = {m}" for m in sizes) + " |", "|---|---|" + "---|" * len(sizes)]
    for c in curves:
        by_m = {r["agents"]: r for r in c["rows"]}
        for key, label in (("success_rate", "S%"), ("covered", "covered")):
            cells = []
            for m in sizes:
                r = by_m.get(m)
                v = None if r is None else r[key]
                cells.append("-" if v is None else (f"{100 * v:.1f}" if key == "success_rate" else f"{v:.3f}"))
            lines.append(f"| `{c['name']}` | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(curves: list[dict], out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 3.8))
    for c in curves:
        m = [r["agents"] for r in c["rows"]]
        style = "s--" if c.get("reference") else "o-"
        axes[0].plot(m, [100 * r["success_rate"] for r in c["rows"]], style, label=c["name"])
        covered = [float("nan") if r["covered"] is None else r["covered"] for r in c["rows"]]
        axes[1].plot(m, covered, style, label=c["name"])
    for ax, label in zip(axes, ("S% (every target within the threshold)", "fraction of targets covered"), strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("team size M (density-scaled arena, rc, neighbour lists)")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))  # beside, not over, the curves
    fig.tight_layout()
    tmp = out + ".tmp.png"
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, out)  # a failed render leaves the old plot


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", help="JSON files (default: results/swarm/zero-shot-*.json, reference-*.json)")
    ap.add_argument("--out", default=DEFAULT_OUT, help="the plot (PNG)")
    ap.add_argument("--no-plot", action="store_true", help="print the table only")
    args = ap.parse_args(argv)
    files = args.files or [p for g in DEFAULT_GLOBS for p in sorted(glob.glob(g))]
    if not files:
        print("swarm_curves: no zero-shot files in results/swarm/", file=sys.stderr)
        return 2
    curves = [read(p) for p in files]
    print(table(curves))
    if not args.no_plot:
        plot(curves, args.out)
        print(f"plot: {os.path.relpath(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
