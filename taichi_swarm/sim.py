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
    agents: int | None = None
    """Team size M (None: not recorded, as in a manifest exported without one; ``make`` needs it)."""
    comm: Literal["uc", "rc"] = "uc"
    """uc: every agent hears every agent; rc: only those within comm_radius."""
    comm_radius: float = 1.0
    """The radius of rc."""
    action_space: Literal["discrete", "fine", "continuous"] = "discrete"
    """discrete: the paper's 5 actions; fine: those and four quarter pushes (physics.FINE);
    continuous: MPE's continuous mode."""
    neighbours: int | None = None
    """K: each agent's K nearest heard agents as index lists, not the M x M graph (None: dense)."""
    landmark_neighbours: int | None = None
    """KL: each agent's KL nearest landmarks within sense_radius (None: every landmark)."""
    sense_radius: float | None = None
    """How far an agent senses landmarks (with landmark_neighbours)."""
    landmark_occupancy: bool = False
    """Each listed landmark also reads its distance to the nearest other agent, capped at sense_radius."""
    landmark_order: Literal["nearest", "radio"] = "nearest"
    """nearest: the KL nearest listed landmarks; radio: the one landmark the agent holds in the
    auction the agents run by messages to the teammates they hear (radio.py)."""
    auction_rounds: int | None = None
    """With landmark_order radio: R message rounds a step (None: radio.DEFAULT_ROUNDS)."""
    scale: Literal["density"] | None = None
    """density: the arena grows with M, keeping the agents per unit area of M = 10."""
    assignment: Literal["exact", "free"] = "exact"
    """exact: the paper's min-sum matching; free (with neighbours): local rewards and a
    threshold matching, no M x M block (nearest.py)."""

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
NULLABLE = tuple(f.name for f in dataclasses.fields(Sim) if f.default is None)  # None: unset
