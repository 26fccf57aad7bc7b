"""Train a BenchMARL algorithm on one of the simulator's tasks, then evaluate it greedily.

``tools/run_baselines.py`` is the command line of ``main``; ``train`` and ``evaluate_policy``
are the two halves. The evaluation reads the paper's metrics (PAPER.md s.5) from the
simulator's episode statistics (the TorchRL env's ("next", "episode", ...) entries, which are
``SwarmEnv.info["episode"]``): one episode per environment, ``episodes`` environments started
from ``seed``; S% = share of episodes ending in success, T = mean episode length (the time
limit for failures), DIST = mean landmark-to-closest-agent distance at the end (coverage).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import torch
import yaml

from taichi_swarm import TASKS
from taichi_swarm.files import atomic_write_json, ensure_writable
from taichi_swarm.metrics import FirstEpisodes

from .benchmarl_tasks import ACTION_CHOICES, SwarmTaskClass, get_task
from .observations import OBS_MODES

EPISODE_STATS = ("success", "length", "dist")


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
    kept. ``overrides``: any other ExperimentConfig field."""
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
        "loggers": ["csv"],
        "create_json": False,
        "render": False,
        "evaluation": False,
        "save_folder": out_dir,
        "checkpoint_interval": checkpoint_every * frames_per_batch,
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
    return cfg


def latest_checkpoint(out_dir: str) -> str | None:
    """The checkpoint with the most env steps in ``out_dir``'s BenchMARL experiment folder
    (``<out>/<experiment>/checkpoints/checkpoint_<frames>.pt``), or None."""
    import glob

    found = glob.glob(os.path.join(out_dir, "*", "checkpoints", "checkpoint_*.pt"))
    folders = {os.path.dirname(os.path.dirname(f)) for f in found}
    if len(folders) > 1:
        raise ValueError(f"--out {out_dir} holds {len(folders)} experiments with checkpoints; keep one: {sorted(folders)}")

    def frames(path: str) -> int:
        return int(os.path.basename(path)[len("checkpoint_") : -len(".pt")])

    return max(found, key=frames) if found else None


def check_resumable(checkpoint: str, algorithm: str, task: SwarmTaskClass, seed: int, config) -> None:
    """Refuse to resume a run of another algorithm, task, seed or batch: a ValueError naming
    what differs between the folder's config.pkl (written by BenchMARL) and this command."""
    import pickle

    with open(os.path.join(os.path.dirname(os.path.dirname(checkpoint)), "config.pkl"), "rb") as f:
        saved_task, saved_task_config, saved_algorithm, _model, saved_seed, saved_config = (
            pickle.load(f) for _ in range(6)
        )
    want = {
        "algorithm": (type(saved_algorithm), type(algorithm_config(algorithm))),
        "task": (saved_task.name, task.name),
        "task config": (saved_task_config, task.config),
        "seed": (saved_seed, seed),
    }
    for name in ("on_policy_collected_frames_per_batch", "off_policy_collected_frames_per_batch"):
        want[name] = (getattr(saved_config, name), getattr(config, name))
    for name, (saved, now) in want.items():
        if saved != now:
            raise ValueError(
                f"--out: {checkpoint} is from a run with another {name} ({saved!r}, this command: {now!r}); "
                "give another --out to start a new run"
            )


