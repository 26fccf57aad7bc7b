"""PPO training of the shared swarm policy (CleanRL-style loop, readable top to bottom).

    rollout:  T steps x E envs with the current policy (sampling), team reward
              scaled by a running return std, stored in [T, E, M, ...] buffers
    update:   per-agent GAE, per-agent advantage normalisation, ``epochs`` x
              ``minibatches`` clipped-PPO steps; a minibatch is a set of whole
              teams (t, env), since messages need every agent of the team
    evaluate: every ``eval_every`` updates, greedy, on fresh seeds
A run directory holds config.json, metrics.jsonl, checkpoint.pt (written
atomically every ``checkpoint_every`` updates, at the end and on Ctrl-C),
policy.pt (the same weights without optimiser state), summary.json and curves.png; ``resume``
continues where the checkpoint stopped.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import threading
import time
import warnings

import torch

import taichi_swarm
from trainer import checkpoint
from trainer.config import TrainConfig, to_dict, train_config_from_dict
from trainer.evaluate import evaluate
from trainer.lock import RunDirLock
from trainer.model import ModelConfig, SwarmPolicy, policy_inputs
from trainer.ppo import DENSE_INPUTS, RewardScaler, Rollout, gae, normalize_per_agent, ppo_loss, sample_actions


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


class TensorBoardLog:
    """metrics.jsonl's scalars as TensorBoard events (RUN_DIR/tensorboard), step = update."""

    def __init__(self, run_dir: str):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            raise ValueError('--tensorboard needs the tensorboard package: pip install -e ".[tensorboard]"') from None
        self.writer = SummaryWriter(os.path.join(run_dir, "tensorboard"))

    def log(self, record: dict) -> None:
        step = record["update"]
        for key, value in record.items():
            if isinstance(value, dict):
                for sub, v in value.items():
                    self.writer.add_scalar(f"{key}/M{sub}", v, step)
            elif isinstance(value, (int, float)) and key != "update":
                self.writer.add_scalar(key, value, step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


class Run:
    """Files of one run directory."""

    def __init__(self, path: str):
        self.path = path
        self.config = os.path.join(path, "config.json")
        self.metrics = os.path.join(path, "metrics.jsonl")
        self.checkpoint = os.path.join(path, "checkpoint.pt")
        self.policy = os.path.join(path, "policy.pt")

    def log(self, record: dict) -> None:
        with open(self.metrics, "a") as f:
            f.write(json.dumps(record) + "\n")

    def truncate_metrics(self, last_update: int) -> None:
        """Drop metric lines written after the checkpoint we resume from."""
        if not os.path.exists(self.metrics):
            return
        with open(self.metrics) as f:
            lines = [line for line in f if line.strip()]
        keep = []
        for number, line in enumerate(lines, 1):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                if number == len(lines):  # the last line, torn by a kill or a full disk mid-write
                    break
                raise ValueError(f"{self.metrics}: line {number} is not JSON; fix or remove it to resume") from None
            if record["update"] <= last_update:
                keep.append(line if line.endswith("\n") else line + "\n")
        checkpoint.atomic_write_bytes(self.metrics, lambda f: f.write("".join(keep).encode()))


def teams(x: torch.Tensor) -> torch.Tensor:
    """[T, E, M, ...] -> [T*E, M, ...]: every (step, env) sample is one whole team."""
    return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])


def model_config_for(cfg: TrainConfig) -> ModelConfig:
    """The model config with the task's L filled in for the "concat" entity mode."""
    m = cfg.model
    if m.entity_mode == "concat":
        L = taichi_swarm.TASK_SPECS[cfg.task].num_landmarks(cfg.agents)
        m = ModelConfig(m.hidden, m.rounds, m.entity_mode, L)
    return m


@dataclasses.dataclass
class RolloutResult:
    """What ``collect_rollout`` returns besides the filled buffer."""

    next_obs: dict  # the observation after the last step (the env's live views)
    advantages: torch.Tensor  # [T, E, M], normalised per agent
    returns: torch.Tensor  # [T, E, M]
    mean_reward: float  # raw team reward per env step
    train_success: float | None  # success rate of the episodes that ended (sampled actions)
    train_length: float | None
    train_episodes: int  # how many episodes ended
    time_sim: float  # seconds in env.step
    time_policy: float  # seconds in the policy forward and sampling


