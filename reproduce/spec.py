"""The paper's tables as data: every cell says what to train, how to evaluate it and
what the paper reported for it.

A spec is a TOML file (``reproduce/specs/paper.toml`` ships Tables 1-4 of
docs/PAPER.md s.7; ``smoke.toml`` is a tiny one for tests and a first try). Its
``[defaults]`` apply to every ``[[cells]]`` entry; a cell's own keys win. Kinds:

- ``train``: one run at ``agents`` for ``updates`` (Table 1: from scratch).
- ``curriculum``: stages over ``sizes``, each from the previous stage's weights,
  advancing at ``threshold`` or after ``max_updates_per_stage`` (Tables 2, 3).

Both may start from another cell's policy (``init_from``, weights only: e.g. an RC
curriculum from a UC M = 3 run) and be trained on after the run, or after every
stage, for ``polish_updates`` at the constant ``polish_lr`` (``swarm curriculum
--polish-updates``); the row reports the polished policy, and the one before it.

Two more kinds:

- ``zero-shot``: the policy of cell ``source`` (its stage at ``source_agents`` for a
  curriculum) evaluated at ``sizes`` without fine-tuning (Table 4).
- ``baseline``: a stock BenchMARL ``algorithm`` (baselines/) trained at ``agents`` for
  ``frames`` env steps with ``obs_mode`` observations (Table 1's baseline rows; needs
  the ``baselines`` extra). A stopped one resumes from its latest checkpoint.

Every number a cell reports comes from ``final_episodes`` fresh greedy episodes at
``eval_seed`` (training never draws seeds below 2**40), not from the evaluations that
decided when a stage stopped.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import sys
from dataclasses import dataclass, field

from taichi_swarm import COMMS, TASK_SPECS, TASKS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

SPECS_DIR = os.path.join(os.path.dirname(__file__), "specs")
KINDS = ("train", "curriculum", "zero-shot", "baseline")
BASELINE_FIELDS = ("algorithm", "frames", "obs_mode", "actions", "baseline_options")
# BenchMARL 1.5's algorithms (benchmarl.algorithms.algorithm_config_registry; a test holds them equal)
BASELINE_ALGORITHMS = ("iddpg", "ippo", "iql", "isac", "maddpg", "mappo", "masac", "qmix", "vdn")
MAX_TEAM_SIZE = 2**16  # any team size a cell names (the simulator's buffers are indexed with int32)
MAX_FRAMES = 10**12
MAX_ENVS = 2**20  # environments of one batch (trainer.config.MAX_NUM_ENVS)
ENTITY_MODES = ("emp", "concat", "padded")  # trainer.model.ENTITY_MODES


class SpecError(ValueError):
    """A spec file or a selection of it is wrong; the message names the cell and the key."""


@dataclass(frozen=True)
class Cell:
    """One cell of a table: one training run, one curriculum chain or one zero-shot row."""

    id: str
    table: int
    kind: str
    task: str
    comm: str = "uc"
    comm_radius: float = 1.0
    entity_mode: str = "emp"
    preset: str = "paper"
    ppo: dict = field(default_factory=dict)
    """Overrides of the preset's PPO options (e.g. {num_envs = 8})."""
    agents: int = 0
    """train, baseline: the team size (train: the size evaluated and reported)."""
    team_sizes: tuple[int, ...] = ()
    """train: train on these team sizes at once, one group of environments per size in
    every rollout (``swarm train --team-sizes``); empty: ``agents`` alone."""
    updates: int = 0
    """train: PPO updates."""
    sizes: tuple[int, ...] = ()
    """curriculum: the stages' team sizes; zero-shot: the sizes evaluated."""
    threshold: float = 0.85
    max_updates_per_stage: int = 4000
    min_updates_per_stage: int = 0
    """curriculum: a stage trains at least this many updates, past the threshold."""
    source: str = ""
    """zero-shot: the id of the cell whose policy is evaluated."""
    init_from: str = ""
    """train, curriculum: the id of a train or curriculum cell whose final policy (weights
    only) the run, or the first stage, starts from."""
    init_agents: int = 0
    """init_from a curriculum: which stage's policy."""
    polish_updates: int = 0
    """train, curriculum: after the run (each stage), this many updates more at the
    constant learning rate polish_lr from its weights (fresh optimiser); the next stage
    starts from the polished policy and the row reports it."""
    polish_lr: float = 3e-5
    source_agents: int = 0
    """zero-shot from a curriculum: which stage's policy."""
    algorithm: str = ""
    """baseline: a BenchMARL algorithm (mappo, ippo, maddpg, qmix, vdn, iql, masac, ...)."""
    frames: int = 0
    """baseline: the training budget in env steps."""
    obs_mode: str = "full"
    """baseline: "full" (the paper's baselines: everything observed, no communication) or "local"."""
    actions: str = "any"
    """baseline: discrete | continuous | any (the algorithm's preference)."""
    baseline_options: dict = field(default_factory=dict)
    """baseline: more options of tools/run_baselines.py, e.g. {num_envs = 4, frames_per_batch = 64}."""
    eval_every: int = 50
    eval_episodes: int = 200
    """Episodes of the evaluations during training (stages advance on them)."""
    transfer_offsets: tuple[int, ...] = ()
    """train, curriculum (others ignore it, as [defaults] give it to every cell): the
    evaluations during training also report S% at these offsets
    from the training team size (metrics.jsonl ``eval_transfer``, the curves): reporting
    only, so not part of the definition (adding them leaves existing results valid)."""
    final_episodes: int = 500
    eval_seed: int = 777
    checkpoint_every: int = 25
    compile: bool = True
    label: str = ""
    """Row label in the rendered table (default: task and comm)."""
    paper: dict = field(default_factory=dict)
    """What the paper reported, by team size: {"3" = {S = 100, T = 14.12, DIST = 0.047, N = 1100}}."""

    def definition(self) -> dict:
        """Everything that decides what is run (not the paper's numbers or the label)."""
        d = dataclasses.asdict(self)
        for key in ("paper", "label", "table", "transfer_offsets"):  # reporting only
            d.pop(key)
        if self.kind != "baseline":  # fields only a baseline reads (older results lack them)
            for key in BASELINE_FIELDS:
                d.pop(key)
        # added later: older definitions lack them, so their defaults are left out
        if not self.min_updates_per_stage:
            d.pop("min_updates_per_stage")
        if not self.init_from:
            d.pop("init_from")
            d.pop("init_agents")
        if not self.polish_updates:
            d.pop("polish_updates")
            d.pop("polish_lr")
        if self.team_sizes:
            d["team_sizes"] = list(self.team_sizes)
        else:
            d.pop("team_sizes")
        d["sizes"] = list(self.sizes)
        return d

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.definition(), sort_keys=True).encode()).hexdigest()[:16]

    def row_label(self) -> str:
        if self.label:
            return self.label
        if self.kind == "baseline":
            return f"{self.task} {self.algorithm.upper()} ({self.obs_mode} obs.)"
        return f"{self.task} {self.comm.upper()}"

    @property
    def needs(self) -> str:
        """The id of the cell whose policy this one reads (source or init_from), or ""."""
        return self.source or self.init_from

    def budget_updates(self) -> int:
        """Most PPO updates the cell can take (a curriculum may stop stages earlier)."""
        if self.kind == "train":
            return self.updates + self.polish_updates
        if self.kind == "curriculum":
            return (self.max_updates_per_stage + self.polish_updates) * len(self.sizes)
        return 0  # zero-shot: none; baseline: ``frames`` env steps (not PPO updates of ours)


