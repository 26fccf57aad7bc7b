"""Train a BenchMARL algorithm on one of the simulator's tasks, then evaluate it greedily.

``tools/run_baselines.py`` is the command line of ``main``; ``train`` and ``evaluate_policy``
are the two halves. The evaluation reads the paper's metrics (PAPER.md s.5) from the
simulator's episode statistics (the TorchRL env's ("next", "episode", ...) entries, which are
``SwarmEnv.info["episode"]``): one episode per environment, ``episodes`` environments started
from ``seed``; S% = share of episodes ending in success, T = mean episode length (the time
limit for failures), DIST = mean landmark-to-closest-agent distance at the end (coverage).

BenchMARL is used through its public API only (``Experiment``, ``ExperimentConfig``,
``Callback``, ``Experiment.reload_from_file``). A stopped run resumes at BenchMARL's own latest
checkpoint, which BenchMARL writes in place: a run stopped while saving leaves that checkpoint
incomplete, and the next command refuses it by name (remove it to resume from the one before).
The optimisers' state travels in the checkpoint (``OptimizerState``); the random number
generators' does not: BenchMARL reseeds from the seed in ``run`` with no public hook before
the first collection, so a resumed run is not the uninterrupted one (its environments start
new episodes too).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import sys
import time

import torch
from benchmarl.experiment import Callback

from taichi_swarm import TASKS, NaNActionsError
from taichi_swarm.files import atomic_write_bytes, atomic_write_json, ensure_writable
from taichi_swarm.metrics import FirstEpisodes

from .benchmarl_tasks import SwarmTaskClass, get_task
from .config import ACTION_CHOICES, OBS_MODES, SETTING, BaselineConfig, parse_overrides

EPISODE_STATS = ("success", "length", "dist", "covered")


def algorithm_names() -> tuple[str, ...]:
    from benchmarl.algorithms import algorithm_config_registry

    return tuple(sorted(algorithm_config_registry))


def algorithm_config(name: str):
    """BenchMARL's default config (its yaml) of algorithm ``name``, or a ValueError naming it."""
    from benchmarl.algorithms import algorithm_config_registry

    if not isinstance(name, str) or name.lower() not in algorithm_config_registry:
        raise ValueError(f"algorithm must be one of {algorithm_names()}, got {name!r}")
    return algorithm_config_registry[name.lower()].get_from_yaml()


def experiment_config(
    frames: int,
    num_envs: int,
    frames_per_batch: int,
    out_dir: str,
    device: str = "cpu",
    overrides: dict | None = None,
    checkpoint_every: int = 25,
):
    """BenchMARL's default ExperimentConfig with the run's budget, batch, folder and device;
    no wandb, no rendering, no evaluation during training (``evaluate_policy`` does it after),
    a checkpoint every ``checkpoint_every`` iterations (0: none) and at the end, the last two
    kept (BenchMARL writes them, in place). ``overrides``: any other ExperimentConfig field."""
    from benchmarl.experiment import ExperimentConfig

    cfg = ExperimentConfig.get_from_yaml()
    settings = {
        "max_n_frames": frames,
        "on_policy_n_envs_per_worker": num_envs,
        "off_policy_n_envs_per_worker": num_envs,
        "on_policy_collected_frames_per_batch": frames_per_batch,
        "off_policy_collected_frames_per_batch": frames_per_batch,
        "sampling_device": device,
        "train_device": device,
        "buffer_device": device,
        "restore_map_location": device,
        "loggers": ["csv"],
        "create_json": False,
        "render": False,
        "evaluation": False,
        "save_folder": out_dir,
        "checkpoint_at_end": True,
        "keep_checkpoints_num": 2,
    }
    fields = {f.name for f in dataclasses.fields(cfg)}
    for key, value in (overrides or {}).items():
        if key not in fields:
            raise ValueError(f"--experiment: {key!r} is not an ExperimentConfig field (known: {sorted(fields)})")
        settings[key] = value
    for key, value in settings.items():
        setattr(cfg, key, value)
    if "checkpoint_interval" not in (overrides or {}):
        # a multiple of both batch sizes (BenchMARL checks it against the one its algorithm uses)
        batch = math.lcm(cfg.on_policy_collected_frames_per_batch, cfg.off_policy_collected_frames_per_batch)
        cfg.checkpoint_interval = checkpoint_every * batch
    if "checkpoint_at_end" not in (overrides or {}) and cfg.checkpoint_interval:
        # a last checkpoint on the interval would be written twice and counted twice towards
        # keep_checkpoints_num (BenchMARL's deque), which then keeps one fewer
        ends = {cfg.get_max_n_iters(p) * cfg.collected_frames_per_batch(p) for p in (True, False)}
        cfg.checkpoint_at_end = any(end % cfg.checkpoint_interval for end in ends)
    return cfg


