"""``swarm train | eval | curriculum | zero-shot | plot``."""

from __future__ import annotations

import json
import os
import sys
from typing import Annotated, Literal, TypedDict

import tyro

from swarm_cli.options import (
    EvalOptions,
    ImportOptions,
    PlotOptions,
    ZeroShotOptions,
    at_least,
    cli,
    fail,
    helptext,
    parse,
    struct_fields,
    without_none,
)  # fmt: skip
from taichi_swarm.sim import FIELDS as SIM_FIELDS
from trainer.checkpoint import CheckpointError, atomic_write_json, ensure_writable
from trainer.rundir import POLICY

USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, CheckpointError)


# `swarm train --help` / `swarm curriculum --help` lists the options a run is most often changed
# by first, then the rest in groups by what they are about; a group's flags keep their plain
# names (--neighbours, not --large-teams.neighbours). The simulated setting's fields (taichi_swarm.Sim,
# the config's ``sim``) are options of their own; those no other group names are "large teams",
# so a field added to the Sim is an option there. A field of the config in no group here is
# listed under "other" (a test keeps that group empty).
GROUPS = {
    "": ("", "task agents comm comm_radius preset updates seed run_dir device"),
    "curriculum": (
        "the stages over team sizes",
        "sizes threshold max_updates_per_stage min_updates_per_stage fresh_eval_episodes fresh_eval_seed "
        "polish_updates polish_lr",
    ),
    "large teams": ("neighbour lists and density scaling (docs/SWARM.md)", "*"),  # (*: the Sim's other fields)
    "faults": ("a lossy radio in training (evaluations are fault-free)", "message_drop drop_per_round"),
    "training": (
        "what the run learns from",
        "reward action_space team_sizes init_from trust_unsigned target_success min_updates",
    ),
    "evaluation": ("the evaluations during the run", "eval_every eval_episodes transfer_offsets"),
    "run management": ("the run directory and its display", "resume checkpoint_every progress tensorboard"),
    "compute": ("where and how the run computes", "arch torch_threads compile precision"),
}
RESUMED = ("updates", "progress", "arch", "device")  # what --resume takes; the rest is the run's own
RESUME = Annotated[
    str | None,
    tyro.conf.arg(
        metavar="RUN_DIR",
        help="continue the stopped run in RUN_DIR from its checkpoint.pt, with its own config: only "
        "--updates (raising its budget), --progress, --arch and --device go with it, each else the run's own",
        help_behavior_hint="",
    ),
]


def _text(value) -> str:
    return " ".join(map(str, value)) if isinstance(value, tuple) else str(value)


def _options(cls, values) -> dict:
    """The fields of dataclass ``cls`` as options tyro leaves out of its result unless given (a
    TypedDict's, total=False), each with its docstring and "(default: ...)": ``values(name)``, the
    field's value under each preset, shown as the default preset's and the others' that differ.
    The config's ``sim`` gives its fields as options of their own."""
    from taichi_swarm.sim import Sim
    from trainer.config import DEFAULT_PRESET, PRESETS

    out = {}
    for f in struct_fields(cls):
        if f.name == "sim":
            out.update(_options(Sim, lambda name: {p: getattr(s, name) for p, s in values("sim").items()}))
            continue
        typ, by_preset = f.type, values(f.name)
        if f.name == "preset":  # a choice: tyro refuses another naming the presets
            typ, by_preset = Literal[tuple(PRESETS)], {DEFAULT_PRESET: DEFAULT_PRESET}
        elif None not in by_preset.values():
            typ = without_none(typ)  # (never None here)
        default = by_preset[DEFAULT_PRESET]
        others = ", ".join(f"{p}: {_text(v)}" for p, v in by_preset.items() if v != default)
        hint = f"(default: {_text(default)}" + (f"; --preset {others})" if others else ")")
        out[f.name] = Annotated[typ, tyro.conf.arg(help=helptext(f), help_behavior_hint=hint)]
    return out


# groups `--help` leaves to `--help-all`: what a first run never changes (the network, PPO, compute)
ADVANCED = ("compute", "model", "ppo")


def _schema(config_type, brief: bool = False):
    """What tyro parses ``swarm train`` / ``swarm curriculum`` into: a dict of the options given,
    the groups of GROUPS nested in it (and model, ppo). ``brief``: without ADVANCED, for
    ``--help`` (those options are then neither listed nor parsed)."""
    from trainer.config import PRESETS, STAGE_SET, PPOConfig
    from trainer.model import ModelConfig

    configs = {p: config_type.with_preset(p) for p in PRESETS}
    fields = _options(config_type, lambda name: {p: getattr(c, name) for p, c in configs.items()})
    if hasattr(config_type, "sizes"):  # (a curriculum's stages set these; it resumes by its own command)
        for name in (*STAGE_SET, "team_sizes"):
            del fields[name]
    else:
        fields["resume"] = RESUME
    top, named = {}, {name for _, names in GROUPS.values() for name in names.split()}
    for title, (about, names) in [*GROUPS.items(), ("other", ("", " ".join(fields)))]:
        if names == "*":
            names = " ".join(name for name in SIM_FIELDS if name not in named)
        group = {name: fields.pop(name) for name in names.split() if name in fields and name not in ("model", "ppo")}
        if not title:
            top = group
        elif group and not (brief and title in ADVANCED):
            top[title] = Annotated[
                TypedDict(title, group, total=False), tyro.conf.OmitArgPrefixes, tyro.conf.arg(help=about)
            ]
    for name, cls in (("model", ModelConfig), ("ppo", PPOConfig)):
        if brief:
            continue
        nested = _options(cls, lambda n, name=name: {p: getattr(getattr(c, name), n) for p, c in configs.items()})
        help_ = fields.pop(name).__metadata__[0].help
        top[name] = Annotated[TypedDict(name, nested, total=False), tyro.conf.arg(help=help_)]
    return TypedDict(config_type.__name__, top, total=False)