def drop_messages(inputs: dict, rate: torch.Tensor) -> None:
    """Drop each message of one step's stored graph with its environment's ``rate`` [E], in
    place (the buffer then holds the graph the agents heard, so the update sees it too). An
    agent always keeps its own state: the dense graph's diagonal is never dropped."""
    if "adj" in inputs:
        adj = inputs["adj"]  # [E, M, M]
        keep = torch.rand(adj.shape, device=adj.device) >= rate[:, None, None]
        keep.diagonal(dim1=-2, dim2=-1).fill_(True)
        adj &= keep
    else:  # neighbour lists hold others only
        mask = inputs["nbr_mask"]  # [E, M, K]
        mask &= torch.rand(mask.shape, device=mask.device) >= rate[:, None, None]


@torch.no_grad()
def collect_rollout(
    policy, env, obs: dict, buf: Rollout, scaler: RewardScaler, p, device, message_drop: float = 0.0
) -> RolloutResult:
    """T steps of every environment with sampled actions into ``buf`` [T, E, M, ...];
    then per-agent GAE and advantage normalisation. ``message_drop`` > 0: each environment
    drops messages at a rate drawn from [0, message_drop] for the rollout (TrainConfig)."""
    T = buf.actions.shape[0]
    # drawn from torch's generator, which the checkpoint carries: a resumed run draws the same
    rate = torch.rand(buf.actions.shape[1], device=device) * message_drop if message_drop > 0 else None
    policy.eval()
    torch.set_num_threads(1)  # batches of E teams: more threads only add wake-up latency
    fused = policy.fused_weights()  # the weights do not change during the rollout
    ep_success, ep_length = [], []
    raw_reward = torch.zeros((), device=device)  # summed on device: no host sync per step
    t_sim = t_policy = 0.0
    for t in range(T):
        inputs = buf.store(t, obs)  # dense adj or neighbour lists, as the simulator observes
        if rate is not None:
            drop_messages(inputs, rate)
        ta = time.perf_counter()
        logits, value = policy(**inputs, fused=fused)
        action, logprob = sample_actions(logits)  # [E, M]
        buf.actions[t] = action
        buf.logprobs[t] = logprob
        buf.values[t] = value
        tb = time.perf_counter()
        obs, reward, done, info = env.step(action if env.device == device else action.to(env.device))
        t_sim += time.perf_counter() - tb
        t_policy += tb - ta
        reward, done = reward.to(device), done.to(device)
        raw_reward += reward.mean()
        scaled = scaler(reward, done)
        if bool(done.any()):
            ep = info["episode"]
            ep_success.append(ep["success"][done].cpu())
            ep_length.append(ep["length"][done].cpu())
            if p.bootstrap_time_limit:
                cut = done & ep["truncated"].to(device)
                if bool(cut.any()):
                    term = info["terminal_obs"]
                    _, v_term = policy(**policy_inputs(term, device), fused=fused)
                    scaled = scaled + p.gamma * v_term.mean(-1) * cut.float()
        buf.rewards[t] = scaled
        buf.dones[t] = done
    _, next_value = policy(**policy_inputs(obs, device), fused=fused)
    advantages, returns = gae(buf.rewards, buf.values, buf.dones, next_value, p.gamma, p.gae_lambda)
    return RolloutResult(
        next_obs=obs,
        advantages=normalize_per_agent(advantages),
        returns=returns,
        mean_reward=float(raw_reward) / T,
        train_success=float(torch.cat(ep_success).float().mean()) if ep_success else None,
        train_length=float(torch.cat(ep_length).float().mean()) if ep_length else None,
        train_episodes=sum(len(x) for x in ep_success),
        time_sim=t_sim,
        time_policy=t_policy,
    )


RESUME_KEYS = ("counters", "optimizer", "reward_scaler", "torch_rng")
MAX_BAD_UPDATES = 3  # consecutive updates with no finite minibatch before training stops


class NonFiniteTraining(ValueError):
    """The loss or gradients stayed NaN/inf: training stopped, the weights untouched."""


# Environment seeds: training streams live at and above 2**40, so an evaluation seed a
# user types (below that: 777 in docs/RESULTS.md) never replays a training episode;
# evaluations during training use EVAL_SEED_BASE + update.
TRAIN_SEED_BASE = 2**40
EVAL_SEED_BASE = 10_000_019


