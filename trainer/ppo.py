"""PPO pieces (Schulman et al. 2017), in the style of CleanRL's ppo.py and the
pytorch-a2c-ppo code the paper ran: rollout storage, reward scaling, GAE,
the clipped losses. Shapes: T steps, E envs, M agents."""

from __future__ import annotations

from dataclasses import dataclass

import torch


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

    The team reward is the same for every agent, so one return per environment.
    ``reset_at_done=False`` is what the paper's published code did: the running return
    is never reset at episode ends, so it grows towards r / (1 - gamma) and the scaled
    rewards are smaller (the usual VecNormalize resets it).
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


# the observation tensors a rollout stores, by the policy's argument names (trainer.model.OBS_INPUTS)
DENSE_INPUTS = ("self_obs", "entities", "adj")
LIST_INPUTS = ("self_obs", "entities", "nbr", "nbr_mask")


@dataclass
class Rollout:
    """Preallocated rollout storage, time first: [T, E, M, ...]. The communication graph is
    either dense (``adj``) or neighbour lists (``nbr``, ``nbr_mask``; ``entity_mask`` with
    landmark lists), as the simulator observes it."""

    self_obs: torch.Tensor  # [T, E, M, 4]
    entities: torch.Tensor  # [T, E, M, L, 2] (L: KL with landmark lists)
    adj: torch.Tensor | None  # [T, E, M, M] bool (dense)
    actions: torch.Tensor  # [T, E, M] int64
    logprobs: torch.Tensor  # [T, E, M]
    values: torch.Tensor  # [T, E, M]
    rewards: torch.Tensor  # [T, E] (scaled team reward)
    dones: torch.Tensor  # [T, E] bool: the episode ended at this step
    nbr: torch.Tensor | None = None  # [T, E, M, K] int32 (lists)
    nbr_mask: torch.Tensor | None = None  # [T, E, M, K] bool
    entity_mask: torch.Tensor | None = None  # [T, E, M, KL] bool (landmark lists)

    @classmethod
    def allocate(
        cls, T: int, E: int, M: int, L: int, device="cpu", neighbours: int | None = None, entity_mask: bool = False
    ) -> Rollout:
        """``neighbours``: K of the simulator's lists (None: dense adj); ``entity_mask``: the
        observation has landmark lists (L is then their KL)."""
        z = dict(device=device)
        lists = neighbours is not None
        return cls(
            self_obs=torch.zeros(T, E, M, 4, **z),
            entities=torch.zeros(T, E, M, L, 2, **z),
            adj=None if lists else torch.zeros(T, E, M, M, dtype=torch.bool, **z),
            actions=torch.zeros(T, E, M, dtype=torch.int64, **z),
            logprobs=torch.zeros(T, E, M, **z),
            values=torch.zeros(T, E, M, **z),
            rewards=torch.zeros(T, E, **z),
            dones=torch.zeros(T, E, dtype=torch.bool, **z),
            nbr=torch.zeros(T, E, M, neighbours, dtype=torch.int32, **z) if lists else None,
            nbr_mask=torch.zeros(T, E, M, neighbours, dtype=torch.bool, **z) if lists else None,
            entity_mask=torch.zeros(T, E, M, L, dtype=torch.bool, **z) if entity_mask else None,
        )

    @classmethod
    def for_env(cls, T: int, env, device="cpu") -> Rollout:
        """Storage shaped like ``env``'s observation (dense or lists)."""
        obs = env.obs
        nbr = obs.get("nbr")
        return cls.allocate(
            T, env.num_envs, env.num_agents, obs["entities"].shape[-2], device,
            neighbours=None if nbr is None else nbr.shape[-1], entity_mask="entity_mask" in obs,
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
            buf = getattr(self, name)[t]
            buf.copy_(obs[keys.get(name, name)])
            out[name] = buf
        return out


def gae(rewards, values, dones, next_value, gamma: float, lam: float):
    """Generalised advantage estimation, per agent.

    rewards [T, E] (team), values [T, E, M], dones [T, E] (episode ended at t, so
    no bootstrap from t+1), next_value [E, M] (value of the state after the last
    step) -> advantages, returns [T, E, M].
    """
    T = rewards.shape[0]
    advantages = torch.zeros_like(values)
    last = torch.zeros_like(next_value)
    for t in reversed(range(T)):
        v_next = next_value if t == T - 1 else values[t + 1]
        live = (~dones[t]).to(values.dtype).unsqueeze(-1)  # [E, 1]
        delta = rewards[t].unsqueeze(-1) + gamma * v_next * live - values[t]
        last = delta + gamma * lam * live * last
        advantages[t] = last
    return advantages, advantages + values


def normalize_per_agent(adv: torch.Tensor) -> torch.Tensor:
    """Normalise [..., M] advantages over every axis but the agent axis."""
    flat = adv.reshape(-1, adv.shape[-1])
    return ((flat - flat.mean(0)) / (flat.std(0) + 1e-8)).reshape(adv.shape)


@dataclass
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


def sample_actions(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """logits [..., A] -> (sampled actions [...] int64, their log-probabilities [...])."""
    logp = torch.log_softmax(logits, dim=-1)
    flat = logp.reshape(-1, logp.shape[-1])
    actions = torch.multinomial(flat.exp(), 1, True)  # [n, 1], as Categorical.sample draws
    return actions.view(logp.shape[:-1]), flat.gather(-1, actions).view(logp.shape[:-1])


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
