"""The task setting a policy is trained for or run in: task, team size, communication.

It travels in every checkpoint (``payload["task"]``) and export manifest (``manifest
["task"]``) as a dict; ``TaskSetting`` is its one typed form. ``from_dict`` reads what a
checkpoint or manifest says, ``override`` fills in what a command line sets, and the
checks run once, here (their messages name the command-line options that set them)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .env import COMMS
from .tasks import TASK_SPECS


@dataclass(frozen=True)
class TaskSetting:
    task: str
    agents: int | None = None
    """Team size (None: not recorded, e.g. a manifest exported without one)."""
    comm: str = "uc"
    comm_radius: float = 1.0

    def __post_init__(self):
        if self.task not in TASK_SPECS:
            raise ValueError(f"--task must be one of {tuple(TASK_SPECS)}, got {self.task!r}")
        if self.comm not in COMMS:
            raise ValueError(f"--comm must be one of {COMMS}, got {self.comm!r}")
        smallest = TASK_SPECS[self.task].min_agents
        if self.agents is not None and (not isinstance(self.agents, int) or self.agents < smallest):
            raise ValueError(f"--agents must be >= {smallest} for {self.task}, got {self.agents!r}")
        if not (isinstance(self.comm_radius, (int, float)) and math.isfinite(self.comm_radius)):
            raise ValueError(f"--comm-radius must be a finite number, got {self.comm_radius!r}")
        if self.comm_radius < 0:
            raise ValueError(f"--comm-radius must be >= 0, got {self.comm_radius}")
        object.__setattr__(self, "comm_radius", float(self.comm_radius))

    @classmethod
    def from_dict(cls, d: dict | None, what: str = "the checkpoint") -> TaskSetting:
        """From a checkpoint's or manifest's ``task`` dict; a missing task is named."""
        d = dict(d or {})
        if d.get("task") is None:
            raise ValueError(f"{what} does not say its task: pass --task")
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"{what}'s task setting has unknown keys {unknown}")
        return cls(**{k: v for k, v in d.items() if v is not None})

    @classmethod
    def resolve(cls, recorded: dict | None, what: str = "the checkpoint", **overrides) -> TaskSetting:
        """The recorded setting with the options a command sets (None: keep the recorded)."""
        base = {k: v for k, v in dict(recorded or {}).items() if v is not None}
        own = base.get("task")
        base.update({k: v for k, v in overrides.items() if v is not None})
        setting = cls.from_dict(base, what)  # (an unknown task is named first)
        if own is not None and setting.task != own:  # its observations and reward are another task's
            raise ValueError(
                f"{what} holds a {own} policy: it cannot run the {setting.task} task (--task {setting.task})"
            )
        return setting

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def team_size(self, what: str = "the checkpoint") -> int:
        """``agents``, or an error that says to pass --agents."""
        if self.agents is None:
            raise ValueError(f"{what} does not say its team size: pass --agents")
        return self.agents
