"""Typed configuration: one dataclass per concern, a docstring per option.

``PRESETS["paper"]`` is s.5 of docs/PAPER.md exactly;
``PRESETS["fast"]`` is what we measured to learn in far fewer env steps and
less wall-clock on a 2-core CPU (docs/FINDINGS.md, "The fast preset against the paper's").
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Literal

from taichi_swarm import NUM_ACTIONS, TASK_SPECS, num_actions
from taichi_swarm.sim import FIELDS as SIM_FIELDS
from taichi_swarm.sim import NULLABLE, Sim
from trainer.evaluate import check_policy_actions
from trainer.model import ENTITY_MODES, MAX_HIDDEN, MAX_ROUNDS, ModelConfig

# Options of experiments that lost, with the value that meant "off": a stored run that set one
# needs the release that still had it (the git tag swarm-chains; docs/FINDINGS.md)
RETIRED = {
    "init_carry": "weights",
    "message_burst": 0.0,
    "hold_reward": 0.0,
    "auction_eps": None,
}
# values of kept options that left with the shared-price auction and the team-wide claim readings
RETIRED_VALUES = {"landmark_order": ("claim-zero", "auction"), "assignment": ("auction", "nearest")}
MAX_TRANSFER_OFFSET = 1000  # |d| of a --transfer-offsets entry
MAX_SEED = 2**31 - 1  # training seeds (the environments' seeds: trainer.train.train_seed)
MAX_NUM_ENVS = 2**20
MAX_NUM_STEPS = 2**16


def rollout_bytes(num_steps: int, num_envs: int, agents: int, landmarks: int, neighbours: int | None = None) -> int:
    """Host or device memory a rollout of this size takes while it is updated on: the buffers
    [T, E, M, ...] (self 4 + landmarks 2L floats, adjacency M bools or K neighbour lists of an
    int32 and a bool each, action, log-prob and value) and the epoch's shuffled copy of them, in
    Python integers (no overflow)."""
    graph = agents if neighbours is None else 5 * neighbours + landmarks
    per_agent_step = 4 * 4 + 4 * 2 * landmarks + graph + 8 + 4 + 4 + 4 + 4  # + advantages and returns
    return 2 * int(num_steps) * int(num_envs) * int(agents) * per_agent_step


def memory_limit() -> int:
    """This machine's physical memory in bytes (what a run may plan to use at most)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2**40