@dataclass(frozen=True)
class Spec:
    name: str
    description: str
    cells: tuple[Cell, ...]
    path: str

    def cell(self, cell_id: str) -> Cell:
        for c in self.cells:
            if c.id == cell_id:
                return c
        raise SpecError(f"{self.path}: no cell {cell_id!r} (cells: {', '.join(c.id for c in self.cells)})")

    def select(self, tables: list[int] | None = None, cell_ids: list[str] | None = None) -> list[Cell]:
        """The cells of ``tables`` and/or named by ``cell_ids``, plus the cells they need
        (a zero-shot row its source, a run its init_from), in an order where those come first."""
        if tables:
            unknown = sorted(set(tables) - {c.table for c in self.cells})
            if unknown:
                raise SpecError(f"--tables {unknown}: the spec {self.name!r} has tables {self.tables()}")
        chosen = [
            c
            for c in self.cells
            if (not tables and not cell_ids) or (tables and c.table in tables) or (cell_ids and c.id in cell_ids)
        ]
        for cid in cell_ids or []:
            self.cell(cid)  # unknown ids are an error
        needed = {c.id for c in chosen}
        for c in list(chosen):
            while c.needs and c.needs not in needed:
                c = self.cell(c.needs)
                needed.add(c.id)
        return [c for c in self.cells if c.id in needed]  # spec order: sources are declared first

    def tables(self) -> list[int]:
        return sorted({c.table for c in self.cells})


