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
import types
import typing
from dataclasses import dataclass, field

from baselines.config import SETTING as BASELINE_SETTING
from baselines.config import BaselineConfig, parse_overrides
from baselines.config import nest as nest_baseline
from taichi_swarm import TASK_SPECS
from taichi_swarm.files import InputFileError, read_input_text
from taichi_swarm.sim import Sim
from trainer.config import PRESETS, RETIRED, SIM_FIELDS, STAGE_SET, CurriculumConfig, TrainConfig, nest_sim, to_dict

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

SPECS_DIR = os.path.join(os.path.dirname(__file__), "specs")
SCHEMA_VERSION = 2
"""Of ``Cell.definition()``: 1 was one flat dict of every cell key; 2 is {kind, asdict(run)}."""
MAX_TEAM_SIZE = 2**16  # any team size a cell names (the simulator's buffers are indexed with int32)
# PPO updates a cell may name (updates, polish_updates, max_updates_per_stage): paper.toml's
# largest is 4000 a stage; a typo of 10**12 would otherwise pass --dry-run as a plan
MAX_UPDATES = 10**6
# TrainConfig fields that are swarm reproduce's, not the spec's: the run's seed, directory and
# machine (set per run), its start (init_from names a cell), what it logs (transfer_offsets:
# the cell's, reporting only) and a curriculum's fresh evaluations (the cell's final ones instead)
SET_BY_REPRODUCE = {
    "seed": 0, "run_dir": "", "init_from": "", "trust_unsigned": False, "arch": "cpu",
    "device": "cpu", "torch_threads": 1, "progress": False, "transfer_offsets": (),
    "fresh_eval_episodes": 0, "fresh_eval_seed": 777,
}  # fmt: skip
BASELINE_SET = ("seed", "out", "device", "threads", "eval_episodes")  # (eval_episodes: final_episodes)


class SpecError(ValueError):
    """A spec file or a selection of it is wrong; the message names the cell and the key."""


def _min_agents(task: str) -> int:
    return TASK_SPECS[task].min_agents if task in TASK_SPECS else 1


def _check_sizes(name: str, sizes, task: str) -> None:
    smallest = _min_agents(task)
    if not sizes or any(not smallest <= m <= MAX_TEAM_SIZE for m in sizes):
        raise ValueError(f"{name} must be team sizes in [{smallest}, {MAX_TEAM_SIZE}], got {list(sizes)}")
    if len(set(sizes)) != len(sizes):
        raise ValueError(f"{name} repeats a size: {list(sizes)}")


def _check_counts(config, **updates: int) -> None:
    """The update counts, and the evaluation episodes (one environment each, as final_episodes)."""
    for name, n in updates.items():
        if n > MAX_UPDATES:
            raise ValueError(f"{name} must be <= {MAX_UPDATES}, got {n}")
    if config.eval_episodes > 2**20:
        raise ValueError(f"eval_episodes must be <= 2^20 (one environment each), got {config.eval_episodes}")


@dataclass(frozen=True, kw_only=True)
class _Evaluated:
    final_episodes: int = 500
    """Fresh greedy episodes of every number the cell reports."""
    eval_seed: int = 777
    """Their seed (training never draws seeds below 2**40)."""

    def __post_init__(self):
        if not 1 <= self.final_episodes <= 2**20:
            raise ValueError(f"final_episodes must be in [1, 2^20] (one environment each), got {self.final_episodes}")
        if not 0 <= self.eval_seed < 2**40:
            raise ValueError(f"eval_seed must be in [0, 2**40): training draws its seeds above, got {self.eval_seed}")


@dataclass(frozen=True, kw_only=True)
class _FromCell(_Evaluated):
    init_from: str = ""
    """The id of a train or curriculum cell whose final policy (weights only) the run starts from."""
    init_agents: int = 0
    """init_from a curriculum: which stage's policy."""

    def __post_init__(self):
        super().__post_init__()
        if self.init_agents and not self.init_from:
            raise ValueError("init_agents names a stage of init_from: set init_from too")

    @property
    def task(self) -> str:
        return self.config.sim.task

    @property
    def comm(self) -> str:
        return self.config.sim.comm

    @property
    def comm_radius(self) -> float:
        return self.config.sim.comm_radius


