"""The tables are generated, not typed: result.json files -> Markdown beside the paper's
numbers, and one figure of learning curves per table.

Every cell of the selection appears; a cell with no result reads "not run". With
more than one seed a number reads ``mean ± h (n)``, h the half-width of the 95%
Student-t interval of the mean over the n seeds; the paper reported single runs.
"""

from __future__ import annotations

import math
import os

from reproduce.cells import read_result, run_dirs
from reproduce.spec import Cell, SpecError
from trainer.rundir import METRICS

DOC_BEGIN = "<!-- BEGIN swarm reproduce (generated: do not edit by hand) -->"
DOC_END = "<!-- END swarm reproduce -->"

TITLES = {
    1: "Table 1: trained from scratch (S%, T; coverage also DIST)",
    2: "Table 2: coverage curriculum, S% and updates N per stage",
    3: "Table 3: formation and line curricula, S% and updates N per stage",
    4: "Table 4: zero-shot S%: one policy at other team sizes, no fine-tuning",
    5: "Beyond the paper: one size against several at once (S%, T at the evaluated size)",
    6: "Beyond the paper: zero-shot S% of those policies at other team sizes",
    7: "Beyond the paper: the coverage curriculum 5 -> 7 -> 10 from each of those M = 3 policies",
    8: "Beyond the paper: formation 3 -> 5 with EMP against the landmark offset concatenated",
    9: "Beyond the paper: zero-shot S% of those formation M = 5 policies (paper: Table 4's formation UC row)",
    10: "Swarms: a curriculum on neighbour lists in density-scaled arenas (S% and updates N per stage)",
    11: "Beyond the paper: policies trained through a lossy radio (fault-free S%; faults in docs/DEPLOY.md)",
    12: "Swarms: formation and line on their density-scaled shapes, by curriculum (S% and updates N per stage)",
    13: "Swarms: coverage on several team sizes at once (S%, T at the evaluated size)",
}


def _stat(values: list[float], scale: float = 1.0, digits: int = 1) -> str:
    """One number: a single seed's value, else ``mean ± h (n)`` with h the half-width of the
    95% Student-t interval of the mean over the n seeds that ran (of those asked)."""
    values = [v * scale for v in values if v is not None and math.isfinite(v)]
    if not values:
        return "-"
    mean = sum(values) / len(values)
    if len(values) == 1:
        return f"{mean:.{digits}f}"
    if len(set(values)) == 1:  # every seed the same (a budget): no interval
        return f"{mean:.{digits}f} ({len(values)})"
    from scipy.stats import t

    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
    half = t.ppf(0.975, len(values) - 1) * sd / math.sqrt(len(values))
    return f"{mean:.{digits}f} ± {half:.{digits}f} ({len(values)})"


def _paper(cell: Cell, agents: int, key: str, digits: int | None = None) -> str:
    value = cell.paper.get(str(agents), {}).get(key)
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if digits is not None else str(value)


def _rows_by_size(results: list[dict]) -> dict[int, list[dict]]:
    out: dict[int, list[dict]] = {}
    for r in results:
        for row in r["rows"]:
            out.setdefault(row["agents"], []).append(row)
    return out


def _results(root: str, cell: Cell, seeds: list[int], source: Cell | None, stale: list[str]) -> list[dict]:
    """The cell's finished results; one made from a policy its ``source`` (zero-shot row)
    or init_from no longer has, because that has been trained again since, is left out
    and named in ``stale``."""
    out = []
    for s in seeds:
        try:
            result = read_result(root, cell, s, source)
        except SpecError:  # trained from an upstream policy that has been replaced
            result = None
            stale.append(f"{cell.id} seed {s}")
        else:
            if result is None and source is not None and read_result(root, cell, s) is not None:
                stale.append(f"{cell.id} seed {s}")
        if result is not None:
            out.append(result)
    return out