def resolve_spec_path(name_or_path: str) -> str:
    """A shipped spec's name (``paper``, ``smoke``) or a path to a TOML file."""
    if os.path.exists(name_or_path):
        return name_or_path
    shipped = os.path.join(SPECS_DIR, f"{name_or_path}.toml")
    if os.path.exists(shipped):
        return shipped
    names = sorted(f[:-5] for f in os.listdir(SPECS_DIR) if f.endswith(".toml"))
    raise SpecError(f"--spec {name_or_path!r} is neither a file nor a shipped spec ({', '.join(names)})")


def load_spec(name_or_path: str) -> Spec:
    path = resolve_spec_path(name_or_path)
    try:
        with open(path, "rb") as f:
            raw = tomllib.load(f)
    except RecursionError:  # (tomllib recurses per nesting level)
        raise SpecError(f"{path}: nested too deeply to be a spec") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML ({exc})") from None
    known_top = {"name", "description", "defaults", "cells"}
    extra = sorted(set(raw) - known_top)
    if extra:
        raise SpecError(f"{path}: unknown top-level keys {extra} (allowed: {sorted(known_top)})")
    defaults = raw.get("defaults", {})
    entries = raw.get("cells", [])
    if not isinstance(defaults, dict):
        raise SpecError(f"{path}: [defaults] must be a table of cell keys, got {defaults!r}")
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise SpecError(f"{path}: cells must be [[cells]] tables")
    if not entries:
        raise SpecError(f"{path}: no [[cells]]")
    cells = tuple(_make_cell(path, i, {**defaults, **entry}) for i, entry in enumerate(entries))
    spec = Spec(
        name=raw.get("name", os.path.splitext(os.path.basename(path))[0]),
        description=raw.get("description", ""),
        cells=cells,
        path=path,
    )
    _check_references(spec)
    return spec


_FIELDS = {f.name: f for f in dataclasses.fields(Cell)}
_SIZE_LISTS = ("sizes", "transfer_offsets", "team_sizes")
# each field's TOML type, from its default (id, table, kind and task have none)
_TYPES = {"id": str, "table": int, "kind": str, "task": str}
for _f in dataclasses.fields(Cell):
    if _f.name not in _TYPES and _f.name not in _SIZE_LISTS:
        _default = _f.default_factory() if _f.default is dataclasses.MISSING else _f.default
        _TYPES[_f.name] = float if isinstance(_default, float) else type(_default)
_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", dict: "a table"}


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _has_type(value, want: type) -> bool:
    if want is bool:
        return isinstance(value, bool)
    if want is float:
        return _is_int(value) or isinstance(value, float)
    return _is_int(value) if want is int else isinstance(value, want)


def _make_cell(path: str, index: int, entry: dict) -> Cell:
    where = f"{path}: cell {entry.get('id', f'#{index + 1}')!r}"
    unknown = sorted(set(entry) - set(_FIELDS))
    if unknown:
        raise SpecError(f"{where}: unknown keys {unknown}")
    for key in ("id", "table", "kind", "task"):
        if key not in entry:
            raise SpecError(f"{where}: missing {key!r}")
    entry = dict(entry)
    for key, value in entry.items():
        want = _TYPES.get(key)
        if key in _SIZE_LISTS:
            if not isinstance(value, list) or not all(_is_int(v) for v in value):
                raise SpecError(f"{where}: {key} must be a list of integers, got {value!r}")
            entry[key] = tuple(value)
        elif not _has_type(value, want):
            raise SpecError(f"{where}: {key} must be {_TYPE_NAMES[want]}, got {value!r}")
    try:
        cell = Cell(**entry)
    except TypeError as exc:
        raise SpecError(f"{where}: {exc}") from None
    _check_cell(where, cell)
    return cell


