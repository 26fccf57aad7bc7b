"""Training runs: a config (or a run directory to resume) in, a trained run directory out.

    config -> run directory -> PPO loop -> checkpoint

``train`` locks the run directory, opens it (new, or resumed from its checkpoint: see
trainer.rundir), builds the policy, Adam and one group of environments per team size,
then loops: one PPO update (trainer.ppo.one_update: rollout, GAE, clipped-PPO epochs),
every ``eval_every`` updates a greedy evaluation on fresh seeds, every
``checkpoint_every`` updates a checkpoint; at the end summary.json and curves.png.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time

import torch

import taichi_swarm
from trainer import checkpoint
from trainer.config import TrainConfig
from trainer.evaluate import evaluate
from trainer.model import ModelConfig, SwarmPolicy
from trainer.ppo import (
    NonFiniteTraining,
    RewardScaler,
    Rollout,
    TeamGroup,
    TrainingState,
    fresh_counters,
    make_loss_fn,
    one_update,  # (called through this module's name: tests wrap it)
)
from trainer.rundir import RunDir, StopAtUpdateEnd, TensorBoardLog

# Environment seeds. A seed reaches the simulator through np.random.default_rng, which hashes
# it into every environment's stream, so two different integers give unrelated episodes: the
# constants below only keep the integers of different uses apart.
TRAIN_SEED_BASE = 2**40  # training streams start here; `swarm eval --seed` is refused from here
# up (swarm_cli.options.EVAL_SEED_LIMIT), so a reported evaluation never replays a training episode
RUN_SEED_STRIDE = 1_000_003  # run seed s: TRAIN_SEED_BASE + s * RUN_SEED_STRIDE (a prime > 10**6)
GROUP_SEED_STRIDE = 7_919  # + k * GROUP_SEED_STRIDE for the k-th team size of the run: distinct
# from every other run's as long as a run has fewer than RUN_SEED_STRIDE / GROUP_SEED_STRIDE (126) sizes
EVAL_SEED_BASE = 10_000_019  # the evaluation after update u runs on seed EVAL_SEED_BASE + u: new
# episodes at every evaluation, away from the small seeds reported evaluations use (777 in docs/RESULTS.md)


def train_seed(run_seed: int, group: int) -> int:
    """The seed of a fresh run's environments of its ``group``-th team size."""
    return TRAIN_SEED_BASE + run_seed * RUN_SEED_STRIDE + group * GROUP_SEED_STRIDE


def resolve_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be cpu, cuda or auto, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device='cuda' but torch finds no CUDA GPU")
    return device


def check_arch(arch: str) -> str:
    """Refuse ``arch="cuda"`` where torch finds no CUDA GPU (Taichi would fall back to the CPU,
    and torch fail later inside the simulator's CUDA buffers)."""
    if arch in ("cuda", "gpu") and not torch.cuda.is_available():
        raise ValueError(f"arch={arch!r} but torch finds no CUDA GPU on this machine: use --arch cpu")
    return arch


def model_config_for(cfg: TrainConfig) -> ModelConfig:
    """The model config with the task's L filled in for the "concat" entity mode, the
    landmark inputs' occupancy feature where the simulator gives it, and the action set's logits."""
    m, sim = cfg.model, cfg.sim
    if sim.landmark_occupancy != m.landmark_occupancy:
        m = dataclasses.replace(m, landmark_occupancy=sim.landmark_occupancy)
    if taichi_swarm.num_actions(sim.action_space) != m.num_actions:
        m = dataclasses.replace(m, num_actions=taichi_swarm.num_actions(sim.action_space))
    if m.entity_mode == "concat":
        L = taichi_swarm.TASK_SPECS[sim.task].num_landmarks(sim.agents)
        m = dataclasses.replace(m, num_landmarks=L)  # every other field as configured
    return m


FINE_START_GAP = 2.0  # a fine action starts this much below its full push's logit: sampled e^-2 as often


def grow_actions(weights: dict, num_actions: int) -> dict:
    """A 5-action policy's weights for ``num_actions`` logits: the four fine pushes (actions
    5..8) start as copies of the full ones (1..4), ``FINE_START_GAP`` lower, so the greedy
    policy is the same and the sampled one tries them from the first rollout."""
    w, b = weights["policy_head.2.weight"], weights["policy_head.2.bias"]
    extra = num_actions - w.shape[0]
    if extra <= 0:
        return weights
    full = slice(1, 1 + extra)
    return {
        **weights,
        "policy_head.2.weight": torch.cat([w, w[full]]),
        "policy_head.2.bias": torch.cat([b, b[full] - FINE_START_GAP]),
    }


