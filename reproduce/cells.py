"""Running one cell of a spec for one seed, resumably, without Ray.

Layout under the reproduction root::

    ROOT/<cell id>/s<seed>/         the run directory (train: the run itself; curriculum:
                                    curriculum.json + stage-m<M>/ per stage)
    ROOT/<cell id>/s<seed>/polish/  a train cell's polish (a curriculum's: stage-m<M>-polish/)
    ROOT/<cell id>/s<seed>/result.json   written last, atomically: the cell is done
    ROOT/<cell id>/s<seed>/attempts.json every start of the cell (pid, host, time)
    ROOT/<cell id>/s<seed>/upstream.json an init_from cell: the upstream result it started from

``run_cell`` is idempotent: a finished cell returns its result.json, a stopped one
resumes from its checkpoints (``train_or_resume``), so running it again after a kill
(of the process, of a Ray worker, of the machine) loses at most the updates since the
last checkpoint. The reported rows come from a fresh evaluation of each final policy
(``final_episodes`` greedy episodes at ``eval_seed``), never from the evaluations that
stopped training.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import socket
import time

from reproduce.spec import Cell, SpecError, canonical
from taichi_swarm.files import atomic_write_json
from trainer.rundir import METRICS, POLICY, RunDirLock, is_held

RESULT = "result.json"
ATTEMPTS = "attempts.json"
DEFINITION = "definition.json"  # written at the first start: a changed cell never mixes with old runs
POLISH_DIR = "polish"  # a train cell's polish run, inside its run directory
UPSTREAM = "upstream.json"  # an init_from cell: which result of its upstream it started from
CELL_LOCK = ".cell.lock"  # held by the process bringing the cell to its result (trainer.rundir.RunDirLock)


def cell_dir(root: str, cell: Cell, seed: int) -> str:
    return os.path.join(root, cell.id, f"s{seed}")


def read_result(root: str, cell: Cell, seed: int, source: Cell | None = None) -> dict | None:
    """The cell's result if it finished, None otherwise; an error if the result on disk
    was made by a different definition of the cell (changed budget, preset, ...). A
    zero-shot row whose ``source`` finished again since (a new policy) reads as None."""
    path = os.path.join(cell_dir(root, cell, seed), RESULT)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        result = json.load(f)
    check_same_definition(path, cell, result.get("definition", {}))
    if source is not None and source.id == cell.needs:
        source_result = read_result(root, source, seed)
        if source_result is None or source_result["finished"] != result.get("source_finished"):
            if cell.kind == "zero-shot":
                return None  # stale: evaluated a policy that is no longer the source's
            raise SpecError(_retrained(path, cell))
    return result


def _retrained(path: str, cell: Cell) -> str:
    return (
        f"{path}: cell {cell.id!r} was trained from a policy of its init_from {cell.needs!r} that has been "
        f"trained again since (or is being); delete {os.path.dirname(path)} to train it from the new one"
    )


def check_same_definition(path: str, cell: Cell, stored: dict) -> None:
    """Refuse a result or run directory made by another definition of the cell: ``stored``,
    of any schema, read as today's code reads a definition (``reproduce.spec.canonical``)."""
    try:
        then = canonical(stored)
    except (ValueError, TypeError, KeyError) as exc:  # (SpecError too)
        raise SpecError(f"{path}: its definition of cell {cell.id!r} cannot be read ({exc})") from None
    changed = _differences(cell.definition(), then)
    if changed:
        raise SpecError(
            f"{path} was made by another definition of cell {cell.id!r} (differs in {changed}); "
            "reproduce into another --root, or delete that directory to run the cell again"
        )


def _differences(now: dict, then: dict, prefix: str = "") -> list[str]:
    """The keys (ppo.lr: nested; a run's config: its own names) whose values differ."""
    out = []
    for key in sorted(set(now) | set(then)):
        a, b = now.get(key), then.get(key)
        if isinstance(a, dict) and isinstance(b, dict) and a != b:
            out += _differences(a, b, "" if key == "config" else f"{prefix}{key}.")
        elif a != b:
            out.append(prefix + key)
    return out


def cell_state(root: str, cell: Cell, seed: int) -> str:
    """done | started | pending (from the files alone: no process is asked; whether a
    started cell is running now: ``progress``)."""
    d = cell_dir(root, cell, seed)
    if os.path.exists(os.path.join(d, RESULT)):
        return "done"
    if os.path.exists(os.path.join(d, ATTEMPTS)):
        return "started"
    return "pending"