def _check_cell(where: str, c: Cell) -> None:
    from trainer.config import MAX_TRANSFER_OFFSET, PRESETS, PPOConfig  # (torch: imported only to check a spec)

    def bad(msg: str):
        raise SpecError(f"{where}: {msg}")

    if not c.id or any(ch in c.id for ch in "/\\ ") or c.id.startswith("."):
        bad("id must be a plain name (no slashes or spaces)")
    if c.kind not in KINDS:
        bad(f"kind must be one of {KINDS}, got {c.kind!r}")
    if c.task not in TASKS:
        bad(f"task must be one of {TASKS}, got {c.task!r}")
    if c.comm not in COMMS:
        bad(f"comm must be one of {COMMS}, got {c.comm!r}")
    if c.entity_mode not in ENTITY_MODES:
        bad(f"entity_mode must be one of {ENTITY_MODES}, got {c.entity_mode!r}")
    smallest = TASK_SPECS[c.task].min_agents
    for name in ("agents", "sizes", "team_sizes", "source_agents", "init_agents"):
        value = getattr(c, name)
        if any(m > MAX_TEAM_SIZE for m in (value if isinstance(value, (list, tuple)) else [value])):
            bad(f"{name} must be team sizes <= {MAX_TEAM_SIZE}, got {value}")
    if c.kind in ("train", "baseline"):
        if c.agents < smallest:
            bad(f"agents must be >= {smallest} for {c.task}, got {c.agents}")
    if c.kind == "train" and c.updates < 1:
        bad(f"updates must be >= 1, got {c.updates}")
    if c.kind == "baseline":
        if not c.algorithm:
            bad("a baseline cell needs algorithm (a BenchMARL algorithm name)")
        if c.algorithm.lower() not in BASELINE_ALGORITHMS:
            bad(f"algorithm must be one of {BASELINE_ALGORITHMS}, got {c.algorithm!r}")
        if c.frames < 1:
            bad(f"frames must be >= 1, got {c.frames}")
        if c.frames > MAX_FRAMES:
            bad(f"frames must be <= 10^12, got {c.frames}")
        if c.obs_mode not in ("full", "local"):
            bad(f"obs_mode must be full or local, got {c.obs_mode!r}")
        if c.actions not in ("any", "discrete", "continuous"):
            bad(f"actions must be any, discrete or continuous, got {c.actions!r}")
        taken = {"algorithm", "task", "agents", "comm", "comm_radius", "obs_mode", "actions", "frames", "seed"}
        clash = sorted(set(c.baseline_options) & (taken | {"eval_episodes", "eval_seed", "device", "out"}))
        if clash:
            bad(f"baseline_options {clash} are set by the cell itself")
        envs = c.baseline_options.get("num_envs", 1)
        if not _is_int(envs) or not 1 <= envs <= MAX_ENVS:
            bad(f"baseline_options.num_envs must be an integer in [1, {MAX_ENVS}], got {envs!r}")
    if c.kind in ("curriculum", "zero-shot"):
        if not c.sizes or any(m < smallest for m in c.sizes):
            bad(f"sizes must be team sizes >= {smallest}, got {list(c.sizes)}")
        if len(set(c.sizes)) != len(c.sizes):
            bad(f"sizes repeats a size: {list(c.sizes)}")
    if c.team_sizes:
        if c.kind != "train":
            bad(f"only train cells have team_sizes (a {c.kind} cell sets its sizes otherwise)")
        if any(m < smallest for m in c.team_sizes):
            bad(f"team_sizes must be team sizes >= {smallest}, got {list(c.team_sizes)}")
        if len(set(c.team_sizes)) != len(c.team_sizes):
            bad(f"team_sizes repeats a size: {list(c.team_sizes)}")
    if c.kind == "curriculum":
        if not 0 < c.threshold <= 1:
            bad(f"threshold must be in (0, 1], got {c.threshold}")
        if c.max_updates_per_stage < 1:
            bad(f"max_updates_per_stage must be >= 1, got {c.max_updates_per_stage}")
        if not 0 <= c.min_updates_per_stage <= c.max_updates_per_stage:
            bad(f"min_updates_per_stage must be in [0, max_updates_per_stage], got {c.min_updates_per_stage}")
    offsets = c.transfer_offsets
    if any(d == 0 or abs(d) > MAX_TRANSFER_OFFSET for d in offsets):
        bad(f"transfer_offsets must be small non-zero team-size offsets, got {list(offsets)}")
    if len(set(offsets)) != len(offsets):
        bad(f"transfer_offsets has a repeated offset: {list(offsets)}")
    if c.init_from and c.kind not in ("train", "curriculum"):
        bad("only train and curriculum cells have init_from")
    if c.init_agents and not c.init_from:
        bad("init_agents names a stage of init_from: set init_from too")
    if c.polish_updates < 0:
        bad(f"polish_updates must be >= 0, got {c.polish_updates}")
    if c.polish_updates and c.kind not in ("train", "curriculum"):
        bad(f"only train and curriculum cells polish: a {c.kind} cell has no polish_updates")
    if not 0 < c.polish_lr <= 1:  # (NaN and inf too)
        bad(f"polish_lr must be in (0, 1], got {c.polish_lr}")
    if c.kind == "zero-shot" and not c.source:
        bad("a zero-shot cell needs source (the id of the cell whose policy it evaluates)")
    if c.kind != "zero-shot" and c.source:
        bad("only zero-shot cells have a source")
    for name in ("eval_every", "eval_episodes", "final_episodes", "checkpoint_every"):
        if getattr(c, name) < 1:
            bad(f"{name} must be >= 1, got {getattr(c, name)}")
    for name in ("eval_episodes", "final_episodes"):  # one environment per episode
        if getattr(c, name) > MAX_ENVS:
            bad(f"{name} must be <= {MAX_ENVS} (one environment each), got {getattr(c, name)}")
    if not 0 <= c.eval_seed < 2**40:
        bad(f"eval_seed must be in [0, 2**40): training draws its seeds above, got {c.eval_seed}")
    if c.preset not in PRESETS:
        bad(f"preset must be one of {tuple(PRESETS)}, got {c.preset!r}")
    ppo_defaults = dataclasses.asdict(PPOConfig())
    unknown_ppo = sorted(set(c.ppo) - set(ppo_defaults))
    if unknown_ppo:
        bad(f"ppo has unknown options {unknown_ppo}")
    for key, value in c.ppo.items():
        default = ppo_defaults[key]
        want = float if default is None else type(default)  # (lr_end: None = lr)
        if not _has_type(value, want):
            bad(f"ppo.{key} must be {_TYPE_NAMES[want]}, got {value!r}")
    if c.kind in ("train", "curriculum"):  # the trainer's own checks, now rather than hours into a run
        agents = c.agents if c.kind == "train" else c.sizes[0]
        updates = c.updates if c.kind == "train" else c.max_updates_per_stage
        train_config(c, 0, "", agents, updates, init_from="(init_from)" if c.init_from else "", where=where)
    if c.entity_mode == "concat" and c.task == "coverage" and c.kind in ("curriculum", "zero-shot"):
        bad("entity_mode 'concat' has a fixed number of landmarks: coverage's changes with the team size")
    for size, row in c.paper.items():
        if not str(size).isdigit() or not isinstance(row, dict):
            bad(f"paper must map team sizes to tables of numbers, got {size!r} = {row!r}")