def render_table(table: int, cells: list[Cell], seeds: list[int], root: str) -> str:
    """``cells``: the selection (the table's cells and the cells they read)."""
    by_id = {c.id: c for c in cells}
    cells = [c for c in cells if c.table == table]
    if not cells:
        return ""
    stale: list[str] = []

    def _results_of(c: Cell) -> list[dict]:
        return _results(root, c, seeds, by_id.get(c.needs), stale)

    kind = cells[0].kind
    lines = [f"### {TITLES.get(table, f'Table {table}')}", ""]
    # a table with polished cells shows S% before the polish (and how many polish updates);
    # N / updates are the run's (stage's) own, env steps and minutes include the polish
    polish = any(getattr(c.run, "polish_updates", 0) for c in cells)
    pol_head, pol_rule = (" S% before polish (+updates) |", "---|") if polish else ("", "")

    def before(rows: list[dict]) -> str:
        if not polish:
            return ""
        polished = [r for r in rows if "before_polish" in r]
        if not polished:
            return " - |"
        added = "/".join(str(n) for n in sorted({r["polish_updates"] for r in polished}))
        return f" {_stat([r['before_polish']['success_rate'] for r in polished], 100)} (+{added}) |"

    def own_updates(rows: list[dict]) -> str:
        return _stat([r.get("updates") and r["updates"] - r.get("polish_updates", 0) for r in rows], digits=0)

    if kind in ("train", "baseline"):
        lines += [
            f"| cell | M | S% | paper S% |{pol_head} T | paper T | DIST | paper DIST | updates "
            "| env steps (M) | minutes |",
            f"|---|---|---|---|{pol_rule}---|---|---|---|---|---|---|",
        ]
        for c in cells:
            res, M = _results_of(c), c.run.agents
            if not res:
                lines.append(
                    f"| {c.row_label()} | {M} | not run | {_paper(c, M, 'S')} |{' - |' if polish else ''}"
                    f" - | {_paper(c, M, 'T')} | - | {_paper(c, M, 'DIST')} | - | - | - |"
                )
                continue
            rows = _rows_by_size(res)[M]
            lines.append(
                f"| {c.row_label()} | {M} | {_stat([r['success_rate'] for r in rows], 100)} | "
                f"{_paper(c, M, 'S')} |{before(rows)} {_stat([r['mean_length'] for r in rows], digits=2)} | "
                f"{_paper(c, M, 'T')} | {_stat([r['dist'] for r in rows], digits=3)} | "
                f"{_paper(c, M, 'DIST')} | {own_updates(rows)} | "
                f"{_stat([r['env_steps'] for r in rows], 1e-6, 2)} | {_stat([r['wall_time'] for r in rows], 1 / 60)} |"
            )
    elif kind == "curriculum":
        lines += [
            f"| cell | M | S% | paper S% |{pol_head} N (updates) | paper N | env steps (M) | minutes "
            "| reached threshold |",
            f"|---|---|---|---|{pol_rule}---|---|---|---|---|",
        ]
        for c in cells:
            start = by_id.get(c.needs)
            M0 = (c.run.init_agents or start.run.agents) if start else 0
            if start and str(M0) in c.paper and M0 not in c.run.sizes:  # the paper's first stage is the chain's start
                rows = _rows_by_size(_results_of(start)).get(M0, [])
                ours = _stat([r["success_rate"] for r in rows], 100) if rows else "not run"
                lines.append(
                    f"| {c.row_label()} | {M0} | {ours} (the start: {start.id}) | {_paper(c, M0, 'S')} |"
                    f"{before(rows)} {own_updates(rows)} | {_paper(c, M0, 'N')} | "
                    f"{_stat([r['env_steps'] for r in rows], 1e-6, 2)} | "
                    f"{_stat([r['wall_time'] for r in rows], 1 / 60)} | - |"
                )
            by_size = _rows_by_size(_results_of(c))
            for M in c.run.sizes:
                rows = by_size.get(M, [])
                if not rows:
                    paper = f"{_paper(c, M, 'S')} |{' - |' if polish else ''} - | {_paper(c, M, 'N')}"
                    lines.append(f"| {c.row_label()} | {M} | not run | {paper} | - | - | - |")
                    continue
                reached = sum(bool(r["reached_threshold"]) for r in rows)
                lines.append(
                    f"| {c.row_label()} | {M} | {_stat([r['success_rate'] for r in rows], 100)} | "
                    f"{_paper(c, M, 'S')} |{before(rows)} {own_updates(rows)} | "
                    f"{_paper(c, M, 'N')} | "
                    f"{_stat([r['env_steps'] for r in rows], 1e-6, 2)} | "
                    f"{_stat([r['wall_time'] for r in rows], 1 / 60)} | {reached} of {len(rows)} |"
                )
    else:
        sizes = sorted({M for c in cells for M in c.run.sizes})
        lines += [
            "| cell | from | " + " | ".join(f"M={M} ours (paper)" for M in sizes) + " |",
            "|---|---|" + "---|" * len(sizes),
        ]
        for c in cells:
            by_size = _rows_by_size(_results_of(c))
            cols = []
            for M in sizes:
                rows = by_size.get(M, [])
                if M not in c.run.sizes:  # another row of the table evaluates this size
                    ours = "-"
                else:
                    ours = _stat([r["success_rate"] for r in rows], 100) if rows else "not run"
                cols.append(f"{ours} ({_paper(c, M, 'S')})")
            source = f"{c.needs} M={c.run.source_agents}" if c.run.source_agents else c.needs
            lines.append(f"| {c.row_label()} | {source} | " + " | ".join(cols) + " |")
    if stale:
        lines += [
            "",
            f"Left out as stale (made from a policy that has been trained again since; `swarm reproduce` "
            f"redoes them): {', '.join(stale)}.",
        ]
    if polish:
        lines += [
            "",
            "Polished cells: S% is the policy after the polish (a constant low learning rate from the "
            "run's weights); updates / N count the run (stage) alone, env steps and minutes include the polish.",
        ]
    lines.append("")
    return "\n".join(lines)


