"""``Sim``: the one declaration of a simulated setting, checked once, here.

    sim = Sim("coverage", 100, comm="rc", neighbours=12, landmark_neighbours=64, sense_radius=6.0,
              landmark_occupancy=True, landmark_order="radio", scale="density", assignment="free")
    env = taichi_swarm.make(sim, num_envs=8)

Every layer takes this object: ``make`` builds the simulator from it, the trainer's config
holds one (``TrainConfig.sim``), a checkpoint and an export manifest store it (as the two
records ``task_record()`` / ``swarm_record()``, the format every stored policy has), and
``swarm eval`` / ``execute`` / ``world`` run a policy in ``policy_sim.override(...)`` of the
options a command sets. A bad value raises ``ConfigError`` naming the field, before
anything is allocated.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Literal

import numpy as np

# (no Taichi here: the command line checks its options with CHECKS before anything compiles;
# the task registry, which is Taichi code, is read when a Sim is made)
from .constants import ACTION_SPACES, COMMS, DEFAULT_ROUNDS, MAX_ROUNDS

SCALES = (None, "density")
ASSIGNMENTS = ("exact", "free")
# landmark lists: the KL nearest; or the one landmark the agents agree on by messages to the
# teammates they hear alone ("radio": radio.py)
LANDMARK_ORDERS = ("nearest", "radio")
MAX_AGENTS = 2**20  # a team's size: B x M x K list slots must stay int32-addressable
MAX_LIST = 1024  # the widest neighbour or landmark list (K, KL)
INT32_MAX = 2**31 - 1
TASK_KEYS = ("task", "agents", "comm", "comm_radius")  # a record's "task" dict; the rest: its "swarm" dict


class ConfigError(ValueError):
    """A value of the experiment refused: ``field`` names it (a dataclass field, the command
    line's --field), the message says why. A ValueError, so callers that treat bad input as one
    still do."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(message)


def check_int(field: str, value, minimum: int, maximum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(field, f"{field} must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(field, f"{field} must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ConfigError(field, f"{field} must be <= {maximum}, got {value}")
    return int(value)


def check_float(field: str, value, minimum: float, strict: bool = False) -> float:
    """A finite real >= minimum (> with ``strict``) that stays finite as the float32 the kernels store."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ConfigError(field, f"{field} must be a finite number, got {value!r}")
    if value < minimum or (strict and value == minimum):
        raise ConfigError(field, f"{field} must be {'>' if strict else '>='} {minimum}, got {value}")
    with np.errstate(over="ignore"):
        narrowed = np.float32(value)
    if not np.isfinite(narrowed):
        raise ConfigError(field, f"{field} must fit a float32 (|x| < 3.4e38), got {value!r}")
    return float(value)


def one_of(field: str, value, choices: tuple):
    if value not in choices:
        raise ConfigError(field, f"{field} must be one of {choices}, got {value!r}")
    return value


def _bool(field: str, value) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(field, f"{field} must be True or False, got {value!r}")
    return value


# Each field's own check (its type and bounds), the one validator of that key: Sim.__post_init__
# runs it on every value it is given, and the command line on every option it parses (a refusal
# before any file is read); the checks between fields follow in __post_init__.
CHECKS = {
    "agents": lambda v: check_int("agents", v, 1, MAX_AGENTS),
    "comm": lambda v: one_of("comm", v, COMMS),
    "comm_radius": lambda v: check_float("comm_radius", v, 0.0),
    "action_space": lambda v: one_of("action_space", v, ACTION_SPACES),
    "neighbours": lambda v: check_int("neighbours", v, 1, MAX_LIST),
    "landmark_neighbours": lambda v: check_int("landmark_neighbours", v, 1, MAX_LIST),
    "sense_radius": lambda v: check_float("sense_radius", v, 0.0, strict=True),
    "landmark_occupancy": lambda v: _bool("landmark_occupancy", v),
    "landmark_order": lambda v: one_of("landmark_order", v, LANDMARK_ORDERS),
    "auction_rounds": lambda v: check_int("auction_rounds", v, 1, MAX_ROUNDS),
    "scale": lambda v: one_of("scale", v, SCALES),
    "assignment": lambda v: one_of("assignment", v, ASSIGNMENTS),
}


def check_value(field: str, value):
    """``value`` of ``field`` as its own check takes it (None: unset, taken as is)."""
    return value if value is None else CHECKS[field](value)


@dataclass(frozen=True)
class Sim:
    """A task, a team and how its agents hear and sense (defaults: the paper's setting)."""

    task: str
    """coverage | formation | line."""
    agents: int | None = None  # (None: a manifest exported without one; make needs it)
    """Team size M."""
    comm: Literal["uc", "rc"] = "uc"
    """uc (everyone hears everyone) | rc (only within comm_radius)."""
    comm_radius: float = 1.0
    """Communication radius of "rc"."""
    action_space: Literal["discrete", "fine", "continuous"] = "discrete"
    """discrete: the paper's 5 actions; fine: 9, the paper's and four pushes at a quarter of the
    force, with which an agent at rest can park within 0.035 of any point (physics.FINE;
    ``--init-from`` a 5-action policy starts the new four as copies of the full pushes, less
    likely); continuous: MPE's continuous mode (no policy here trains on it)."""
    neighbours: int | None = None
    """K: each agent hears its K nearest (within comm_radius under rc) as neighbour lists, not the
    dense M x M graph; the network's cost per agent then depends on K, not M (None: dense)."""
    landmark_neighbours: int | None = None
    """KL: each agent senses its KL nearest landmarks within sense_radius (None: every landmark)."""
    sense_radius: float | None = None
    """Landmark sensing radius of ``landmark_neighbours``."""
    landmark_occupancy: bool = False
    """With neighbours and landmark_neighbours: each sensed landmark also carries its distance to
    the nearest other agent (capped at sense_radius), as a range sensor at the landmark would
    report it; the network takes it as a third landmark input (docs/SWARM.md)."""
    landmark_order: Literal["nearest", "radio"] = "nearest"
    """With landmark_occupancy: nearest, the KL nearest landmarks within sense_radius; radio
    (with assignment free), only the landmark the agent holds in an auction the agents run by
    messages to the teammates they hear, each over the landmarks it senses: a planner picks the
    landmark, the network drives (radio.py, docs/SWARM.md)."""
    auction_rounds: int | None = None
    """With landmark_order radio: R message rounds a step (None: 4)."""
    scale: Literal["density"] | None = None
    """density: the arena and shapes grow with M so agents per unit area stay as at M = 10
    (None: the paper's geometry)."""
    assignment: Literal["exact", "free"] = "exact"
    """How targets are matched to agents for the reward: exact, the paper's min-sum matching; free
    (with neighbours), each agent paid by its matched target or, unmatched, the nearest free one,
    success from a maximum matching within the threshold: local, no M x M block (nearest.py)."""

    def __post_init__(self):
        from .tasks import TASK_SPECS

        one_of("task", self.task, tuple(TASK_SPECS))
        spec = TASK_SPECS[self.task]
        for name in CHECKS:  # each field's own check (None only where it means unset), then those between fields
            value = getattr(self, name)
            object.__setattr__(self, name, check_value(name, value) if name in NULLABLE else CHECKS[name](value))
        if self.agents is not None and self.agents < spec.min_agents:
            raise ConfigError("agents", f"agents must be >= {spec.min_agents} for {self.task}, got {self.agents}")
        if self.landmark_neighbours is not None:
            if not spec.landmark_lists:
                raise ConfigError(
                    "landmark_neighbours",
                    f"landmark_neighbours is for tasks with a landmark per agent; {spec.name!r} keeps its landmarks "
                    "global",
                )
            if self.sense_radius is None:
                raise ConfigError(
                    "sense_radius", "landmark_neighbours needs sense_radius (how far an agent senses landmarks)"
                )
        elif self.sense_radius is not None:
            raise ConfigError("sense_radius", "sense_radius is only used with landmark_neighbours")
        if self.scale == "density" and not spec.density_scale:
            raise ConfigError("scale", f"scale='density' is not implemented for task {spec.name!r}")
        if self.landmark_neighbours is not None and spec.listed_landmarks is not None and self.scale != "density":
            raise ConfigError(
                "scale",
                f"{spec.name}'s listed landmarks are the points of its density-scaled lattice: landmark_neighbours "
                "needs scale='density'",
            )
        if self.assignment == "free" and self.neighbours is None:
            raise ConfigError(
                "assignment",
                "assignment='free' needs neighbours=K: it finds each target's nearest agent through the agents' "
                "cell grid the neighbour lists build",
            )
        if self.landmark_occupancy and (self.neighbours is None or self.landmark_neighbours is None):
            raise ConfigError(
                "landmark_occupancy",
                "landmark_occupancy needs neighbours=K and landmark_neighbours=KL: it is read off the agents' cell "
                "grid for each listed landmark",
            )
        if self.landmark_order == "radio":
            if not self.landmark_occupancy:
                raise ConfigError(
                    "landmark_order",
                    "landmark_order='radio' needs landmark_occupancy=True (and so neighbours and "
                    "landmark_neighbours): agents exchange their auction tables with the teammates on their lists",
                )
            if self.assignment != "free":
                raise ConfigError(
                    "landmark_order",
                    f"landmark_order='radio' needs assignment 'free', got {self.assignment!r}: its rewards and "
                    "success come from the threshold matching over the agents' grid",
                )
        if self.auction_rounds is not None:
            if self.landmark_order != "radio":
                raise ConfigError(
                    "auction_rounds",
                    f"auction_rounds is the radio auction's message rounds a step: it needs landmark_order 'radio', "
                    f"got {self.landmark_order!r}",
                )

    # ------------------------------------------------------------------ derived
    @property
    def rounds(self) -> int | None:
        """The radio's message rounds a step (None: no radio)."""
        if self.landmark_order != "radio":
            return None
        return self.auction_rounds or DEFAULT_ROUNDS

    def team_size(self, what: str = "the checkpoint") -> int:
        """``agents``, or an error that says to pass --agents."""
        if self.agents is None:
            raise ConfigError("agents", f"{what} does not say its team size: pass --agents")
        return self.agents

    # ------------------------------------------------------------------ records
    def task_record(self) -> dict:
        """The "task" dict a checkpoint or manifest stores."""
        return {k: getattr(self, k) for k in TASK_KEYS}

    def swarm_record(self) -> dict:
        """The "swarm" dict a checkpoint or manifest stores: the options that differ from the
        paper's setting (none: the dense layout, the paper's geometry and 5 actions)."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name not in TASK_KEYS and getattr(self, f.name) != f.default
        }

    @classmethod
    def from_record(cls, task: dict | None, swarm: dict | None = None, what: str = "the checkpoint") -> Sim:
        """From a checkpoint's or manifest's "task" and "swarm" dicts; a missing task is named."""
        task, swarm = dict(task or {}), dict(swarm or {})
        if task.get("task") is None:
            raise ConfigError("task", f"{what} does not say its task: pass --task")
        for record, keys in ((task, TASK_KEYS), (swarm, SWARM_KEYS)):
            unknown = sorted(set(record) - set(keys))
            if unknown:
                raise ConfigError(unknown[0], f"{what}'s setting has unknown keys {unknown}")
        return cls(**{k: v for k, v in {**task, **swarm}.items() if v is not None})

    @classmethod
    def resolve(cls, task: dict | None, swarm: dict | None, what: str = "the checkpoint", /, **overrides) -> Sim:
        """The recorded setting with the options a command sets over it (``override``); a record
        that names no task takes the command's."""
        task = dict(task or {})
        if not task.get("task"):
            task["task"] = overrides.get("task")
        return cls.from_record(task, swarm, what).override(what, **overrides)

    def override(self, what: str = "the checkpoint", /, **options) -> Sim:
        """This setting with the options a command sets over it (None: keep this one's). A policy
        runs only its own task; a landmark order other than radio drops the radio's rounds."""
        from .tasks import TASK_SPECS

        given = {k: v for k, v in options.items() if v is not None}
        unknown = sorted(set(given) - set(FIELDS))
        if unknown:
            raise ConfigError(unknown[0], f"unknown setting {unknown[0]!r}; known: {FIELDS}")
        one_of("task", given.get("task", self.task), tuple(TASK_SPECS))
        if given.get("task", self.task) != self.task:  # its observations and reward are another task's
            raise ConfigError(
                "task",
                f"{what} holds a {self.task} policy: it cannot run the {given['task']} task (--task {given['task']})",
            )
        if given.get("landmark_order", "radio") != "radio" and "auction_rounds" not in given:
            given["auction_rounds"] = None
        return dataclasses.replace(self, **given)


FIELDS = tuple(f.name for f in dataclasses.fields(Sim))
SWARM_KEYS = tuple(k for k in FIELDS if k not in TASK_KEYS)
# what a command may set over a stored policy's setting: not its task's keys (their own options),
# nor the network's inputs and outputs (its occupancy input, its action set)
RUN_TIME_KEYS = tuple(k for k in SWARM_KEYS if k not in ("action_space", "landmark_occupancy"))
NULLABLE = tuple(f.name for f in dataclasses.fields(Sim) if f.default is None)  # None: unset