def _atomic_experiment_class():
    """BenchMARL's Experiment, its checkpoints written to a temporary file and renamed, so a
    run stopped while saving leaves the previous checkpoint whole."""
    from benchmarl.experiment import Experiment

    class AtomicCheckpointExperiment(Experiment):
        def _save_experiment(self) -> None:
            path = self.folder_name / "checkpoints" / f"checkpoint_{self.total_frames}.pt"
            if path in self._checkpointed_files:  # the end of a run on an interval: rewritten, not counted twice
                self._checkpointed_files.remove(path)
            if self.config.keep_checkpoints_num is not None:
                while len(self._checkpointed_files) >= self.config.keep_checkpoints_num:
                    self._checkpointed_files.popleft().unlink(missing_ok=True)
            path.parent.mkdir(parents=False, exist_ok=True)
            tmp = path.with_suffix(".pt.tmp")
            torch.save(self.state_dict(), tmp)
            os.replace(tmp, path)
            self._checkpointed_files.append(path)

        def _load_experiment(self):
            # the checkpoints already written count towards keep_checkpoints_num
            found = (self.folder_name / "checkpoints").glob("checkpoint_*.pt")
            self._checkpointed_files.extend(sorted(found, key=lambda p: int(p.stem.split("_")[1])))
            # the checkpoint holds the collector's and buffers' plain-Python state too
            self.load_state_dict(
                torch.load(self.config.restore_file, map_location=self.config.restore_map_location, weights_only=False)
            )
            return self

    return AtomicCheckpointExperiment


def train(
    algorithm: str,
    task: SwarmTaskClass,
    seed: int,
    config,
    model: str = "mlp",
    restore_file: str | None = None,
):
    """Build and run a BenchMARL Experiment, from ``restore_file`` (a checkpoint of the same
    run) where given; returns it (its ``policy`` is the trained one)."""
    from benchmarl.models import model_config_registry

    if model not in model_config_registry:
        raise ValueError(f"model must be one of {sorted(model_config_registry)}, got {model!r}")
    if restore_file is not None:
        check_resumable(restore_file, algorithm, task, seed, config)
        config.restore_file = restore_file
    model_cfg = model_config_registry[model].get_from_yaml()
    experiment = _atomic_experiment_class()(
        task=task,
        algorithm_config=algorithm_config(algorithm),
        model_config=model_cfg,
        critic_model_config=model_config_registry[model].get_from_yaml(),
        seed=seed,
        config=config,
    )
    experiment.run()
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


def _parse_overrides(items: list[str]) -> dict:
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
    return yaml.safe_load(text)


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
    ap = argparse.ArgumentParser(
        prog="run_baselines.py",
        description="Train a BenchMARL algorithm on a taichi_swarm task, then evaluate it greedily "
        "(S%%, T, DIST on fresh episodes) and write the result as JSON.",
    )
    ap.add_argument(
        "--algorithm", default="mappo", help="BenchMARL algorithm: mappo, ippo, maddpg, iql, ... (default mappo)"
    )
    ap.add_argument("--task", default="coverage", help=f"one of {', '.join(TASKS)} (default coverage)")
    ap.add_argument("--agents", type=int, default=3, help="team size M (default 3)")
    ap.add_argument("--comm", default="uc", help="uc or rc: the comm graph (local observations only; default uc)")
    ap.add_argument("--comm-radius", type=float, default=1.0, help="rc radius (default 1.0)")
    ap.add_argument(
        "--obs-mode",
        default="full",
        help=f"one of {OBS_MODES}: full = the paper's baselines (default), local = the paper's own observation",
    )
    ap.add_argument(
        "--actions",
        default="any",
        help=f"one of {ACTION_CHOICES}: any lets the algorithm choose "
        "(continuous where it can, BenchMARL's prefer_continuous_actions)",
    )
    ap.add_argument("--max-steps", type=int, default=50, help="episode length limit (default 50)")
    ap.add_argument("--frames", type=_count, default=1_000_000, help="training budget in env steps (default 1e6)")
    ap.add_argument("--num-envs", type=int, default=32, help="environments stepped together (default 32)")
    ap.add_argument(
        "--frames-per-batch",
        type=int,
        default=4096,
        help="env steps collected per iteration (default 4096 = 32 x 128, the paper's PPO batch)",
    )
    ap.add_argument("--model", default="mlp", help="BenchMARL model for actor and critic (default mlp)")
    ap.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    ap.add_argument("--eval-episodes", type=int, default=500, help="evaluation episodes (default 500)")
    ap.add_argument("--eval-seed", type=int, default=12345, help="evaluation seed (default 12345)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda: simulator, sampling and training (default cpu)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1; 0 = torch's default)")
    ap.add_argument(
        "--experiment",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a BenchMARL ExperimentConfig field, e.g. --experiment lr=3e-4 (repeatable)",
    )
    ap.add_argument(
        "--checkpoint-every",
        type=int,
        default=25,
        help="iterations between checkpoints (default 25; 0 = only at the end); the last two are kept",
    )
    ap.add_argument(
        "--out",
        required=True,
        help="output directory: BenchMARL's experiment folder and results.json; a run stopped "
        "part-way resumes from its latest checkpoint when the same command is given again",
    )
    return ap


