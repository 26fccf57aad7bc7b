"""The options of every ``swarm`` command, as typed dataclasses parsed by tyro.

One config system for the whole CLI: each command's options are one dataclass here
(train and curriculum parse into ``trainer.config.TrainConfig`` / ``CurriculumConfig``, in
groups and over a preset: ``swarm_cli.train``); a field's docstring is its ``--help`` text
and its default is shown beside it. Checks
that need no file or library run in ``__post_init__`` and raise ``OptionError``; tyro
reports those like a value it refuses itself (a message naming the option, then
SystemExit(2), which ``swarm_cli.main.dispatch`` returns as the exit status). A list
option given with no value is refused too. Shared pieces (the task setting a checkpoint is run in, the
recording and video outputs) are base classes, so each option is declared once.

This module imports neither torch nor Taichi: ``swarm execute`` and ``swarm replay``
stay torch-free.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import os
import re
import sys
import types
import typing
from dataclasses import dataclass
from typing import Annotated, Literal

import tyro

from taichi_swarm.sim import RUN_TIME_KEYS

Positional = tyro.conf.Positional


def Default(meaning: str, metavar: str | None = None):
    """What an unset (None) option means, shown in --help as "(default: meaning)"."""
    return tyro.conf.arg(metavar=metavar, help_behavior_hint=f"(default: {meaning})")


class OptionError(ValueError):
    """A command-line value that is out of range or inconsistent with another."""


def box_message(text: str) -> str:
    """The message of a box tyro drew (after its title, up to the next rule), as one line;
    rich draws it in Unicode or, where the output cannot take that, in ASCII."""
    lines = [line.strip().strip("│┃|").strip() for line in text.splitlines()]
    lines = [line for line in lines if line]

    def is_rule(line: str) -> bool:
        return set(line) <= set("─━-=+╭╮╰╯ ")

    body, started = [], False
    for line in lines[1:]:  # (the first is the title)
        if is_rule(line):
            if started:
                break
            continue
        started = True
        body.append(line)
    message = re.sub(r"\s+", " ", " ".join(body)).strip() or text.strip()
    return re.sub(r"^Error parsing [A-Za-z_]\w*: ", "", message)  # (a dataclass's name: a flag's stays)


def cli(options_type, argv: list[str], prog: str, **kwargs):
    """``tyro.cli``, with a refusal printed as one line, ``prog: error: why``, as every other
    refusal is (tyro draws a box); --help and its exit pass through."""
    if "-h" in argv or "--help" in argv:  # help as tyro draws it, at the terminal's width
        return tyro.cli(options_type, args=argv, prog=prog, **kwargs)
    captured = io.StringIO()
    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100000"  # no wrapping inside the box: its message is taken whole
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(options_type, args=argv, prog=prog, **kwargs)
    except SystemExit as exc:
        text = captured.getvalue()
        if exc.code not in (0, None) and text.strip():
            print(f"{prog}: error: {box_message(text)} (see {prog} --help)", file=sys.stderr)
        else:
            sys.stderr.write(text)
        raise
    finally:
        if columns is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = columns


def parse(options_type, argv: list[str], prog: str, default=None, description: str | None = None):
    """``options_type`` from ``argv`` (tyro). A refused value prints why in one line and raises
    SystemExit(2), as argparse does; so does a list option given no value (tyro accepts
    ``--drop`` alone as an empty list, which no option here means)."""
    options = cli(options_type, argv, prog, default=default, description=description)
    for f in dataclasses.fields(options):
        if getattr(options, f.name) == ():
            print(f"{prog}: error: --{f.name.replace('_', '-')} needs at least one value", file=sys.stderr)
            raise SystemExit(2)
    return options


def fail(prog: str, exc: BaseException | str) -> int:
    """One error line for a refused input found after parsing (a missing file, a bad
    checkpoint); returns the exit status 2. A refused setting (taichi_swarm.ConfigError) names
    its field as the command line spells it."""
    print(f"{prog}: error: {option_text(exc)}", file=sys.stderr)
    return 2


def option_text(exc: BaseException | str) -> str:
    """A refusal's message, a setting's field (taichi_swarm.ConfigError) named as its option."""
    text, field = str(exc), getattr(exc, "field", None)
    if field and text.startswith(field):
        text = f"--{field.replace('_', '-')}{text[len(field) :]}"
    return text


def check_setting(options: dict) -> dict:
    """The setting's options set, each through its own check (taichi_swarm.sim.CHECKS, the one
    validator of that key; no Taichi is imported), refused as the option; returns them."""
    from taichi_swarm.sim import CHECKS, ConfigError, check_value

    given = {k: v for k, v in options.items() if v is not None}
    for name, value in given.items():
        try:
            if name in CHECKS:  # (the task's name is checked against the registry, by the Sim)
                check_value(name, value)
        except ConfigError as exc:
            raise OptionError(option_text(exc)) from None
    return given


def at_least(value, low, name: str) -> None:
    if value is not None and not value >= low:
        raise OptionError(f"--{name} must be >= {low}, got {value}")


def positive(value, name: str) -> None:
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise OptionError(f"--{name} must be a positive finite number, got {value}")


Comm = Literal["uc", "rc"]
OWN = "the policy's own"
MAX_SEEDS = 1000  # swarm reproduce --seeds
MAX_EXECUTE_EPISODES = 10_000  # swarm execute: one environment per episode, all in one batch (its state arrays)
EVAL_SEED_LIMIT = 2**40  # trainer.train.TRAIN_SEED_BASE: training's environment streams (not imported: no torch here)
Arch = Literal["cpu", "cuda", "gpu", "auto"]  # Taichi arch (taichi_swarm.runtime.ARCHES)


# ----------------------------------------------------------------------------- shared pieces
def struct_fields(cls) -> list:
    """The fields of dataclass ``cls`` as tyro reads them (name, type, default, helptext)."""
    from tyro.constructors import ConstructorRegistry, StructTypeInfo

    return ConstructorRegistry.get_struct_spec(StructTypeInfo.make(cls, tyro.MISSING_NONPROP, False)).fields


def helptext(f) -> str:
    """A tyro struct field's --help text (its docstring)."""
    return f.helptext() if callable(f.helptext) else f.helptext