@dataclass(frozen=True, kw_only=True)
class Train(_FromCell):
    """One run at ``config.agents`` for ``config.updates``, then ``polish_updates`` more at
    the constant ``polish_lr`` from its weights (fresh optimiser); the row reports the polished policy."""

    config: TrainConfig
    polish_updates: int = 0
    polish_lr: float = 3e-5

    def __post_init__(self):
        super().__post_init__()
        _check_sizes("agents", [self.agents], self.task)
        if self.config.team_sizes:
            _check_sizes("team_sizes", self.config.team_sizes, self.task)
        _check_counts(self.config, updates=self.config.updates, polish_updates=self.polish_updates)
        if self.polish_updates < 0:
            raise ValueError(f"polish_updates must be >= 0, got {self.polish_updates}")
        if not 0 < self.polish_lr <= 1:  # (NaN and inf too)
            raise ValueError(f"polish_lr must be in (0, 1], got {self.polish_lr}")
        self.config.validate()

    @property
    def agents(self) -> int:
        return self.config.sim.agents

    def budget_updates(self) -> int:
        return self.config.updates + self.polish_updates


@dataclass(frozen=True, kw_only=True)
class Curriculum(_FromCell):
    """Stages over ``config.sizes``, each from the previous stage's weights (trainer.curriculum)."""

    config: CurriculumConfig

    def __post_init__(self):
        from trainer.curriculum import check_curriculum

        super().__post_init__()
        c = self.config
        _check_sizes("sizes", c.sizes, self.task)
        _check_counts(c, max_updates_per_stage=c.max_updates_per_stage, polish_updates=c.polish_updates)
        if c.model.entity_mode == "concat" and self.task == "coverage":
            raise ValueError(
                "entity_mode 'concat' has a fixed number of landmarks: coverage's changes with the team size"
            )
        c.sim, c.updates = c.sim_at(c.sizes[0]), c.max_updates_per_stage  # (the stages set them: the first stage's)
        check_curriculum(c)

    sizes = property(lambda self: self.config.sizes)
    polish_updates = property(lambda self: self.config.polish_updates)
    polish_lr = property(lambda self: self.config.polish_lr)

    def budget_updates(self) -> int:  # (a curriculum may stop stages earlier)
        return (self.config.max_updates_per_stage + self.config.polish_updates) * len(self.sizes)


@dataclass(frozen=True, kw_only=True)
class ZeroShot(_Evaluated):
    """The policy of cell ``source`` (its stage at ``source_agents`` for a curriculum)
    evaluated at ``sizes`` without fine-tuning."""

    task: str
    source: str
    sizes: tuple[int, ...]
    source_agents: int = 0
    comm: str = "uc"
    comm_radius: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        Sim(self.task, _min_agents(self.task), self.comm, self.comm_radius)  # the setting, by the Sim's own checks
        _check_sizes("sizes", self.sizes, self.task)
        if not self.source:
            raise ValueError("a zero-shot cell needs source (the id of the cell whose policy it evaluates)")

    def budget_updates(self) -> int:
        return 0


@dataclass(frozen=True, kw_only=True)
class Baseline:
    """A stock BenchMARL algorithm (baselines/, the ``baselines`` extra) at ``config.agents``
    for ``config.frames`` env steps; a stopped one resumes from its latest checkpoint."""

    config: BaselineConfig

    def __post_init__(self):
        _check_sizes("agents", [self.agents], self.task)

    task = property(lambda self: self.config.sim.task)
    comm = property(lambda self: self.config.sim.comm)
    comm_radius = property(lambda self: self.config.sim.comm_radius)
    agents = property(lambda self: self.config.sim.agents)
    eval_seed = property(lambda self: self.config.eval_seed)

    @property
    def final_episodes(self) -> int:
        return self.config.eval_episodes

    def budget_updates(self) -> int:  # ``frames`` env steps, not PPO updates of ours
        return 0