def final_eval(policy_path: str, cell: Cell, agents: int, arch: str = "cpu") -> dict:
    """S%, T, DIST (and the fraction of landmarks covered, where the task reports it) of a
    policy on ``final_episodes`` fresh greedy episodes at ``eval_seed``."""
    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate

    policy, _ = load_policy(policy_path)
    run = cell.run
    config = getattr(run, "config", None)  # the lists / density scaling a run trained on, as its evaluations
    if hasattr(config, "sim_at"):
        sim = config.sim_at(agents)
    else:
        sim = policy.sim.override(task=run.task, agents=agents, comm=run.comm, comm_radius=run.comm_radius)
    r = evaluate(policy, sim, run.final_episodes, run.eval_seed, arch=arch)
    row = {k: r[k] for k in ("agents", "success_rate", "mean_length", "dist", "episodes", "seed")}
    return {**row, "covered": r["covered"]} if r.get("covered") is not None else row


def policy_path(root: str, cell: Cell, seed: int, agents: int = 0, polished: bool = True) -> str:
    """Where a train cell's (or a curriculum stage's) final policy lies: the polished one
    where the cell polishes (``polished=False``: the one before the polish)."""
    d = cell_dir(root, cell, seed)
    if cell.kind == "curriculum":
        d = os.path.join(d, f"stage-m{agents}")
        if cell.run.polish_updates and polished:
            d += "-polish"  # trainer.curriculum's layout
    elif cell.run.polish_updates and polished:
        d = os.path.join(d, POLISH_DIR)
    return os.path.join(d, POLICY)


def run_dirs(root: str, cell: Cell, seed: int) -> list[str]:
    """The run directories of a train or curriculum cell in training order (a
    curriculum: stage by stage, each followed by its polish)."""
    d = cell_dir(root, cell, seed)
    if cell.kind == "train":
        return [d] + ([os.path.join(d, POLISH_DIR)] if cell.run.polish_updates else [])
    if cell.kind == "curriculum":
        return [
            os.path.dirname(policy_path(root, cell, seed, M, polished))
            for M in cell.run.sizes
            for polished in ((False, True) if cell.run.polish_updates else (False,))
        ]
    return []