def without_none(typ):
    """``typ`` less None (``int | None`` -> ``int``)."""
    if typing.get_origin(typ) not in (typing.Union, types.UnionType):
        return typ
    return typing.Union[tuple(a for a in typing.get_args(typ) if a is not type(None))]


def _sim_view(name: str, keys: tuple, method: str, about: str):
    """A dataclass of the options a command sets over a stored policy's setting: the fields
    ``keys`` of taichi_swarm.Sim, each with the Sim's docstring as its --help, unset (None: the
    policy's own) by default, checked at parse time by the Sim's own check of that key. ``method``
    returns those given, as ``Sim.override`` keywords."""
    from taichi_swarm.sim import Sim

    docs = {f.name: helptext(f) for f in struct_fields(Sim)}
    hints, fields = typing.get_type_hints(Sim), []
    for key in keys:
        typ, base = hints[key], without_none(hints[key])
        metavar = None if typing.get_origin(base) is typing.Literal else base.__name__.upper()
        arg = tyro.conf.arg(help=docs[key], metavar=metavar, help_behavior_hint=f"(default: {OWN})")
        fields.append((key, Annotated[typ | None, arg], dataclasses.field(default=None)))

    def given(self) -> dict:
        return check_setting({key: getattr(self, key) for key in keys})

    def post_init(self):
        given(self)

    namespace = {"__post_init__": post_init, method: given, "__module__": __name__, "__doc__": about}
    return dataclasses.make_dataclass(name, fields, kw_only=True, namespace=namespace)


