"""What one BenchMARL baseline run is: ``BaselineConfig``, checked once in ``__post_init__``.

The command line (baselines/run.py, tools/run_baselines.py) parses into it and a
``swarm reproduce`` baseline cell holds one; ``baselines.run.run`` takes it. Importing this
module imports neither torch nor BenchMARL (a spec with baseline cells loads without them).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from taichi_swarm.sim import Sim

OBS_MODES = ("local", "full")
ACTION_CHOICES = ("any", "discrete", "continuous")
# BenchMARL 1.5's algorithms (benchmarl.algorithms.algorithm_config_registry; a test holds them equal)
ALGORITHMS = ("iddpg", "ippo", "iql", "isac", "maddpg", "mappo", "masac", "qmix", "vdn")
MAX_FRAMES = 10**12
MAX_ENVS = 2**20  # environments of one batch (trainer.config.MAX_NUM_ENVS)
# The Sim's fields a baseline sets: the algorithms run the paper's dense layout (every entity
# observed, no lists or auction), so the rest keep the Sim's defaults.
SETTING = ("task", "agents", "comm", "comm_radius")


@dataclass
class BaselineConfig:
    """One run: train ``algorithm`` on ``task`` for ``frames`` env steps, then evaluate it
    greedily on ``eval_episodes`` fresh episodes from ``eval_seed``."""

    algorithm: str = "mappo"
    """A BenchMARL algorithm: mappo, ippo, maddpg, iql, ..."""
    sim: Sim = Sim("coverage", 3)
    """The setting (its task, agents, comm and comm_radius: ``SETTING``)."""
    obs_mode: str = "full"
    """full: the paper's baselines (everything observed, no communication); local: the paper's own observation."""
    actions: str = "any"
    """any lets the algorithm choose (continuous where it can); discrete or continuous forces one."""
    max_steps: int = 50
    """Episode length limit."""
    frames: int = 1_000_000
    """Training budget in env steps."""
    num_envs: int = 32
    """Environments stepped together."""
    frames_per_batch: int = 4096
    """Env steps collected per iteration (32 x 128, the paper's PPO batch)."""
    model: str = "mlp"
    """BenchMARL model of actor and critic."""
    seed: int = 0
    """Training seed."""
    eval_episodes: int = 500
    eval_seed: int = 12345
    device: str = "cpu"
    """cpu or cuda: simulator, sampling and training."""
    threads: int = 1
    """torch threads (0: torch's default)."""
    experiment: dict = field(default_factory=dict)
    """Overrides of BenchMARL ExperimentConfig fields, e.g. {"lr": 3e-4}."""
    checkpoint_every: int = 25
    """Iterations between checkpoints (0: only at the end); the last two are kept."""
    out: str = ""
    """Output directory: BenchMARL's experiment folder and results.json."""

    @classmethod
    def of(cls, **options) -> BaselineConfig:
        """From flat options (a command line's, a spec cell's): task, agents, comm and
        comm_radius set the Sim, checked by the Sim's own checks."""
        d = nest(options)
        return cls(**{**d, "sim": Sim(**d["sim"])})

    def to_dict(self) -> dict:
        """Flat, as a spec cell names it (``of``'s inverse)."""
        d = dataclasses.asdict(self)
        d.pop("sim")
        return {**{k: getattr(self.sim, k) for k in SETTING}, **d}

    def __post_init__(self):
        self.algorithm = self.algorithm.lower() if isinstance(self.algorithm, str) else self.algorithm
        if self.algorithm not in ALGORITHMS:
            raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}")
        if not isinstance(self.sim, Sim) or self.sim != Sim(*(getattr(self.sim, k) for k in SETTING)):
            raise ValueError(f"sim: a baseline runs the dense layout, set by {', '.join(SETTING)} alone")
        if self.obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode must be one of {OBS_MODES}, got {self.obs_mode!r}")
        if self.actions not in ACTION_CHOICES:
            raise ValueError(f"actions (the task's action_space) must be one of {ACTION_CHOICES}, got {self.actions!r}")
        for name in ("frames", "num_envs", "frames_per_batch", "eval_episodes", "max_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.frames > MAX_FRAMES:
            raise ValueError(f"frames must be <= 10^12, got {self.frames}")
        if self.num_envs > MAX_ENVS or self.eval_episodes > MAX_ENVS:
            raise ValueError(f"num_envs and eval_episodes must be <= {MAX_ENVS} (one environment each)")
        if self.frames_per_batch % self.num_envs:
            # TorchRL would round each batch up, and checkpoints at multiples of the batch never come
            raise ValueError(
                f"frames_per_batch ({self.frames_per_batch}) must be a multiple of num_envs ({self.num_envs})"
            )
        if self.checkpoint_every < 0:
            raise ValueError(f"checkpoint_every must be >= 0, got {self.checkpoint_every}")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0, got {self.threads}")


def nest(options: dict) -> dict:
    """Flat options with the setting's keys as one "sim" dict (the default's where absent)."""
    d = {k: v for k, v in options.items() if k not in SETTING}
    d["sim"] = {k: options.get(k, getattr(BaselineConfig.sim, k)) for k in SETTING}
    return d


def parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--experiment takes KEY=VALUE, got {item!r}")
        out[key.strip()] = _parse_value(value.strip())
    return out


def _parse_value(text: str):
    """An int, a float (also 3e-4, which YAML 1.1 reads as a string), else YAML (true, null, [csv])."""
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    import yaml

    return yaml.safe_load(text)
