"""What a task is, for the simulator: one ``Task`` record, three Taichi functions and its reward terms.

A task module (coverage.py, formation.py, line.py) defines

- a frozen dataclass of its overridable parameters (the paper's values as defaults;
  ``success_threshold`` in every task),
- the Taichi functions the fused kernels call, with the task as a compile-time
  constant (kernels.py dispatches through ``tasks.funcs_of``):
    ``landmark_count(sm, ib) -> i32``   L for the env's M
    ``spawn_landmarks(sm, f, ib, b)``   the landmarks of a fresh episode of env b
                                        (the agents are spawned by the caller first)
    ``place_targets(sm, f, ib, b)``     the M targets of env b from its current state
- one Taichi function ``term(f, ctx) -> f32`` per named per-agent reward term
  (``Task.reward_terms``): ``ctx`` is the agent's ``Context`` (its matched distance, its
  position, how many teammates it touched this step) and ``f``, the float buffer, holds the
  env's parameters. An agent's own reward is the sum of its terms, each reported by name in
  ``info["reward_terms"]``, and the team reward is the mean of the agents', so a new term (a
  collision penalty, say) is a change in the task module alone.
- and ``TASK = Task(...)``, registered in tasks/__init__.py.

Success is the same rule for every task (every matched distance below
``success_threshold``), in kernels.py.
"""

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import taichi as ti

# Overridable parameters every task has (``taichi_swarm.make(..., max_steps=...)``).
COMMON_PARAMS = {"max_steps": 50}
FUNCS = ("landmark_count", "spawn_landmarks", "place_targets")
# What a per-agent reward term sees of its agent (kernels.settle builds it): its matched distance
# d*_i (with assignment "free": to its matched or nearest free target), its position, and the
# teammates it touched this step (closer than the two radii, as the contact force sees them).
Context = ti.types.struct(d=ti.f32, pos=ti.math.vec2, contacts=ti.f32)


@dataclass(frozen=True)
class Task:
    """Everything the simulator knows about one task."""

    name: str
    task_id: int
    """Compile-time constant of the kernels (unique)."""
    agent_radius: float
    landmark_radius: float
    min_agents: int
    params_type: type
    """Frozen dataclass of the task's parameters; its defaults are the paper's."""
    landmarks: Callable[[int], int]
    """L for M agents (Python side; ``landmark_count`` is the kernels' side)."""
    funcs: object
    """The module (or any object) holding the task's Taichi functions (FUNCS)."""
    kernel_param: str = ""
    """The parameter the kernels read (float header slot P_TASK_PARAM), if any."""
    reports_dist: bool = False
    """Whether DIST (mean distance from each landmark to its closest agent) is a metric."""
    density_scale: bool = False
    """Whether the task implements ``scale="density"`` (spawn square of half-width
    sqrt(M / 10), read as f[P_ARENA] by its spawn)."""
    landmark_lists: bool = False
    """Whether its landmarks may be sensed as lists (``landmark_neighbours``): coverage's
    M landmarks; formation's and line's targets (``listed_landmarks``)."""
    listed_landmarks: Callable[[int], int] | None = None
    """L for M agents when the landmarks are sensed as lists, where that differs from
    ``landmarks`` (formation: its M lattice points, which only ``scale="density"`` has)."""
    reward_terms: tuple[str, ...] = ()
    """The named per-agent reward terms an agent's reward sums, each a Taichi function of the
    module, ``term(f, ctx) -> f32`` (ctx: the agent's ``Context``)."""
    doc: str = ""

    def __post_init__(self):
        if not self.reward_terms:
            raise ValueError(f"task {self.name!r}: reward_terms must name at least one per-agent term")
        missing = [name for name in FUNCS + self.reward_terms if not callable(getattr(self.funcs, name, None))]
        if missing:
            raise ValueError(f"task {self.name!r}: its funcs lack the Taichi functions {missing}")
        if not dataclasses.is_dataclass(self.params_type):
            raise ValueError(f"task {self.name!r}: params_type must be a dataclass")
        if "success_threshold" not in self.params:
            raise ValueError(f"task {self.name!r}: its parameters must include success_threshold")
        if self.listed_landmarks is not None and not (self.landmark_lists and self.density_scale):
            raise ValueError(f"task {self.name!r}: listed_landmarks needs landmark_lists and density_scale")
        if self.kernel_param and self.kernel_param not in self.params:
            raise ValueError(f"task {self.name!r}: kernel_param {self.kernel_param!r} is not one of its parameters")

    @property
    def params(self) -> dict:
        """The task's parameters and their defaults."""
        return dataclasses.asdict(self.params_type())

    def num_landmarks(self, num_agents: int, listed: bool = False) -> int:
        """L for M agents; ``listed``: with landmark lists (``landmark_neighbours``)."""
        if listed and self.listed_landmarks is not None:
            return self.listed_landmarks(num_agents)
        return self.landmarks(num_agents)


@ti.func
def clipped_matched_distance(f: ti.template(), ctx: Context) -> ti.f32:
    """-clip(d*_i, 0, 2): a per-agent term whose mean is the team reward -mean_clipped_d
    (formation's and line's ``matched_distance``)."""
    return -ti.math.clamp(ctx.d, 0.0, 2.0)
