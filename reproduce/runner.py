"""Scheduling the cells of a spec on Ray: one Ray task per (cell, seed).

A curriculum chain is one task (its stages run in order inside it); a zero-shot row
takes its source's task as an argument, so Ray starts it once the source is done.
Locally, Ray is started embedded with ``workers`` CPUs (one per task); with
``address`` it joins a running cluster (every node needs this package installed and
the reproduction root on a shared file system). A task whose worker dies (killed,
out of memory, node lost) is retried by Ray and resumes from its checkpoints.
"""

from __future__ import annotations

import os
import sys

from reproduce.cells import cell_state, progress, read_result, run_cell
from reproduce.spec import Cell

# For the time-left estimate: seconds a zero-shot row takes (no training), and the env
# steps per second of a BenchMARL baseline (stock MAPPO, coverage M = 3, one core here).
ZERO_SHOT_SECONDS = 60.0
BASELINE_FRAMES_PER_SECOND = 450.0


def _run_cell_task(cell: Cell, seed: int, root: str, source: Cell | None, arch: str, device: str, *upstream):
    """The Ray task: ``upstream`` (the source's result) only orders the tasks."""
    result = run_cell(cell, seed, root, source=source, arch=arch, device=device)
    return {"cell": cell.id, "seed": seed, "attempts": result["attempts"]}