RUNS = {"train": Train, "curriculum": Curriculum, "zero-shot": ZeroShot, "baseline": Baseline}
KINDS = tuple(RUNS)


@dataclass(frozen=True)
class Cell:
    """One cell of a table: what it runs (``run``, one dataclass per kind), and how it is reported."""

    id: str
    table: int
    run: Train | Curriculum | ZeroShot | Baseline
    paper: dict = field(default_factory=dict)
    """What the paper reported, by team size: {"3" = {S = 100, T = 14.12, DIST = 0.047, N = 1100}}."""
    label: str = ""
    """Row label in the rendered table (default: task and comm)."""
    transfer_offsets: tuple[int, ...] = ()
    """train, curriculum: the evaluations during training also report S% at these offsets from
    the training team size (metrics.jsonl ``eval_transfer``): reporting only, not in the definition."""

    def __post_init__(self):
        from trainer.config import MAX_TRANSFER_OFFSET

        if not self.id or any(ch in self.id for ch in "/\\ ") or self.id.startswith("."):
            raise ValueError("id must be a plain name (no slashes or spaces)")
        offsets = self.transfer_offsets
        if any(d == 0 or abs(d) > MAX_TRANSFER_OFFSET for d in offsets):
            raise ValueError(f"transfer_offsets must be small non-zero team-size offsets, got {list(offsets)}")
        if len(set(offsets)) != len(offsets):
            raise ValueError(f"transfer_offsets has a repeated offset: {list(offsets)}")
        for size, row in self.paper.items():
            if not str(size).isdigit() or not isinstance(row, dict):
                raise ValueError(f"paper must map team sizes to tables of numbers, got {size!r} = {row!r}")

    @property
    def kind(self) -> str:
        return next(k for k, cls in RUNS.items() if type(self.run) is cls)

    def definition(self) -> dict:
        """Everything that decides what is run: the run's config (not the paper's numbers,
        the label, the table or the transfer offsets), as JSON holds it."""
        return _as_json({"schema": SCHEMA_VERSION, "kind": self.kind, **_flat(self.run)})

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.definition(), sort_keys=True).encode()).hexdigest()[:16]

    def row_label(self) -> str:
        if self.label:
            return self.label
        if self.kind == "baseline":
            return f"{self.run.task} {self.run.config.algorithm.upper()} ({self.run.config.obs_mode} obs.)"
        return f"{self.run.task} {self.run.comm.upper()}"

    @property
    def needs(self) -> str:
        """The id of the cell whose policy this one reads (source or init_from), or ""."""
        return getattr(self.run, "source", "") or getattr(self.run, "init_from", "")

    def budget_updates(self) -> int:
        """Most PPO updates the cell can take (a curriculum may stop stages earlier)."""
        return self.run.budget_updates()


def _as_json(value):
    return json.loads(json.dumps(value))


# --- definitions stored by older versions ----------------------------------------------


