"""Curriculum over team sizes (s.6): train M = 3, then 5, 7, 10, each stage
starting from the previous stage's weights with a fresh optimiser and reward
normaliser, moving on once evaluation success reaches the threshold.
Records S% and the number of updates N per stage (the paper's tables 2, 3), and,
with ``fresh_eval_episodes``, each stage's final policy on that many fresh greedy
episodes: the evaluation that ended a stage is the first of several noisy ones to
pass the threshold, so it overstates the stage. Re-running the same command
resumes: finished stages are skipped (their fresh evaluation is kept in the stage
directory), a stopped stage continues from its checkpoint.

With ``polish_updates``, each stage is then trained on for that many updates at a low
constant learning rate (``polish_lr``) from its weights, with no target, in a sibling run
directory ``stage-m<M>-polish``; the next stage starts from the polished weights. Measured
here (docs/FINDINGS.md, polishing): 300-400 such updates at 3e-5 took coverage RC M = 10 from
81.0 to 87.4%, line RC M = 10 from 83.8 to 94.8%, coverage RC M = 3 from 95.4 to 98.4%, and
left coverage RC M = 5 where it was (94.8 / 94.2%)."""

from __future__ import annotations

import dataclasses
import json
import os

from trainer import checkpoint
from trainer.config import CurriculumConfig, TrainConfig
from trainer.evaluate import evaluate
from trainer.rundir import CHECKPOINT, FRESH_EVAL, POLICY, POLISH_OF, STARTED_FROM
from trainer.train import resolve_device, train_or_resume

MIN_STAGE_EVAL_EPISODES = 200
CURRICULUM = "curriculum.json"  # in the curriculum's directory: every stage's record


def fresh_evaluation(stage_dir: str, cfg: TrainConfig, update: int, episodes: int, seed: int) -> dict:
    """S%, T, DIST of the stage's final policy (``stage_dir/policy.pt``, at ``update``) on
    ``episodes`` fresh greedy episodes from ``seed``, in the setting the policy was trained
    in (its own task, team size, comm and radius, whatever this command says); kept in
    ``stage_dir/fresh-eval.json`` and reused while policy, setting, episodes and seed match."""
    policy, _ = checkpoint.load_policy(os.path.join(stage_dir, POLICY))
    sim = policy.sim
    if sim is None:
        raise checkpoint.CheckpointError(f"{stage_dir}/{POLICY} does not say its task")
    sim.team_size(f"{stage_dir}/{POLICY}")
    key = {
        "update": update,
        "episodes": episodes,
        "seed": seed,
        "arch": cfg.arch,
        **sim.task_record(),
        **sim.swarm_record(),
    }
    path = os.path.join(stage_dir, FRESH_EVAL)
    if os.path.exists(path):
        with open(path) as f:
            saved = json.load(f)
        if all(saved.get(k) == v for k, v in key.items()):
            return saved
    device = resolve_device(cfg.device)
    policy.to(device)
    result = evaluate(policy, sim, episodes, seed, arch=cfg.arch, device=device)
    fresh = {**key, **{k: result[k] for k in ("success_rate", "mean_length", "dist")}}
    checkpoint.atomic_write_json(path, fresh)
    return fresh


def check_curriculum(cfg: CurriculumConfig) -> None:
    """run_curriculum's checks of its options and of every stage's config, before anything is
    written (``swarm reproduce`` runs them when it loads a spec)."""
    sizes, base = cfg.sizes, cfg.train_config()
    if not sizes:
        raise ValueError("--sizes must name at least one team size")
    if len(set(sizes)) != len(sizes):  # a repeated stage would train the same size twice, from itself
        raise ValueError(f"--sizes must not repeat a team size, got {list(sizes)}")
    if not 0 < cfg.threshold <= 1:
        raise ValueError(f"--threshold must be in (0, 1], got {cfg.threshold}")
    if cfg.max_updates_per_stage < 1:
        raise ValueError(f"--max-updates-per-stage must be >= 1, got {cfg.max_updates_per_stage}")
    if not 0 <= cfg.min_updates_per_stage <= cfg.max_updates_per_stage:
        raise ValueError(
            f"--min-updates-per-stage must be in [0, --max-updates-per-stage={cfg.max_updates_per_stage}], "
            f"got {cfg.min_updates_per_stage}"
        )
    if cfg.fresh_eval_episodes < 0:
        raise ValueError(f"--fresh-eval-episodes must be >= 0, got {cfg.fresh_eval_episodes}")
    if cfg.fresh_eval_seed < 0:
        raise ValueError(f"--fresh-eval-seed must be >= 0, got {cfg.fresh_eval_seed}")
    if cfg.polish_updates < 0:
        raise ValueError(f"--polish-updates must be >= 0, got {cfg.polish_updates}")
    if not 0 < cfg.polish_lr <= 1:  # (NaN and inf too: before stage 1 trains, not after it)
        raise ValueError(f"--polish-lr must be in (0, 1], got {cfg.polish_lr}")
    if base.team_sizes:  # every stage would train on them and be judged at its own size
        raise ValueError(
            f"--team-sizes {list(base.team_sizes)} cannot go with a curriculum: each stage trains on its "
            "own team size (--sizes)"
        )
    for M in sizes:  # every stage's config checked before the run directory is made
        dataclasses.replace(
            base,
            sim=base.sim_at(M),
            updates=cfg.max_updates_per_stage,
            target_success=cfg.threshold,
            min_updates=cfg.min_updates_per_stage,
        ).validate()