def run_on_ray(
    cells: list[Cell],
    seeds: list[int],
    root: str,
    workers: int = 1,
    address: str | None = None,
    gpus_per_cell: float = 0.0,
    arch: str = "cpu",
    device: str = "cpu",
    progress_every: float = 60.0,
    max_retries: int = 3,
    out=sys.stdout,
) -> dict:
    """Run every unfinished (cell, seed); returns {"done": [...], "failed": {key: error}}."""
    import ray

    if not gpus_per_cell and {arch, device} & {"cuda", "gpu", "auto"}:
        raise ValueError(
            "--arch/--device cuda, gpu or auto needs --gpus-per-cell > 0: Ray hides the GPUs from tasks that ask "
            "for none"
        )
    root = os.path.abspath(root)
    by_id = {c.id: c for c in cells}
    # every result on disk checked before anything starts (a changed cell stops the run here)
    finished = {
        (c.id, seed) for c in cells for seed in seeds if read_result(root, c, seed, by_id.get(c.needs)) is not None
    }
    if address is None:
        ray.init(
            num_cpus=workers,
            num_gpus=None if gpus_per_cell else 0,
            include_dashboard=False,
            logging_level="WARNING",
            object_store_memory=256 * 1024**2,
            # the workers import this package from the driver's environment
            runtime_env={"env_vars": {"OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}},
            # Ray runs its workers at nice 15: a cell then gets a sixth of a core beside any other
            # job on the machine (measured: 17% CPU beside two training runs on two cores)
            _system_config={"worker_niceness": 0},
        )
    else:
        ray.init(address=address, logging_level="WARNING")
    try:
        task = ray.remote(num_cpus=1, num_gpus=gpus_per_cell, max_retries=max_retries)(_run_cell_task)
        refs: dict[tuple[str, int], object] = {}
        for cell, seed in submission_order(cells, seeds, root, finished):
            source = by_id.get(cell.needs)
            upstream = [refs[(cell.needs, seed)]] if (cell.needs, seed) in refs else []
            refs[(cell.id, seed)] = task.remote(cell, seed, root, source, arch, device, *upstream)
        key_of = {ref: key for key, ref in refs.items()}
        live = set(refs)  # submitted and not yet returned
        pending = list(refs.values())
        failed: dict[str, str] = {}
        done: list[str] = []
        print(format_progress(cells, seeds, root, workers, live=live), file=out, flush=True)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=progress_every)
            for ref in ready:
                cell_id, seed = key_of[ref]
                live.discard((cell_id, seed))
                try:
                    ray.get(ref)
                    done.append(f"{cell_id}/s{seed}")
                    print(f"done: {cell_id} seed {seed}", file=out, flush=True)
                except Exception as exc:  # noqa: BLE001 - one failed cell never stops the others
                    needs = by_id[cell_id].needs
                    if f"{needs}/s{seed}" in failed:  # Ray fails a task whose upstream failed
                        failed[f"{cell_id}/s{seed}"] = f"not run: {needs} failed"
                    else:
                        failed[f"{cell_id}/s{seed}"] = _short_error(exc)
                    print(f"FAILED: {cell_id} seed {seed}: {failed[f'{cell_id}/s{seed}']}", file=out, flush=True)
            if not ready:
                print(format_progress(cells, seeds, root, workers, live=live), file=out, flush=True)
        return {"done": done, "failed": failed}
    finally:
        ray.shutdown()


def submission_order(cells: list[Cell], seeds: list[int], root: str, finished: set) -> list[tuple[Cell, int]]:
    """The unfinished (cell, seed) pairs in the order they are submitted (Ray hands queued
    tasks to free workers in that order): first the zero-shot rows whose source has
    finished (minutes each: their numbers come early), then the started cells, fewest
    updates left first, so that a resumed run finishes what it had begun before it
    begins anything new, then the rest in spec order. A source (``needs``) always comes
    before the cells that read it (a started cell whose source is to run again waits for it)."""

    def key(pair: tuple[Cell, int]) -> tuple[int, int]:
        cell, seed = pair
        if cell.kind == "zero-shot" and (cell.needs, seed) in finished:
            return (0, 0)
        p = progress(root, cell, seed)
        return (1, p["budget"] - p["updates"]) if p["state"] == "started" else (2, 0)

    todo = sorted([(c, s) for c in cells for s in seeds if (c.id, s) not in finished], key=key)
    order, placed = [], set()
    while todo:  # each pass places every pair whose source is placed or not to run
        waiting = {(c.id, s) for c, s in todo}
        ready = [(c, s) for c, s in todo if (c.needs, s) in placed or (c.needs, s) not in waiting]
        if not ready:  # a cycle of sources, which load_spec refuses; never loop on one
            raise ValueError(f"cells wait on each other: {sorted(waiting)}")
        order += ready
        placed |= {(c.id, s) for c, s in ready}
        todo = [pair for pair in todo if (pair[0].id, pair[1]) not in placed]
    return order


def _short_error(exc: Exception) -> str:
    cause = getattr(exc, "cause", None) or exc
    text = str(cause).strip().splitlines()
    return text[-1] if text else type(cause).__name__


def format_progress(cells: list[Cell], seeds: list[int], root: str, workers: int, live: set | None = None) -> str:
    """Which cells are done, running (a process holds the cell's lock), queued (``live``:
    submitted in this run, no worker on it yet), stopped, pending or waiting for their
    source; how far each is, and the time left at the measured seconds per update."""
    rows, remaining_updates, remaining_fixed, longest = [], 0, 0.0, 0.0
    per_update = []
    info = {}
    for cell in cells:
        for seed in seeds:
            p = progress(root, cell, seed)
            info[(cell.id, seed)] = p
            if p["updates"] and p["wall_time"]:
                per_update.append(p["wall_time"] / p["updates"])
    rate = sum(per_update) / len(per_update) if per_update else None
    for cell in cells:
        for seed in seeds:
            p = info[(cell.id, seed)]
            state = p["state"]
            if p["running"]:  # a process holds the cell's lock, this one's worker or another's
                state = "running"
            elif state == "pending" and cell.needs and cell_state(root, _find(cells, cell.needs), seed) != "done":
                state = f"waits for {cell.needs}"
            elif state != "done" and live is not None and (cell.id, seed) in live:
                state = "queued"  # submitted in this run, waiting for a worker
            elif state == "started":
                state = "stopped"  # started before, no process on it now
            budget = p["budget"]
            where = f" ({p['stage']})" if p["stage"] else ""
            done_txt = f"{p['updates']}/{budget}{where}" if budget else "-"
            left = ""
            if p["state"] != "done":
                if cell.kind == "zero-shot":
                    remaining_fixed += ZERO_SHOT_SECONDS
                elif cell.kind == "baseline":
                    remaining_fixed += cell.run.config.frames / BASELINE_FRAMES_PER_SECOND
                else:
                    remaining_updates += max(budget - p["updates"], 0)
                    if rate:
                        longest = max(longest, max(budget - p["updates"], 0) * rate)
                        left = _minutes(max(budget - p["updates"], 0) * rate)
            last = p["last_eval"]
            last_txt = f"{100 * last['success_rate']:.1f} @{last['update']}" if last and p["state"] != "done" else ""
            trained = _minutes(p["wall_time"]) if p["wall_time"] else ""
            rows.append((cell.id, str(seed), state, done_txt, last_txt, trained, left))
    head = ("cell", "seed", "state", "updates", "last eval S%", "trained", "left (at most)")
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in [head, *rows]]
    counts = {}
    for r in rows:
        key = r[2].split(" ")[0]
        counts[key] = counts.get(key, 0) + 1
    summary = ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
    if rate:
        # the cells share the workers, but no cell goes faster than its own remaining time
        total = max((remaining_updates * rate + remaining_fixed) / max(workers, 1), longest)
        summary += (
            f"; time left at most {_minutes(total)} on {workers} worker(s) "
            f"({rate:.2f} s/update measured; curricula counted at their full stage budgets)"
        )
    return "\n".join([*lines, summary])


def _find(cells: list[Cell], cell_id: str) -> Cell:
    return next(c for c in cells if c.id == cell_id)


def _minutes(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.1f} min"
