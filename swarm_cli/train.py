"""``swarm train | eval | curriculum | zero-shot | plot``."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import sys

from swarm_cli.options import EvalOptions, ImportOptions, PlotOptions, ResumeOptions, ZeroShotOptions, cli, fail, parse
from trainer.checkpoint import CheckpointError, atomic_write_json, ensure_writable
from trainer.rundir import POLICY

USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, CheckpointError)


def _config_from_argv(argv: list[str], prog: str, config_type=None):
    """Pre-read --preset, then let tyro parse the rest over that preset's defaults
    (``config_type``: TrainConfig, or CurriculumConfig which extends it)."""

    from trainer.config import DEFAULT_PRESET, PRESET_UPDATES, PRESETS, TrainConfig

    config_type = config_type or TrainConfig
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default=DEFAULT_PRESET)
    known, _ = pre.parse_known_args(argv)
    if known.preset not in PRESETS:
        raise ValueError(f"--preset must be one of {tuple(PRESETS)}, got {known.preset!r}")
    # the chosen preset's values are the defaults tyro parses over and --help shows
    default = config_type(
        preset=known.preset, updates=PRESET_UPDATES[known.preset], ppo=copy.deepcopy(PRESETS[known.preset])
    )
    others = ", ".join(f"--preset {p}" for p in PRESETS if p != known.preset)
    description = f"{prog}: the defaults shown are those of --preset {known.preset} (others: {others})."
    return cli(config_type, argv, prog, default=default, description=description)


def train_main(argv: list[str]) -> int:
    """swarm train --resume RUN_DIR [--updates N] | [config options, see --help]"""
    from trainer.train import train

    try:
        if "--resume" in argv or any(a.startswith("--resume=") for a in argv):
            opts = parse(ResumeOptions, argv, "swarm train --resume RUN_DIR")
            given = any(a in ("--progress", "--no-progress") for a in argv)  # else the run's own setting
            summary = train(
                resume=opts.resume,
                updates=opts.updates,
                progress=opts.progress if given else None,
                arch=opts.arch,
                device=opts.device,
            )
        else:
            if "-h" in argv or "--help" in argv:
                print(
                    "swarm train --resume RUN_DIR [--updates N] [--no-progress] [--arch A] [--device D]\n"
                    "                      continue a stopped run (N raises its update budget)\n"
                    "swarm train [options below]   start a run\n"
                )
            summary = train(_config_from_argv(argv, "swarm train"))
    except KeyboardInterrupt:
        return 130
    except USER_ERRORS as exc:
        return fail("swarm train", exc)
    ev = summary["last_eval"]
    msg = (
        f"run {summary['run_dir']}: {summary['update']} updates, {summary['env_steps']} env steps, "
        f"{summary['wall_time'] / 60:.1f} min"
    )
    if ev:
        msg += f"; eval S% {100 * ev['success_rate']:.1f}, T {ev['mean_length']:.2f}"
    print(msg)
    policy = os.path.join(summary["run_dir"], POLICY)
    print(f"policy: {policy}")
    print(f"next: swarm eval {policy} --episodes 500 --seed 777")
    return 0


def _eval_settings(opts, payload: dict, agents: int | None = None):
    """The checkpoint's task setting with the command's --task/--comm/--comm-radius (and
    --agents) over it (taichi_swarm.TaskSetting)."""
    from taichi_swarm import TaskSetting

    return TaskSetting.resolve(
        payload.get("task"), "this checkpoint", task=opts.task, agents=agents, comm=opts.comm,
        comm_radius=opts.comm_radius,
    )  # fmt: skip


def swarm_setting(opts, payload: dict) -> dict:
    """The neighbour lists / density scaling the policy was trained on (its "swarm"
    record), with the command's --neighbours / --landmark-neighbours / --sense-radius /
    --scale over them."""
    from trainer.evaluate import swarm_options

    saved = payload.get("swarm") or {}
    if not isinstance(saved, dict) or set(saved) - {"neighbours", "landmark_neighbours", "sense_radius", "scale"}:
        raise ValueError(f"the checkpoint's swarm setting is not one of make()'s list options: {saved!r}")
    return swarm_options(**{**saved, **opts.swarm_kwargs()})


SAMPLED_NOTE = "(sampled actions: a diagnostic; the paper's numbers are greedy)"


def eval_main(argv: list[str]) -> int:
    opts = parse(EvalOptions, argv, "swarm eval")
    import torch

    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate, format_table

    try:
        for out, what in ((opts.json, "--json"), (opts.record, "--record")):
            if out:
                ensure_writable(out, what)
        torch.set_num_threads(1)
        policy, payload = load_policy(opts.checkpoint, trust_unsigned=opts.trust_unsigned)
        s = _eval_settings(opts, payload, opts.agents)
        agents = s.team_size("this checkpoint")
        from deploy.video import open_recorders

        recorder = open_recorders(opts, s.task, opts.episodes, agents, s.comm, s.comm_radius)
        try:
            result = evaluate(
                policy, s.task, agents, s.comm, s.comm_radius, opts.episodes, opts.seed, arch=opts.arch,
                recorder=recorder, actions=opts.actions, swarm=swarm_setting(opts, payload),
            )  # fmt: skip
        except BaseException:  # (Ctrl-C too): no recording or video written, none replaced
            if recorder is not None:
                recorder.close(ok=False)
            raise
        if recorder is not None:
            recorder.close()
            recorder.report()
    except USER_ERRORS as exc:
        return fail("swarm eval", exc)
    print(format_table([result]))
    if opts.sampled:
        print(SAMPLED_NOTE)
    if opts.json:
        atomic_write_json(opts.json, {"checkpoint": opts.checkpoint, **result})
    return 0


def zero_shot_main(argv: list[str]) -> int:
    opts = parse(ZeroShotOptions, argv, "swarm zero-shot")
    import torch

    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate, format_table, parse_sizes

    try:
        if opts.json:
            ensure_writable(opts.json, "--json")
        sizes = parse_sizes(list(opts.sizes))
        torch.set_num_threads(1)
        policy, payload = load_policy(opts.checkpoint, trust_unsigned=opts.trust_unsigned)
        s = _eval_settings(opts, payload)
        rows = []
        for M in sizes:
            rows.append(evaluate(policy, s.task, M, s.comm, s.comm_radius, opts.episodes, opts.seed,
                                 arch=opts.arch, actions=opts.actions, swarm=swarm_setting(opts, payload)))  # fmt: skip
            print(format_table(rows[-1:]).splitlines()[-1], flush=True)
    except USER_ERRORS as exc:
        return fail("swarm zero-shot", exc)
    print()
    print(format_table(rows))
    if opts.sampled:
        print(SAMPLED_NOTE)
    if opts.json:
        atomic_write_json(
            opts.json,
            {
                "checkpoint": opts.checkpoint,
                "trained_agents": payload.get("task", {}).get("agents"),
                "results": [{k: v for k, v in r.items() if k != "per_episode"} for r in rows],
            },
        )
    return 0


def curriculum_main(argv: list[str]) -> int:
    """swarm curriculum [--sizes 3 5 7 10] [--threshold 0.85] [--max-updates-per-stage N] [--polish-updates N]
    [train options]"""
    from trainer.config import CurriculumConfig
    from trainer.curriculum import format_stages, run_curriculum

    try:
        cfg = _config_from_argv(argv, "swarm curriculum", CurriculumConfig)
        if cfg.max_updates_per_stage < 1:
            raise ValueError(f"--max-updates-per-stage must be >= 1, got {cfg.max_updates_per_stage}")
        run_dir = cfg.default_run_dir()
        base = dataclasses.replace(cfg.train_config(), run_dir=run_dir)
        stages = run_curriculum(
            base, list(cfg.sizes), cfg.threshold, cfg.max_updates_per_stage, run_dir, cfg.min_updates_per_stage,
            cfg.fresh_eval_episodes, cfg.fresh_eval_seed, cfg.polish_updates, cfg.polish_lr,
        )  # fmt: skip
    except KeyboardInterrupt:
        # the stage said how to resume it alone; the curriculum resumes it and the stages after
        print("swarm curriculum: stopped; the same swarm curriculum command resumes it", file=sys.stderr)
        return 130
    except USER_ERRORS as exc:
        return fail("swarm curriculum", exc)
    print(format_stages(stages))
    return 0


def plot_main(argv: list[str]) -> int:
    opts = parse(PlotOptions, argv, "swarm plot")
    from trainer.plot import plot_run, plot_zero_shot

    try:
        if opts.zero_shot:
            print(plot_zero_shot(list(opts.zero_shot), opts.out, list(opts.labels) if opts.labels else None))
        else:
            print(plot_run(opts.run_dir, opts.out))
    except (FileNotFoundError, ValueError, json.JSONDecodeError) as exc:
        return fail("swarm plot", exc)
    return 0


def import_main(argv: list[str]) -> int:
    opts = parse(ImportOptions, argv, "swarm import")
    from trainer.published import import_to

    try:
        payload = import_to(opts.published, opts.out, task=opts.task, comm=opts.comm, comm_radius=opts.comm_radius)
    except USER_ERRORS as exc:
        return fail("swarm import", exc)
    except OSError as exc:
        return fail("swarm import", ValueError(f"cannot write {opts.out}: {exc.strerror}"))
    t = payload["task"]
    print(f"{opts.out}: {t['task']} policy for M={t['agents']}, {payload['model_config']['entity_mode']} entities")
    return 0