def run_curriculum(cfg: CurriculumConfig) -> list[dict]:
    """Train the stages of ``cfg`` in its run directory (``default_run_dir``), or resume them."""
    check_curriculum(cfg)
    run_dir = cfg.default_run_dir()
    base = dataclasses.replace(cfg.train_config(), run_dir=run_dir)
    sizes, threshold, max_updates_per_stage = cfg.sizes, cfg.threshold, cfg.max_updates_per_stage
    min_updates_per_stage, polish_updates, polish_lr = cfg.min_updates_per_stage, cfg.polish_updates, cfg.polish_lr
    fresh_eval_episodes, fresh_eval_seed = cfg.fresh_eval_episodes, cfg.fresh_eval_seed
    os.makedirs(run_dir, exist_ok=True)
    results_path = os.path.join(run_dir, CURRICULUM)
    stages: list[dict] = []
    previous_ckpt, previous_update = base.init_from, None
    for M in sizes:
        stage_dir = os.path.join(run_dir, f"stage-m{M}")
        if previous_update is not None:
            previous_dir = os.path.dirname(previous_ckpt)
            then = _pin_upstream(stage_dir, STARTED_FROM, {"run": previous_dir, "update": previous_update}, "update")
            if then is not None:
                raise ValueError(
                    f"{stage_dir} started from {previous_dir} as it was at update {then}; it now ends at update "
                    f"{previous_update}: move {stage_dir} and the stages after it away to train them from it"
                )
        stage_cfg = dataclasses.replace(
            base,
            sim=base.sim_at(M),
            run_dir=stage_dir,
            init_from=previous_ckpt,
            updates=max_updates_per_stage,
            target_success=threshold,
            min_updates=min_updates_per_stage,
            # a stage advances on an evaluation of at least 200 episodes: 100 overstated
            # stages by up to 10 points (docs/FINDINGS.md)
            eval_episodes=max(base.eval_episodes, MIN_STAGE_EVAL_EPISODES),
        )
        summary = train_or_resume(stage_cfg)
        stage = {
            "agents": M,
            **run_record(summary),
            "reached_threshold": summary["reached_target"],
            "run_dir": stage_dir,
        }
        if fresh_eval_episodes:
            stage["fresh_eval"] = fresh_evaluation(
                stage_dir, stage_cfg, summary["update"], fresh_eval_episodes, fresh_eval_seed
            )
        final_dir = stage_dir
        if polish_updates:
            final_dir = f"{stage_dir}-polish"
            stage["polish"] = polish_stage(
                stage_cfg, final_dir, polish_updates, polish_lr, fresh_eval_episodes, fresh_eval_seed, summary["update"]
            )
        stages.append(stage)
        checkpoint.atomic_write_json(
            results_path, {"task": base.sim.task, "comm": base.sim.comm, "threshold": threshold, "stages": stages}
        )
        previous_ckpt = os.path.join(final_dir, CHECKPOINT)
        previous_update = stage["polish"]["updates"] if polish_updates else summary["update"]
        if not summary["reached_target"]:
            print(
                f"stage M={M} stopped at {summary['update']} updates below the threshold; "
                "later stages start from its weights anyway"
            )
    return stages


