"""The model zoo: curated policies addressable by name.

``models/index.toml`` lists one entry per published setting (task x UC/RC x team size,
and the transfer policies): where its weights lie, their sha256, what trained them and
what they score on 500 fresh greedy episodes. Every command that takes a checkpoint also
takes a zoo name (``swarm eval coverage-rc-m10``): ``trainer.checkpoint.load`` turns the
name into the weights' path and checks the file against the index's sha256, so a name
always means the bytes that were measured.

The weights are the spec results themselves (``results/reproduce-*``, where the generated
tables read them): the zoo names them, it does not copy them.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import math
import os
from dataclasses import dataclass, field

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ZOO_DIR = os.path.join(ROOT, "models")
INDEX = os.path.join(ZOO_DIR, "index.toml")


class ZooError(ValueError):
    """A zoo name that is not in the index, or a file that does not match its entry."""


@dataclass(frozen=True)
class ZooEntry:
    """One curated policy (an ``[[model]]`` table of models/index.toml)."""

    name: str
    task: str
    comm: str
    agents: int
    """The team size it was trained (and is evaluated) at."""
    weights: str
    """Path of policy.pt, relative to the repository root."""
    sha256: str
    """sha256 of the weights file's bytes."""
    spec: str
    """The ``swarm reproduce`` spec whose cell trained it."""
    cell: str
    seed: int
    comm_radius: float = 1.0
    entity_mode: str = "emp"
    trained_on: tuple[int, ...] = ()
    """Team sizes of its training (a curriculum's stages up to it, or several at once)."""
    success: float = 0.0
    """S% on ``episodes`` fresh greedy episodes at ``eval_seed`` (a fraction)."""
    mean_length: float = 0.0
    dist: float | None = None
    covered: float | None = None
    """The mean fraction of landmarks covered at the episodes' ends (coverage, where recorded)."""
    episodes: int = 500
    eval_seed: int = 777
    paper_success: float | None = None
    """The paper's S% for the same setting, where it reports one (a fraction)."""
    updates: int = 0
    env_steps: int = 0
    minutes: float = 0.0
    zero_shot: dict = field(default_factory=dict)
    """{team size: S%} of the same policy at other team sizes, no fine-tuning (500 episodes)."""
    curves: str = ""
    """Path of its learning curves (curves.png), relative to the repository root."""
    summary: str = ""
    """One line on what it is."""
    use: str = ""
    """One line on when to pick it (the card's first line; unset: the paper's table cell)."""

    @property
    def path(self) -> str:
        return os.path.join(ROOT, self.weights)

    def when(self) -> str:
        """When to pick it: ``use``, else the paper's table cell it reproduces."""
        if self.use:
            return self.use
        paper = "" if self.paper_success is None else f" (the paper: {100 * self.paper_success:.0f})"
        return f"Use it for {self.task} {self.comm.upper()} at M = {self.agents}: S% {100 * self.success:.1f}{paper}."

    def command(self) -> str:
        seed = f" --first-seed {self.seed}" if self.seed else ""
        if self.spec == "radio":  # two swarm train cells (tools/make_zoo.py, RADIO)
            return f"tools/radio_recipe.sh {self.task}"
        return f"swarm reproduce --spec {self.spec} --cells {self.cell}{seed}"


def load_index(path: str = INDEX) -> list[ZooEntry]:
    """Every entry of the index, in its order; a malformed index is a ZooError naming the entry."""
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ZooError(f"the model zoo index {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ZooError(f"the model zoo index {path} is not valid TOML: {exc}") from None
    names = {f.name for f in dataclasses.fields(ZooEntry)}
    entries = []
    for i, raw in enumerate(data.get("model", [])):
        unknown = sorted(set(raw) - names)
        if unknown:
            raise ZooError(f"{path}: model #{i + 1} has unknown keys {unknown}")
        raw = dict(raw)
        raw["trained_on"] = tuple(raw.get("trained_on", ()))
        raw["zero_shot"] = {int(k): float(v) for k, v in raw.get("zero_shot", {}).items()}
        try:
            entries.append(ZooEntry(**raw))
        except TypeError as exc:
            raise ZooError(f"{path}: model #{i + 1}: {exc}") from None
    seen = set()
    for e in entries:
        if e.name in seen:
            raise ZooError(f"{path}: the name {e.name!r} appears twice")
        seen.add(e.name)
    return entries


def get(name: str) -> ZooEntry:
    entries = {e.name: e for e in load_index()}
    if name not in entries:
        close = difflib.get_close_matches(name, list(entries), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else " (swarm models lists them)"
        raise ZooError(f"{name!r} is not a file, a run directory or a model zoo name{hint}")
    return entries[name]


def file_sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def looks_like_name(text: str) -> bool:
    """A zoo name has no path separator and no file suffix (``coverage-rc-m10``)."""
    return bool(text) and os.sep not in text and "/" not in text and not os.path.splitext(text)[1]


def verify(entry: ZooEntry) -> None:
    if not os.path.isfile(entry.path):
        raise ZooError(f"zoo entry {entry.name}: its weights {entry.weights} are missing")
    digest = file_sha256(entry.path)
    if digest != entry.sha256:
        raise ZooError(
            f"zoo entry {entry.name}: {entry.weights} does not match the index's sha256 "
            "(the file was changed or corrupted)"
        )


def select(entries: list[ZooEntry], task: str | None = None, comm: str | None = None, agents: int | None = None):
    """The entries of ``task`` and ``comm`` (None: any); with ``agents``, the one to use for a team
    of that size per (task, comm): the entry trained at the nearest team size (by ratio, since a
    policy's reach grows with its size), the higher S% on a tie."""
    chosen = [e for e in entries if task in (None, e.task) and comm in (None, e.comm)]
    if agents is None:
        return chosen
    best = {}
    for e in sorted(chosen, key=lambda e: (abs(math.log(e.agents / agents)), -e.success)):
        best.setdefault((e.task, e.comm), e)  # the first of each setting is the nearest
    return [e for e in chosen if best[(e.task, e.comm)] is e]