CHECKPOINT_NAME = re.compile(r"checkpoint_(\d+)\.pt")


def _checkpoint_frames(path) -> int | None:
    match = CHECKPOINT_NAME.fullmatch(os.path.basename(path))
    return int(match.group(1)) if match else None


def _checkpoints(out_dir: str) -> list[str]:
    """BenchMARL's checkpoints in ``out_dir``, fewest env steps first: the layout that
    ``Experiment.reload_from_file`` reads, ``<out>/<experiment>/checkpoints/checkpoint_<frames>.pt``
    beside ``<out>/<experiment>/config.pkl``."""
    import glob

    found = [
        f
        for f in glob.glob(os.path.join(out_dir, "*", "checkpoints", "checkpoint_*.pt"))
        if _checkpoint_frames(f) is not None
    ]
    folders = {os.path.dirname(os.path.dirname(f)) for f in found}
    if len(folders) > 1:
        raise ValueError(
            f"--out {out_dir} holds {len(folders)} experiments with checkpoints; keep one: {sorted(folders)}"
        )
    return sorted(found, key=_checkpoint_frames)


def latest_checkpoint(out_dir: str) -> str | None:
    """The checkpoint with the most env steps in ``out_dir``'s BenchMARL experiment folder, or None."""
    found = _checkpoints(out_dir)
    return found[-1] if found else None


# ExperimentConfig fields a resumed run may change: its length, where it saves, how it checkpoints
RESUMABLE_CHANGES = {
    "max_n_frames",
    "restore_map_location",
    "save_folder",
    "checkpoint_interval",
    "checkpoint_at_end",
    "keep_checkpoints_num",
}


def check_resumable(experiment, algorithm: str, task: SwarmTaskClass, seed: int, model_cfg, config) -> None:
    """Refuse to resume another run: a ValueError naming what differs (algorithm, task and its
    config, seed, model, or any ExperimentConfig field but the run's length and checkpointing)
    between the run ``Experiment.reload_from_file`` rebuilt from its folder and this command."""
    want = {
        "--algorithm": (experiment.algorithm_config, algorithm_config(algorithm)),
        "--task": (experiment.task.name, task.name),
        "task config (--agents, --comm, --obs-mode, --actions, --max-steps)": (experiment.task.config, task.config),
        "--seed": (experiment.seed, seed),
        "--model": (experiment.model_config, model_cfg),
    }
    for field in dataclasses.fields(config):
        if field.name not in RESUMABLE_CHANGES | {"restore_file"}:
            want[f"{field.name} (--num-envs, --frames-per-batch, --device or --experiment)"] = (
                getattr(experiment.config, field.name),
                getattr(config, field.name),
            )
    for name, (saved, now) in want.items():
        if saved != now:
            raise ValueError(
                f"--out: {experiment.config.restore_file} is from a run with another {name} ({saved!r}, "
                f"this command: {now!r}); give the run's own options, or another --out to start a new run"
            )


