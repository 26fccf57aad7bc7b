"""PPO (Schulman et al. 2017) top to bottom, in the shape of CleanRL's ppo.py and of the
pytorch-a2c-ppo code the paper ran. Shapes: T steps, E environments, M agents.

    1. storage     Rollout: preallocated [T, E, M, ...] buffers, time first
    2. rewards     RewardScaler: the team reward / std(discounted return), clipped
    3. rollout     collect_rollout: T steps with sampled actions, per-agent rewards, and at a
                   time-limit end each agent bootstraps on its own value of the final state
    4. GAE         gae: per-agent advantages and returns; normalize_per_agent
    5. loss        ppo_loss: clipped surrogate, clipped value loss, entropy bonus
    6. update      ppo_update: epochs x minibatches of whole teams, gradient clipping,
                   no NaN/inf ever reaching the weights
    7. iteration   one_update: rollout -> GAE -> update for every team size, one metrics record

Everything about the run directory (files, checkpoints, resume, signals) is in
trainer.rundir; the loop that calls ``one_update``, evaluates and checkpoints is
trainer.train.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import torch

from trainer.model import SwarmPolicy, policy_inputs

# ----------------------------------------------------------------------------- 1. storage

# the observation tensors a rollout stores, by the policy's argument names (trainer.model.OBS_INPUTS)
DENSE_INPUTS = ("self_obs", "entities", "adj")
LIST_INPUTS = ("self_obs", "entities", "nbr", "nbr_mask")


@dataclasses.dataclass
class Rollout:
    """Preallocated rollout storage, time first: [T, E, M, ...]. The communication graph is
    either dense (``adj``) or neighbour lists (``nbr``, ``nbr_mask``; ``entity_mask`` with
    landmark lists), as the simulator observes it."""

    self_obs: torch.Tensor  # [T, E, M, 4]
    entities: torch.Tensor  # [T, E, M, L, F] (L: KL with landmark lists; F: 2, 3 with occupancy)
    adj: torch.Tensor | None  # [T, E, M, M] bool (dense); [T, E, R, M, M] with a graph per round
    actions: torch.Tensor  # [T, E, M] int64
    logprobs: torch.Tensor  # [T, E, M]
    values: torch.Tensor  # [T, E, M]
    rewards: torch.Tensor  # [T, E, M]: the scaled team reward, + gamma * V(final state) at a time-limit end
    dones: torch.Tensor  # [T, E] bool: the episode ended at this step (every agent's)
    nbr: torch.Tensor | None = None  # [T, E, M, K] int32 (lists)
    nbr_mask: torch.Tensor | None = None  # [T, E, M, K] bool; [T, E, R, M, K] per round
    entity_mask: torch.Tensor | None = None  # [T, E, M, KL] bool (landmark lists)

    @classmethod
    def allocate(
        cls, T: int, E: int, M: int, L: int, device="cpu", neighbours: int | None = None, entity_mask: bool = False,
        rounds: int = 0, features: int = 2,
    ) -> Rollout:  # fmt: skip
        """``neighbours``: K of the simulator's lists (None: dense adj); ``entity_mask``: the
        observation has landmark lists (L is then their KL); ``rounds`` > 0: a graph per round
        (TrainConfig.drop_per_round); ``features``: per landmark (3 with landmark occupancy)."""
        z = dict(device=device)
        lists = neighbours is not None
        R = (rounds,) if rounds else ()
        return cls(
            self_obs=torch.zeros(T, E, M, 4, **z),
            entities=torch.zeros(T, E, M, L, features, **z),
            adj=None if lists else torch.zeros(T, E, *R, M, M, dtype=torch.bool, **z),
            actions=torch.zeros(T, E, M, dtype=torch.int64, **z),
            logprobs=torch.zeros(T, E, M, **z),
            values=torch.zeros(T, E, M, **z),
            rewards=torch.zeros(T, E, M, **z),
            dones=torch.zeros(T, E, dtype=torch.bool, **z),
            nbr=torch.zeros(T, E, M, neighbours, dtype=torch.int32, **z) if lists else None,
            nbr_mask=torch.zeros(T, E, *R, M, neighbours, dtype=torch.bool, **z) if lists else None,
            entity_mask=torch.zeros(T, E, M, L, dtype=torch.bool, **z) if entity_mask else None,
        )

    @classmethod
    def for_env(cls, T: int, env, device="cpu", rounds: int = 0) -> Rollout:
        """Storage shaped like ``env``'s observation (dense or lists)."""
        obs = env.obs
        nbr = obs.get("nbr")
        return cls.allocate(
            T, env.num_envs, env.num_agents, obs["entities"].shape[-2], device,
            neighbours=None if nbr is None else nbr.shape[-1], entity_mask="entity_mask" in obs, rounds=rounds,
            features=obs["entities"].shape[-1],
        )  # fmt: skip

    def input_names(self) -> tuple[str, ...]:
        """The policy arguments stored, in order (what ``inputs`` returns)."""
        names = DENSE_INPUTS if self.adj is not None else LIST_INPUTS
        return names + (("entity_mask",) if self.entity_mask is not None else ())

    def inputs(self) -> list[torch.Tensor]:
        """The stored observation tensors [T, E, M, ...], in ``input_names`` order."""
        return [getattr(self, k) for k in self.input_names()]

    def store(self, t: int, obs: dict) -> dict:
        """Copy the simulator's observation into step ``t``; returns the policy's keyword
        arguments at that step (views of the buffers)."""
        keys = {"self_obs": "self", "entities": "entities"}
        out = {}
        for name in self.input_names():
            buf, src = getattr(self, name)[t], obs[keys.get(name, name)]
            buf.copy_(src.unsqueeze(1) if buf.dim() > src.dim() else src)  # (every round's graph the same)
            out[name] = buf
        return out