def transfer_sizes(cfg: TrainConfig) -> list[int]:
    """The neighbouring team sizes evaluated beside the training size: those the task has
    and the network can take ("concat": the training size's number of landmarks; "padded":
    at most PADDED_SLOTS landmarks)."""
    spec, model = taichi_swarm.TASK_SPECS[cfg.task], model_config_for(cfg)
    sizes = [cfg.agents + d for d in cfg.transfer_offsets if d != 0 and cfg.agents + d >= spec.min_agents]
    return [M for M in sizes if not model.landmark_misfit(spec.num_landmarks(M))]


def evaluate_during_training(policy, cfg: TrainConfig, update: int, device) -> dict:
    """Greedy S%, T, DIST at the training size; S% at the transfer sizes (``transfer``)."""
    policy.eval()
    seed = EVAL_SEED_BASE + update
    common = dict(comm=cfg.comm, comm_radius=cfg.comm_radius, seed=seed, arch=cfg.arch, device=device)
    common["swarm"] = cfg.swarm_options()
    result = evaluate(policy, cfg.task, cfg.agents, episodes=cfg.eval_episodes, **common)
    out = {k: result[k] for k in ("success_rate", "mean_length", "dist")}
    out["update"] = update
    sizes = transfer_sizes(cfg)
    if sizes:
        out["transfer"] = {
            str(M): evaluate(policy, cfg.task, M, episodes=cfg.eval_episodes, **common)["success_rate"] for M in sizes
        }
    return out


def rollout_stats(rollouts: list[RolloutResult]) -> dict:
    """Reward, sampled success and length over the team-size groups of one update."""
    n = sum(r.train_episodes for r in rollouts)

    def mean(key):
        return sum(getattr(r, key) * r.train_episodes for r in rollouts if r.train_episodes) / n if n else None

    return {
        "reward": sum(r.mean_reward for r in rollouts) / len(rollouts),
        "train_success": mean("train_success"),
        "train_length": mean("train_length"),
    }