class OptimizerState(Callback):
    """Adds the optimisers' state to each BenchMARL checkpoint and loads it back on resume, so
    Adam continues where it stopped (BenchMARL checkpoints the losses, buffers and collector,
    not the optimisers). BenchMARL pickles its callbacks into config.pkl and
    ``reload_from_file`` brings this one back with the run."""

    def __getstate__(self):
        return {}  # not the experiment it is attached to (BenchMARL attaches it again)

    def on_state_dict(self, state_dict) -> None:
        state_dict["optimizers"] = {
            group: {name: opt.state_dict() for name, opt in optimizers.items()}
            for group, optimizers in self.experiment.optimizers.items()
        }

    def on_load_state_dict(self, state_dict) -> None:
        for group, optimizers in state_dict.get("optimizers", {}).items():
            for name, opt_state in optimizers.items():
                self.experiment.optimizers[group][name].load_state_dict(opt_state)


def resume(restore_file: str, algorithm: str, task: SwarmTaskClass, seed: int, model_cfg, config):
    """The run that wrote ``restore_file``, rebuilt by ``Experiment.reload_from_file`` from its
    config.pkl and checkpoint, with this command's length and checkpointing; refused (a
    ValueError, config.pkl as it was) when this command describes another run."""
    from benchmarl.experiment import Experiment

    # reload_from_file rewrites config.pkl with the patch before we can compare: a refused
    # command puts its bytes back (read and written whole, never unpickled here)
    pkl = os.path.join(os.path.dirname(os.path.dirname(restore_file)), "config.pkl")
    try:
        with open(pkl, "rb") as f:
            saved = f.read()
    except OSError as exc:
        raise ValueError(f"--out: cannot resume {restore_file}: {exc}") from None
    patch = {name: getattr(config, name) for name in RESUMABLE_CHANGES}
    try:
        experiment = Experiment.reload_from_file(restore_file, experiment_patch=patch)
    except Exception as exc:  # noqa: BLE001 - an unreadable config.pkl or checkpoint, whatever the cause
        atomic_write_bytes(pkl, lambda f: f.write(saved))
        raise ValueError(
            f"--out: cannot resume {restore_file} ({type(exc).__name__}: {exc}); a checkpoint "
            "whose save was stopped part-way is incomplete: remove it to resume from the one before"
        ) from None
    try:
        check_resumable(experiment, algorithm, task, seed, model_cfg, config)
    except ValueError:
        experiment.close()
        atomic_write_bytes(pkl, lambda f: f.write(saved))
        raise
    return experiment


def train(
    algorithm: str,
    task: SwarmTaskClass,
    seed: int,
    config,
    model: str = "mlp",
    restore_file: str | None = None,
):
    """Build and run a BenchMARL Experiment, resumed at ``restore_file`` (a checkpoint of the
    same run) where given; returns it (its ``policy`` is the trained one)."""
    from benchmarl.experiment import Experiment
    from benchmarl.models import model_config_registry

    if model not in model_config_registry:
        raise ValueError(f"model must be one of {sorted(model_config_registry)}, got {model!r}")
    model_cfg = model_config_registry[model].get_from_yaml()
    if restore_file is not None:
        experiment = resume(restore_file, algorithm, task, seed, model_cfg, config)
    else:
        experiment = Experiment(
            task=task,
            algorithm_config=algorithm_config(algorithm),
            model_config=model_cfg,
            critic_model_config=model_config_registry[model].get_from_yaml(),
            seed=seed,
            config=config,
            callbacks=[OptimizerState()],
        )
    experiment.run()
    if config.keep_checkpoints_num is not None:
        # BenchMARL counts only the checkpoints this command wrote: those from before a resume go here
        for stale in _checkpoints(os.path.dirname(str(experiment.folder_name)))[: -config.keep_checkpoints_num]:
            os.remove(stale)
    return experiment