@dataclass
class PPOConfig:
    """PPO hyperparameters (defaults: the paper's)."""

    num_envs: int = 32
    """Parallel environments per rollout."""
    num_steps: int = 128
    """Steps per environment per rollout (num_envs x num_steps env steps per update)."""
    lr: float = 1e-4
    """Adam learning rate."""
    lr_end: float | None = None
    """If set, the learning rate decays linearly from ``lr`` to ``lr_end`` over the run's
    ``updates`` (None: constant). A resume that raises ``updates`` stretches the decay over
    the new budget, so the rate goes back up to where that schedule is (to train a finished
    run on at a low rate, start a new run from its weights: ``--init-from``, as the
    curriculum's polish does)."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    clip: float = 0.2
    """PPO ratio clip, also the value-function clip."""
    epochs: int = 4
    """Optimisation epochs per update."""
    minibatches: int = 32
    """Minibatches per epoch; each holds whole teams (all agents of a (t, env) sample)."""
    entropy_coef: float = 0.01
    """Entropy bonus coefficient."""
    value_coef: float = 0.5
    """Value loss coefficient (the value loss itself is 0.5 * max(clipped, unclipped) MSE)."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip."""
    reward_scale: bool = True
    """Divide rewards by a running std of the discounted return, then clip to +-reward_clip."""
    reward_clip: float = 10.0
    """Clip of the scaled reward."""
    reset_return: bool = False
    """Reset the running discounted return of the reward scaler at episode ends. False
    (the paper's published code): never reset, so it tends to r / (1 - gamma) and the
    scaled rewards are smaller against the fixed entropy bonus. True: the usual VecNormalize."""
    bootstrap_time_limit: bool = False
    """False (the paper): the 50-step limit is terminal, no bootstrap. True: bootstrap
    V(terminal observation) on time-limit ends (partial-episode bootstrapping)."""

    def validate(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"ppo.{f.name} must be a finite number, got {value}")
        for name in ("entropy_coef", "value_coef"):
            if getattr(self, name) < 0:
                raise ValueError(f"ppo.{name} must be >= 0, got {getattr(self, name)}")
        if self.lr > 1.0:
            raise ValueError(f"ppo.lr must be <= 1, got {self.lr}")
        if self.lr_end is not None and self.lr_end > 1.0:
            raise ValueError(f"ppo.lr_end must be <= 1, got {self.lr_end}")
        if not 1 <= self.num_envs <= MAX_NUM_ENVS:
            raise ValueError(f"ppo.num_envs must be in [1, {MAX_NUM_ENVS}], got {self.num_envs}")
        if not 1 <= self.num_steps <= MAX_NUM_STEPS:
            raise ValueError(f"ppo.num_steps must be in [1, {MAX_NUM_STEPS}], got {self.num_steps}")
        for name in ("num_envs", "num_steps", "epochs", "minibatches"):
            if getattr(self, name) < 1:
                raise ValueError(f"ppo.{name} must be >= 1, got {getattr(self, name)}")
        if self.num_envs * self.num_steps < self.minibatches:
            raise ValueError("ppo.minibatches must be <= num_envs * num_steps")
        if self.lr_end is not None and self.lr_end < 0:
            raise ValueError(f"ppo.lr_end must be >= 0, got {self.lr_end}")
        for name in ("lr", "clip", "max_grad_norm", "reward_clip"):
            if getattr(self, name) <= 0:
                raise ValueError(f"ppo.{name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"ppo.{name} must be in [0, 1], got {getattr(self, name)}")


PRESETS: dict[str, PPOConfig] = {
    "paper": PPOConfig(),
    # The recipe behind the zoo's policies (docs/FINDINGS.md): bigger steps on fewer, bigger
    # minibatches; short rollouts from many envs; bootstrap at the time limit; a lower
    # learning rate late in the run for the last few percent of success; and the published
    # code's never-reset running return, which kept coverage M = 3 policies carrying to M = 5.
    "fast": PPOConfig(
        num_envs=64,
        num_steps=32,
        lr=7e-4,
        lr_end=1e-4,
        epochs=4,
        minibatches=4,
        bootstrap_time_limit=True,
        reset_return=False,
    ),
}
# Large batches for one GPU (docs/BENCHMARKS.md, GPU): `fast` with 4096 environments x 16
# steps = 65536 env steps per update, in 16 minibatches of 4096 teams; coverage M = 3 from
# scratch reached 97.6% greedy after 40 updates (2.6 M env steps, 30 s on one H200).
PRESETS["gpu"] = dataclasses.replace(PRESETS["fast"], num_envs=4096, num_steps=16, minibatches=16)
# A preset's update budget, the default of --updates: the paper's 1100 updates of 4096 env
# steps; fast's 2200 of 2048 (the same 4.5 M env steps); gpu's 300 of 65536.
PRESET_UPDATES = {"paper": 1100, "fast": 2200, "gpu": 300}
DEFAULT_PRESET = "fast"  # what `swarm train` and `swarm curriculum` start from
DEFAULT_SIM = Sim("coverage", 3)  # a run's setting where it names none: the paper's smallest team


@dataclass
class TrainConfig:
    """``swarm train``: one task, one team size, PPO from scratch or from a checkpoint."""

    sim: Sim = DEFAULT_SIM
    """The simulated setting: the task, the team and how its agents hear and sense
    (``taichi_swarm.Sim``, where each of its options is declared and checked). The command line
    and the specs give its fields as options of their own (--task, --agents, --neighbours ...)."""
    message_drop: float = 0.0
    """Train through a lossy radio: every rollout draws, per environment, a drop rate uniformly
    from [0, message_drop], and every step drops each message (an edge of the communication
    graph, never an agent's own) with that rate, in the rollout and in the PPO update alike, so a
    policy learns to act on what it hears (0: no faults; evaluations are always fault-free)."""
    drop_per_round: bool = False
    """With message_drop: every round of the step draws its own drops, as `swarm execute --drop`
    and the networked agents lose messages, instead of one draw per step that the rounds share
    (the buffer then holds each round's graph: R times the adjacency)."""
    reward: Literal["team", "agent"] = "team"
    """team: every agent is trained on the team reward (the paper); agent: each on its own
    terms (the simulator's info["agent_reward"], whose mean the team reward is), each with its
    own running return in the reward normaliser: the signal a team reward gives one agent is
    diluted M times, which matters for large teams (docs/SWARM.md)."""
    preset: str = "paper"
    """PPO preset, the values of the ``ppo`` options and ``updates`` not given (``with_preset``
    makes a config from one): fast (the recipe behind the model zoo) | paper (the paper's schedule) |
    gpu (4096 environments, for one GPU)."""
    updates: int = 1100
    """PPO updates to run (the preset's budget: 4.5 M env steps for fast and paper)."""
    target_success: float = 0.0
    """Stop early once the evaluation success rate reaches this (0 = never)."""
    min_updates: int = 0
    """The target stops the run only from this update on (0: from the first evaluation)."""
    eval_every: int = 50
    """Evaluate (greedy, decentralised, fresh seeds) every this many updates."""
    eval_episodes: int = 100
    """Episodes per evaluation."""
    team_sizes: tuple[int, ...] = ()
    """Train on several team sizes at once (e.g. 3 4 5 6): every rollout has one group of
    num_envs / len(team_sizes) environments per size and every epoch minibatches of each
    size in random order; the network is size-invariant. () trains on ``agents`` alone;
    ``agents`` stays the size evaluated and recorded. For coverage UC, 3 4 (with agents 3)
    kept the M = 3 policy from piling agents up at M = 5 (docs/FINDINGS.md)."""
    transfer_offsets: tuple[int, ...] = (-1, 1, 2)
    """Every evaluation also measures S% at these team sizes relative to ``agents``
    (zero-shot transfer: metrics.jsonl ``eval_transfer``, the progress bar, the plot);
    () for none. Sizes the network cannot take are left out (entity_mode "concat": another
    number of landmarks; "padded": more than 10)."""
    checkpoint_every: int = 25
    """Write the checkpoint every this many updates (and at the end, and on Ctrl-C)."""
    seed: int = 0
    """Seed of the environments, the network init and the sampling."""
    run_dir: str = ""
    """Where the run lives (default runs/<task>-m<agents>-<comm>-s<seed>)."""
    init_from: str = ""
    """Start from these weights (a checkpoint: its weights only, with a fresh optimiser and reward
    normaliser, as the paper's curriculum does)."""
    trust_unsigned: bool = False
    """Take ``init_from`` even if it carries no sha256 (from before digests existed): corruption
    in it cannot be detected."""
    arch: str = "cpu"
    """Where the simulator runs: cpu | cuda | auto."""
    device: str = "cpu"
    """Where the network runs: cpu | cuda | auto."""
    torch_threads: int = 1
    """torch threads for the PPO update (rollouts always use 1). 1 by default: on this 2-core
    machine 2 threads were 1.3x faster only while the other core was idle, and 8x slower
    (0.13x) when another process used it; two 1-thread runs side by side use both cores
    better (docs/BENCHMARKS.md, training)."""
    compile: bool = True
    """Compile the policy forward and PPO loss of the update with torch.compile (needs a
    C++ compiler; ~30 s once per team size, then faster updates: docs/BENCHMARKS.md)."""
    precision: Literal["fp32", "bf16"] = "fp32"
    """Arithmetic of the update's forward and backward: fp32, or bf16 autocast (GEMMs in
    bfloat16, parameters, optimiser and loss reductions in fp32). bf16 is faster on CPUs
    with AVX-512 BF16 / AMX and on GPUs (1.2x at M = 3, 1.6x at M = 10 per minibatch here:
    docs/BENCHMARKS.md); its effect on learning, measured on two runs, is in docs/FINDINGS.md."""
    tensorboard: bool = False
    """Also write every scalar of metrics.jsonl as TensorBoard events under
    RUN_DIR/tensorboard (needs the tensorboard package: pip install -e ".[tensorboard]")."""
    progress: bool = True
    """Show a progress bar."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Network architecture."""
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """PPO hyperparameters (those not given: the preset's)."""

    @classmethod
    def of(cls, **options):
        """This config from its options as the command line, the specs and ``to_dict`` name them:
        the Sim's fields (task, agents, neighbours ...) among the others (``nest_sim``)."""
        d = nest_sim(options)
        return cls(**{**d, "sim": Sim(**d["sim"])})

    @classmethod
    def with_preset(cls, preset: str = DEFAULT_PRESET, ppo: dict | None = None, **options):
        """This config as ``preset`` makes it: the preset's PPO values and update budget, with the
        ``ppo`` fields and ``options`` (``of``'s) given over them (what ``swarm train`` parses into)."""
        if preset not in PRESETS:
            raise ValueError(f"--preset must be one of {tuple(PRESETS)}, got {preset!r}")
        options.setdefault("updates", PRESET_UPDATES[preset])
        return cls.of(preset=preset, ppo=dataclasses.replace(PRESETS[preset], **(ppo or {})), **options)

    def validate(self) -> None:
        sim = self.sim
        sim.team_size("the run")
        check_policy_actions(sim)  # (the Sim checked itself when it was made)
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {tuple(PRESETS)}, got {self.preset!r}")
        if self.reward not in ("team", "agent"):
            raise ValueError(f"reward must be 'team' or 'agent', got {self.reward!r}")
        if self.model.entity_mode not in ENTITY_MODES:
            raise ValueError(f"model.entity_mode must be one of {ENTITY_MODES}")
        for name in ("updates", "eval_every", "eval_episodes", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        smallest = TASK_SPECS[sim.task].min_agents
        if any(m < smallest for m in self.team_sizes):
            raise ValueError(f"team_sizes must be >= {smallest} for {sim.task}, got {self.team_sizes}")
        if len(set(self.team_sizes)) != len(self.team_sizes):
            raise ValueError(f"team_sizes must not repeat a size, got {self.team_sizes}")
        if self.team_sizes and self.ppo.num_envs % len(self.team_sizes):
            raise ValueError(
                f"ppo.num_envs ({self.ppo.num_envs}) must be a multiple of the number of team_sizes "
                f"({len(self.team_sizes)}): each size gets the same number of environments"
            )
        if self.team_sizes and self.ppo.minibatches < len(self.team_sizes):
            raise ValueError(
                f"ppo.minibatches ({self.ppo.minibatches}) must be >= the number of team_sizes "
                f"({len(self.team_sizes)}): every minibatch holds one size"
            )
        if self.model.num_landmarks:  # the trainer sets it from the task; another value would be dropped silently
            L = TASK_SPECS[sim.task].num_landmarks(sim.agents)
            if self.model.entity_mode != "concat" or self.model.num_landmarks != L:
                raise ValueError(
                    f"model.num_landmarks follows the task (concat: {sim.task} at M = {sim.agents} has {L}): "
                    "leave it unset"
                )
        if self.team_sizes and self.model.entity_mode == "concat" and sim.task == "coverage":
            raise ValueError("entity_mode='concat' has a fixed number of landmarks: coverage's L changes with M")
        if self.torch_threads < 1:
            raise ValueError(f"torch_threads must be >= 1, got {self.torch_threads}")
        if self.precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be fp32 or bf16, got {self.precision!r}")
        if not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"seed must be in [0, 2^31 - 1], got {self.seed}")
        if not 0 <= self.model.rounds <= MAX_ROUNDS:
            raise ValueError(f"model.rounds must be in [0, {MAX_ROUNDS}], got {self.model.rounds}")
        if not 1 <= self.model.hidden <= MAX_HIDDEN:
            raise ValueError(f"model.hidden must be in [1, {MAX_HIDDEN}], got {self.model.hidden}")
        if any(abs(d) > MAX_TRANSFER_OFFSET for d in self.transfer_offsets):
            raise ValueError(f"transfer_offsets must be small team-size offsets, got {self.transfer_offsets}")
        if len(set(self.transfer_offsets)) != len(self.transfer_offsets):
            raise ValueError(f"transfer_offsets has a repeated offset: {self.transfer_offsets}")
        if not 0 <= self.min_updates <= self.updates:
            raise ValueError(f"min_updates must be in [0, updates={self.updates}], got {self.min_updates}")
        if not 0 <= self.message_drop < 1:
            raise ValueError(f"message_drop must be in [0, 1), got {self.message_drop}")
        if self.drop_per_round and not self.message_drop > 0:
            raise ValueError("drop_per_round draws losses per round: set message_drop > 0 with it")
        if not 0 <= self.target_success <= 1:
            raise ValueError(f"target_success must be in [0, 1], got {self.target_success}")
        if self.model.landmark_occupancy and not sim.landmark_occupancy:
            raise ValueError("model.landmark_occupancy follows landmark_occupancy (the simulator's): set that instead")
        if self.model.num_actions not in (NUM_ACTIONS, num_actions(sim.action_space)):
            raise ValueError("model.num_actions follows action_space (the simulator's): set that instead")
        self.ppo.validate()
        self.validate_memory()

    def validate_memory(self) -> None:
        """Refuse, before anything is allocated, a rollout larger than this machine's memory."""
        sizes = self.training_sizes()
        sim, per_size = self.sim, self.ppo.num_envs // len(sizes)
        need = sum(
            rollout_bytes(
                self.ppo.num_steps,
                per_size,
                M,
                sim.landmark_neighbours or TASK_SPECS[sim.task].num_landmarks(M),
                sim.neighbours,
            )
            for M in sizes
        )
        have = memory_limit()
        if need > have:
            raise ValueError(
                f"ppo.num_steps={self.ppo.num_steps} x ppo.num_envs={self.ppo.num_envs} at M = "
                f"{','.join(map(str, sizes))} needs {need / 2**30:.1f} GiB for its rollout, "
                f"this machine has {have / 2**30:.1f} GiB: lower ppo.num_steps or ppo.num_envs"
            )

    def sim_at(self, agents: int) -> Sim:
        """``sim`` at another team size (team_sizes, transfer evaluations)."""
        return dataclasses.replace(self.sim, agents=agents)

    def training_sizes(self) -> list[int]:
        """The team sizes the rollouts use: ``team_sizes``, else ``agents``."""
        return list(self.team_sizes) or [self.sim.agents]

    def default_run_dir(self) -> str:
        s = self.sim
        return self.run_dir or f"runs/{s.task}-m{s.agents}-{s.comm}-s{self.seed}"


# What a curriculum's stages set (each stage's team size, budget and stopping rule): not options
# of ``swarm curriculum`` or keys of a spec's curriculum cell; team_sizes, several sizes in one
# stage, cannot go with one.
STAGE_SET = ("agents", "updates", "target_success", "min_updates")


@dataclass
class CurriculumConfig(TrainConfig):
    """``swarm curriculum``: train stage by stage over team sizes, each stage from the last
    stage's weights (fresh optimiser and reward normaliser), moving on once a greedy
    evaluation of at least 200 episodes reaches ``threshold`` (docs/PAPER.md s.6). Every
    option of ``swarm train`` applies to every stage, except those the stages set (STAGE_SET)
    and ``team_sizes``. The run directory (default
    runs/curriculum-<task>-<comm>-s<seed>) holds curriculum.json and one stage-m<M>/ run
    per stage; the same command again resumes where it stopped."""

    sizes: tuple[int, ...] = (3, 5, 7, 10)
    """Team sizes of the stages, in order."""
    threshold: float = 0.85
    """Evaluation success rate that ends a stage (the paper: 85%)."""
    max_updates_per_stage: int = 4000
    """A stage that never reaches the threshold stops here; the next starts from its weights.
    The same command with a larger value continues the stages that ran out below the threshold
    (a later stage, trained from such a stage's old weights, is then refused: move it away)."""
    min_updates_per_stage: int = 0
    """A stage trains at least this many updates, past the threshold (0: it ends at its first
    evaluation over the threshold). Longer stages transfer better: our coverage M = 7 stage
    stopped after 125 updates ran at M = 10 at 69%, after 725 at 86% (docs/FINDINGS.md)."""
    fresh_eval_episodes: int = 500
    """After each stage, its final policy on this many fresh greedy episodes (0: skip), beside
    the evaluation that ended it: that one is the first of several noisy evaluations to pass
    the threshold, so it overstates the stage (by 3 points for our RC M = 10 stage)."""
    fresh_eval_seed: int = 777
    """Seed of those episodes (training never uses it)."""
    polish_updates: int = 0
    """After each stage, train it on for this many updates at the constant ``polish_lr``
    from its weights (fresh optimiser and normaliser), no target, in stage-m<M>-polish/; the
    next stage starts from there (0: no polish). 300-400 at 3e-5 added 3-11 points to three of
    four of our stages that had stopped short of the paper (docs/FINDINGS.md, polishing)."""
    polish_lr: float = 3e-5
    """Constant learning rate of the polish."""

    @classmethod
    def over(cls, base: TrainConfig, **options) -> CurriculumConfig:
        """The curriculum whose stages share ``base``'s options, with ``options`` over them (its
        sizes, threshold ...)."""
        return cls(**{**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)}, **options})

    def train_config(self) -> TrainConfig:
        """The options every stage shares, as a TrainConfig."""
        names = [f.name for f in dataclasses.fields(TrainConfig)]
        return TrainConfig(**{name: getattr(self, name) for name in names})

    def default_run_dir(self) -> str:
        return self.run_dir or f"runs/curriculum-{self.sim.task}-{self.sim.comm}-s{self.seed}"