def transfer_sizes(cfg: TrainConfig) -> list[int]:
    """The neighbouring team sizes evaluated beside the training size: those the task has
    and the network can take ("concat": the training size's number of landmarks; "padded":
    at most PADDED_SLOTS landmarks)."""
    spec, model, M = taichi_swarm.TASK_SPECS[cfg.sim.task], model_config_for(cfg), cfg.sim.agents
    sizes = [M + d for d in cfg.transfer_offsets if d != 0 and M + d >= spec.min_agents]
    return [M for M in sizes if not model.landmark_misfit(spec.num_landmarks(M))]


def evaluate_during_training(policy, cfg: TrainConfig, update: int, device) -> dict:
    """Greedy S%, T, DIST at the training size; S% at the transfer sizes (``transfer``)."""
    policy.eval()
    seed = EVAL_SEED_BASE + update
    common = dict(episodes=cfg.eval_episodes, seed=seed, arch=cfg.arch, device=device)
    result = evaluate(policy, cfg.sim, **common)
    out = {k: result[k] for k in ("success_rate", "mean_length", "dist")}
    out["update"] = update
    sizes = transfer_sizes(cfg)
    if sizes:
        out["transfer"] = {str(M): evaluate(policy, cfg.sim_at(M), **common)["success_rate"] for M in sizes}
    return out


def scaler_slots(cfg: TrainConfig, num_envs: int, size: int) -> int:
    """How many running returns a team size's reward normaliser keeps: one per env, or one
    per agent of every env with ``reward="agent"``."""
    return num_envs * size if cfg.reward == "agent" else num_envs


def build_state(cfg: TrainConfig, payload: dict | None, device: str) -> TrainingState:
    """The policy (fresh, from --init-from, or from the checkpoint ``payload``), Adam, and one
    group of environments per team size, started fresh or restored exactly as checkpointed."""
    p = cfg.ppo
    torch.manual_seed(cfg.seed)
    policy = SwarmPolicy(model_config_for(cfg)).to(device)
    init_payload = None
    if cfg.init_from and payload is None:
        init_policy, init_payload = checkpoint.load_policy(cfg.init_from, trust_unsigned=cfg.trust_unsigned)
        # the same shapes; self_position only changes what the encoder is fed, and relative
        # edges and landmark occupancy add weights that start at zero (the same function), so a
        # policy may be fine-tuned into relative inputs, edges and occupancy; the fine actions'
        # logits start from the full pushes' (greedy: the same function)
        grown = ("self_position", "edge_position", "landmark_occupancy", "num_actions")
        relative = {k: getattr(policy.config, k) for k in grown}
        dropped = (
            (init_policy.config.edge_position == "relative" and policy.config.edge_position == "none")
            or (init_policy.config.landmark_occupancy and not policy.config.landmark_occupancy)
            or init_policy.config.num_actions > policy.config.num_actions
        )
        if dropped or dataclasses.replace(init_policy.config, **relative) != policy.config:
            raise checkpoint.CheckpointError(
                f"--init-from {cfg.init_from} has model {init_policy.config}, this run wants {policy.config}"
            )
        own = policy.state_dict()
        weights = grow_actions(init_policy.state_dict(), policy.config.num_actions)
        policy.load_state_dict({**own, **{k: v for k, v in weights.items() if k in own}})
    # fused: one kernel for every parameter (the per-tensor loop cost ~1.4 ms per minibatch)
    optimizer = torch.optim.Adam(policy.parameters(), lr=p.lr, eps=1e-5, fused=True)
    sizes = cfg.training_sizes()
    E = p.num_envs // len(sizes)  # validate() checks that the sizes share num_envs evenly
    groups = []
    for size in sizes:
        env = taichi_swarm.make(cfg.sim_at(size), E, arch=cfg.arch)
        # one running return per agent slot when each agent is rewarded on its own terms
        scaler = RewardScaler(
            scaler_slots(cfg, E, size), p.gamma, p.reward_clip, p.reward_scale, p.reset_return, device=device
        )
        rounds = cfg.model.rounds if cfg.drop_per_round else 0  # a graph per round to drop from
        groups.append(TeamGroup(size, env, {}, Rollout.for_env(p.num_steps, env, device, rounds), scaler))
    state = TrainingState(policy, optimizer, groups, fresh_counters(), [])
    if payload is not None:
        checkpoint.restore(state, payload, device)
    else:
        for k, g in enumerate(groups):
            g.obs = g.env.reset(seed=train_seed(cfg.seed, k))
    return state