def make_loss_fn(policy, p, compile: bool = False, precision: str = "fp32", inputs=DENSE_INPUTS):
    """``loss_fn(batch) -> (loss, stats [5])``: the policy's forward and the clipped PPO
    loss on one minibatch of whole teams; with ``compile``, through torch.compile (fused
    elementwise loops around the GEMMs: 1.3-1.7x per minibatch on this CPU), falling back
    to eager with a warning where compilation fails (no C++ compiler, say). ``precision``
    "bf16": the forward under bfloat16 autocast (the loss itself in fp32). ``inputs``: the
    names of the observation tensors the batch starts with (``Rollout.input_names``)."""
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision must be fp32 or bf16, got {precision!r}")
    n_in = len(inputs)

    def loss_fn(*batch):  # the observation tensors, then actions, old log-probs and values, advantages, returns
        obs = dict(zip(inputs, batch[:n_in], strict=True))
        with torch.autocast(batch[0].device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
            logits, values = policy(**obs)
        batch = batch[n_in:]
        logits, values = logits.float(), values.float()
        loss, info = ppo_loss(logits, values, *batch, p.clip, p.value_coef, p.entropy_coef)
        return loss, torch.stack([info.policy, info.value, info.entropy, info.approx_kl, info.clipfrac])

    if not compile:
        return loss_fn
    compiled = torch.compile(loss_fn, dynamic=False)
    state = {"fn": compiled}

    def guarded(*batch):
        try:
            return state["fn"](*batch)
        except Exception as exc:  # noqa: BLE001 - e.g. no C++ compiler on this machine
            if state["fn"] is loss_fn:
                raise
            msg = f"torch.compile failed ({type(exc).__name__}: {exc}); training continues eagerly"
            warnings.warn(msg, stacklevel=2)
            state["fn"] = loss_fn
            return loss_fn(*batch)

    return guarded


def ppo_update(policy, optimizer, groups: list[tuple[Rollout, torch.Tensor, torch.Tensor]], p, loss_fn):
    """``p.epochs`` x ``p.minibatches`` clipped-PPO steps over the rollout; a minibatch is
    a set of whole teams (t, env) of one team size. ``groups``: (buffer [T, E, M, ...],
    advantages, returns [T, E, M]) per team size; with several sizes each gets
    ``minibatches / len(groups)`` minibatches per epoch, taken in random order.
    Returns (the mean of the loss statistics [5], the number of minibatches skipped
    because their loss or gradient was not finite)."""
    policy.train()
    data = []
    for buf, advantages, returns in groups:
        batch = [teams(x) for x in (*buf.inputs(), buf.actions, buf.logprobs, buf.values)]
        data.append(batch + [teams(advantages), teams(returns)])
    device = groups[0][1].device
    params = [q for q in policy.parameters() if q.requires_grad]
    per_group = max(1, p.minibatches // len(groups))
    stats, steps, skipped = torch.zeros(5, device=device), 0, 0
    for _ in range(p.epochs):
        minibatches = []  # (shuffled group data, start, size)
        for batch in data:
            n = batch[0].shape[0]
            perm = torch.randperm(n, device=device)
            shuffled = [x[perm] for x in batch]  # one gather per epoch; minibatches are contiguous slices
            start = 0
            for size in (len(c) for c in perm.tensor_split(per_group)):  # (chunk may give fewer)
                if not size:
                    continue
                minibatches.append((shuffled, start, size))
                start += size
        if len(data) > 1:  # sizes interleaved (one size keeps the RNG stream of a plain run)
            minibatches = [minibatches[i] for i in torch.randperm(len(minibatches)).tolist()]
        for shuffled, start, size in minibatches:
            loss, s = loss_fn(*(x[start : start + size] for x in shuffled))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            norm = torch.nn.utils.clip_grad_norm_(policy.parameters(), p.max_grad_norm)
            if not torch.isfinite(norm):  # a NaN/inf loss or gradient never reaches the weights
                skipped += 1
                continue
            optimizer.step()
            if not all_finite(params):  # finite gradients, yet NaN/inf weights: Adam's own state is not finite
                raise NonFiniteTraining(
                    "an optimiser step made the weights NaN/inf from finite gradients (Adam's moments or the "
                    "learning rate are not finite); stopped before anything was written"
                )
            stats += s.detach()
            steps += 1
    if steps == 0:
        return torch.full((5,), float("nan")), skipped
    return stats / steps, skipped


def all_finite(tensors) -> bool:
    """Whether every float tensor of ``tensors`` is finite: one fused norm per tensor and one
    host sync (~0.1 ms for the default network, a tenth of a loop of isfinite calls); a norm is
    NaN/inf when its tensor holds one (or when its squares overflow float32: entries of 1e16 and more,
    a broken run too)."""
    floats = [t.detach() for t in tensors if t.is_floating_point()]
    return bool(torch.isfinite(torch.stack(torch._foreach_norm(floats))).all()) if floats else True


def env_state(env) -> dict:
    """``env.snapshot()`` as torch tensors (checkpoints load with weights_only=True)."""
    snap = env.snapshot()
    return {"shape": list(snap["shape"]), "buffers": {k: torch.from_numpy(v) for k, v in snap["buffers"].items()}}


@dataclasses.dataclass
class TeamGroup:
    """The environments of one team size, with their rollout buffer and reward scaler."""

    agents: int
    env: object
    obs: dict
    buf: Rollout
    scaler: RewardScaler


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
        run_dir = resume
    elif cfg is None:
        raise ValueError("train() needs a config or a run directory to resume")
    else:
        run_dir = cfg.default_run_dir()
        cfg.validate()  # a refused config leaves no run directory behind
    # what a resume may change in the run's config (None: keep the run's own)
    given = (("updates", updates), ("progress", progress), ("arch", arch), ("device", device))
    overrides = {k: v for k, v in given if v is not None}
    if "arch" in overrides or cfg is not None:
        check_arch(overrides.get("arch", cfg.arch if cfg is not None else "cpu"))
    resolve_device(overrides.get("device", cfg.device if cfg is not None else "cpu"))
    created = not os.path.exists(run_dir)
    with RunDirLock(run_dir):
        try:
            return _train_locked(cfg, resume, on_update, overrides)
        except BaseException:
            if created and not os.path.exists(os.path.join(run_dir, "checkpoint.pt")):
                shutil.rmtree(run_dir, ignore_errors=True)  # a run that failed before its first checkpoint
            raise


def train_or_resume(cfg: TrainConfig) -> dict:
    """Bring the run of ``cfg`` to its end from whatever state its directory is in:
    finished (summary.json is read back), stopped (resumed from checkpoint.pt) or new.
    A larger ``cfg.updates`` than the run had raises its budget: a stopped run trains to
    it, and so does a finished one that ran out of updates short of its target (a
    curriculum stage given more updates per stage); one that reached its target stays done.
    A resumed run runs on ``cfg``'s arch and device, whatever it ran on before."""
    run = Run(cfg.default_run_dir())
    summary_path = os.path.join(run.path, "summary.json")
    if os.path.exists(summary_path):
        with open(summary_path) as f:
            summary = json.load(f)
        budget_left = not summary.get("reached_target") and summary["update"] < cfg.updates
        if not (budget_left and os.path.exists(run.checkpoint)):
            return summary
    if os.path.exists(run.checkpoint):
        with open(run.config) as f:
            budget = json.load(f)["updates"]
        updates = cfg.updates if cfg.updates > budget else None
        return train(resume=run.path, updates=updates, arch=cfg.arch, device=cfg.device)  # (maybe another machine)
    return train(cfg)


def open_run(cfg: TrainConfig | None, resume: str | None, overrides: dict | None = None):
    """The run directory of a new run, or of one to resume (its checkpoint checked, its
    config read back, leftovers of a killed write repaired; ``overrides``: the config fields a
    resume changes, e.g. updates, progress). Returns (run, cfg, payload)."""
    if resume is None:
        if cfg is None:
            raise ValueError("train() needs a config or a run directory to resume")
        run = Run(cfg.default_run_dir())
        if os.path.exists(run.checkpoint):
            raise FileExistsError(
                f"{run.path} already holds a run; continue it with --resume {run.path} or pick another --run-dir"
            )
        os.makedirs(run.path, exist_ok=True)
        cfg.validate()
        run.truncate_metrics(0)  # lines a run killed before its first checkpoint left behind
        checkpoint.atomic_write_json(run.config, to_dict(cfg))
        return run, cfg, None
    run = Run(resume)
    checkpoint.clean_leftovers(run.path)  # a kill during a write leaves a .tmp-* file
    payload = checkpoint.load(run.checkpoint)
    if "train_config" not in payload:
        raise checkpoint.CheckpointError(f"{run.checkpoint} is not a training checkpoint (no train_config)")
    lacking = [k for k in RESUME_KEYS if k not in payload]
    if lacking:
        raise checkpoint.CheckpointError(f"{run.checkpoint} cannot resume a run: it lacks {lacking}")
    checkpoint.check_counters(run.checkpoint, payload["counters"])  # (before policy.pt is repaired from them)
    try:
        cfg = train_config_from_dict(payload["train_config"])
    except (TypeError, ValueError) as exc:
        raise checkpoint.CheckpointError(
            f"{run.checkpoint} holds a training config this version cannot read: {exc}"
        ) from None
    if os.path.exists(run.policy):  # a kill between the two writes leaves policy.pt one behind
        if checkpoint.load(run.policy).get("counters") != payload.get("counters"):
            checkpoint.save_policy_only(payload, run.policy)
    cfg = dataclasses.replace(cfg, **(overrides or {}))
    run.truncate_metrics(payload["counters"]["update"])
    cfg.validate()
    checkpoint.atomic_write_json(run.config, to_dict(cfg))
    return run, cfg, payload


@dataclasses.dataclass
class TrainingState:
    """Everything a checkpoint holds, live."""

    policy: SwarmPolicy
    optimizer: torch.optim.Optimizer
    groups: list[TeamGroup]
    counters: dict  # update, env_steps, wall_time, skipped_minibatches
    evals: list[dict]
    bad_updates: int = 0  # consecutive updates without one finite minibatch


def build_state(cfg: TrainConfig, payload: dict | None, device: str) -> TrainingState:
    """The policy (fresh, from --init-from, or from the checkpoint), Adam, and one group of
    environments per team size, started fresh or restored exactly as checkpointed."""
    p = cfg.ppo
    torch.manual_seed(cfg.seed)
    policy = SwarmPolicy(model_config_for(cfg)).to(device)
    init_payload = None
    if cfg.init_from and payload is None:
        init_policy, init_payload = checkpoint.load_policy(cfg.init_from, trust_unsigned=cfg.trust_unsigned)
        # the same shapes; self_position only changes what the encoder is fed, so a policy
        # may be fine-tuned into relative inputs
        if dataclasses.replace(init_policy.config, self_position=policy.config.self_position) != policy.config:
            raise checkpoint.CheckpointError(
                f"--init-from {cfg.init_from} has model {init_policy.config}, this run wants {policy.config}"
            )
        policy.load_state_dict(init_policy.state_dict())
    # fused: one kernel for every parameter (the per-tensor loop cost ~1.4 ms per minibatch)
    optimizer = torch.optim.Adam(policy.parameters(), lr=p.lr, eps=1e-5, fused=True)
    sizes = cfg.training_sizes()
    E = p.num_envs // len(sizes)  # validate() checks that the sizes share num_envs evenly
    groups = []
    for size in sizes:
        env = taichi_swarm.make(
            cfg.task, E, size, comm=cfg.comm, comm_radius=cfg.comm_radius, arch=cfg.arch, **cfg.swarm_options()
        )
        scaler = RewardScaler(E, p.gamma, p.reward_clip, p.reward_scale, p.reset_return, device=device)
        groups.append(TeamGroup(size, env, {}, Rollout.for_env(p.num_steps, env, device), scaler))
    state = TrainingState(policy, optimizer, groups, {"update": 0, "env_steps": 0, "wall_time": 0.0}, [])
    if init_payload is not None and cfg.init_carry != "weights":
        carry_training_state(init_payload, cfg, state)
    if payload is not None:  # every piece checked (shape, dtype, finite) before it is used
        checkpoint.load_weights(policy, payload["model"])
        checkpoint.check_optimizer_state("checkpoint", payload["optimizer"], policy)
        optimizer.load_state_dict(payload["optimizer"])
        scaler_states = reward_scaler_states(payload)
        if not isinstance(scaler_states, list) or len(scaler_states) != len(groups):
            raise checkpoint.CheckpointError(f"the checkpoint does not hold one reward scaler per team size {sizes}")
        for g, scaler_state in zip(groups, scaler_states, strict=True):
            checkpoint.check_scaler_state("checkpoint", scaler_state, E)
            g.scaler.load_state_dict(scaler_state)
        torch.set_rng_state(checkpoint.check_rng_state("checkpoint torch_rng", payload["torch_rng"]))
        cuda_rng = payload.get("cuda_rng") or []
        for i, t in enumerate(cuda_rng):
            checkpoint.check_tensor(f"checkpoint cuda_rng[{i}]", t, dtype=torch.uint8)
        if device.startswith("cuda") and len(cuda_rng) == torch.cuda.device_count():  # (not: another machine)
            torch.cuda.set_rng_state_all(cuda_rng)
        state.counters = dict(checkpoint.check_counters("checkpoint", payload["counters"]))
        state.evals = list(payload.get("evals", []))
    env_states = (payload or {}).get("env_states")
    if env_states is not None and (not isinstance(env_states, list) or len(env_states) != len(groups)):
        raise checkpoint.CheckpointError(f"the checkpoint's env_states do not hold one state per team size {sizes}")
    for k, g in enumerate(groups):
        if env_states is not None:  # resume bit-identically: the environments' buffers as they were
            g.obs = restore_env(g.env, env_states[k], f"env_states[{k}]")
        else:  # a fresh run (or a checkpoint from before env states were saved)
            seed = TRAIN_SEED_BASE + cfg.seed * 1_000_003 + state.counters["update"] + 7_919 * k
            g.obs = g.env.reset(seed=seed)
    return state


def restore_env(env, saved, where: str) -> dict:
    """``env.restore`` from a checkpoint's entry (its buffers checked by ``restore``)."""
    if not isinstance(saved, dict) or not isinstance(saved.get("buffers"), dict):
        raise checkpoint.CheckpointError(f"checkpoint {where} is not an environment state")
    buffers = {}
    for name, t in saved["buffers"].items():
        buffers[name] = checkpoint.check_tensor(f"{where}.buffers.{name}", t, finite=False).numpy()
    try:
        return env.restore({"shape": tuple(saved.get("shape", ())), "buffers": buffers})
    except ValueError as exc:
        raise checkpoint.CheckpointError(f"checkpoint {where}: {exc}") from None


def reward_scaler_states(payload: dict) -> list[dict]:
    """The reward normalisers a checkpoint holds, one per team size (checkpoints from before
    several sizes hold one, as "reward_scaler"); [] for a weights-only policy.pt."""
    if "reward_scalers" in payload:
        return payload["reward_scalers"]
    return [payload["reward_scaler"]] if "reward_scaler" in payload else []


def carry_training_state(init_payload: dict, cfg: TrainConfig, state: TrainingState) -> None:
    """--init-carry normaliser|optimiser: the reward normalisers' running statistics (not
    the per-environment running returns, which start at 0) and, for optimiser, Adam's moments
    (at this run's learning rate) from the --init-from checkpoint."""
    scaler_states = reward_scaler_states(init_payload)
    if not scaler_states:
        raise checkpoint.CheckpointError(
            f"--init-carry {cfg.init_carry} needs a training checkpoint (checkpoint.pt): "
            f"{cfg.init_from} holds weights only"
        )
    if len(scaler_states) not in (1, len(state.groups)):
        raise checkpoint.CheckpointError(
            f"--init-from {cfg.init_from} holds {len(scaler_states)} reward normalisers; "
            f"this run has {len(state.groups)} team sizes (carry needs 1 or as many)"
        )
    for k, g in enumerate(state.groups):
        scaler_state = scaler_states[k if len(scaler_states) > 1 else 0]
        checkpoint.check_scaler_state(f"--init-from {cfg.init_from}", scaler_state, None)
        g.scaler.rms.load_state_dict(scaler_state["rms"])
    if cfg.init_carry == "optimiser":
        checkpoint.check_optimizer_state(f"--init-from {cfg.init_from}", init_payload["optimizer"], state.policy)
        state.optimizer.load_state_dict(init_payload["optimizer"])
        for group in state.optimizer.param_groups:
            group["lr"] = cfg.ppo.lr


def save_checkpoint(run: Run, state: TrainingState, cfg: TrainConfig) -> None:
    """checkpoint.pt (everything to resume bit-identically), then policy.pt (weights only:
    small enough to commit; loads in `swarm eval` / `export`). A state holding NaN/inf is
    never written: the last good checkpoint stays."""
    moments = [t for entry in state.optimizer.state.values() for t in entry.values() if isinstance(t, torch.Tensor)]
    if not all_finite(list(state.policy.parameters()) + moments):
        raise NonFiniteTraining(
            f"the weights or Adam's moments hold NaN/inf: not written (last good checkpoint: {run.checkpoint})"
        )
    payload = {
        "model_config": state.policy.config.to_dict(),
        "model": state.policy.state_dict(),
        "task": taichi_swarm.TaskSetting(cfg.task, cfg.agents, cfg.comm, cfg.comm_radius).to_dict(),
        "swarm": cfg.swarm_options(),  # the neighbour lists / density scaling it trained on ({}: dense)
        "counters": dict(state.counters),
        "evals": list(state.evals),
        "optimizer": state.optimizer.state_dict(),
        "env_states": [env_state(g.env) for g in state.groups],
        "reward_scaler": state.groups[0].scaler.state_dict(),
        "reward_scalers": [g.scaler.state_dict() for g in state.groups],
        "torch_rng": torch.get_rng_state(),
        # on a GPU, sampling and minibatch shuffles draw from CUDA's generators
        "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else [],
        "train_config": to_dict(cfg),
    }
    checkpoint.save(run.checkpoint, payload)
    checkpoint.save_policy_only(payload, run.policy)


def one_update(state: TrainingState, cfg: TrainConfig, loss_fn, device: str, run: Run) -> dict:
    """Rollout -> advantages -> clipped-PPO epochs; returns the update's metrics record."""
    p = cfg.ppo
    t0 = time.perf_counter()
    if p.lr_end is not None:  # linear decay from lr to lr_end over the run
        frac = state.counters["update"] / max(cfg.updates - 1, 1)
        state.optimizer.param_groups[0]["lr"] = p.lr + (p.lr_end - p.lr) * min(frac, 1.0)
    rollouts = []
    for g in state.groups:
        rollouts.append(collect_rollout(state.policy, g.env, g.obs, g.buf, g.scaler, p, device, cfg.message_drop))
        g.obs = rollouts[-1].next_obs
    tc = time.perf_counter()
    torch.set_num_threads(cfg.torch_threads)
    batches = [(g.buf, r.advantages, r.returns) for g, r in zip(state.groups, rollouts, strict=True)]
    stats, skipped = ppo_update(state.policy, state.optimizer, batches, p, loss_fn)
    if device.startswith("cuda"):
        torch.cuda.synchronize()  # the update's kernels are queued: time them, not their launch
    t_update = time.perf_counter() - tc
    state.counters["skipped_minibatches"] = state.counters.get("skipped_minibatches", 0) + skipped
    # (a stats row of NaN: no finite minibatch; with several sizes there may be fewer than
    # epochs * minibatches of them, so the count is not the test)
    state.bad_updates = state.bad_updates + 1 if bool(torch.isnan(stats).all()) else 0
    if state.bad_updates >= MAX_BAD_UPDATES:
        raise NonFiniteTraining(
            f"every minibatch of the last {state.bad_updates} updates had a NaN/inf loss or gradient; "
            f"stopped before any reached the weights (last good checkpoint: {run.checkpoint}). "
            "Lower --ppo.lr or check the configuration."
        )
    n = p.num_steps * p.num_envs
    state.counters["update"] += 1
    state.counters["env_steps"] += n
    s = stats.tolist()
    return {
        "update": state.counters["update"],
        "env_steps": state.counters["env_steps"],
        "sps": n / (time.perf_counter() - t0),
        **rollout_stats(rollouts),
        "loss_policy": s[0],
        "loss_value": s[1],
        "entropy": s[2],
        "approx_kl": s[3],
        "clipfrac": s[4],
        "time_sim": sum(r.time_sim for r in rollouts),
        "time_policy": sum(r.time_policy for r in rollouts),
        "time_update": t_update,
        "skipped_minibatches": skipped,
        "lr": state.optimizer.param_groups[0]["lr"],
    }


class Reporter:
    """Where each update's record goes: metrics.jsonl, TensorBoard, the progress bar and
    the caller's ``on_update``."""

    def __init__(self, run: Run, cfg: TrainConfig, start: int, on_update=None):
        self.run, self.on_update = run, on_update
        self.tensorboard = TensorBoardLog(run.path) if cfg.tensorboard else None
        self.progress = None
        if cfg.progress:
            from tqdm import tqdm

            sizes = ",".join(map(str, cfg.training_sizes()))
            desc = f"{cfg.task} M={sizes} {cfg.comm}"
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


class StopAtUpdateEnd:
    """While inside: Ctrl-C (SIGINT) or SIGTERM during an update lets the update, its
    evaluation and its checkpoint finish, then takes the signal's own path (its previous
    handler, else a KeyboardInterrupt), so a stopped run resumes from a whole update. A
    second signal takes that path at once. Signals the process ignores stay ignored; off
    the main thread (where no signal arrives) it does nothing."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.pending: int | None = None
        self.previous: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                if signal.getsignal(s) is not signal.SIG_IGN:
                    self.previous[s] = signal.signal(s, self._note)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    def _restore(self) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
        self.previous = {}

    def _note(self, signum, frame) -> None:
        if self.pending is not None:
            self.take(signum)
        self.pending = signum

    def check(self) -> None:
        """At an update's end: stop now if a signal came."""
        if self.pending is not None:
            self.take(self.pending)

    def take(self, signum: int) -> None:
        handler = self.previous.get(signum)
        self._restore()
        if callable(handler):
            handler(signum, None)  # e.g. Python's SIGINT handler, `swarm`'s SIGTERM one: raise KeyboardInterrupt
        raise KeyboardInterrupt(f"stopped by {signal.Signals(signum).name}")


def _train_locked(cfg, resume, on_update, overrides: dict) -> dict:
    run, cfg, payload = open_run(cfg, resume, overrides)
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
                record = one_update(state, cfg, loss_fn, device, run)
                done = counters["update"] >= cfg.updates
                if counters["update"] % cfg.eval_every == 0 or done:
                    last_eval = evaluate_during_training(state.policy, cfg, counters["update"], device)
                    state.evals.append(last_eval)
                    record.update({f"eval_{k}": v for k, v in last_eval.items() if k != "update"})
                    done = done or reached_target(cfg, last_eval, counters["update"])
                counters["wall_time"] = record["wall_time"] = time.perf_counter() - start_wall
                reporter.report(record, last_eval)
                if counters["update"] % cfg.checkpoint_every == 0 or done or stop.pending is not None:
                    save_checkpoint(run, state, cfg)
                    saved = counters["update"]
                if done:
                    break
                stop.check()
        except KeyboardInterrupt:
            if stop.pending is None:  # raised in code, not by a signal (a callback, a test): as Ctrl-C was
                counters["wall_time"] = time.perf_counter() - start_wall
                save_checkpoint(run, state, cfg)
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
        save_checkpoint(run, state, cfg)
        summary = {
            "run_dir": run.path,
            **counters,
            "last_eval": last_eval,
            "evals": state.evals,
            "reached_target": reached_target(cfg, last_eval, cfg.updates),
        }
        checkpoint.atomic_write_json(os.path.join(run.path, "summary.json"), summary)  # the run is done
        try:
            from trainer.plot import plot_run

            plot_run(run.path)
        except Exception as exc:  # noqa: BLE001 - a missing plot never loses a run
            print(f"(could not draw curves: {exc})")
        stop.check()  # a signal during the last update: the run is complete, and the caller stops
    return summary


__all__ = ["Run", "resolve_device", "train", "train_or_resume"]
