"""``swarm models``: list the model zoo, show a card, re-evaluate entries, render the cards."""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass
from typing import Annotated, Literal

from swarm_cli.options import Default, OptionError, Positional, at_least, fail, parse

DESCRIPTION = """\
The model zoo: one curated policy per setting (task x UC/RC x team size, and the transfer
policies), each addressable by name wherever a checkpoint is taken
(`swarm eval coverage-rc-m10`, `swarm export line-uc-m5 --out DIR`, `--init-from NAME`).

examples:
  swarm models                          every entry: S% on 500 fresh episodes beside the paper's
  swarm models --task line --comm rc    a selection
  swarm models --task line --agents 50  the entry to use for a team of 50 (the nearest trained size)
  swarm models coverage-rc-m10          one entry's card
  swarm models --check                  re-evaluate every entry at another seed, print the drift
  swarm models --render                 write models/README.md and models/cards/ from the index
"""

CARD_SEED = 777  # the seed every card's numbers were measured at
DRIFT_POINTS = 3.0  # --check flags an entry whose S% moved more than this


@dataclass
class ModelsOptions:
    name: Positional[Annotated[str | None, Default("list the zoo", "NAME")]] = None
    """a zoo entry: print its card"""
    task: Literal["coverage", "formation", "line"] | None = None
    """list only this task"""
    comm: Literal["uc", "rc"] | None = None
    """list only this communication mode"""
    agents: int | None = None
    """the entry to use for a team of this size, per task and comm: the one trained at the nearest size"""
    check: bool = False
    """re-evaluate the entries listed (500 greedy episodes at --seed) and print each drift from its card"""
    episodes: int = 500
    """--check: episodes per entry"""
    seed: int = 4242
    """--check: evaluation seed (the cards used 777)"""
    render: bool = False
    """write models/README.md and models/cards/NAME.md from models/index.toml"""

    def __post_init__(self):
        at_least(self.agents, 1, "agents")
        at_least(self.episodes, 1, "episodes")
        if not 0 <= self.seed < 2**40:
            raise OptionError(f"--seed must be in [0, 2**40), got {self.seed}")
        if self.render and (self.check or self.name):
            raise OptionError("--render writes every card: give it alone")
        filters = [f"--{k}" for k in ("task", "comm", "agents") if getattr(self, k) is not None]
        if self.name and filters:  # a filter would be silently ignored: NAME is one entry already
            names = " ".join(filters)
            raise OptionError(f"{names}: filters of the list, not of a NAME ({self.name}): give one or the other")