@torch.no_grad()
def evaluate_policy(
    policy,
    task: SwarmTaskClass,
    continuous_actions: bool,
    episodes: int = 500,
    seed: int = 12345,
    device: str = "cpu",
) -> dict:
    """Greedy (deterministic) actions on ``episodes`` fresh episodes, one per environment, from
    ``seed``; returns S% as success_rate, T as mean_length, DIST as dist (None unless coverage)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    name = task.name.lower()
    cfg = task.config
    env = task.make_env(episodes, continuous_actions, seed, device)
    tally = FirstEpisodes(episodes)
    steps = 0
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        while not tally.all_done():
            if steps > cfg["max_steps"]:  # every episode ends by the time limit
                raise RuntimeError(f"evaluation: episodes still running after {steps} steps")
            stepped, td = env.step_and_maybe_reset(policy(td))
            nxt = stepped.get("next")
            stats = {k: nxt.get(("episode", k)).squeeze(-1) for k in EPISODE_STATS}
            tally.add(nxt.get("done").squeeze(-1), stats)
            steps += 1
    return {
        "task": name,
        "agents": cfg["num_agents"],
        "comm": cfg["comm"],
        "episodes": episodes,
        "seed": seed,
        **tally.summary(name),
    }


def _count(text: str) -> int:
    """An env-step count: 1000000, 1_000_000 or 1e6."""
    try:
        value = float(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number like 1000000 or 1e6, got {text!r}") from None
    if not value.is_integer():
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}")
    return int(value)


def build_parser() -> argparse.ArgumentParser:
    """The command line over BaselineConfig: one option per field (its docstring's help, its
    default); ``--experiment KEY=VALUE`` repeated for the ``experiment`` overrides."""
    d = {f.name: f.default for f in dataclasses.fields(BaselineConfig) if f.name not in ("experiment", "sim")}
    d.update({k: getattr(BaselineConfig.sim, k) for k in SETTING})
    ap = argparse.ArgumentParser(
        prog="run_baselines.py",
        description="Train a BenchMARL algorithm on a taichi_swarm task, then evaluate it greedily "
        "(S%%, T, DIST on fresh episodes) and write the result as JSON.",
    )
    add = ap.add_argument
    add(
        "--algorithm", default=d["algorithm"], help="BenchMARL algorithm: mappo, ippo, maddpg, iql, ... (default mappo)"
    )
    add("--task", default=d["task"], help=f"one of {', '.join(TASKS)} (default coverage)")
    add("--agents", type=int, default=d["agents"], help="team size M (default 3)")
    add("--comm", default=d["comm"], help="uc or rc: the comm graph (local observations only; default uc)")
    add("--comm-radius", type=float, default=d["comm_radius"], help="rc radius (default 1.0)")
    add("--obs-mode", default=d["obs_mode"], help=f"one of {OBS_MODES}: full = the paper's baselines (default)")
    add("--actions", default=d["actions"], help=f"one of {ACTION_CHOICES}: any lets the algorithm choose")
    add("--max-steps", type=int, default=d["max_steps"], help="episode length limit (default 50)")
    add("--frames", type=_count, default=d["frames"], help="training budget in env steps (default 1e6)")
    add("--num-envs", type=int, default=d["num_envs"], help="environments stepped together (default 32)")
    add("--frames-per-batch", type=int, default=d["frames_per_batch"], help="env steps per iteration (default 4096)")
    add("--model", default=d["model"], help="BenchMARL model for actor and critic (default mlp)")
    add("--seed", type=int, default=d["seed"], help="training seed (default 0)")
    add("--eval-episodes", type=int, default=d["eval_episodes"], help="evaluation episodes (default 500)")
    add("--eval-seed", type=int, default=d["eval_seed"], help="evaluation seed (default 12345)")
    add("--device", default=d["device"], help="cpu or cuda: simulator, sampling and training (default cpu)")
    add("--threads", type=int, default=d["threads"], help="torch threads (default 1; 0 = torch's default)")
    add(
        "--experiment",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a BenchMARL ExperimentConfig field, e.g. --experiment lr=3e-4 (repeatable)",
    )
    add(
        "--checkpoint-every",
        type=int,
        default=d["checkpoint_every"],
        help="iterations between checkpoints (default 25; 0 = only at the end); the last two are kept",
    )
    add(
        "--out",
        required=True,
        help="output directory: BenchMARL's experiment folder and results.json; a run stopped "
        "part-way resumes from its latest checkpoint when the same command is given again",
    )
    return ap


def config_from_args(args: argparse.Namespace) -> BaselineConfig:
    """The parsed command line as the run's BaselineConfig (a ValueError names a bad value)."""
    return BaselineConfig.of(**{**vars(args), "experiment": parse_overrides(args.experiment)})


