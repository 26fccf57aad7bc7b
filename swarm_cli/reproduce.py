"""``swarm reproduce``: the paper's tables as one resumable command."""

from __future__ import annotations

import os
import shlex
import sys

from reproduce.spec import SpecError
from swarm_cli.options import ReproduceOptions, fail, parse

DESCRIPTION = """\
Run the cells of the paper's Tables 1-4 (or a selection) on Ray, resumably, and render
the tables beside the paper's numbers.

Each (cell, seed) is one Ray task with its own run directory ROOT/<cell>/s<seed>; a
second call skips finished cells, resumes stopped ones from their checkpoints (also
after a killed worker: Ray retries the task) and refuses a cell another call is
running. Without --address, Ray runs embedded on this machine with --workers CPUs (no
cluster to start); with --address it joins a running cluster (every node needs this
package and ROOT on a shared file system).

examples:
  swarm reproduce --spec smoke --workers 2              a tiny spec end to end (~2 min)
  swarm reproduce --tables 1 --dry-run                  what Table 1 would run
  swarm reproduce --cells t1-coverage-rc-m3 --seeds 3   one cell, three seeds (0, 1, 2)
  swarm reproduce --cells t1-coverage-rc-m3 --seeds 2 --first-seed 3   two more (3, 4)
  swarm reproduce --status                              progress from the files
  swarm reproduce --render --update-doc docs/RESULTS.md the tables into a document
"""


ADDRESS_TIMEOUT_S = 10.0  # a Ray address that does not answer within this is refused (ray.init retries for minutes)


def check_address(address: str, timeout: float = ADDRESS_TIMEOUT_S) -> None:
    """Refuse a Ray address (HOST:PORT or ray://HOST:PORT) where nothing accepts a connection."""
    import socket

    if address == "auto":
        return
    where = address.split("://", 1)[-1]
    host, _, port = where.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--address must be HOST:PORT, ray://HOST:PORT or auto, got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        raise ValueError(
            f"--address {address}: no Ray head answers there within {timeout:g} s ({exc.strerror or exc}); "
            "start one with `ray start --head` or drop --address to run on this machine"
        ) from None


def reproduce_main(argv: list[str]) -> int:
    from reproduce.cells import cell_state
    from reproduce.runner import format_progress
    from reproduce.spec import load_spec
    from reproduce.tables import render_all, update_doc

    args = parse(ReproduceOptions, argv, "swarm reproduce", description=DESCRIPTION)
    workers = args.workers or max(1, os.cpu_count() or 1)
    try:
        spec = load_spec(args.spec)
        if args.update_doc:
            if not os.path.isfile(args.update_doc):
                raise ValueError(f"--update-doc {args.update_doc} is not a file")
            from reproduce.tables import check_doc_markers

            check_doc_markers(args.update_doc, spec_name=spec.name)  # before any cell runs
        cells = spec.select(list(args.tables) if args.tables else None, list(args.cells) if args.cells else None)
        seeds = list(range(args.first_seed, args.first_seed + args.seeds))
        root = args.root or os.path.join("runs", "reproduce", spec.name)
        if args.dry_run:
            print(_dry_run(cells, seeds, root, spec.name))
            return 0
        if args.status:
            print(format_progress(cells, seeds, root, workers))
            return 0
        failed: dict = {}
        if not args.render:
            try:
                import ray  # noqa: F401
            except ImportError:
                raise ValueError(
                    'running cells needs Ray: pip install -e ".[reproduce]" (--dry-run, --status and --render do not)'
                ) from None
            from reproduce.runner import run_on_ray

            if args.address:
                check_address(args.address)

            todo = [(c.id, s) for c in cells for s in seeds if cell_state(root, c, s) != "done"]
            print(f"swarm reproduce: {len(todo)} of {len(cells) * len(seeds)} (cell, seed) to run, in {root}")
            outcome = run_on_ray(
                cells,
                seeds,
                root,
                workers=workers,
                address=args.address,
                gpus_per_cell=args.gpus_per_cell,
                arch=args.arch,
                device=args.device,
                progress_every=args.progress_every,
            )
            failed = outcome["failed"]
        from taichi_swarm.files import atomic_write_bytes

        os.makedirs(root, exist_ok=True)
        tables_md = os.path.join(root, "tables.md")
        command = "swarm reproduce " + shlex.join(argv)
        text = render_all(cells, seeds, root, spec.name, figure_dir=args.figures, command=command)
        atomic_write_bytes(tables_md, lambda f: f.write(text.encode()))
        print(text)
        print(f"(tables: {tables_md})")
        if args.update_doc:
            doc_dir = os.path.dirname(os.path.abspath(args.update_doc))
            markdown = render_all(cells, seeds, root, spec.name, doc_dir, args.figures, command)
            update_doc(args.update_doc, markdown, spec.name)
            print(f"(written into {args.update_doc})")
    except KeyboardInterrupt:
        return 130
    except (SpecError, ValueError, FileNotFoundError) as exc:
        return fail("swarm reproduce", exc)
    if failed:
        print(f"swarm reproduce: {len(failed)} cell(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def _dry_run(cells, seeds, root, spec_name: str) -> str:
    from reproduce.cells import cell_state

    lines = [f"spec {spec_name}, root {root}, seeds {seeds}", ""]
    head = f"{'cell':<24} {'kind':<10} {'task':<9} {'comm':<4} {'net':<7} {'sizes':<14} {'budget':>22}  state"
    lines += [head, "-" * len(head)]
    total_steps = 0
    for c in cells:
        run = c.run
        ppo = run.config.ppo if c.kind in ("train", "curriculum") else None
        steps = (
            run.config.frames
            if c.kind == "baseline"
            else c.budget_updates() * (ppo.num_envs * ppo.num_steps if ppo else 0)
        )
        total_steps += steps * len(seeds)
        sizes = str(run.agents) if c.kind in ("train", "baseline") else " ".join(map(str, run.sizes))
        if c.kind == "train" and run.config.team_sizes:
            sizes += f" (on {' '.join(map(str, run.config.team_sizes))})"
        if c.kind == "baseline":
            budget = f"{run.config.algorithm} / {_steps(steps)} steps"
        elif steps:
            budget = f"{c.budget_updates()} upd / {_steps(steps)} steps"
        else:
            budget = f"{run.final_episodes} episodes"
        states = ", ".join(f"s{s} {cell_state(root, c, s)}" for s in seeds)
        states += f"  (reads {c.needs})" if c.needs else ""  # a zero-shot row's source, a run's init_from
        net = run.config.model.entity_mode if ppo else "-"  # (a zero-shot row: its source's)
        lines.append(f"{c.id:<24} {c.kind:<10} {run.task:<9} {run.comm:<4} {net:<7} {sizes:<14} {budget:>22}  {states}")
    lines.append(f"\nat most {_steps(total_steps)} env steps in all (curricula at their full stage budgets)")
    return "\n".join(lines)


def _steps(n: int) -> str:
    return f"{n / 1e6:.1f}M" if n >= 1e5 else f"{n / 1e3:.1f}k"