def _pct(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{100 * x:.{digits}f}"


def _paper(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f}"


def list_table(entries) -> str:
    head = "| name | task | comm | M | S% | paper S% | T | DIST | zero-shot S% (M: S%) |"
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    for e in entries:
        zs = ", ".join(f"{m}: {_pct(s, 0)}" for m, s in sorted(e.zero_shot.items()) if m != e.agents) or "-"
        dist = "-" if e.dist is None else f"{e.dist:.3f}"
        lines.append(
            f"| `{e.name}` | {e.task} | {e.comm.upper()} | {e.agents} | {_pct(e.success)} | {_paper(e.paper_success)} "
            f"| {e.mean_length:.2f} | {dist} | {zs} |"
        )
    return "\n".join(lines)


def card(e, card_dir: str) -> str:
    """One entry's model card (Markdown); paths relative to ``card_dir``."""
    from trainer.zoo import ROOT

    rel = lambda p: os.path.relpath(os.path.join(ROOT, p), card_dir)  # noqa: E731
    trained = " -> ".join(str(m) for m in e.trained_on) if e.trained_on else str(e.agents)
    if len(e.trained_on) > 1 and e.cell.startswith("x-"):
        trained = " and ".join(str(m) for m in e.trained_on) + " together"
    net = {"emp": "entity message passing (EMP)", "concat": "landmark offset concatenated (the authors' formation net)"}
    lines = [
        f"# `{e.name}`",
        "",
        f"**{e.when()}**",
        "",
        e.summary,
        "",
        "| | |",
        "|---|---|",
        f"| setting | {e.task}, {e.comm.upper()}"
        + (f" (radius {e.comm_radius:g})" if e.comm == "rc" else "")
        + f", M = {e.agents} |",
        f"| network | {net.get(e.entity_mode, e.entity_mode)} |",
        f"| trained on | M = {trained} |",
        f"| S% | **{_pct(e.success)}** (paper {_paper(e.paper_success)}) on {e.episodes} fresh greedy episodes, "
        f"seed {e.eval_seed} |",
        f"| T (mean episode length) | {e.mean_length:.2f} |",
    ]
    if e.dist is not None:
        lines.append(f"| DIST | {e.dist:.3f} |")
    if e.covered is not None:
        covered = f"{e.covered:.3f} (mean fraction at the episodes' ends, by the matching S% is read on)"
        lines.append(f"| landmarks covered | {covered} |")
    lines += [
        f"| training | {e.updates} PPO updates, {e.env_steps / 1e6:.2f} M env steps, {e.minutes:.1f} min wall-clock "
        "(this run or stage and its polish) |",
        f"| made by | `{e.command()}` (seed {e.seed}) |",
        f"| weights | [`{e.weights}`]({rel(e.weights)}), sha256 `{e.sha256[:16]}...` |",
        "",
    ]
    if e.zero_shot:
        sizes = sorted(e.zero_shot)
        lines += [
            "Zero-shot: the same weights at other team sizes, no fine-tuning (S%, 500 episodes, seed 777):",
            "",
            "| M | " + " | ".join(str(m) for m in sizes) + " |",
            "|---|" + "---|" * len(sizes),
            "| S% | " + " | ".join(_pct(e.zero_shot[m]) for m in sizes) + " |",
            "",
        ]
    if e.curves:
        lines += ["Learning curves:", "", f"![learning curves]({rel(e.curves)})", ""]
    lines += [
        "Reproduce the number:",
        "",
        "```bash",
        f"swarm eval {e.name} --episodes {e.episodes} --seed {e.eval_seed}",
        "```",
        "",
    ]
    return "\n".join(lines)


def readme(entries) -> str:
    return "\n".join(
        [
            "# The model zoo",
            "",
            "One curated policy per setting, addressable by name wherever a checkpoint is taken:",
            "`swarm eval coverage-rc-m10`, `swarm export line-uc-m5 --out exported/line`,",
            "`swarm train ... --init-from formation-rc-m7`. S% on 500 fresh greedy episodes at seed 777",
            "(never a training seed), beside the paper's number; T is the mean episode length. Each name",
            "links its card: how it was trained, its zero-shot row and its learning curves.",
            "",
            "Generated from `models/index.toml` by `swarm models --render` (the index by",
            "`python tools/make_zoo.py` from the spec results). `swarm models --check` re-evaluates",
            "every entry at another seed and prints its drift from the card: at seed 4242 (500 episodes",
            "each) 29 of the 31 paper-scale entries read within 3 points of their cards; `coverage-rc-m7` read 92.4",
            "(card 89.0, z = 1.9) and `line-uc-m7` 92.6 (card 87.4, z = 2.8), both above.",
            "",
            _linked_table(entries),
            "",
        ]
    )


def _linked_table(entries) -> str:
    lines = list_table(entries).splitlines()
    out = lines[:2]
    for e, line in zip(entries, lines[2:], strict=True):
        out.append(line.replace(f"`{e.name}`", f"[`{e.name}`](cards/{e.name}.md)", 1))
    return "\n".join(out)


def rendered_files(entries) -> dict[str, str]:
    """{path: text} of every generated file of the zoo."""
    from trainer.zoo import ZOO_DIR

    card_dir = os.path.join(ZOO_DIR, "cards")
    files = {os.path.join(ZOO_DIR, "README.md"): readme(entries)}
    for e in entries:
        files[os.path.join(card_dir, f"{e.name}.md")] = card(e, card_dir)
    return files


def check(entries, episodes: int, seed: int) -> int:
    """Re-evaluate each entry; print its drift from the card in points and in standard errors."""
    import torch

    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate

    torch.set_num_threads(1)
    print(f"re-evaluating {len(entries)} entries: {episodes} greedy episodes at seed {seed} (cards: seed {CARD_SEED})")
    print(f"{'name':<26} {'card S%':>8} {'now S%':>8} {'drift':>7} {'z':>6}")
    worst = 0.0
    flagged = []
    for e in entries:
        policy, _ = load_policy(e.name)  # by name: the file is checked against the index's sha256
        result = evaluate(
            policy, policy.sim.override(agents=e.agents, comm=e.comm, comm_radius=e.comm_radius), episodes, seed
        )
        now = result["success_rate"]
        drift = 100 * (now - e.success)
        # two independent binomial samples: the standard error of their difference
        se = math.sqrt(e.success * (1 - e.success) / e.episodes + now * (1 - now) / episodes)
        z = (now - e.success) / se if se > 0 else 0.0
        mark = "  <- more than 3 points" if abs(drift) > DRIFT_POINTS else ""
        if mark:
            flagged.append(e.name)
        worst = max(worst, abs(drift))
        print(f"{e.name:<26} {_pct(e.success):>8} {_pct(now):>8} {drift:>+7.1f} {z:>+6.1f}{mark}", flush=True)
    print(f"largest drift {worst:.1f} points; {len(flagged)} of {len(entries)} beyond {DRIFT_POINTS:g}")
    return 1 if flagged else 0


def models_main(argv: list[str]) -> int:
    opts = parse(ModelsOptions, argv, "swarm models", description=DESCRIPTION)
    from trainer import zoo
    from trainer.checkpoint import CheckpointError

    try:
        entries = zoo.load_index()
        if opts.render:
            from taichi_swarm.files import atomic_write_bytes

            for path, text in rendered_files(entries).items():
                os.makedirs(os.path.dirname(path), exist_ok=True)
                atomic_write_bytes(path, lambda f, t=text: f.write(t.encode()))
            print(f"wrote models/README.md and {len(entries)} cards under models/cards/")
            return 0
        if opts.name:
            entry = zoo.get(opts.name)
            if not opts.check:
                print(card(entry, os.path.join(zoo.ZOO_DIR, "cards")))
                return 0
            selected = [entry]
        else:
            selected = zoo.select(entries, opts.task, opts.comm, opts.agents)
            if not selected:
                raise ValueError("no zoo entry matches --task / --comm / --agents")
        if opts.check:
            return check(selected, opts.episodes, opts.seed)
        print(list_table(selected))
        which = f" (the one to use at M = {opts.agents} per task and comm)" if opts.agents else ""
        print(f"\n{len(selected)} of {len(entries)} entries{which}; `swarm models NAME` shows one's card")
    except (zoo.ZooError, CheckpointError, ValueError) as exc:
        return fail("swarm models", exc)
    return 0


if __name__ == "__main__":
    sys.exit(models_main(sys.argv[1:]))