class Reporter:
    """Where each update's record goes: metrics.jsonl, TensorBoard, the progress bar and
    the caller's ``on_update``."""

    def __init__(self, run: RunDir, cfg: TrainConfig, start: int, on_update=None):
        self.run, self.on_update = run, on_update
        self.tensorboard = TensorBoardLog(run.path) if cfg.tensorboard else None
        self.progress = None
        if cfg.progress:
            from tqdm import tqdm

            sizes = ",".join(map(str, cfg.training_sizes()))
            desc = f"{cfg.sim.task} M={sizes} {cfg.sim.comm}"
            self.progress = tqdm(total=cfg.updates, initial=start, desc=desc, unit="upd", dynamic_ncols=True)

    def report(self, record: dict, last_eval: dict | None) -> None:
        self.run.log(record)
        if self.tensorboard is not None:
            self.tensorboard.log(record)
        if self.progress is not None:
            post = {"sps": f"{record['sps']:.0f}", "rew": f"{record['reward']:.3f}"}
            if last_eval:
                post["S%"] = f"{100 * last_eval['success_rate']:.0f}"
                post["T"] = f"{last_eval['mean_length']:.1f}"
                for size, rate in last_eval.get("transfer", {}).items():
                    post[f"S%@{size}"] = f"{100 * rate:.0f}"
            self.progress.set_postfix(post)
            self.progress.update(1)
        if self.on_update is not None:
            self.on_update(record)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.close()
        if self.tensorboard is not None:
            self.tensorboard.close()


def reached_target(cfg, last_eval: dict | None, update: int) -> bool:
    """Whether the run stops at its target: ``last_eval`` reached ``cfg.target_success``
    (when set) and ``update`` is at least ``cfg.min_updates``."""
    hit = bool(last_eval) and 0 < cfg.target_success <= last_eval["success_rate"]
    return hit and update >= cfg.min_updates


def train(
    cfg: TrainConfig | None = None,
    resume: str | None = None,
    on_update=None,
    updates: int | None = None,
    progress: bool | None = None,
    arch: str | None = None,
    device: str | None = None,
) -> dict:
    """Train from ``cfg``, or continue the run in directory ``resume`` (``updates``
    then raises its total update budget; ``progress`` overrides whether it shows a bar;
    ``arch`` / ``device``, where it runs: a run may stop on one machine and go on on another).

    ``on_update(record)`` is called after every update (tests, curriculum).
    Returns a summary: run_dir, updates done, env steps, wall time, last eval.
    The run directory is locked for the whole call: a second process is refused.
    """
    if resume is not None:
        if not os.path.isdir(resume):
            raise FileNotFoundError(f"run directory {resume} does not exist")
        run = RunDir(resume)
    elif cfg is None:
        raise ValueError("train() needs a config or a run directory to resume")
    else:
        run = RunDir(cfg.default_run_dir())
        cfg.validate()  # a refused config leaves no run directory behind
    # what a resume may change in the run's config (None: keep the run's own)
    given = (("updates", updates), ("progress", progress), ("arch", arch), ("device", device))
    overrides = {k: v for k, v in given if v is not None}
    if "arch" in overrides or cfg is not None:
        check_arch(overrides.get("arch", cfg.arch if cfg is not None else "cpu"))
    resolve_device(overrides.get("device", cfg.device if cfg is not None else "cpu"))
    created = not os.path.exists(run.path)
    with run.lock():
        try:
            return _train_locked(cfg, resume, on_update, overrides)
        except BaseException:
            if created and not os.path.exists(run.checkpoint):
                shutil.rmtree(run.path, ignore_errors=True)  # a run that failed before its first checkpoint
            raise