def render_all(
    cells: list[Cell],
    seeds: list[int],
    root: str,
    spec_name: str,
    link_from: str | None = None,
    figure_dir: str | None = None,
    command: str | None = None,
) -> str:
    """Markdown of every table of ``cells``, and the learning-curve figures (written to
    ``figure_dir``/curves-table-N.png, default ROOT, linked relative to ``link_from``:
    where the Markdown goes)."""
    tables = sorted({c.table for c in cells})
    n_eps = sorted({c.run.final_episodes for c in cells})
    parts = [
        f"Generated by `{command or f'swarm reproduce --spec {spec_name}'}` from {root}, seeds {seeds}: "
        f"every S% / T / DIST from {', '.join(map(str, n_eps))} fresh greedy episodes at seed "
        f"{', '.join(str(s) for s in sorted({c.run.eval_seed for c in cells}))} (never a training seed); "
        "'minutes' is training wall-clock. With several seeds a number reads mean ± the half-width of "
        "its 95% Student-t interval (n of seeds).",
        "",
    ]
    for t in tables:
        parts.append(render_table(t, cells, seeds, root))
        figure = plot_curves(t, cells, seeds, root, figure_dir or root)
        if figure:
            rel = os.path.relpath(figure, link_from or root)
            parts += [f"![learning curves, table {t}]({rel})", ""]
    return "\n".join(parts)


def plot_curves(table: int, cells: list[Cell], seeds: list[int], root: str, out_dir: str) -> str | None:
    """Evaluation S% against env steps of every training cell of ``table`` (curricula:
    the stages one after another, a dotted line where a stage, or a polish, starts)."""
    from trainer.plot import _save, read_metrics

    cells = [c for c in cells if c.table == table and c.kind in ("train", "curriculum")]
    curves = []
    for c in cells:
        for seed in seeds:
            xs, ys, starts, offset = [], [], [], 0
            for run in run_dirs(root, c, seed):
                if not os.path.exists(os.path.join(run, METRICS)):
                    break
                rows = read_metrics(run)
                starts.append(offset / 1e6)
                ev = [r for r in rows if r.get("eval_success_rate") is not None]
                xs += [(offset + r["env_steps"]) / 1e6 for r in ev]
                ys += [100 * r["eval_success_rate"] for r in ev]
                offset += rows[-1]["env_steps"] if rows else 0
            if xs:
                curves.append((f"{c.id} s{seed}", xs, ys, starts[1:]))
    if not curves:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for label, xs, ys, starts in curves:
        (line,) = ax.plot(xs, ys, "o-", ms=3, label=label)
        for s in starts:
            ax.axvline(s, color=line.get_color(), ls=":", alpha=0.6)
    ax.set(xlabel="env steps (M)", ylabel="evaluation S% (during training)", ylim=(-2, 102), title=TITLES.get(table))
    ax.legend(fontsize=7)
    os.makedirs(out_dir, exist_ok=True)
    return _save(fig, os.path.join(out_dir, f"curves-table-{table}.png"))


def doc_markers(spec_name: str = "paper") -> tuple[str, str]:
    """The pair of markers a document holds for the tables of ``spec_name`` (one pair per
    spec, so one document can hold the paper spec's tables and another's)."""
    if spec_name == "paper":
        return DOC_BEGIN, DOC_END
    return (
        f"<!-- BEGIN swarm reproduce --spec {spec_name} (generated: do not edit by hand) -->",
        f"<!-- END swarm reproduce --spec {spec_name} -->",
    )


def check_doc_markers(doc_path: str, text: str | None = None, spec_name: str = "paper") -> None:
    """Raise ValueError unless ``doc_path`` holds the spec's begin marker, then its end
    marker, once each."""
    if text is None:
        with open(doc_path) as f:
            text = f.read()
    begin_mark, end_mark = doc_markers(spec_name)
    begin, end = text.find(begin_mark), text.find(end_mark)
    if begin < 0 or end < begin or text.count(begin_mark) != 1 or text.count(end_mark) != 1:
        raise ValueError(f"{doc_path} must hold the markers {begin_mark!r} and then {end_mark!r}, once each")


def update_doc(doc_path: str, markdown: str, spec_name: str = "paper") -> None:
    """Replace what lies between the spec's markers in ``doc_path`` (atomically)."""
    from taichi_swarm.files import atomic_write_bytes

    with open(doc_path) as f:
        text = f.read()
    check_doc_markers(doc_path, text, spec_name)
    begin_mark, end_mark = doc_markers(spec_name)
    head, rest = text.split(begin_mark, 1)
    _, tail = rest.split(end_mark, 1)
    new = f"{head}{begin_mark}\n{markdown.rstrip()}\n{end_mark}{tail}"
    atomic_write_bytes(doc_path, lambda f: f.write(new.encode()))