def migrate(definition: dict, version: int) -> dict:
    """A definition stored by schema ``version`` in the current schema's terms; the keys it
    lacks take the run dataclasses' defaults when it is read (``canonical``), so a field added
    with a default (the behaviour before it) leaves every stored definition matching."""
    if version == SCHEMA_VERSION:
        return definition
    if version != 1:
        raise SpecError(f"a definition of schema {version}: this code reads schemas 1 to {SCHEMA_VERSION}")
    d = definition  # 1: one flat dict of every cell key; the keys its kind did not read are dropped

    def pick(names: str) -> dict:
        return {k: d[k] for k in names.split() if k in d}  # (absent: added after it, at the default)

    kind = d["kind"]
    head = {"schema": SCHEMA_VERSION, "kind": kind}
    evaluation = pick("final_episodes eval_seed")
    if kind == "zero-shot":
        return {**head, **pick("task comm comm_radius source sizes source_agents"), **evaluation}
    if kind == "baseline":
        options = dict(d.get("baseline_options", {}))
        if "experiment" in options:
            items = options["experiment"]
            options["experiment"] = parse_overrides(items if isinstance(items, list) else [items])
        config = pick("algorithm task agents comm comm_radius obs_mode actions frames eval_seed")
        return {**head, "config": {**config, "eval_episodes": d["final_episodes"], **options}}
    ppo = dataclasses.asdict(dataclasses.replace(PRESETS[d["preset"]], **d["ppo"]))
    config = {**_set_by_reproduce(kind), "model": {"entity_mode": d["entity_mode"]}, "ppo": ppo}
    config.update(pick("task comm comm_radius preset eval_every eval_episodes checkpoint_every compile"))
    if kind == "train":
        config.update(pick("agents updates team_sizes"))
        return {**head, "config": config, **pick("init_from init_agents polish_updates polish_lr"), **evaluation}
    config.update(pick("sizes threshold max_updates_per_stage min_updates_per_stage polish_updates polish_lr"))
    return {**head, "config": config, **pick("init_from init_agents"), **evaluation}


def _without_retired(d: dict) -> dict:
    """A definition less the options of experiments that lost (trainer.config.RETIRED), where
    they hold the value that meant "off": such a cell ran as today's code runs it."""
    out = {}
    for k, v in d.items():
        if k in RETIRED and v == RETIRED[k]:
            continue
        out[k] = _without_retired(v) if isinstance(v, dict) else v
    return out


def canonical(stored: dict) -> dict:
    """A stored definition (result.json, definition.json) as ``Cell.definition()`` of today's
    code would write it: migrated from its schema, read into the run's dataclass."""
    d = _without_retired(migrate(stored, stored.get("schema", 1)))
    run = RUNS[d["kind"]]
    values = {k: v for k, v in d.items() if k not in ("schema", "kind")}
    if "config" in values and d["kind"] in ("train", "curriculum"):
        values["config"] = nest_sim(values["config"])
    elif "config" in values and d["kind"] == "baseline":
        values["config"] = nest_baseline(values["config"])
    return _as_json({"schema": SCHEMA_VERSION, "kind": d["kind"], **_flat(convert(run, values))})


def _flat(run) -> dict:
    """``asdict(run)`` with a train or curriculum config as ``to_dict`` stores it (the Sim's fields
    among the others, as a spec names them)."""
    if isinstance(run, (Train, Curriculum)):
        return {**dataclasses.asdict(run), "config": to_dict(run.config)}
    if isinstance(run, Baseline):
        return {**dataclasses.asdict(run), "config": run.config.to_dict()}
    return dataclasses.asdict(run)


# --- TOML values into the dataclasses ---------------------------------------------------

_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", dict: "a table"}


def convert(cls, data: dict, prefix: str = ""):
    """``cls(**data)`` with every value checked against the field's type (nested dataclasses
    from tables, tuples from lists, ints as floats); a SpecError names the field."""
    try:
        return cls(**_typed(cls, data, prefix))
    except TypeError as exc:  # a missing key
        raise SpecError(f"{prefix}{exc}") from None


def _typed(cls, data: dict, prefix: str = "") -> dict:
    if not isinstance(data, dict):
        raise SpecError(f"{prefix.rstrip('.')} must be a table, got {data!r}")
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise SpecError(f"{prefix.rstrip('.')} has unknown options {unknown}" if prefix else f"unknown keys {unknown}")
    hints = typing.get_type_hints(cls)
    return {k: _value(hints[k], v, prefix + k) for k, v in data.items()}