def run(args: argparse.Namespace) -> dict:
    """Check everything, train, evaluate, write ``<out>/results.json``; returns the result."""
    for name in ("frames", "num_envs", "frames_per_batch", "eval_episodes", "agents", "max_steps"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.checkpoint_every < 0:
        raise ValueError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    if args.threads < 0:
        raise ValueError(f"--threads must be >= 0, got {args.threads}")
    algorithm_config(args.algorithm)  # a bad name fails here, before any work
    task = get_task(
        args.task,
        {
            "num_agents": args.agents,
            "comm": args.comm,
            "comm_radius": args.comm_radius,
            "obs_mode": args.obs_mode,
            "action_space": args.actions,
            "max_steps": args.max_steps,
        },
    )
    out_json = os.path.join(args.out, "results.json")
    ensure_writable(out_json, "--out")
    os.makedirs(args.out, exist_ok=True)
    config = experiment_config(
        args.frames,
        args.num_envs,
        args.frames_per_batch,
        os.path.abspath(args.out),
        args.device,
        _parse_overrides(args.experiment),
        args.checkpoint_every,
    )
    restore = latest_checkpoint(args.out)
    if restore is not None:
        print(f"run_baselines.py: resuming from {restore}", file=sys.stderr)
    if args.threads:
        torch.set_num_threads(args.threads)
    start = time.time()
    experiment = train(args.algorithm, task, args.seed, config, args.model, restore_file=restore)
    train_s = time.time() - start
    continuous = bool(experiment.continuous_actions)
    start = time.time()
    result = evaluate_policy(
        experiment.policy, task, continuous, episodes=args.eval_episodes, seed=args.eval_seed, device=args.device
    )
    eval_s = time.time() - start
    summary = {
        "algorithm": args.algorithm.lower(),
        "obs_mode": args.obs_mode,
        "actions": "continuous" if continuous else "discrete",
        "max_steps": args.max_steps,
        "frames": int(experiment.total_frames),
        "train_seed": args.seed,
        "S%": 100.0 * result["success_rate"],
        "T": result["mean_length"],
        "DIST": result["dist"],
        **result,
        # wall-clock of this command; a resumed run counts BenchMARL's own iteration time instead
        "train_seconds": round(train_s if restore is None else float(experiment.total_time), 1),
        "resumed_from": None if restore is None else os.path.relpath(restore),
        "eval_seconds": round(eval_s, 1),
        "experiment_folder": os.path.relpath(str(experiment.folder_name)),  # relative: results.json is committed
        "versions": _versions(),
    }
    atomic_write_json(out_json, summary)
    try:
        plot_curves(args.out)
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
        summary = run(args)
    except ValueError as exc:
        print(f"run_baselines.py: error: {exc}", file=sys.stderr)
        return 2
    dist = "-" if summary["DIST"] is None else f"{summary['DIST']:.3f}"
    print(
        f"{summary['algorithm']} {summary['task']} M={summary['agents']} {summary['obs_mode']} {summary['actions']}: "
        f"S% {summary['S%']:.1f}  T {summary['T']:.2f}  DIST {dist}  ({summary['episodes']} episodes, "
        f"seed {summary['seed']}) -> {os.path.join(args.out, 'results.json')}"
    )
    return 0


__all__ = [
    "algorithm_config",
    "algorithm_names",
    "build_parser",
    "evaluate_policy",
    "experiment_config",
    "latest_checkpoint",
    "main",
    "run",
    "train",
]