def _note_attempt(directory: str) -> int:
    path = os.path.join(directory, ATTEMPTS)
    attempts = []
    if os.path.exists(path):
        with open(path) as f:
            attempts = json.load(f)
    attempts.append({"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()})
    atomic_write_json(path, attempts)
    return len(attempts)


def run_cell(
    cell: Cell, seed: int, root: str, source: Cell | None = None, arch: str = "cpu", device: str = "cpu"
) -> dict:
    """Bring one (cell, seed) to its result: train / run the curriculum / evaluate, then
    evaluate afresh and write result.json. ``source``: the cell this one reads (a
    zero-shot row's source, a run's init_from: ``cell.needs``); ``arch`` / ``device``:
    where the simulator / the network run (not part of the cell's definition: the same
    cell on a GPU is the same experiment). One process at a time per (cell, seed): a
    second is refused while the first holds the cell's lock."""
    done = read_result(root, cell, seed, source)
    if done is not None:
        return done
    source_result = None
    if cell.needs:  # checked before anything is written: an error leaves no trace
        role = "source" if cell.kind == "zero-shot" else "init_from"
        if source is None or source.id != cell.needs:
            raise SpecError(f"cell {cell.id!r} needs its {role} cell {cell.needs!r}")
        source_result = read_result(root, source, seed)
        if source_result is None:
            raise SpecError(f"cell {cell.id!r}: its {role} {source.id!r} (seed {seed}) has not finished")
    lock = RunDirLock(
        cell_dir(root, cell, seed),
        CELL_LOCK,
        holder=f"another `swarm reproduce` running cell {cell.id!r} (seed {seed})",
        advice="wait for it to finish, or stop it (it resumes where it stopped)",
    )
    with lock:
        return _bring_to_result(cell, seed, root, source, source_result, arch, device)


def _bring_to_result(
    cell: Cell, seed: int, root: str, source: Cell | None, source_result: dict | None, arch: str, device: str
) -> dict:
    """run_cell's work, under the cell's lock (its checks of ``source`` done)."""
    import torch

    done = read_result(root, cell, seed, source)  # (finished by another process meanwhile)
    if done is not None:
        return done
    run = cell.run
    init_from = getattr(run, "init_from", "")
    init = policy_path(root, source, seed, run.init_agents or source.run.agents) if init_from else ""
    directory = cell_dir(root, cell, seed)
    # options checked before anything is written: a fixed spec must not find a stale definition
    if cell.kind in ("train", "curriculum"):
        cfg = run_config(cell, seed, directory, arch, device, init)
    elif cell.kind == "baseline":
        cfg = baseline_config(cell, seed, directory, device)
    definition_path = os.path.join(directory, DEFINITION)
    if os.path.exists(definition_path):  # started before: by the same definition?
        with open(definition_path) as f:
            check_same_definition(definition_path, cell, json.load(f))
    else:
        atomic_write_json(definition_path, cell.definition())
    if init_from:  # a run resumes only from the upstream policy it started from
        upstream_path = os.path.join(directory, UPSTREAM)
        if not os.path.exists(upstream_path):
            atomic_write_json(upstream_path, {"cell": source.id, "finished": source_result["finished"]})
        with open(upstream_path) as f:
            if json.load(f)["finished"] != source_result["finished"]:
                raise SpecError(_retrained(upstream_path, cell))
    attempt = _note_attempt(directory)
    torch.set_num_threads(1)
    start = time.time()
    if cell.kind == "train":
        from trainer.curriculum import polish_stage, run_record
        from trainer.train import train_or_resume

        record = _training(run_record(train_or_resume(cfg)))
        if run.polish_updates:
            polish_dir = os.path.join(directory, POLISH_DIR)
            polish = polish_stage(cfg, polish_dir, run.polish_updates, run.polish_lr, 0, 0, record["updates"])
            before = final_eval(policy_path(root, cell, seed, polished=False), cell, run.agents, arch)
            record = _polished(record, polish, before)
        rows = [{**final_eval(policy_path(root, cell, seed), cell, run.agents, arch), **record}]
    elif cell.kind == "curriculum":
        from trainer.curriculum import run_curriculum

        stages = run_curriculum(cfg)  # (its run_dir: directory)
        rows = []
        for stage in stages:
            M = stage["agents"]
            record = {
                **_training(stage),
                "reached_threshold": stage["reached_threshold"],
                "stopping_success_rate": stage["success_rate"],
            }
            if "polish" in stage:
                before = final_eval(policy_path(root, cell, seed, M, polished=False), cell, M, arch)
                record = _polished(record, stage["polish"], before)
            rows.append({**final_eval(policy_path(root, cell, seed, M), cell, M, arch), **record})
    elif cell.kind == "baseline":
        rows = [run_baseline(cfg)]
    else:
        path = policy_path(root, source, seed, run.source_agents)
        rows = [final_eval(path, cell, M, arch) for M in run.sizes]
    result = {
        "cell": cell.id,
        "table": cell.table,
        "kind": cell.kind,
        "seed": seed,
        "digest": cell.digest(),
        "definition": cell.definition(),
        "rows": rows,
        "attempts": attempt,
        "source_finished": source_result["finished"] if source_result else None,
        "wall_time_last_attempt": time.time() - start,
        "finished": time.time(),
    }
    atomic_write_json(os.path.join(directory, RESULT), result)
    return result


def run_config(cell: Cell, seed: int, directory: str, arch: str = "cpu", device: str = "cpu", init_from: str = ""):
    """A train or curriculum cell's TrainConfig / CurriculumConfig for one run: the spec's,
    with the run's seed, directory, machine and start (a policy path), and the cell's transfer
    offsets; checked by the trainer."""
    cfg = dataclasses.replace(
        copy.deepcopy(cell.run.config), seed=seed, run_dir=directory, arch=arch, device=device,
        init_from=init_from, transfer_offsets=cell.transfer_offsets,
    )  # fmt: skip
    try:
        (cfg.train_config() if cell.kind == "curriculum" else cfg).validate()
    except ValueError as exc:
        raise SpecError(f"cell {cell.id!r}: {exc}") from None
    return cfg


def baseline_config(cell: Cell, seed: int, directory: str, device: str = "cpu"):
    """A baseline cell's BaselineConfig for one run (baselines.run.run takes it)."""
    from trainer.train import resolve_device

    return dataclasses.replace(cell.run.config, seed=seed, out=directory, device=resolve_device(device))


def run_baseline(cfg) -> dict:
    """Train and evaluate a stock BenchMARL algorithm (baselines.run.run) as ``cfg`` says; the
    row in this module's format. A stopped one resumes from its latest BenchMARL checkpoint
    (BenchMARL writes one every 25 iterations, as baselines/run.py sets it)."""
    try:
        from baselines.run import run
    except ImportError as exc:
        raise SpecError(f'a BenchMARL baseline: pip install -c constraints.txt -e ".[baselines]" ({exc})') from None
    summary = _finished_baseline(cfg)
    if summary is None:  # (a run killed after BenchMARL's results.json is not trained again)
        summary = run(cfg)
    return {
        "agents": cfg.sim.agents,
        "success_rate": summary["success_rate"],
        "mean_length": summary["mean_length"],
        "dist": summary["dist"],
        "episodes": summary["episodes"],
        "seed": summary["seed"],
        "env_steps": summary["frames"],
        "wall_time": summary["train_seconds"],
        "algorithm": summary["algorithm"],
        "actions": summary["actions"],
    }


def _finished_baseline(cfg) -> dict | None:
    """baselines/run.py's results.json in ``cfg.out`` if it answers ``cfg``."""
    path = os.path.join(cfg.out, "results.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        summary = json.load(f)
    same = (
        summary.get("algorithm") == cfg.algorithm
        and summary.get("task") == cfg.sim.task
        and summary.get("agents") == cfg.sim.agents
        and summary.get("obs_mode") == cfg.obs_mode
        and summary.get("train_seed") == cfg.seed
        and summary.get("frames", 0) >= cfg.frames
        and summary.get("episodes") == cfg.eval_episodes
        and summary.get("seed") == cfg.eval_seed
        and cfg.actions in ("any", summary.get("actions"))
    )
    return summary if same else None


def _training(record: dict) -> dict:
    """updates, env_steps, wall_time of a run's record (trainer.curriculum.run_record: a
    curriculum stage's, a polish's or a train cell's)."""
    return {k: record[k] for k in ("updates", "env_steps", "wall_time")}


def _polished(record: dict, polish: dict, before: dict) -> dict:
    """A run's counters with its polish added, and the fresh S% / T / DIST before it."""
    return {
        **record,
        "updates": record["updates"] + polish["updates"],
        "env_steps": record["env_steps"] + polish["env_steps"],
        "wall_time": record["wall_time"] + polish["wall_time"],
        "polish_updates": polish["updates"],
        "before_polish": {k: before[k] for k in ("success_rate", "mean_length", "dist")},
    }


def progress(root: str, cell: Cell, seed: int) -> dict:
    """How far a cell is, from its files: updates done (all stages), the budget, the
    training wall-clock so far (for the time-left estimate), and whether a process is
    working on it now (it holds the cell's lock)."""
    # the lock before the files: a cell that finishes in between reads done, not stopped
    running = is_held(cell_dir(root, cell, seed), CELL_LOCK)
    state = cell_state(root, cell, seed)
    updates, wall, stage, last_eval = 0, 0.0, None, None
    for run in run_dirs(root, cell, seed):
        rows = _last_metrics(os.path.join(run, METRICS))
        if rows:
            updates += rows[-1]["update"]
            wall += rows[-1].get("wall_time", 0.0)
            stage = os.path.basename(run) if cell.kind == "curriculum" else None
            evals = [r for r in rows if r.get("eval_success_rate") is not None]
            last_eval = (
                {"update": evals[-1]["update"], "success_rate": evals[-1]["eval_success_rate"]} if evals else None
            )
    return {
        "state": state,
        "running": running and state != "done",
        "updates": updates,
        "budget": cell.budget_updates(),
        "wall_time": wall,
        "stage": stage,
        "last_eval": last_eval,  # the latest evaluation during training of the latest run (stage)
    }


def _last_metrics(path: str, tail_bytes: int = 65536) -> list[dict]:
    """The records in the last ``tail_bytes`` of a metrics.jsonl, oldest first ([] if there
    is none): the last update's and, at eval_every up to about 100, the latest evaluation's."""
    if not os.path.exists(path):
        return []
    rows = []
    with open(path, "rb") as f:
        try:
            f.seek(-tail_bytes, os.SEEK_END)
        except OSError:
            f.seek(0)
        for line in f.read().decode(errors="replace").splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:  # a line cut by the seek, or one being written
                continue
    return rows