def train_config(
    cell: Cell,
    seed: int,
    run_dir: str,
    agents: int,
    updates: int,
    arch: str = "cpu",
    device: str = "cpu",
    init_from: str = "",
    where: str = "",
):
    """The TrainConfig of a cell's run (a curriculum changes agents/run_dir per stage),
    checked by the trainer; ``init_from``: a policy whose weights the run starts from;
    ``where``: how an error names the cell (default: its id)."""
    from trainer.config import PRESETS, TrainConfig
    from trainer.model import ModelConfig

    where = where or f"cell {cell.id!r}"
    try:
        ppo = dataclasses.replace(copy.deepcopy(PRESETS[cell.preset]), **cell.ppo)
    except KeyError:
        raise SpecError(f"{where}: preset must be one of {tuple(PRESETS)}, got {cell.preset!r}") from None
    except TypeError as exc:
        raise SpecError(f"{where}: ppo has an unknown option ({exc})") from None
    cfg = TrainConfig(
        task=cell.task,
        agents=agents,
        team_sizes=cell.team_sizes,
        comm=cell.comm,
        comm_radius=cell.comm_radius,
        preset=cell.preset,
        updates=updates,
        eval_every=cell.eval_every,
        eval_episodes=cell.eval_episodes,
        transfer_offsets=cell.transfer_offsets,
        checkpoint_every=cell.checkpoint_every,
        seed=seed,
        run_dir=run_dir,
        init_from=init_from,
        init_carry="weights",
        compile=cell.compile,
        progress=False,
        arch=arch,
        device=device,
        model=ModelConfig(entity_mode=cell.entity_mode),  # (concat: the trainer takes the task's L)
        ppo=ppo,
    )
    try:
        cfg.validate()
    except (ValueError, TypeError) as exc:  # (TypeError: a ppo value of the wrong type)
        raise SpecError(f"{where}: {exc}") from None
    return cfg


