"""``swarm train | eval | curriculum | zero-shot | plot``."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import sys

from trainer.checkpoint import CheckpointError, atomic_write_json, ensure_writable

USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, CheckpointError)


def _fail(cmd: str, exc: Exception) -> int:
    print(f"swarm {cmd}: error: {exc}", file=sys.stderr)
    return 2


def _config_from_argv(argv: list[str], prog: str, config_type=None):
    """Pre-read --preset, then let tyro parse the rest over that preset's defaults
    (``config_type``: TrainConfig, or CurriculumConfig which extends it)."""
    import tyro

    from trainer.config import PRESETS, TrainConfig

    config_type = config_type or TrainConfig
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default="paper")
    known, _ = pre.parse_known_args(argv)
    if known.preset not in PRESETS:
        raise ValueError(f"--preset must be one of {tuple(PRESETS)}, got {known.preset!r}")
    default = config_type(preset=known.preset, ppo=copy.deepcopy(PRESETS[known.preset]))
    return tyro.cli(config_type, args=argv, default=default, prog=prog)


def train_main(argv: list[str]) -> int:
    """swarm train [--resume RUN_DIR [--updates N]] | [config options, see --help]"""
    from trainer.train import train

    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--resume", default=None)
    known, rest = pre.parse_known_args(argv)
    if not known.resume and ("-h" in rest or "--help" in rest):
        print(
            "swarm train --resume RUN_DIR [--updates N]   continue a stopped run (N raises its update budget)\n"
            "swarm train [options below]                  start a run\n"
        )
    try:
        if known.resume:
            extra = argparse.ArgumentParser(prog="swarm train --resume RUN_DIR")
            extra.add_argument("--updates", type=int, default=None, help="raise the run's total update budget")
            more = extra.parse_args(rest)
            summary = train(resume=known.resume, updates=more.updates) if more.updates else train(resume=known.resume)
        else:
            cfg = _config_from_argv(rest, "swarm train")
            summary = train(cfg)
    except KeyboardInterrupt:
        return 130
    except USER_ERRORS as exc:
        return _fail("train", exc)
    ev = summary["last_eval"]
    msg = (
        f"run {summary['run_dir']}: {summary['update']} updates, {summary['env_steps']} env steps, "
        f"{summary['wall_time'] / 60:.1f} min"
    )
    if ev:
        msg += f"; eval S% {100 * ev['success_rate']:.1f}, T {ev['mean_length']:.2f}"
    print(msg)
    return 0


def _eval_parser(prog: str, sizes: bool) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog)
    ap.add_argument("checkpoint", help="checkpoint file or run directory")
    if sizes:
        ap.add_argument("--sizes", nargs="+", default=["2-8"], help="team sizes, e.g. 2-8 or 3 5 7")
    else:
        ap.add_argument("--agents", type=int, default=None, help="team size M (default: the training size)")
    ap.add_argument("--task", default=None, help="task (default: the training task)")
    ap.add_argument("--comm", default=None, help="uc | rc (default: the training setting)")
    ap.add_argument("--comm-radius", type=float, default=None, help="rc radius (default: the training setting)")
    ap.add_argument("--episodes", type=int, default=100, help="episodes, one per environment (default 100)")
    ap.add_argument("--seed", type=int, default=12345, help="seed of the evaluation episodes (default 12345)")
    ap.add_argument("--arch", default="cpu", help="simulator arch: cpu | cuda | auto")
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    if not sizes:
        ap.add_argument("--record", default=None, help="write a Rerun recording (.rrd) of the episodes")
        from deploy.video import add_output_options

        add_output_options(ap, "render the first episodes to a .gif or .mp4 (or a directory of PNG frames)")
    return ap


def _eval_settings(args, payload: dict, agents: int | None = None):
    """The checkpoint's task setting with the command's --task/--comm/--comm-radius (and
    --agents) over it (taichi_swarm.TaskSetting)."""
    from taichi_swarm import TaskSetting

    return TaskSetting.resolve(
        payload.get("task"), "this checkpoint", task=args.task, agents=agents, comm=args.comm,
        comm_radius=args.comm_radius,
    )  # fmt: skip


def eval_main(argv: list[str]) -> int:
    import torch

    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate, format_table

    args = _eval_parser("swarm eval", sizes=False).parse_args(argv)
    try:
        if args.episodes < 1:
            raise ValueError("--episodes must be >= 1")
        for out, what in ((args.json, "--json"), (args.record, "--record")):
            if out:
                ensure_writable(out, what)
        torch.set_num_threads(1)
        policy, payload = load_policy(args.checkpoint)
        s = _eval_settings(args, payload, args.agents)
        agents = s.team_size("this checkpoint")
        from deploy.video import open_recorders

        recorder = open_recorders(args, s.task, args.episodes, agents, s.comm, s.comm_radius)
        result = evaluate(
            policy,
            s.task,
            agents,
            s.comm,
            s.comm_radius,
            args.episodes,
            args.seed,
            arch=args.arch,
            recorder=recorder,
        )
        if recorder is not None:
            recorder.close()
            recorder.report()
    except USER_ERRORS as exc:
        return _fail("eval", exc)
    print(format_table([result]))
    if args.json:
        atomic_write_json(args.json, {"checkpoint": args.checkpoint, **result})
    return 0


def zero_shot_main(argv: list[str]) -> int:
    import torch

    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate, format_table, parse_sizes

    args = _eval_parser("swarm zero-shot", sizes=True).parse_args(argv)
    try:
        if args.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
        if args.json:
            ensure_writable(args.json, "--json")
        sizes = parse_sizes(args.sizes)
        torch.set_num_threads(1)
        policy, payload = load_policy(args.checkpoint)
        s = _eval_settings(args, payload)
        rows = []
        for M in sizes:
            rows.append(evaluate(policy, s.task, M, s.comm, s.comm_radius, args.episodes, args.seed, arch=args.arch))
            print(format_table(rows[-1:]).splitlines()[-1], flush=True)
    except USER_ERRORS as exc:
        return _fail("zero-shot", exc)
    print()
    print(format_table(rows))
    if args.json:
        atomic_write_json(
            args.json,
            {
                "checkpoint": args.checkpoint,
                "trained_agents": payload.get("task", {}).get("agents"),
                "results": [{k: v for k, v in r.items() if k != "per_episode"} for r in rows],
            },
        )
    return 0


def curriculum_main(argv: list[str]) -> int:
    """swarm curriculum [--sizes 3 5 7 10] [--threshold 0.85] [--max-updates-per-stage N] [train options]"""
    from trainer.config import CurriculumConfig
    from trainer.curriculum import format_stages, run_curriculum

    try:
        cfg = _config_from_argv(argv, "swarm curriculum", CurriculumConfig)
        if cfg.max_updates_per_stage < 1:
            raise ValueError(f"--max-updates-per-stage must be >= 1, got {cfg.max_updates_per_stage}")
        run_dir = cfg.default_run_dir()
        base = dataclasses.replace(cfg.train_config(), run_dir=run_dir)
        stages = run_curriculum(base, list(cfg.sizes), cfg.threshold, cfg.max_updates_per_stage, run_dir)
    except KeyboardInterrupt:
        return 130
    except USER_ERRORS as exc:
        return _fail("curriculum", exc)
    print(format_stages(stages))
    return 0


def plot_main(argv: list[str]) -> int:
    from trainer.plot import plot_run

    ap = argparse.ArgumentParser(prog="swarm plot", description="learning curves of a run, or zero-shot S% vs M")
    ap.add_argument("run_dir", nargs="?", help="run directory (learning curves)")
    ap.add_argument("--out", default=None, help="PNG path (default RUN_DIR/curves.png)")
    ap.add_argument("--zero-shot", nargs="+", default=None, metavar="JSON", help="`swarm zero-shot --json` files")
    ap.add_argument("--labels", nargs="+", default=None, help="legend labels of the --zero-shot files")
    args = ap.parse_args(argv)
    try:
        if args.zero_shot:
            from trainer.plot import plot_zero_shot

            if not args.out:
                raise ValueError("--zero-shot needs --out FILE.png")
            print(plot_zero_shot(args.zero_shot, args.out, args.labels))
            return 0
        if not args.run_dir:
            raise ValueError("pass a run directory, or --zero-shot JSON files with --out")
        print(plot_run(args.run_dir, args.out))
    except (FileNotFoundError, ValueError, json.JSONDecodeError) as exc:
        return _fail("plot", exc)
    return 0


def import_main(argv: list[str]) -> int:
    from trainer.published import import_to

    ap = argparse.ArgumentParser(
        prog="swarm import",
        description="Convert a checkpoint in the paper authors' published format (marl_transfer "
        "models/naM_uc.pt) into this project's policy format, for eval, zero-shot, export, "
        "execute and --init-from.",
    )
    ap.add_argument("published", help="the published .pt file")
    ap.add_argument("--out", required=True, help="where to write the converted policy (.pt)")
    ap.add_argument("--task", default=None, help="coverage | formation | line (default: from the input width)")
    ap.add_argument("--comm", default="uc", choices=("uc", "rc"), help="communication it is to run with")
    ap.add_argument("--comm-radius", type=float, default=1.0, help="rc radius (default 1.0)")
    args = ap.parse_args(argv)
    try:
        payload = import_to(args.published, args.out, task=args.task, comm=args.comm, comm_radius=args.comm_radius)
    except USER_ERRORS as exc:
        return _fail("import", exc)
    except OSError as exc:
        return _fail("import", ValueError(f"cannot write {args.out}: {exc.strerror}"))
    t = payload["task"]
    print(f"{args.out}: {t['task']} policy for M={t['agents']}, {payload['model_config']['entity_mode']} entities")
    return 0