def _pin_upstream(run_dir: str, marker: str, record: dict, key: str) -> int | None:
    """A run made from another (a stage from the stage before it, a polish from its stage)
    is only ever resumed or read back from that run as it ended when this one began: the
    first time, ``record`` (that run's last update at ``key``) is written to ``marker``.
    Returns the update it was made from if that differs from ``record[key]`` now (the caller
    refuses: a stage continued with a larger --max-updates-per-stage would otherwise hand its
    old weights' successors on as if made from the new ones), else None."""
    path = os.path.join(run_dir, marker)
    if os.path.exists(path):
        with open(path) as f:
            then = json.load(f)[key]
        return then if then != record[key] else None
    os.makedirs(run_dir, exist_ok=True)
    checkpoint.atomic_write_json(path, record)
    return None


def run_record(summary: dict) -> dict:
    """A finished run's last evaluation and counters, as curriculum.json records them."""
    last = summary["last_eval"] or {}
    return {
        "success_rate": last.get("success_rate"),
        "mean_length": last.get("mean_length"),
        "dist": last.get("dist"),
        "updates": summary["update"],
        "env_steps": summary["env_steps"],
        "wall_time": summary["wall_time"],
    }


def polish_stage(
    stage_cfg: TrainConfig,
    polish_dir: str,
    updates: int,
    lr: float,
    fresh_eval_episodes: int,
    fresh_eval_seed: int,
    stage_update: int,
) -> dict:
    """Train the finished stage of ``stage_cfg`` on from its weights (fresh optimiser and
    normaliser) for ``updates`` updates at the constant learning rate ``lr``, no target;
    resumes like a stage. ``stage_update``: where the stage ended; a polish of the stage as
    it ended before (a stage given more updates since) is an error, never reused. Returns
    its record for curriculum.json."""
    polish_cfg = dataclasses.replace(
        stage_cfg,
        run_dir=polish_dir,
        init_from=os.path.join(stage_cfg.run_dir, CHECKPOINT),
        updates=updates,
        target_success=0.0,
        min_updates=0,
        ppo=dataclasses.replace(stage_cfg.ppo, lr=lr, lr_end=None),
    )
    polish_cfg.validate()  # before its directory and polish-of.json are made
    then = _pin_upstream(
        polish_dir, POLISH_OF, {"stage": stage_cfg.run_dir, "stage_update": stage_update}, "stage_update"
    )
    if then is not None:
        raise ValueError(
            f"{polish_dir} polished {stage_cfg.run_dir} as it was at update {then}; it now ends at "
            f"update {stage_update}: move {polish_dir} away to polish the stage again"
        )
    summary = train_or_resume(polish_cfg)
    record = {**run_record(summary), "lr": lr, "run_dir": polish_dir}
    if fresh_eval_episodes:
        record["fresh_eval"] = fresh_evaluation(
            polish_dir, polish_cfg, summary["update"], fresh_eval_episodes, fresh_eval_seed
        )
    return record


def format_stages(stages: list[dict]) -> str:
    """S% is the evaluation that ended the stage; "fresh S%" its final policy on fresh
    episodes (shown where the curriculum ran with fresh_eval_episodes); "polished S%" and
    "+N" the stage trained on (``polish_updates``), on fresh episodes where those ran."""
    fresh = any("fresh_eval" in s for s in stages)
    polished = any("polish" in s for s in stages)
    head = f"{'M':>3} {'S%':>6}" + (f" {'fresh S%':>9} {'T':>6}" if fresh else "")
    head += f" {'N (updates)':>12} {'env steps':>10} {'minutes':>8}  reached"
    head += f" {'polished S%':>12} {'+N':>5}" if polished else ""
    lines = [head, "-" * len(head)]
    for s in stages:
        line = f"{s['agents']:>3} {percent(s['success_rate']):>6}"
        if fresh:
            f = s.get("fresh_eval")
            line += f" {100 * f['success_rate']:>9.1f} {f['mean_length']:>6.2f}" if f else f" {'-':>9} {'-':>6}"
        line += (
            f" {s['updates']:>12} {s['env_steps']:>10} "
            f"{s['wall_time'] / 60:>8.1f}  {'yes' if s['reached_threshold'] else 'no':<7}"
        )
        if polished:
            p = s.get("polish")
            sr = (p.get("fresh_eval") or p)["success_rate"] if p else None
            line += f" {percent(sr):>12} {p['updates'] if p else '-':>5}"
        lines.append(line.rstrip())
    if fresh:
        f = next(s["fresh_eval"] for s in stages if "fresh_eval" in s)
        lines.append(f"fresh S%, T: the stage's final policy on {f['episodes']} greedy episodes, seed {f['seed']}")
    return "\n".join(lines)


def percent(rate: float | None) -> str:
    return "-" if rate is None else f"{100 * rate:.1f}"
