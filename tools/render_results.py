"""Render docs/RESULTS.md's generated tables from the spec results committed under results/.

    python tools/render_results.py            # rewrite the three generated blocks and their figures
    python tools/render_results.py --check    # exit 1 if a block differs from a fresh render

Each block is what `swarm reproduce --render --update-doc docs/RESULTS.md` writes for one spec
(the command is printed at the head of the block); this script runs the three with the roots
and seeds that are committed, so the document cannot drift from the result files.
"""

from __future__ import annotations

import argparse
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

DOC = os.path.join(ROOT, "docs", "RESULTS.md")

# spec -> (root, figure folder, [(cells or None for all, seeds)]): what is committed for each
# spec; a spec whose cells ran at different seeds renders one selection after the other
BLOCKS = {
    "recipe": ("results/reproduce-recipe", "docs/media/reproduce-recipe", [(None, [0, 1, 2, 3])]),
    "beyond": (
        "results/reproduce-beyond",
        "docs/media/reproduce-beyond",
        [
            (["x-coverage-uc-m3", "x-coverage-uc-m34", "x-zs-coverage-uc-m3", "x-zs-coverage-uc-m34"], [6, 7, 8, 9]),
            (
                [
                    "x-cur-formation-uc-emp",
                    "x-cur-formation-uc-concat",
                    "x-zs-formation-uc-emp",
                    "x-zs-formation-uc-concat",
                ],
                [0, 1, 2],
            ),
        ],
    ),  # fmt: skip
    "paper": ("results/reproduce", "docs/media/reproduce", [(["t1-coverage-rc-m3", "t1-coverage-uc-m6"], [0])]),
}


def command(spec: str, root: str, cells, seeds: list[int], figures: str) -> str:
    parts = ["swarm reproduce"] + ([] if spec == "paper" else [f"--spec {spec}"])
    if cells:
        parts.append("--cells " + " ".join(cells))
    if seeds != [0]:
        parts.append(f"--seeds {len(seeds)}" + (f" --first-seed {seeds[0]}" if seeds[0] else ""))
    parts += [f"--root {root}", "--render", f"--figures {figures}"]
    return " ".join(parts)


def render(spec_name: str, figures: str | None = None) -> str:
    """One spec's block, as `swarm reproduce --render` writes it (run from the repository root)."""
    from reproduce.spec import load_spec
    from reproduce.tables import render_all

    spec = load_spec(spec_name)
    root, own_figures, selections = BLOCKS[spec_name]
    figures_out = figures or own_figures  # (a check draws its figures elsewhere; the command names the doc's)
    parts = []
    for cells, seeds in selections:
        assert seeds == list(range(seeds[0], seeds[0] + len(seeds))), "a selection's seeds are contiguous"
        selected = spec.select(None, cells)
        how = command(spec_name, root, cells, seeds, own_figures)
        parts.append(render_all(selected, seeds, root, spec.name, "docs", figures_out, how))
    return "\n".join(parts)


def _figure_free(text: str) -> list[str]:
    """The lines of a block without its figure links (a check renders its figures elsewhere)."""
    return [line for line in text.strip().splitlines() if not line.startswith("![learning curves")]


def _between(text: str, spec: str) -> str:
    from reproduce.tables import doc_markers

    begin, end = doc_markers(spec)
    return text.split(begin, 1)[1].split(end, 1)[0].strip()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--check", action="store_true", help="compare the document with a fresh render (exit 1 if stale)"
    )
    args = parser.parse_args(argv)
    import tempfile

    from reproduce.tables import update_doc

    os.chdir(ROOT)  # the roots, the figures and the document are named from the repository root
    if args.check:
        with open(DOC) as f:
            doc = f.read()
        stale = []
        with tempfile.TemporaryDirectory() as figures:
            for spec in BLOCKS:
                if _figure_free(_between(doc, spec)) != _figure_free(render(spec, figures)):
                    stale.append(spec)
        print("docs/RESULTS.md is up to date" if not stale else f"docs/RESULTS.md is stale for: {', '.join(stale)}")
        return 1 if stale else 0
    for spec in BLOCKS:
        update_doc(DOC, render(spec), spec)
        print(f"rendered the {spec} spec's tables from {BLOCKS[spec][0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