def given_options(argv: list[str], prog: str, config_type) -> dict:
    """The options given in ``argv``, as ``config_type.with_preset`` takes them (model and ppo:
    dicts of their fields given; resume too, for swarm train)."""
    from trainer.config import DEFAULT_PRESET, PRESETS

    others = ", ".join(p for p in PRESETS if p != DEFAULT_PRESET)
    staged = hasattr(config_type, "sizes")  # (a curriculum's stages set --updates)
    description = (
        f"{prog}: {'' if staged else '--updates and '}the --ppo options not given take the preset's values "
        f"(shown: --preset {DEFAULT_PRESET}'s, then {others} where they differ); an option given wins over the preset."
    )
    # --help shows the options a run is changed by first; --help-all every one (network, PPO, compute)
    brief = any(a in ("-h", "--help") for a in argv) and "--help-all" not in argv
    if brief:
        description += " --help-all lists the network (--model.*), PPO (--ppo.*) and compute options too."
    argv = ["--help" if a == "--help-all" else a for a in argv]
    given = {}
    for key, value in cli(_schema(config_type, brief), argv, prog, description=description).items():
        if key in GROUPS or key == "other":
            given.update(value)
        else:
            given[key] = value
    return given


def config_from_argv(argv: list[str], prog: str, config_type=None):
    """``config_type`` (TrainConfig, or CurriculumConfig which extends it) from the command line:
    the preset's values under the options given."""
    from trainer.config import TrainConfig

    config_type = config_type or TrainConfig
    return _config(config_type, given_options(argv, prog, config_type))


def _config(config_type, given: dict):
    from trainer.model import ModelConfig

    model = ModelConfig(**given.pop("model"))
    return config_type.with_preset(**given, model=model)


def train_main(argv: list[str]) -> int:
    """swarm train [options, see --help] | --resume RUN_DIR [--updates N]"""
    from trainer.config import TrainConfig
    from trainer.train import train

    try:
        given = given_options(argv, "swarm train", TrainConfig)
        resume = given.pop("resume", None)
        if resume is None:
            summary = train(_config(TrainConfig, given))
        else:
            others = [
                " ".join(f"--{k}.{n}" for n in v) if isinstance(v, dict) else f"--{k}"
                for k, v in given.items()
                if k not in RESUMED and v != {}
            ]
            if others:
                raise ValueError(
                    "--resume continues the run with its own config: only --updates, --progress, --arch and "
                    f"--device go with it, not {' '.join(others).replace('_', '-')}"
                )
            at_least(given.get("updates"), 1, "updates")
            summary = train(resume=resume, **{k: given.get(k) for k in RESUMED})
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


def run_sim(opts, payload: dict, agents: int | None = None):
    """The setting the checkpoint records (``taichi_swarm.Sim``), with the options the command
    sets over it (``Sim.override``: the same checks as training)."""
    from taichi_swarm.sim import Sim

    overrides = {"agents": agents, **opts.setting_options(), **opts.swarm_kwargs()}
    return Sim.resolve(payload.get("task"), payload.get("swarm"), "this checkpoint", **overrides)


SAMPLED_NOTE = "(sampled actions: a diagnostic; the paper's numbers are greedy)"


def eval_main(argv: list[str]) -> int:
    opts = parse(EvalOptions, argv, "swarm eval")
    import torch

    from trainer.checkpoint import load_policy
    from trainer.evaluate import evaluate, format_table

    try:
        opts.check_outputs()
        torch.set_num_threads(1)
        policy, payload = load_policy(opts.checkpoint, trust_unsigned=opts.trust_unsigned)
        s = run_sim(opts, payload, opts.agents)
        agents = s.team_size("this checkpoint")
        from deploy.video import open_recorders

        recorder = open_recorders(opts, s.task, opts.episodes, agents, s.comm, s.comm_radius)
        try:
            result = evaluate(
                policy, s, opts.episodes, opts.seed, arch=opts.arch, recorder=recorder, actions=opts.actions,
                progress=True,
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
    if "messages_per_agent_step" in result:  # the agents' auction by radio
        m, b = result["messages_per_agent_step"], result["bytes_per_agent_step"]
        print(f"auction by radio: {m:.1f} messages ({b / 1e3:.2f} kB) received per agent-step")
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
        if opts.json is not None:  # ('' too: refused, not skipped)
            ensure_writable(opts.json, "--json")
        sizes = parse_sizes(list(opts.sizes))
        torch.set_num_threads(1)
        policy, payload = load_policy(opts.checkpoint, trust_unsigned=opts.trust_unsigned)
        s = run_sim(opts, payload)
        rows = []
        for M in sizes:
            rows.append(evaluate(policy, s.override(agents=M), opts.episodes, opts.seed, arch=opts.arch,
                                 actions=opts.actions, progress=True))  # fmt: skip
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
                # the lists the policy trained on: a curve run on others is told apart by them
                "trained_swarm": payload.get("swarm") or {},
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
        stages = run_curriculum(config_from_argv(argv, "swarm curriculum", CurriculumConfig))
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