def teams(x: torch.Tensor) -> torch.Tensor:
    """[T, E, M, ...] -> [T*E, M, ...]: every (step, env) sample is one whole team."""
    return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])


# ----------------------------------------------------------------------------- 2. rewards


class RunningMeanStd:
    """Running mean/variance (Chan et al. parallel update), as in VecNormalize."""

    def __init__(self, shape=(), device="cpu"):
        self.mean = torch.zeros(shape, dtype=torch.float64, device=device)
        self.var = torch.ones(shape, dtype=torch.float64, device=device)
        self.count = 1e-4

    def update(self, x: torch.Tensor) -> None:
        x = x.double()
        batch_mean, batch_var, n = x.mean(0), x.var(0, unbiased=False), x.shape[0]
        delta = batch_mean - self.mean
        total = self.count + n
        self.mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.var = m2 / total
        self.count = total

    def state_dict(self) -> dict:
        return {"mean": self.mean.cpu(), "var": self.var.cpu(), "count": float(self.count)}

    def load_state_dict(self, d: dict) -> None:
        self.mean = d["mean"].to(self.mean.device)
        self.var = d["var"].to(self.var.device)
        self.count = float(d["count"])


class RewardScaler:
    """r / std(discounted return), clipped (pytorch-a2c-ppo's VecNormalize(ob=False)).

    The simulator gives one team reward per environment (every agent of a team gets the
    same), so the running return is one per environment. ``reset_at_done=False`` is what
    the paper's published code did: the running return is never reset at episode ends, so
    it grows towards r / (1 - gamma) and the scaled rewards are smaller (the usual
    VecNormalize resets it).
    """

    def __init__(
        self, num_envs: int, gamma: float, clip: float, enabled: bool = True, reset_at_done: bool = True, device="cpu"
    ):
        self.gamma, self.clip, self.enabled, self.reset_at_done = gamma, clip, enabled, reset_at_done
        self.ret = torch.zeros(num_envs, dtype=torch.float64, device=device)
        self.rms = RunningMeanStd(device=device)

    def __call__(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """reward, done [E] -> scaled reward [E] (float32)."""
        if not self.enabled:
            return reward.float()
        self.ret = self.ret * self.gamma + reward.double()
        self.rms.update(self.ret)
        scaled = torch.clamp(reward.double() / torch.sqrt(self.rms.var + 1e-8), -self.clip, self.clip)
        if self.reset_at_done:
            self.ret = self.ret * (~done).double()
        return scaled.float()

    def state_dict(self) -> dict:
        return {"ret": self.ret.cpu(), "rms": self.rms.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        if d["ret"].shape != self.ret.shape:
            raise ValueError("reward normaliser was saved for a different number of environments")
        self.ret = d["ret"].to(self.ret.device)
        self.rms.load_state_dict(d["rms"])


# ----------------------------------------------------------------------------- 3. rollout


def sample_actions(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """logits [..., A] -> (sampled actions [...] int64, their log-probabilities [...])."""
    logp = torch.log_softmax(logits, dim=-1)
    flat = logp.reshape(-1, logp.shape[-1])
    actions = torch.multinomial(flat.exp(), 1, True)  # [n, 1], as Categorical.sample draws
    return actions.view(logp.shape[:-1]), flat.gather(-1, actions).view(logp.shape[:-1])


def drop_messages(inputs: dict, rate: torch.Tensor) -> None:
    """Drop each message of one step's stored graph with its environment's ``rate`` [E], in
    place (the buffer then holds the graph the agents heard, so the update sees it too). An
    agent always keeps its own state: the dense graph's diagonal is never dropped."""
    graph = inputs["adj"] if "adj" in inputs else inputs["nbr_mask"]  # [E, (R,) M, M | K]
    keep = torch.rand(graph.shape, device=graph.device) >= rate.view(-1, *[1] * (graph.dim() - 1))
    if "adj" in inputs:
        keep.diagonal(dim1=-2, dim2=-1).fill_(True)  # (neighbour lists hold others only)
    graph &= keep


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


@torch.no_grad()
def collect_rollout(
    policy,
    env,
    obs: dict,
    buf: Rollout,
    scaler: RewardScaler,
    p,
    device,
    message_drop: float = 0.0,
    per_agent: bool = False,
) -> RolloutResult:
    """T steps of every environment with sampled actions into ``buf`` [T, E, M, ...];
    then per-agent GAE and advantage normalisation (``p``: a PPOConfig). ``message_drop``
    > 0: each environment drops messages at a rate drawn from [0, message_drop] for the
    rollout (TrainConfig.message_drop). ``per_agent``: each agent's own reward terms
    (info["agent_reward"]) instead of the team's, normalised per agent slot (TrainConfig.reward)."""
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
        if per_agent:
            own = info["agent_reward"].to(device)  # [E, M]
            E, M = own.shape
            buf.rewards[t] = scaler(own.reshape(E * M), done.repeat_interleave(M)).view(E, M)
        else:
            buf.rewards[t] = scaler(reward, done).unsqueeze(-1)  # the team's reward, for each of its agents
        buf.dones[t] = done
        if bool(done.any()):
            ep = info["episode"]
            ep_success.append(ep["success"][done].cpu())
            ep_length.append(ep["length"][done].cpu())
            if p.bootstrap_time_limit:
                # an episode cut by the time limit did not end: GAE sees done and does not look
                # past it, so each agent's reward takes its own gamma * V(final state) here
                # (Pardo et al. 2018); the final state is the one before the env's auto-reset
                cut = done & ep["truncated"].to(device)
                if bool(cut.any()):
                    _, v_term = policy(**policy_inputs(info["terminal_obs"], device), fused=fused)  # [E, M]
                    buf.rewards[t] += p.gamma * v_term * cut.unsqueeze(-1)
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


# ----------------------------------------------------------------------------- 4. GAE


def gae(rewards, values, dones, next_value, gamma: float, lam: float):
    """Generalised advantage estimation, per agent.

    rewards [T, E, M], values [T, E, M], dones [T, E] (the episode ended at t, so no
    bootstrap from t+1), next_value [E, M] (value of the state after the last step)
    -> advantages, returns [T, E, M].
    """
    T = rewards.shape[0]
    advantages = torch.zeros_like(values)
    last = torch.zeros_like(next_value)
    for t in reversed(range(T)):
        v_next = next_value if t == T - 1 else values[t + 1]
        live = (~dones[t]).to(values.dtype).unsqueeze(-1)  # [E, 1]: one episode end for the whole team
        delta = rewards[t] + gamma * v_next * live - values[t]
        last = delta + gamma * lam * live * last
        advantages[t] = last
    return advantages, advantages + values


def normalize_per_agent(adv: torch.Tensor) -> torch.Tensor:
    """Normalise [..., M] advantages over every axis but the agent axis."""
    flat = adv.reshape(-1, adv.shape[-1])
    return ((flat - flat.mean(0)) / (flat.std(0) + 1e-8)).reshape(adv.shape)


# ----------------------------------------------------------------------------- 5. loss


@dataclasses.dataclass
class LossInfo:
    policy: torch.Tensor
    value: torch.Tensor
    entropy: torch.Tensor
    approx_kl: torch.Tensor
    clipfrac: torch.Tensor


def log_probs_and_entropy(logits: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """logits [..., A], actions [...] -> (log pi(a) [...], entropy [...]); what
    ``torch.distributions.Categorical`` computes, without building the object."""
    logp = torch.log_softmax(logits, dim=-1)
    chosen = logp.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    entropy = -(logp.exp() * logp).sum(-1)
    return chosen, entropy


def ppo_loss(
    logits,
    values,
    actions,
    old_logprobs,
    old_values,
    advantages,
    returns,
    clip: float,
    value_coef: float,
    entropy_coef: float,
):
    """The clipped PPO objective (to minimise) and its parts; every tensor [..., M]
    except logits [..., M, 5]. Value loss: 0.5 * max((v - R)^2, (v_clip - R)^2)."""
    logprobs, entropy = log_probs_and_entropy(logits, actions)
    log_ratio = logprobs - old_logprobs
    ratio = log_ratio.exp()
    pg = torch.max(-advantages * ratio, -advantages * torch.clamp(ratio, 1 - clip, 1 + clip)).mean()
    v_clipped = old_values + torch.clamp(values - old_values, -clip, clip)
    v_loss = 0.5 * torch.max((values - returns) ** 2, (v_clipped - returns) ** 2).mean()
    entropy = entropy.mean()
    total = pg + value_coef * v_loss - entropy_coef * entropy
    with torch.no_grad():
        approx_kl = ((ratio - 1) - log_ratio).mean()
        clipfrac = ((ratio - 1).abs() > clip).float().mean()
    return total, LossInfo(pg.detach(), v_loss.detach(), entropy.detach(), approx_kl, clipfrac)


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


# ----------------------------------------------------------------------------- 6. update


class NonFiniteTraining(ValueError):
    """The loss or gradients stayed NaN/inf: training stopped, the weights untouched."""


def all_finite(tensors) -> bool:
    """Whether every float tensor of ``tensors`` is finite: one fused norm per tensor and one
    host sync (~0.1 ms for the default network, a tenth of a loop of isfinite calls); a norm is
    NaN/inf when its tensor holds one (or when its squares overflow float32: entries of 1e16 and more,
    a broken run too)."""
    floats = [t.detach() for t in tensors if t.is_floating_point()]
    return bool(torch.isfinite(torch.stack(torch._foreach_norm(floats))).all()) if floats else True


def ppo_update(policy, optimizer, groups: list[tuple[Rollout, torch.Tensor, torch.Tensor]], p, loss_fn):
    """``p.epochs`` x ``p.minibatches`` clipped-PPO steps over the rollout; a minibatch is
    a set of whole teams (t, env) of one team size, since messages need every agent of the
    team. ``groups``: (buffer [T, E, M, ...], advantages, returns [T, E, M]) per team size;
    with several sizes each gets ``minibatches / len(groups)`` minibatches per epoch, taken
    in random order. Returns (the mean of the loss statistics [5], the number of
    minibatches skipped because their loss or gradient was not finite)."""
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


# ----------------------------------------------------------------------------- 7. iteration

MAX_BAD_UPDATES = 3  # consecutive updates with no finite minibatch before training stops


@dataclasses.dataclass
class TeamGroup:
    """The environments of one team size, with their rollout buffer and reward scaler."""

    agents: int
    env: object
    obs: dict
    buf: Rollout
    scaler: RewardScaler


@dataclasses.dataclass
class TrainingState:
    """Everything a checkpoint holds, live (trainer.rundir saves and restores it)."""

    policy: SwarmPolicy
    optimizer: torch.optim.Optimizer
    groups: list[TeamGroup]
    counters: dict  # update, env_steps, wall_time, skipped_minibatches
    evals: list[dict]
    bad_updates: int = 0  # consecutive updates without one finite minibatch


def fresh_counters() -> dict:
    return {"update": 0, "env_steps": 0, "wall_time": 0.0, "skipped_minibatches": 0}


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


def one_update(state: TrainingState, cfg, loss_fn, device: str) -> dict:
    """Rollout -> advantages -> clipped-PPO epochs for every team size (``cfg``: a
    TrainConfig); returns the update's metrics record."""
    p = cfg.ppo
    t0 = time.perf_counter()
    if p.lr_end is not None:  # linear decay from lr to lr_end over the run
        frac = state.counters["update"] / max(cfg.updates - 1, 1)
        state.optimizer.param_groups[0]["lr"] = p.lr + (p.lr_end - p.lr) * min(frac, 1.0)
    rollouts = []
    for g in state.groups:
        rollouts.append(
            collect_rollout(
                state.policy,
                g.env,
                g.obs,
                g.buf,
                g.scaler,
                p,
                device,
                cfg.message_drop,
                cfg.reward == "agent",
            )
        )
        g.obs = rollouts[-1].next_obs
    tc = time.perf_counter()
    torch.set_num_threads(cfg.torch_threads)
    batches = [(g.buf, r.advantages, r.returns) for g, r in zip(state.groups, rollouts, strict=True)]
    stats, skipped = ppo_update(state.policy, state.optimizer, batches, p, loss_fn)
    if device.startswith("cuda"):
        torch.cuda.synchronize()  # the update's kernels are queued: time them, not their launch
    t_update = time.perf_counter() - tc
    state.counters["skipped_minibatches"] += skipped
    # (a stats row of NaN: no finite minibatch; with several sizes there may be fewer than
    # epochs * minibatches of them, so the count is not the test)
    state.bad_updates = state.bad_updates + 1 if bool(torch.isnan(stats).all()) else 0
    if state.bad_updates >= MAX_BAD_UPDATES:
        raise NonFiniteTraining(
            f"every minibatch of the last {state.bad_updates} updates had a NaN/inf loss or gradient; "
            "stopped before any reached the weights. Lower --ppo.lr or check the configuration"
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