def to_dict(cfg) -> dict:
    """The config as a checkpoint and a spec's definition store it: one flat dict, the Sim's
    fields among the others, as the command line names them."""
    d = dataclasses.asdict(cfg)
    d.update(d.pop("sim"))
    return d


def nest_sim(d: dict) -> dict:
    """``to_dict``'s flat dict with the Sim's fields as one "sim" dict: those it lacks, and None
    where a stored config left the Sim's default (its assignment), are the default Sim's."""
    d = dict(d)
    sim = {k: d.pop(k) for k in SIM_FIELDS if k in d}
    d["sim"] = {"task": DEFAULT_SIM.task, "agents": DEFAULT_SIM.agents}
    d["sim"].update({k: v for k, v in sim.items() if v is not None or k in NULLABLE})
    return d


def train_config_from_dict(d: dict) -> TrainConfig:
    """Inverse of ``to_dict`` (for resuming); unknown keys are an error."""
    d = dict(d)
    for key, off in RETIRED.items():
        if key in d and d.pop(key) != off:
            raise ValueError(f"{key}: the run was made with an option this version no longer has (tag swarm-chains)")
    for key, values in RETIRED_VALUES.items():
        if d.get(key) in values:
            raise ValueError(
                f"{key}: the run was made with {d[key]!r}, which this version no longer has (tag swarm-chains)"
            )
    d.setdefault("compile", False)  # runs from before the option existed ran eagerly
    d.setdefault("tensorboard", False)
    for key in ("transfer_offsets", "team_sizes"):
        d[key] = tuple(d.get(key, ()))
    model = ModelConfig.from_dict(d.pop("model"))
    ppo_dict = dict(d.pop("ppo"))
    ppo_dict.setdefault("reset_return", True)  # runs from before the option existed reset it
    ppo = PPOConfig(**ppo_dict)
    return TrainConfig.of(**d, model=model, ppo=ppo)