def train_or_resume(cfg: TrainConfig) -> dict:
    """Bring the run of ``cfg`` to its end from whatever state its directory is in:
    finished (summary.json is read back), stopped (resumed from checkpoint.pt) or new.
    A larger ``cfg.updates`` than the run had raises its budget: a stopped run trains to
    it, and so does a finished one that ran out of updates short of its target (a
    curriculum stage given more updates per stage); one that reached its target stays done.
    A resumed run runs on ``cfg``'s arch and device, whatever it ran on before."""
    run = RunDir(cfg.default_run_dir())
    summary = run.read_summary()
    if summary is not None:
        budget_left = not summary.get("reached_target") and summary["update"] < cfg.updates
        if not (budget_left and os.path.exists(run.checkpoint)):
            return summary
    if os.path.exists(run.checkpoint):
        updates = cfg.updates if cfg.updates > run.budget() else None
        return train(resume=run.path, updates=updates, arch=cfg.arch, device=cfg.device)  # (maybe another machine)
    return train(cfg)


def _train_locked(cfg, resume, on_update, overrides: dict) -> dict:
    run, cfg, payload = checkpoint.open_run(cfg, resume, overrides)
    check_arch(cfg.arch)
    device = resolve_device(cfg.device)
    state = build_state(cfg, payload, device)
    inputs = state.groups[0].buf.input_names()
    loss_fn = make_loss_fn(state.policy, cfg.ppo, compile=cfg.compile, precision=cfg.precision, inputs=inputs)
    counters = state.counters
    reporter = Reporter(run, cfg, counters["update"], on_update)
    last_eval = state.evals[-1] if state.evals else None
    start_wall = time.perf_counter() - counters["wall_time"]
    # a run that stopped at its target and was killed before summary.json stays stopped
    reached = reached_target(cfg, last_eval, counters["update"])
    saved = counters["update"]  # the update the checkpoint on disk holds
    with StopAtUpdateEnd() as stop:
        try:
            while counters["update"] < cfg.updates and not reached:
                try:
                    record = one_update(state, cfg, loss_fn, device)
                except NonFiniteTraining as exc:
                    raise NonFiniteTraining(f"{exc} (last good checkpoint: {run.checkpoint})") from None
                done = counters["update"] >= cfg.updates
                if counters["update"] % cfg.eval_every == 0 or done:
                    last_eval = evaluate_during_training(state.policy, cfg, counters["update"], device)
                    state.evals.append(last_eval)
                    record.update({f"eval_{k}": v for k, v in last_eval.items() if k != "update"})
                    done = done or reached_target(cfg, last_eval, counters["update"])
                counters["wall_time"] = record["wall_time"] = time.perf_counter() - start_wall
                reporter.report(record, last_eval)
                if counters["update"] % cfg.checkpoint_every == 0 or done or stop.pending is not None:
                    checkpoint.save_checkpoint(run, state, cfg)
                    saved = counters["update"]
                if done:
                    break
                stop.check()
        except KeyboardInterrupt:
            if stop.pending is None:  # raised in code, not by a signal (a callback, a test): as Ctrl-C was
                counters["wall_time"] = time.perf_counter() - start_wall
                checkpoint.save_checkpoint(run, state, cfg)
                saved = counters["update"]
            reporter.close()
            if saved == counters["update"]:
                print(
                    f"\ninterrupted: checkpoint saved at update {saved}; continue with: swarm train --resume {run.path}"
                )
            else:  # a second signal, mid-update: the last whole update's checkpoint is kept
                print(f"\ninterrupted: resume from update {saved} with: swarm train --resume {run.path}")
            raise
        reporter.close()
        checkpoint.save_checkpoint(run, state, cfg)
        summary = {
            "run_dir": run.path,
            **counters,
            "last_eval": last_eval,
            "evals": state.evals,
            "reached_target": reached_target(cfg, last_eval, cfg.updates),
        }
        run.write_summary(summary)  # the run is done
        try:
            from trainer.plot import plot_run

            plot_run(run.path)
        except Exception as exc:  # noqa: BLE001 - a missing plot never loses a run
            print(f"(could not draw curves: {exc})")
        stop.check()  # a signal during the last update: the run is complete, and the caller stops
    return summary


__all__ = ["resolve_device", "train", "train_or_resume"]