def _check_references(spec: Spec) -> None:
    seen: dict[str, Cell] = {}
    for c in spec.cells:
        if c.id in seen:
            raise SpecError(f"{spec.path}: two cells named {c.id!r}")
        if c.init_from:
            _check_init_from(spec, c, seen.get(c.init_from))
        if c.source:
            src = seen.get(c.source)
            if src is None:
                raise SpecError(f"{spec.path}: cell {c.id!r}: source {c.source!r} must be a cell declared before it")
            if src.kind in ("zero-shot", "baseline"):
                raise SpecError(
                    f"{spec.path}: cell {c.id!r}: source {c.source!r} is a {src.kind} cell (no policy of ours)"
                )
            if src.kind == "curriculum" and c.source_agents not in src.sizes:
                raise SpecError(
                    f"{spec.path}: cell {c.id!r}: source_agents must be one of {c.source!r}'s stage sizes "
                    f"{list(src.sizes)}, got {c.source_agents}"
                )
            if src.kind == "train" and c.source_agents not in (0, src.agents):
                raise SpecError(
                    f"{spec.path}: cell {c.id!r}: source {c.source!r} is a train cell at M = {src.agents}: "
                    f"leave source_agents out, got {c.source_agents}"
                )
            if src.entity_mode == "concat" and src.task == "coverage":
                raise SpecError(
                    f"{spec.path}: cell {c.id!r}: source {c.source!r} has entity_mode 'concat', a fixed number of "
                    "landmarks: coverage's changes with the team size"
                )
            if (src.task, src.comm, src.comm_radius) != (c.task, c.comm, c.comm_radius):
                raise SpecError(
                    f"{spec.path}: cell {c.id!r}: task / comm / comm_radius {c.task, c.comm, c.comm_radius} differ "
                    f"from its source's {src.task, src.comm, src.comm_radius}"
                )
        seen[c.id] = c
    layouts: dict[int, tuple[str, str]] = {}  # a table is rendered in one layout: its cells' kinds must share it
    for c in spec.cells:
        layout = "train" if c.kind == "baseline" else c.kind
        first = layouts.setdefault(c.table, (layout, c.id))
        if first[0] != layout:
            raise SpecError(
                f"{spec.path}: cell {c.id!r} is a {c.kind} cell in table {c.table}, whose cell {first[1]!r} is "
                f"a {first[0]} cell: a table holds train and baseline cells, or curricula, or zero-shot rows"
            )


def _check_init_from(spec: Spec, c: Cell, src: Cell | None) -> None:
    where = f"{spec.path}: cell {c.id!r}: init_from {c.init_from!r}"
    if src is None:
        raise SpecError(f"{where} must be a cell declared before it")
    if src.kind not in ("train", "curriculum"):
        raise SpecError(f"{where} is a {src.kind} cell (no policy of ours to start from)")
    if src.kind == "curriculum" and c.init_agents not in src.sizes:
        raise SpecError(f"{where}: init_agents must be one of its stage sizes {list(src.sizes)}, got {c.init_agents}")
    if src.kind == "train" and c.init_agents not in (0, src.agents):
        raise SpecError(f"{where} is a train cell at M = {src.agents}: leave init_agents out, got {c.init_agents}")
    if (src.task, src.entity_mode) != (c.task, c.entity_mode):
        raise SpecError(
            f"{where}: task / entity_mode {c.task, c.entity_mode} differ from its {src.task, src.entity_mode} "
            "(the weights would not fit)"
        )