# The Sim's fields a command runs a stored policy on, made from the Sim, so a field added there is an
# option of eval, zero-shot and execute too: the task's (SettingOptions; world and export take
# those alone), and the simulator's (SwarmOptions: sim.RUN_TIME_KEYS).
SettingOptions = _sim_view(
    "SettingOptions", ("task", "comm", "comm_radius"), "setting_options",
    "The task setting to run a policy in; each unset field keeps the checkpoint's.",
)  # fmt: skip
SwarmOptions = _sim_view(
    "SwarmOptions", RUN_TIME_KEYS, "swarm_kwargs",
    "The simulator's lists, sensing, auction and scaling to run a policy on; each unset keeps the policy's.",
)  # fmt: skip


@dataclass(kw_only=True)
class VideoOption:
    video: Annotated[str | None, tyro.conf.arg(aliases=("--gif", "--mp4"))] = None
    """render to a .gif or .mp4 (a path without extension: a directory of PNG frames)"""


@dataclass(kw_only=True)
class OutputOptions(VideoOption):
    record: str | None = None
    """record the episodes: FILE.npz the trajectory record (`swarm replay` reads it), else a Rerun .rrd"""
    record_envs: int = 4
    """environments drawn by --record / --video"""

    def __post_init__(self):
        at_least(self.record_envs, 1, "record-envs")

    def check_outputs(self) -> None:
        """--json, --record and --video writable, checked before any episode runs (a command
        that fails on its last write would have wasted the run, or left half its files)."""
        from taichi_swarm.files import ensure_writable

        for out, what in ((getattr(self, "json", None), "--json"), (self.record, "--record")):
            if out is not None:  # ('' too: refused, not skipped)
                ensure_writable(out, what)
        if self.video is not None:
            from deploy.video import check_video_path

            check_video_path(self.video)


# ----------------------------------------------------------------------------- trainer commands
@dataclass(kw_only=True)
class EvaluationOptions(SettingOptions, SwarmOptions):
    """What every evaluation of a checkpoint takes (swarm eval, swarm zero-shot)."""

    checkpoint: Annotated[str, Positional, tyro.conf.arg(metavar="CHECKPOINT")]
    """checkpoint file or run directory"""
    episodes: int = 100
    """episodes (per team size), one per environment"""
    seed: int = 777
    """seed of the evaluation episodes (777, the documented numbers', is one training never uses)"""
    arch: Arch = "cpu"
    """simulator arch"""
    json: str | None = None
    """also write the results to this JSON file"""
    trust_unsigned: bool = False
    """load a checkpoint that carries no sha256 (from before digests existed): corruption in it cannot be detected"""
    sampled: bool = False
    """draw actions from the policy's distribution instead of argmax (a diagnostic: the paper
    and docs/RESULTS.md report greedy actions; a large gap shows a policy that relies on
    randomness, e.g. to break ties between agents)"""

    def __post_init__(self):
        SettingOptions.__post_init__(self)
        SwarmOptions.__post_init__(self)
        at_least(self.episodes, 1, "episodes")
        if not 0 <= self.seed < EVAL_SEED_LIMIT:
            raise OptionError(f"--seed must be in [0, 2^40) (training seeds from 2^40 up), got {self.seed}")

    @property
    def actions(self) -> str:
        return "sampled" if self.sampled else "greedy"


@dataclass(kw_only=True)
class EvalOptions(EvaluationOptions, OutputOptions):
    """Evaluate a checkpoint greedily: S% (success rate), T (mean episode length), DIST."""

    agents: Annotated[int | None, Default("the training size")] = None
    """team size M"""

    def __post_init__(self):
        EvaluationOptions.__post_init__(self)
        OutputOptions.__post_init__(self)
        check_setting({"agents": self.agents})


@dataclass(kw_only=True)
class ZeroShotOptions(EvaluationOptions):
    """Evaluate one checkpoint at many team sizes without fine-tuning."""

    sizes: tuple[str, ...] = ("2-8",)
    """team sizes, e.g. 2-8 or 3 5 7"""


