"""The agent-entity graph network of Agarwal, Kumar, Sycara 2019 (s.4 of
docs/PAPER.md), one set of weights shared by every agent.

Per agent i (all agents of a team batched, N teams, M agents, L landmarks):
    h_i = ReLU(f_a(X_i))                                   agent encoder, X_i = (vel, pos)
    EMP: e_l = ReLU(f_e(landmark_l - pos_i));  m_e = Attn(h_i, {e_l})
         h_i = ReLU(W_e [h_i ; m_e])
    K rounds (same weights): m_i = Attn(h_i, {h_j : j in N(i), i included})
         h_i = ReLU(W_c [h_i ; m_i])
    logits_i = pi(h_i) [5];  value_i = V(h_i)
The graph comes in one of two layouts, the same function on both:
- dense: adj [N, M, M] bool (adj[n, i, j]: i hears j, the diagonal true), every
  agent attending over all M (masked); what the paper's team sizes use;
- neighbour lists: nbr [N, M, K] int (indices of the agents i hears, self
  excluded) with nbr_mask [N, M, K] bool; each round gathers the K listed
  agents' embeddings and attends over [self; listed], so the cost per agent
  depends on K, not on M. ``entity_mask`` [N, M, L] marks the landmark slots an
  agent senses (landmark lists); a masked slot is the same as a landmark left out.
Masked, with no scatter in the per-agent pieces, so they export to ONNX; the
parameter count depends on neither M nor L (except the "concat" entity mode,
whose input width is fixed by the task's L).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, fields
from typing import NamedTuple

import torch
from torch import nn

# the observation layout and the actions are defined once, there
from taichi_swarm.constants import EDGE_POSITIONS, ENTITY_MODES, NUM_ACTIONS, NUM_FINE_ACTIONS
from taichi_swarm.layout import SELF_DIM

MAX_ROUNDS = 64  # message rounds (the export manifest's schema has the same bound)
MAX_HIDDEN = 4096  # hidden width: 4096 is ~170 M weights, 0.7 GB
PADDED_SLOTS = 10  # the paper's "without EMP" baseline: 10 landmarks x 2 = 20 inputs
MASK_FILL = -1e9  # finite: an all-masked row must not turn into NaN (and exports cleanly)
SELF_POSITIONS = ("absolute", "none")

# the simulator's observation keys -> the forward's arguments (``policy_inputs``)
OBS_INPUTS = {
    "self": "self_obs",
    "entities": "entities",
    "adj": "adj",
    "nbr": "nbr",
    "nbr_mask": "nbr_mask",
    "entity_mask": "entity_mask",
}


def policy_inputs(obs: dict, device=None) -> dict:
    """An observation dict of the simulator (dense or neighbour lists) -> the keyword
    arguments of ``SwarmPolicy.forward`` (the keys the observation has, on ``device``)."""
    out = {arg: obs[key] for key, arg in OBS_INPUTS.items() if key in obs}
    if "adj" not in out and "nbr" not in out:
        raise ValueError("the observation has neither 'adj' nor 'nbr': no communication graph")
    if device is not None:
        out = {k: v.to(device) for k, v in out.items()}
    return out


def neighbour_slots(nbr: torch.Tensor, nbr_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """nbr, nbr_mask [N, M, K] -> (slots [N, M, 1 + K] int64, mask [N, M, 1 + K] bool):
    the agent itself first (always heard, as the dense adj's diagonal), then its list.

    A padded slot (masked, any index, -1 included) points at the agent itself so the
    gather stays in range; a listed index equal to the agent's own is masked, so self
    is never counted twice whatever the simulator pads with.
    """
    if nbr.shape != nbr_mask.shape or nbr.dim() != 3:
        raise ValueError(f"nbr and nbr_mask must both be [N, M, K], got {tuple(nbr.shape)} and {tuple(nbr_mask.shape)}")
    N, M, _ = nbr.shape
    me = torch.arange(M, device=nbr.device).view(1, M, 1).expand(N, M, 1)
    nbr = nbr.long()
    mask = nbr_mask.bool() & (nbr != me) & (nbr >= 0) & (nbr < M)
    slots = torch.cat([me, torch.where(mask, nbr, me)], dim=-1)
    return slots, torch.cat([torch.ones_like(me, dtype=torch.bool), mask], dim=-1)


def gather_agents(x: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """x [N, M, D], slots [N, M, S] (agent indices within each team) -> [N, M, S, D]."""
    N, M, D = x.shape
    S = slots.shape[-1]
    flat = (slots + torch.arange(N, device=slots.device).view(N, 1, 1) * M).reshape(-1)
    return x.reshape(N * M, D).index_select(0, flat).view(N, M, S, D)


def lists_to_adj(slots: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """[self; listed] slots and mask [N, M, S] -> the dense adj [N, M, M] bool they describe."""
    N, M, _ = slots.shape
    heard = mask.new_zeros(N, M, M, dtype=torch.float32).scatter_add_(-1, slots, mask.float())
    return heard > 0


def lists_to_dense(weights: torch.Tensor, slots: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Attention over [self; listed] [N, M, S] -> the dense [N, M, M] (what recordings draw)."""
    N, M, _ = weights.shape
    dense = weights.new_zeros(N, M, M)
    return dense.scatter_add_(-1, slots, weights * mask.to(weights.dtype))


_FIELD_KINDS = {"int": int, "str": str, "bool": bool}  # ModelConfig's annotations (strings: future annotations)


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the policy; stored in every checkpoint and export manifest."""

    hidden: int = 128
    """Width of every hidden layer and message."""
    rounds: int = 3
    """K: rounds of inter-agent attention (same weights each round)."""
    entity_mode: str = "emp"
    """"emp": attention over landmarks (the paper's method, any L); "concat": landmark
    offsets concatenated into the agent input (the published code for formation/line,
    fixed L); "padded": the paper's "without EMP" baseline, 10 zero-padded slots."""
    num_landmarks: int = 0
    """L the "concat" mode was built for (unused otherwise; 0: the trainer takes the task's)."""
    self_position: str = "absolute"
    """"absolute": an agent's input holds its own position (px, py), as the paper's does;
    "none": zeroed, so everything the agent sees is its velocity and relative offsets. A
    density-scaled arena (scale="density") grows as sqrt(M), and absolute positions there
    leave the range seen in training; relative inputs are what a robot without a shared
    frame has too (docs/SWARM.md)."""
    edge_position: str = "none"
    """"none": a message is the sender's key and value alone (the paper); "relative": the
    receiver adds what it measures of the sender, the offset p_j - p_i, to both
    (k_ij = W_k h_j + E_k (p_j - p_i), likewise v_ij), so agents without a shared frame
    still know where their neighbours are. E_k, E_v start at zero: a policy without them
    is the same function with them, and may be fine-tuned into them (docs/SWARM.md)."""
    landmark_occupancy: bool = False
    """Each landmark input is (dx, dy, occupancy), the simulator's ``landmark_occupancy``
    (its distance to the nearest other agent): a third encoder input through its own weights,
    which start at zero, so a policy without it is the same function with it and may be
    fine-tuned into it ("emp" only; the trainer sets it from ``landmark_occupancy``)."""

    num_actions: int = NUM_ACTIONS
    """Logits of the policy head: the simulator's actions, 5 (the paper's) or 9 with
    ``action_space="fine"`` (the trainer sets it from that)."""

    def __post_init__(self):
        # types first: a crafted or hand-edited config (hidden = 128.0, rounds = True) must be
        # refused here, by field, not deep inside torch's layer constructors
        for f in fields(self):
            value = getattr(self, f.name)
            kind = _FIELD_KINDS[f.type]
            if kind is int:
                # bool is an int subclass and 3.0 == 3: both are refused, neither is what was written
                if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                    raise ValueError(f"{f.name} must be an integer, got {value!r} ({type(value).__name__})")
                object.__setattr__(self, f.name, int(value))  # (a numpy integer -> int: configs are JSON)
            elif not isinstance(value, kind):
                raise ValueError(f"{f.name} must be a {kind.__name__}, got {value!r} ({type(value).__name__})")
        if self.num_actions not in (NUM_ACTIONS, NUM_FINE_ACTIONS):
            raise ValueError(f"num_actions must be {NUM_ACTIONS} or {NUM_FINE_ACTIONS}, got {self.num_actions!r}")
        if self.entity_mode not in ENTITY_MODES:
            raise ValueError(f"entity_mode must be one of {ENTITY_MODES}, got {self.entity_mode!r}")
        if self.self_position not in SELF_POSITIONS:
            raise ValueError(f"self_position must be one of {SELF_POSITIONS}, got {self.self_position!r}")
        if self.edge_position not in EDGE_POSITIONS:
            raise ValueError(f"edge_position must be one of {EDGE_POSITIONS}, got {self.edge_position!r}")
        if self.hidden < 1 or self.rounds < 0:
            raise ValueError(f"hidden must be >= 1 and rounds >= 0, got {self.hidden}, {self.rounds}")
        if self.num_landmarks < 0:
            raise ValueError(f"num_landmarks must be >= 0, got {self.num_landmarks}")
        if self.landmark_occupancy and self.entity_mode != "emp":
            raise ValueError(f"landmark_occupancy needs entity_mode 'emp', got {self.entity_mode!r}")

    @property
    def entity_features(self) -> int:
        """Features of one landmark input: the offset (dx, dy), and its occupancy if taken."""
        return 3 if self.landmark_occupancy else 2

    def landmark_misfit(self, L: int) -> str:
        """Why this network cannot take ``L`` landmarks ("" when it can)."""
        if self.entity_mode == "padded" and L > PADDED_SLOTS:
            return f"entity_mode 'padded' holds at most {PADDED_SLOTS} landmarks, got {L}"
        if self.entity_mode == "concat" and L != self.num_landmarks:
            return f"this policy concatenates {self.num_landmarks} landmark offsets, got {L}"
        return ""

    def input_dim(self) -> int:
        if self.entity_mode == "concat":
            return SELF_DIM + 2 * self.num_landmarks
        if self.entity_mode == "padded":
            return SELF_DIM + 2 * PADDED_SLOTS
        return SELF_DIM

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        """A stored config: ``to_dict``'s, or one written while ``goal_pass`` (a goal network,
        an experiment since removed) was a field, where it is false in every shipped file."""
        d = dict(d)
        if d.get("goal_pass") is True:
            raise ValueError("goal_pass: this policy has a goal network, which this version no longer supports")
        if d.get("goal_pass") is False:
            del d["goal_pass"]
        return cls(**d)


class Attention(nn.Module):
    """Single-head scaled dot-product attention with W_q, W_k, W_v, W_out (no bias).

    Written out (matmul, masked fill, softmax) rather than with
    F.scaled_dot_product_attention: that exports differently on fully masked rows
    and fails on zero keys (docs/PAPER.md s.8).
    """

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim
        self.w_q = nn.Linear(dim, dim, bias=False)
        self.w_k = nn.Linear(dim, dim, bias=False)
        self.w_v = nn.Linear(dim, dim, bias=False)
        self.w_out = nn.Linear(dim, dim, bias=False)

    def attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None = None):
        """q [..., Q, D] (projected), k, v [..., S, D] (projected), mask [..., Q, S] bool.

        Returns (output [..., Q, D], weights [..., Q, S]); masked pairs get weight 0,
        a row with no key at all outputs 0.
        """
        scores = q @ k.transpose(-1, -2) / math.sqrt(self.dim)
        if mask is not None:
            scores = scores.masked_fill(~mask, MASK_FILL)
        weights = torch.softmax(scores, dim=-1)
        if mask is not None:
            weights = weights * mask.to(weights.dtype)
        return self.w_out(weights @ v), weights


class FusedWeights(NamedTuple):
    """Weight products of ``SwarmPolicy.forward`` (see ``SwarmPolicy.fused_weights``)."""

    entity: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None  # EMP: own [H, 2H], own_bias [2H], heard [H, H]
    comm: tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # the communication round, same layout
    heads: tuple[torch.Tensor, torch.Tensor]  # first layers of both heads: [H, 2H], [2H]
    # edge_position "relative": h -> its score with an offset [H, 2], pooled offset -> update [2, H]
    edge: tuple[torch.Tensor, torch.Tensor] | None = None


class SwarmPolicy(nn.Module):
    """Shared actor-critic: ``forward(self_obs, entities, adj) -> (logits, value)``, or
    ``forward(self_obs, entities, nbr=..., nbr_mask=..., entity_mask=...)`` on lists.

    self_obs [N, M, 4], entities [N, M, L, 2], adj [N, M, M] bool (adj[n, i, j]: i hears j)
    -> logits [N, M, A] (A = config.num_actions), value [N, M].
    """

    def __init__(self, config: ModelConfig = ModelConfig()):
        super().__init__()
        if config.entity_mode == "concat" and config.num_landmarks < 1:
            raise ValueError("entity_mode='concat' needs num_landmarks >= 1 (the trainer takes the task's)")
        self.config = config
        H = config.hidden
        self.agent_encoder = nn.Linear(config.input_dim(), H)
        if config.entity_mode == "emp":
            self.entity_encoder = nn.Linear(2, H)
            if config.landmark_occupancy:
                self.entity_occupancy = nn.Linear(1, H, bias=False)
            self.entity_attention = Attention(H)
            self.entity_update = nn.Linear(2 * H, H)
        self.comm_attention = Attention(H)
        self.comm_update = nn.Linear(2 * H, H)
        if config.edge_position == "relative":
            self.edge_key = nn.Linear(2, H, bias=False)
            self.edge_value = nn.Linear(2, H, bias=False)
        self.policy_head = nn.Sequential(nn.Linear(H, H), nn.ReLU(), nn.Linear(H, config.num_actions))
        self.value_head = nn.Sequential(nn.Linear(H, H), nn.ReLU(), nn.Linear(H, 1))
        self._init_weights()

    def _init_weights(self) -> None:
        # s.4.6: orthogonal gain 1 and zero bias on every Linear; attention matrices U(+-1/sqrt(H)).
        bound = 1.0 / math.sqrt(self.config.hidden)
        for module in self.modules():
            if isinstance(module, Attention):
                for lin in (module.w_q, module.w_k, module.w_v, module.w_out):
                    nn.init.uniform_(lin.weight, -bound, bound)
        attention_linears = {id(m) for a in self.modules() if isinstance(a, Attention) for m in a.children()}
        for module in self.modules():
            if isinstance(module, nn.Linear) and id(module) not in attention_linears:
                nn.init.orthogonal_(module.weight, gain=1.0)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
        if self.config.edge_position == "relative":  # zero: the paper's network until trained
            nn.init.zeros_(self.edge_key.weight)
            nn.init.zeros_(self.edge_value.weight)
        if self.config.landmark_occupancy:  # likewise: the network without occupancy until trained
            nn.init.zeros_(self.entity_occupancy.weight)

    # --- the three pieces one agent runs (deploy/ exports exactly these) -----------------
    def own_input(self, self_obs: torch.Tensor) -> torch.Tensor:
        """The agent's own observation as the encoder takes it: (vx, vy, px, py), or with
        self_position "none" (vx, vy, 0, 0) (zeroed, not dropped: the encoder's shape, and so
        every checkpoint, is the same either way)."""
        if self.config.self_position == "none":
            return torch.cat([self_obs[..., :2], torch.zeros_like(self_obs[..., 2:])], dim=-1)
        return self_obs

    def encode(
        self,
        self_obs: torch.Tensor,
        entities: torch.Tensor,
        entity_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """[..., 4], [..., L, 2] (and the sensed slots [..., L] bool) -> h [..., H]: agent
        encoder and entity message passing."""
        mode = self.config.entity_mode
        self._check_entity_mask(entities, entity_mask)
        self_obs = self.own_input(self_obs)
        if mode == "emp":
            h = torch.relu(self.agent_encoder(self_obs))
            e = self.embed_entities(entities)  # [..., L, H]
            att = self.entity_attention
            q, k = att.w_q(h).unsqueeze(-2), att.w_k(e)  # [..., 1, H], [..., L, H]
            mask = None if entity_mask is None else entity_mask.unsqueeze(-2)  # [..., 1, L]
            m_e, _ = att.attend(q, k, att.w_v(e), mask)
            return torch.relu(self.entity_update(torch.cat([h, m_e.squeeze(-2)], dim=-1)))
        if entity_mask is not None:  # "padded": an unsensed slot is a zero slot, as the padding is
            entities = entities * entity_mask.unsqueeze(-1).to(entities.dtype)
        flat = entities.flatten(-2)  # [..., 2L]
        L = entities.shape[-2]
        misfit = self.config.landmark_misfit(L)
        if misfit:
            raise ValueError(misfit)
        if mode == "padded":
            flat = nn.functional.pad(flat, (0, 2 * (PADDED_SLOTS - L)))
        return torch.relu(self.agent_encoder(torch.cat([self_obs, flat], dim=-1)))

    def embed_entities(self, entities: torch.Tensor) -> torch.Tensor:
        """EMP's landmark embeddings relu(W e + b) [..., L, H], W e + b + w_o * occupancy with
        landmark occupancy."""
        e = self.entity_encoder(entities[..., :2])
        if self.config.landmark_occupancy:
            e = e + self.entity_occupancy(entities[..., 2:])
        return torch.relu(e)

    def _check_entity_mask(self, entities: torch.Tensor, entity_mask: torch.Tensor | None) -> None:
        F = self.config.entity_features
        if entities.shape[-1] != F:
            raise ValueError(
                f"entities must hold {F} features per landmark"
                + (" (dx, dy, occupancy: the simulator's landmark_occupancy)" if F == 3 else " (dx, dy)")
                + f", got {entities.shape[-1]}"
            )
        if entity_mask is None:
            return
        if self.config.entity_mode == "concat":
            raise ValueError(
                "entity_mode 'concat' takes every landmark; landmark lists (entity_mask) need 'emp' or 'padded'"
            )
        if entity_mask.shape != entities.shape[:-1]:
            raise ValueError(f"entity_mask must be {tuple(entities.shape[:-1])}, got {tuple(entity_mask.shape)}")

    def message(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What an agent sends its neighbours: its attention key and value [..., H] each."""
        return self.comm_attention.w_k(h), self.comm_attention.w_v(h)

    def update(
        self,
        h: torch.Tensor,
        keys: torch.Tensor,
        values: torch.Tensor,
        mask: torch.Tensor,
        offsets: torch.Tensor | None = None,
    ):
        """One communication round: h [..., Q, H] attends over keys/values [..., S, H]
        heard (mask [..., Q, S]); with edge_position "relative", ``offsets`` [..., Q, S, 2]
        (p_j - p_i, as receiver i measures sender j) are added to each key and value.
        Returns (new h [..., Q, H], attention weights [..., Q, S])."""
        att = self.comm_attention
        if self.config.edge_position == "relative":
            if offsets is None:
                raise ValueError('edge_position "relative" needs the offsets of the heard agents')
            q = att.w_q(h).unsqueeze(-2)  # [..., Q, 1, H]: one query per receiver, keys per edge
            k = keys.unsqueeze(-3) + self.edge_key(offsets)  # [..., Q, S, H]
            v = values.unsqueeze(-3) + self.edge_value(offsets)
            edge_mask = None if mask is None else mask.unsqueeze(-2)  # [..., Q, 1, S]
            m, weights = att.attend(q, k, v, edge_mask)
            m, weights = m.squeeze(-2), weights.squeeze(-2)
        else:
            m, weights = att.attend(att.w_q(h), keys, values, mask)
        return torch.relu(self.comm_update(torch.cat([h, m], dim=-1))), weights

    def heads(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """h [..., H] -> logits [..., 5], value [...]."""
        return self.policy_head(h), self.value_head(h).squeeze(-1)

    # --- the whole team at once (training, rollouts, evaluation) --------------------------
    def fused_weights(self) -> FusedWeights:
        """The products of weight matrices the fast forward uses (differentiable)."""
        H = self.config.hidden
        scale = 1.0 / math.sqrt(H)

        def fuse(att: Attention, upd: nn.Linear) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            # scores_ij = (h_i W_q^T)(x_j W_k^T)^T / sqrt(H) = (h_i [W_q^T W_k / sqrt(H)]) . x_j
            # update   = W_u [h_i ; (sum_j w_ij x_j) W_v^T W_out^T] + b
            #          = h_i W_u1^T + (sum_j w_ij x_j) [W_v^T W_out^T W_u2^T] + b
            qk = (att.w_q.weight.t() @ att.w_k.weight) * scale  # [H, H]
            own = torch.cat([qk, upd.weight[:, :H].t()], dim=1)  # [H, 2H]: h -> (query, own part)
            own_bias = torch.cat([upd.bias.new_zeros(H), upd.bias])  # [2H]
            heard = att.w_v.weight.t() @ (att.w_out.weight.t() @ upd.weight[:, H:].t())  # [H, H]
            return own, own_bias, heard

        entity = fuse(self.entity_attention, self.entity_update) if self.config.entity_mode == "emp" else None
        comm = fuse(self.comm_attention, self.comm_update)
        p0, v0 = self.policy_head[0], self.value_head[0]
        heads = (torch.cat([p0.weight, v0.weight]).t(), torch.cat([p0.bias, v0.bias]))  # [H, 2H], [2H]
        edge = None
        if self.config.edge_position == "relative":
            # score_ij += (h_i W_q^T E_k / sqrt(H)) . r_ij; update += (sum_j w_ij r_ij) E_v^T W_out^T W_u2^T
            att, upd = self.comm_attention, self.comm_update
            edge = (
                (att.w_q.weight.t() @ self.edge_key.weight) * scale,  # [H, 2]
                self.edge_value.weight.t() @ (att.w_out.weight.t() @ upd.weight[:, H:].t()),  # [2, H]
            )
        return FusedWeights(entity, comm, heads, edge)

    def edge_offsets(self, self_obs: torch.Tensor, slots: torch.Tensor | None) -> torch.Tensor | None:
        """p_j - p_i of every heard pair (edge_position "relative"; else None), from the
        positions in self_obs [N, M, 4]: [N, M, M, 2] dense, [N, M, S, 2] over the lists' slots."""
        if self.config.edge_position != "relative":
            return None
        p = self_obs[..., 2:4]
        if slots is None:
            return p.unsqueeze(-3) - p.unsqueeze(-2)  # [n, i, j] = p_j - p_i
        return gather_agents(p, slots) - p.unsqueeze(-2)

    def _graph(self, self_obs, adj, nbr, nbr_mask):
        """The communication graph in either layout -> (adj per round, None) dense or
        (slots [N, M, S], mask per round [N, M, S]) on lists. A mask with a round axis
        (adj [N, R, M, M], nbr_mask [N, R, M, K], R the rounds) gives each round the messages
        that arrived in it, as a radio that loses messages per round does (training through
        faults, TrainConfig.drop_per_round); without, every round hears the same graph."""
        if (adj is None) == (nbr is None):
            raise ValueError("give the communication graph either dense (adj) or as lists (nbr, nbr_mask), not both")
        N, M = self_obs.shape[:2]
        R = self.config.rounds
        mask = adj if nbr is None else nbr_mask
        if mask is None:
            raise ValueError("nbr needs nbr_mask (which of the K slots hold a heard agent)")
        per_round = mask.dim() == 4
        if adj is not None:
            if adj.shape not in ((N, M, M), (N, R, M, M)):
                want = f"[N, M, M] = {(N, M, M)} or per round {(N, R, M, M)}"
                raise ValueError(f"adj must be {want}, got {tuple(adj.shape)}")
            return [adj[:, r] if per_round else adj for r in range(R)], None
        if nbr.shape[:2] != (N, M) or (per_round and nbr_mask.shape[1] != R):
            want = f"[N, M, K] with N, M = {N}, {M} (nbr_mask per round [N, {R}, M, K])"
            raise ValueError(f"nbr must be {want}, got {tuple(nbr.shape)}")
        if not per_round:
            slots, listed = neighbour_slots(nbr, nbr_mask)
            return [listed] * R, slots
        slots, _ = neighbour_slots(nbr, nbr_mask.any(1))  # a slot masked in a round points at self
        return [neighbour_slots(nbr, nbr_mask[:, r])[1] for r in range(R)], slots

    def forward(
        self,
        self_obs: torch.Tensor,
        entities: torch.Tensor,
        adj: torch.Tensor | None = None,
        return_attention: bool = False,
        fused: FusedWeights | None = None,
        *,
        nbr: torch.Tensor | None = None,
        nbr_mask: torch.Tensor | None = None,
        entity_mask: torch.Tensor | None = None,
    ):
        """self_obs [N, M, 4], entities [N, M, L, 2], and the graph: adj [N, M, M] or
        nbr, nbr_mask [N, M, K] (``entity_mask`` [N, M, L] with landmark lists)
        -> logits [N, M, A] (A = config.num_actions), value [N, M].(and the K rounds' attention with
        ``return_attention``: [N, M, M] dense, [N, M, 1 + K] on [self; listed] with lists).

        The same function as ``forward_reference`` (to float rounding), rearranged so that
        nothing is projected per landmark or per neighbour: the attention scores use
        W_q W_k^T on the query side and the weighted sum of embeddings is projected once,
        through W_v W_out folded into the update layer (docs/BENCHMARKS.md, training).
        ``fused``: ``fused_weights()`` computed once and reused while the weights do not
        change (rollouts, evaluation); recomputed per call otherwise (training).
        """
        masks, slots = self._graph(self_obs, adj, nbr, nbr_mask)
        self._check_entity_mask(entities, entity_mask)
        if slots is not None and not return_attention and self_obs.shape[1] <= slots.shape[-1]:
            # M <= 1 + K: the team fits in the lists, and the dense rounds over M are cheaper
            # than gathering 1 + K slots (the same function: the slots scattered into adj)
            masks, slots = [lists_to_adj(slots, m) for m in masks], None
        fw = self.fused_weights() if fused is None else fused
        h, _ = self._landmarks(self_obs, entities, entity_mask, fw)
        h, attention = self._rounds(h, self_obs, masks, slots, fw)
        H, N, M = self.config.hidden, self_obs.shape[0], self_obs.shape[1]
        w_heads, b_heads = fw.heads
        z = torch.relu(torch.addmm(b_heads, h, w_heads))  # [NM, 2H]
        logits = self.policy_head[2](z[:, :H]).view(N, M, -1)
        value = self.value_head[2](z[:, H:]).view(N, M)
        if return_attention:
            return logits, value, attention  # K x [N, M, M] or [N, M, 1 + K]
        return logits, value

    def _landmarks(self, self_obs, entities, entity_mask, fw):
        """``forward``'s landmark attention -> (h [NM, H], its scores [NM, L], unsensed slots
        MASK_FILL; None outside "emp")."""
        H = self.config.hidden
        N, M = self_obs.shape[0], self_obs.shape[1]
        if self.config.entity_mode != "emp":
            return self.encode(self_obs, entities, entity_mask).reshape(N * M, H), None
        h = torch.relu(self.agent_encoder(self.own_input(self_obs))).reshape(N * M, H)  # [NM, H]
        e = self.embed_entities(entities).reshape(N * M, -1, H)  # [NM, L, H]
        own, own_bias, heard = fw.entity
        q_own = torch.addmm(own_bias, h, own)  # [NM, 2H]
        # NOTE: broadcast-multiply-sum, not bmm: batched GEMMs of these tiny matrices
        # ran 3x slower forward+backward on the CPU (docs/BENCHMARKS.md, training)
        scores = (e * q_own[:, None, :H]).sum(-1)  # [NM, L]
        if entity_mask is None:
            weights = torch.softmax(scores, dim=-1)
        else:
            sensed = entity_mask.reshape(N * M, -1)
            scores = scores.masked_fill(~sensed, MASK_FILL)
            weights = torch.softmax(scores, dim=-1) * sensed.to(h.dtype)
        pooled = (weights.unsqueeze(-1) * e).sum(1)  # [NM, H]
        return torch.relu(torch.addmm(q_own[:, H:], pooled, heard)), scores

    def _rounds(self, h, self_obs, masks, slots, fw):
        """``forward``'s message rounds from h [NM, H] -> (h [NM, H], the rounds' attention)."""
        H = self.config.hidden
        N, M = self_obs.shape[0], self_obs.shape[1]
        own, own_bias, heard = fw.comm
        offsets = self.edge_offsets(self_obs, slots)  # [N, M, M, 2] dense, [N, M, S, 2] lists, or None
        if slots is not None:  # [N, M, S]: self, then the K listed
            S = slots.shape[-1]
            masks = [m.view(N * M, S) for m in masks]
            offsets = None if offsets is None else offsets.reshape(N * M, S, 2)
        attention = []
        shared = (~masks[0], masks[0].to(h.dtype)) if masks else None
        for heard_now in masks:  # the rounds, each with the messages that arrived in it
            blocked, heard_mask = shared if heard_now is masks[0] else (~heard_now, heard_now.to(h.dtype))
            q_own = torch.addmm(own_bias, h, own)  # [NM, 2H]
            if slots is None:
                h3 = h.view(N, 1, M, H)
                scores = (q_own[:, :H].reshape(N, M, 1, H) * h3).sum(-1)  # [N, M, M]
                if offsets is not None:
                    scores = scores + (offsets * (h @ fw.edge[0]).view(N, M, 1, 2)).sum(-1)
                weights = torch.softmax(scores.masked_fill(blocked, MASK_FILL), dim=-1) * heard_mask
                pooled = (weights.unsqueeze(-1) * h3).sum(2).view(N * M, H)
                if offsets is not None:
                    pooled_offset = (weights.unsqueeze(-1) * offsets).sum(2).view(N * M, 2)
            else:  # a gather of the S = 1 + K heard embeddings per agent: O(K), whatever M
                hs = gather_agents(h.view(N, M, H), slots).view(N * M, S, H)
                scores = (q_own[:, None, :H] * hs).sum(-1)  # [NM, S]
                if offsets is not None:
                    scores = scores + (offsets * (h @ fw.edge[0]).unsqueeze(1)).sum(-1)
                weights = torch.softmax(scores.masked_fill(blocked, MASK_FILL), dim=-1) * heard_mask
                pooled = (weights.unsqueeze(-1) * hs).sum(1)  # [NM, H]
                if offsets is not None:
                    pooled_offset = (weights.unsqueeze(-1) * offsets).sum(1)  # [NM, 2]
                weights = weights.view(N, M, S)
            update = torch.addmm(q_own[:, H:], pooled, heard)
            if offsets is not None:
                update = update + pooled_offset @ fw.edge[1]
            h = torch.relu(update)
            attention.append(weights)
        return h, attention

    def landmark_scores(self, self_obs, entities, adj=None, *, nbr=None, nbr_mask=None, entity_mask=None):
        """The landmark attention's scores [N, M, L] (unsensed slots MASK_FILL) that decide
        which landmarks an agent's summary holds."""
        masks, slots = self._graph(self_obs, adj, nbr, nbr_mask)
        self._check_entity_mask(entities, entity_mask)
        if self.config.entity_mode != "emp":
            raise ValueError("landmark scores need entity_mode 'emp'")
        return self._landmarks(self_obs, entities, entity_mask, self.fused_weights())[1].view(*self_obs.shape[:2], -1)

    def forward_reference(
        self, self_obs, entities, adj=None, return_attention=False, *, nbr=None, nbr_mask=None, entity_mask=None
    ):
        """The network written as the paper states it (the per-agent pieces deploy exports):
        with lists, each agent's query attends over the keys and values of [self; listed]."""
        masks, slots = self._graph(self_obs, adj, nbr, nbr_mask)
        h = self.encode(self_obs, entities, entity_mask)
        h, attention = self._rounds_reference(h, self_obs, masks, slots)
        logits, value = self.heads(h)
        if return_attention:
            return logits, value, attention  # K x [N, M, M] or [N, M, 1 + K]
        return logits, value

    def _rounds_reference(self, h, self_obs, masks, slots):
        """``forward_reference``'s message rounds from h [N, M, H] -> (h, the rounds' attention)."""
        offsets = self.edge_offsets(self_obs, slots)
        attention = []
        for listed in masks:
            keys, values = self.message(h)
            if slots is None:
                h, w = self.update(h, keys, values, listed, offsets)
            else:
                heard_k, heard_v = gather_agents(keys, slots), gather_agents(values, slots)  # [N, M, S, H]
                edge = None if offsets is None else offsets.unsqueeze(-3)  # [N, M, 1, S, 2]
                h, w = self.update(h.unsqueeze(-2), heard_k, heard_v, listed.unsqueeze(-2), edge)
                h, w = h.squeeze(-2), w.squeeze(-2)
            attention.append(w)
        return h, attention

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