def _value(tp, value, name: str):
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _value(next(a for a in args if a is not type(None)), value, name)
    if origin is typing.Literal:
        if value not in args:
            raise SpecError(f"{name} must be one of {args}, got {value!r}")
        return value
    if origin is tuple:
        item = args[0]
        if not isinstance(value, (list, tuple)) or not all(_is(item, v) for v in value):
            raise SpecError(f"{name} must be a list of {_TYPE_NAMES[item].split(' ', 1)[1]}s, got {value!r}")
        return tuple(value)
    if dataclasses.is_dataclass(tp):
        return convert(tp, value, "" if name in ("config", "sim") else name + ".")  # (a run's config: its own names)
    want = origin or tp
    if want in _TYPE_NAMES and not _is(want, value):
        raise SpecError(f"{name} must be {_TYPE_NAMES[want]}, got {value!r}")
    return float(value) if want is float else value


def _is(want: type, value) -> bool:
    if want is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if want is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, want)


CELL_KEYS = ("id", "table", "kind", "paper", "label", "transfer_offsets")


def _keys(kind: str) -> set[str]:
    """The spec keys of a ``kind`` cell (besides CELL_KEYS)."""
    run = RUNS[kind]
    own = {f.name for f in dataclasses.fields(run)} - {"config"}
    if kind == "zero-shot":
        return own
    if kind == "baseline":
        names = {f.name for f in dataclasses.fields(BaselineConfig)} - {"sim"} | set(BASELINE_SETTING)
        return (names - set(BASELINE_SET)) | {"final_episodes"}
    config = {f.name for f in dataclasses.fields(CurriculumConfig if kind == "curriculum" else TrainConfig)}
    config = config - {"sim"} | set(SIM_FIELDS)  # (a spec names the Sim's fields as its own keys)
    return own | (config - set(SET_BY_REPRODUCE) - (set(STAGE_SET) if kind == "curriculum" else set()))


def _nest(kind: str, entry: dict) -> dict:
    """A cell's flat spec keys as its run's dataclass arguments."""
    if kind == "zero-shot":
        return entry
    if kind == "baseline":
        config = {k: v for k, v in entry.items() if k != "final_episodes"}
        if "final_episodes" in entry:
            config["eval_episodes"] = entry["final_episodes"]
        return {"config": nest_baseline(config)}
    own = {f.name for f in dataclasses.fields(RUNS[kind])}
    config = {k: v for k, v in entry.items() if k not in own}
    preset = config.get("preset", TrainConfig.preset)
    if preset not in PRESETS:
        raise SpecError(f"preset must be one of {tuple(PRESETS)}, got {preset!r}")
    overrides = config.get("ppo", {})
    if not isinstance(overrides, dict):
        raise SpecError(f"ppo must be a table, got {overrides!r}")
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(PRESETS[preset])})
    if unknown:
        raise SpecError(f"ppo has unknown options {unknown}")
    config["ppo"] = {**dataclasses.asdict(copy.deepcopy(PRESETS[preset])), **overrides}
    return {**{k: v for k, v in entry.items() if k in own}, "config": nest_sim({**config, **_set_by_reproduce(kind)})}


def _set_by_reproduce(kind: str) -> dict:
    """SET_BY_REPRODUCE's fields of a train or curriculum cell's config."""
    names = {f.name for f in dataclasses.fields(CurriculumConfig if kind == "curriculum" else TrainConfig)}
    return {k: v for k, v in SET_BY_REPRODUCE.items() if k in names}


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
    try:  # a regular file of bounded size: a FIFO would block the read
        raw = tomllib.loads(read_input_text(path, "--spec"))
    except InputFileError as exc:
        raise SpecError(str(exc)) from None
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
    every = set(CELL_KEYS).union(*map(_keys, KINDS))
    unknown = sorted(set(defaults) - every)
    if unknown:
        raise SpecError(f"{path}: [defaults] has unknown keys {unknown}")
    cells = tuple(_make_cell(path, i, defaults, entry, every) for i, entry in enumerate(entries))
    spec = Spec(
        name=raw.get("name", os.path.splitext(os.path.basename(path))[0]),
        description=raw.get("description", ""),
        cells=cells,
        path=path,
    )
    _check_references(spec)
    return spec