@dataclass(kw_only=True)
class PlotOptions:
    """Learning curves of a run, or zero-shot S% against M from `swarm zero-shot --json` files."""

    run_dir: Annotated[
        str | None, Positional, tyro.conf.arg(metavar="RUN_DIR", help_behavior_hint="(optional with --zero-shot)")
    ] = None
    """run directory (learning curves)"""
    out: Annotated[str | None, Default("RUN_DIR/curves.png; required with --zero-shot")] = None
    """PNG path"""
    zero_shot: tuple[str, ...] | None = None
    """`swarm zero-shot --json` files to plot instead"""
    labels: tuple[str, ...] | None = None
    """legend labels of the --zero-shot files"""

    def __post_init__(self):
        if self.zero_shot and not self.out:
            raise OptionError("--zero-shot needs --out FILE.png")
        if not self.zero_shot and not self.run_dir:
            raise OptionError("pass a run directory, or --zero-shot JSON files with --out")
        if self.labels and len(self.labels) != len(self.zero_shot or ()):
            raise OptionError(f"--labels gives {len(self.labels)} labels for {len(self.zero_shot or ())} files")


@dataclass(kw_only=True)
class ImportOptions:
    """Convert a checkpoint in the paper authors' published format (marl_transfer
    models/naM_uc.pt) into this project's policy format, for eval, zero-shot, export,
    execute and --init-from."""

    published: Annotated[str, Positional, tyro.conf.arg(metavar="PUBLISHED")]
    """the published .pt file"""
    out: str
    """where to write the converted policy (.pt)"""
    task: Annotated[str | None, Default("from the input width")] = None
    """coverage | formation | line"""
    comm: Comm = "uc"
    """communication it is to run with"""
    comm_radius: float = 1.0
    """rc radius"""

    def __post_init__(self):
        check_setting({"comm": self.comm, "comm_radius": self.comm_radius})


# ----------------------------------------------------------------------------- deploy commands
@dataclass(kw_only=True)
class ExportOptions(SettingOptions):
    """Export a checkpoint to per-agent ONNX pieces (encode, round, heads) and a manifest.json;
    the task setting given here is what the manifest records."""

    checkpoint: Annotated[str, Positional, tyro.conf.arg(metavar="CHECKPOINT")]
    """checkpoint file or run directory"""
    out: str
    """output directory (created)"""
    agents: Annotated[int | None, Default("the training size")] = None
    """team size to record"""
    trust_unsigned: bool = False
    """load a checkpoint that carries no sha256 (from before digests existed): corruption in it cannot be detected"""

    def __post_init__(self):
        SettingOptions.__post_init__(self)
        check_setting({"agents": self.agents})


@dataclass(kw_only=True)
class ExecuteOptions(SettingOptions, SwarmOptions, OutputOptions):
    """Run exported models decentralised: one onnxruntime agent per agent, messages only
    along the communication graph; prints S%, T, DIST per drop rate."""

    directory: Annotated[str, Positional, tyro.conf.arg(metavar="DIRECTORY")]
    """directory written by `swarm export`; a zoo name or a checkpoint is exported first (that step needs torch)"""
    agents: Annotated[int | None, Default("the manifest's")] = None
    """team size M"""
    episodes: int = 10
    """episodes, one per environment"""
    drop: tuple[float, ...] = (0.0,)
    """message drop probabilities, one row each (e.g. --drop 0 0.1 0.3); --record/--video draw the first"""
    delay: int = 0
    """deliver messages this many steps late"""
    burst_loss: float = 0.0
    """Gilbert-Elliott bursty loss on every link, as `swarm agent --burst-loss`: mean loss Q"""
    burst_len: float = 4.0
    """mean length of a loss burst, in messages (with --burst-loss)"""
    hold: int = 0
    """a lost message is replaced by the sender's last one heard, if at most N steps old (0: off; not with --delay)"""
    seed: int = 777
    """seed of the episodes and of the drops"""
    threads: int = 1
    """onnxruntime intra-op threads per session"""
    json: str | None = None
    """also write the rows to this JSON file"""

    def __post_init__(self):
        SettingOptions.__post_init__(self)
        SwarmOptions.__post_init__(self)
        OutputOptions.__post_init__(self)
        at_least(self.threads, 1, "threads")
        cores = os.cpu_count() or 1
        if self.threads > cores:  # (more onnxruntime threads than cores only wait on each other)
            raise OptionError(f"--threads must be <= {cores}, this machine's cores, got {self.threads}")
        if self.episodes > MAX_EXECUTE_EPISODES:
            raise OptionError(
                f"--episodes must be <= {MAX_EXECUTE_EPISODES} (they run as one batch of environments), "
                f"got {self.episodes}"
            )