class TrainingDiverged(RuntimeError):
    """The policy produced NaN actions during training: the run diverged (the simulator refuses
    NaN); not a bad input. The message names the last checkpoint and how to evaluate it."""


def _diverged_message(algorithm: str, out_dir: str, cause: Exception) -> str:
    last = latest_checkpoint(out_dir)
    head = f"training diverged: the {algorithm} policy's actions became NaN ({cause})."
    if last is None:
        return (
            f"{head} No checkpoint was written before it; lower the learning rate "
            "(--experiment lr=...) or checkpoint more often (--checkpoint-every)."
        )
    frames = _checkpoint_frames(last)
    return (
        f"{head} The latest checkpoint is {last} ({frames} env steps): give the same "
        f"command with --frames {frames} to evaluate that policy without training further."
    )


def run(cfg: BaselineConfig) -> dict:
    """Train, evaluate, write ``<cfg.out>/results.json``; returns the result."""
    if not cfg.out:
        raise ValueError("out: the run needs an output directory")
    algorithm_config(cfg.algorithm)  # a bad name fails here, before any work
    task = get_task(
        cfg.sim.task,
        {
            "num_agents": cfg.sim.agents,
            "comm": cfg.sim.comm,
            "comm_radius": cfg.sim.comm_radius,
            "obs_mode": cfg.obs_mode,
            "action_space": cfg.actions,
            "max_steps": cfg.max_steps,
        },
    )
    out_json = os.path.join(cfg.out, "results.json")
    ensure_writable(out_json, "--out", make_dirs=True)  # (the run's directory, made below)
    os.makedirs(cfg.out, exist_ok=True)
    config = experiment_config(
        cfg.frames,
        cfg.num_envs,
        cfg.frames_per_batch,
        os.path.abspath(cfg.out),
        cfg.device,
        cfg.experiment,
        cfg.checkpoint_every,
    )
    restore = latest_checkpoint(cfg.out)
    if restore is not None:
        print(f"run_baselines.py: resuming from {restore}", file=sys.stderr)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    start = time.time()
    try:
        experiment = train(cfg.algorithm, task, cfg.seed, config, cfg.model, restore_file=restore)
    except NaNActionsError as exc:
        raise TrainingDiverged(_diverged_message(cfg.algorithm, cfg.out, exc)) from exc
    train_s = time.time() - start
    continuous = bool(experiment.continuous_actions)
    start = time.time()
    try:
        result = evaluate_policy(
            experiment.policy, task, continuous, episodes=cfg.eval_episodes, seed=cfg.eval_seed, device=cfg.device
        )
    except NaNActionsError as exc:
        raise TrainingDiverged(
            f"the trained {cfg.algorithm} policy ({experiment.total_frames} env steps) gives NaN actions ({exc}): "
            "its weights diverged; checkpoints are in "
            f"{os.path.join(cfg.out, '*', 'checkpoints')} (an earlier one may still be finite: keep it alone "
            "there and give --frames its env steps)"
        ) from exc
    eval_s = time.time() - start
    summary = {
        "algorithm": cfg.algorithm.lower(),
        "obs_mode": cfg.obs_mode,
        "actions": "continuous" if continuous else "discrete",
        "max_steps": cfg.max_steps,
        "frames": int(experiment.total_frames),
        "train_seed": cfg.seed,
        "S%": 100.0 * result["success_rate"],
        "T": result["mean_length"],
        "DIST": result["dist"],
        **result,
        # a fresh run: this command's wall-clock; resumed: BenchMARL's summed iteration times
        # over every command (without setup, and without iterations redone after a stop)
        "train_seconds": round(train_s if restore is None else float(experiment.total_time), 1),
        "wall_seconds_this_command": round(train_s, 1),
        "resumed_from": None if restore is None else os.path.relpath(restore),
        "eval_seconds": round(eval_s, 1),
        "experiment_folder": os.path.relpath(str(experiment.folder_name)),  # relative: results.json is committed
        "versions": _versions(),
    }
    atomic_write_json(out_json, summary)
    try:
        plot_curves(cfg.out)
    except Exception as exc:  # noqa: BLE001 - a missing plot never loses a result
        print(f"(could not draw curves: {exc})", file=sys.stderr)
    return summary