REQUIRED = {
    "train": ("task", "agents", "updates"), "curriculum": ("task", "sizes"), "zero-shot": ("task", "source", "sizes"),
    "baseline": ("task", "algorithm", "agents", "frames"),
}  # fmt: skip


def _make_cell(path: str, index: int, defaults: dict, entry: dict, every: set[str]) -> Cell:
    """A [[cells]] entry over the [defaults] (those its kind has no use for are left out)."""
    where = f"{path}: cell {entry.get('id', f'#{index + 1}')!r}"
    merged = {**defaults, **entry}
    for key in ("id", "table", "kind", "task"):
        if key not in merged:
            raise SpecError(f"{where}: missing {key!r}")
    kind = merged["kind"]
    if kind not in RUNS:
        raise SpecError(f"{where}: kind must be one of {KINDS}, got {kind!r}")
    for key in REQUIRED[kind]:
        if key not in merged:
            raise SpecError(f"{where}: a {kind} cell needs {key}")
    known = _keys(kind)
    unknown = sorted(set(entry) - known - set(CELL_KEYS))
    if unknown:
        raise SpecError(f"{where}: unknown keys {unknown}" + (f" for a {kind} cell" if set(unknown) <= every else ""))
    try:
        run = convert(RUNS[kind], _nest(kind, {k: v for k, v in merged.items() if k in known}))
        own = {k: merged[k] for k in CELL_KEYS if k in merged and k != "kind"}
        return Cell(run=run, **_typed(Cell, own))
    except (ValueError, TypeError) as exc:  # (SpecError too; TypeError: a ppo value of the wrong type)
        raise SpecError(f"{where}: {exc}") from None


def _check_references(spec: Spec) -> None:
    seen: dict[str, Cell] = {}
    for c in spec.cells:
        if c.id in seen:
            raise SpecError(f"{spec.path}: two cells named {c.id!r}")
        if c.needs:
            _check_needs(spec, c, seen.get(c.needs))
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


def _check_needs(spec: Spec, c: Cell, src: Cell | None) -> None:
    """A zero-shot row's source, a run's init_from: a cell declared before it with a policy of
    ours that fits (a curriculum's at one of its stage sizes)."""
    zero_shot = c.kind == "zero-shot"
    role, agents_key = ("source", "source_agents") if zero_shot else ("init_from", "init_agents")
    where = f"{spec.path}: cell {c.id!r}: {role} {c.needs!r}"
    if src is None:
        raise SpecError(f"{where} must be a cell declared before it")
    if src.kind not in ("train", "curriculum"):
        raise SpecError(f"{where} is a {src.kind} cell (no policy of ours)")
    agents = getattr(c.run, agents_key)
    if src.kind == "curriculum" and agents not in src.run.sizes:
        raise SpecError(f"{where}: {agents_key} must be one of its stage sizes {list(src.run.sizes)}, got {agents}")
    if src.kind == "train" and agents not in (0, src.run.agents):
        raise SpecError(f"{where} is a train cell at M = {src.run.agents}: leave {agents_key} out, got {agents}")
    model = src.run.config.model.entity_mode
    if zero_shot:
        if model == "concat" and src.run.task == "coverage":
            raise SpecError(
                f"{where} has entity_mode 'concat', a fixed number of landmarks: coverage's changes with the team size"
            )
        ours, theirs = (c.run.task, c.run.comm, c.run.comm_radius), (src.run.task, src.run.comm, src.run.comm_radius)
        if ours != theirs:
            raise SpecError(f"{where}: task / comm / comm_radius {ours} differ from its source's {theirs}")
    elif model != c.run.config.model.entity_mode or (model == "concat" and src.run.task != c.run.task):
        # the weights fit another task's only where neither concatenates a task's own landmark
        # count (e.g. coverage's policy into formation's sensed lattice: the same inputs)
        raise SpecError(
            f"{where}: task / entity_mode {c.run.task, c.run.config.model.entity_mode} differ from its "
            f"{src.run.task, model} (the weights would not fit)"
        )