@dataclass(kw_only=True)
class ReplayOptions(VideoOption):
    """Inspect a recording (--stats), render a trajectory record (--video, --rrd) or open either
    in a Rerun viewer."""

    file: Annotated[str, Positional, tyro.conf.arg(metavar="FILE")]
    """a trajectory record (.npz) or Rerun recording (.rrd) written by --record"""
    stats: bool = False
    """print a summary (the record's setting and outcomes; a .rrd's entity paths) and exit"""
    rrd: str | None = None
    """write the Rerun recording of a trajectory record to this .rrd file"""
    serve_web: bool = False
    """serve the web viewer on 127.0.0.1 (no GPU needed)"""
    port: int | None = None
    """web viewer port (with --serve-web)"""

    def __post_init__(self):
        if self.port is not None and not 0 < self.port < 65536:
            raise OptionError(f"--port must be in 1..65535, got {self.port}")


# ----------------------------------------------------------------------------- reproduce
@dataclass(kw_only=True)
class ReproduceOptions:
    spec: str = "paper"
    """a shipped spec (paper, recipe, beyond, quick, smoke) or a TOML file"""
    tables: tuple[int, ...] | None = None
    """only these tables (e.g. 2 3)"""
    cells: tuple[str, ...] | None = None
    """only these cell ids (and the cells they need)"""
    seeds: int = 1
    """N seeds of every cell: K..K+N-1 (K: --first-seed)"""
    first_seed: int = 0
    """K, the first seed (e.g. --first-seed 6 --seeds 2: seeds 6 and 7)"""
    root: Annotated[str | None, Default("runs/reproduce/<spec>")] = None
    """where the runs and results live"""
    workers: int = 0
    """local Ray CPUs = parallel cells (0: this machine's CPU count)"""
    address: str | None = None
    """join this Ray cluster instead of starting one (e.g. auto)"""
    gpus_per_cell: float = 0.0
    """GPU share of each cell's task (e.g. 0.25)"""
    arch: Arch = "cpu"
    """simulator arch of every cell"""
    device: str = "cpu"
    """network (torch) device of every cell: cpu | cuda | auto"""
    progress_every: float = 60.0
    """seconds between progress views"""
    dry_run: bool = False
    """list what would run and what is done; run nothing"""
    status: bool = False
    """print the progress view from the files; run nothing"""
    render: bool = False
    """only render the tables from the results on disk"""
    update_doc: Annotated[str | None, tyro.conf.arg(metavar="FILE")] = None
    """also write the tables into FILE between its markers"""
    figures: Annotated[str | None, Default("ROOT", "DIR")] = None
    """where the learning-curve figures go"""

    def __post_init__(self):
        at_least(self.seeds, 1, "seeds")
        at_least(self.first_seed, 0, "first-seed")
        if self.seeds > MAX_SEEDS or self.first_seed + self.seeds > 2**31:
            raise OptionError(
                f"--seeds must be <= {MAX_SEEDS} and --first-seed + --seeds <= 2^31 (training seeds), "
                f"got {self.seeds} from {self.first_seed}"
            )
        at_least(self.workers, 0, "workers")
        at_least(self.gpus_per_cell, 0, "gpus-per-cell")
        positive(self.progress_every, "progress-every")