def plot_curves(out_dir: str) -> str | None:
    """Learning curves of the BenchMARL run in ``out_dir`` (its csv scalars: sampled success
    rate, episode reward and length per iteration, against env steps) -> out_dir/curves.png."""
    import csv
    import glob

    found = sorted(glob.glob(os.path.join(out_dir, "*", "*", "scalars")), key=os.path.getmtime)
    if not found:
        return None
    scalars = found[-1]  # the latest experiment in the folder

    def series(name: str) -> dict[int, float]:
        path = os.path.join(scalars, f"{name}.csv")
        if not os.path.exists(path):
            return {}
        with open(path) as f:
            return {int(float(row[0])): float(row[1]) for row in csv.reader(f) if len(row) >= 2}

    frames = series("counters_total_frames")
    panels = [
        ("collection_success_rate", "sampled success rate, % (training)", 100.0),
        ("collection_reward_episode_reward_mean", "mean episode return (team)", 1.0),
        ("collection_episode_length", "episode length", 1.0),
    ]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(13, 3.6))
    for ax, (name, title, scale) in zip(axes, panels, strict=True):
        points = sorted(series(name).items())
        xs = [frames.get(i, float("nan")) / 1e6 for i, _ in points]
        ax.plot(xs, [v * scale for _, v in points])
        ax.set(title=title, xlabel="env steps (M)")
    fig.suptitle(os.path.basename(os.path.normpath(out_dir)))
    fig.tight_layout()
    out = os.path.join(out_dir, "curves.png")
    tmp = out + ".tmp.png"
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, out)
    return out


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("benchmarl", "torchrl", "tensordict", "torch", "taichi"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        summary = run(config_from_args(args))
    except ValueError as exc:
        print(f"run_baselines.py: error: {exc}", file=sys.stderr)
        return 2
    except TrainingDiverged as exc:
        print(f"run_baselines.py: {exc}", file=sys.stderr)
        return 3
    dist = "-" if summary["DIST"] is None else f"{summary['DIST']:.3f}"
    print(
        f"{summary['algorithm']} {summary['task']} M={summary['agents']} {summary['obs_mode']} {summary['actions']}: "
        f"S% {summary['S%']:.1f}  T {summary['T']:.2f}  DIST {dist}  ({summary['episodes']} episodes, "
        f"seed {summary['seed']}) -> {os.path.join(args.out, 'results.json')}"
    )
    return 0


__all__ = [
    "TrainingDiverged",
    "algorithm_config",
    "algorithm_names",
    "BaselineConfig",
    "build_parser",
    "config_from_args",
    "evaluate_policy",
    "experiment_config",
    "latest_checkpoint",
    "main",
    "run",
    "train",
]
