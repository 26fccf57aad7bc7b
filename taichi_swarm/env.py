"""``SwarmEnv``: a batch of B teams of M agents, stepped by fused Taichi kernels.

Shapes: B environments, M agents, L landmarks.
    obs["self"]      float32 [B, M, 4]     (vx, vy, px, py) of each agent
    obs["entities"]  float32 [B, M, L, 2]  landmark position - agent position
    obs["adj"]       bool    [B, M, M]     adj[b, i, j]: agent i hears agent j
  with neighbour lists (``neighbours=K``; no M x M block is allocated, obs has no "adj"):
    obs["nbr"]       int32   [B, M, K]     the K nearest agents i hears, nearest first,
                                           itself excluded; unused slots hold i itself
    obs["nbr_mask"]  bool    [B, M, K]     which slots hold a neighbour
  with landmark lists (``landmark_neighbours=KL``, ``sense_radius``):
    obs["entities"]  float32 [B, M, KL, 2] the KL nearest landmarks within sense_radius,
                                           nearest first, zeros where none
    obs["entity_mask"] bool  [B, M, KL]
  and with ``landmark_occupancy=True``:
    obs["entities"]  float32 [B, M, KL, 3] (dx, dy, occupancy): occupancy is the landmark's
                                           distance to its nearest agent other than the
                                           observer, capped at sense_radius
  and with ``landmark_order="radio"`` the one landmark the agent holds in the agents' own
  auction by messages (radio.py), or, holding none, the held ones listed last, reading 0
    actions          int64   [B, M]        discrete (default): 0..4, see ``step``
                     float32 [B, M, 2]     action_space="continuous": force 5 clip(u, -1, 1)
    reward           float32 [B]           team reward of the step just taken
    info["agent_reward"] float32 [B, M]    each agent's own reward terms summed (their mean:
                                           reward)
    info["reward_terms"] {name: float32 [B, M]}  each of the task's named terms (tasks/base.py)
    done             bool    [B]           the episode ended at this step
Every returned array is a zero-copy view of the env's preallocated buffers and
is overwritten by the next ``step``/``reset``: copy what you keep.
"""

from __future__ import annotations

import sys

import numpy as np

from . import assignment, kernels, nearest, neighbours, radio, rng, runtime
from .layout import (
    FLOAT_HEADER,
    H_COMM_RC,
    H_DENSITY,
    H_MAX_STEPS,
    H_ROUNDS,
    P_AGENT_RADIUS,
    P_ARENA,
    P_BID_EPS,
    P_CELL,
    P_COMM_RADIUS,
    P_LCELL,
    P_SENSE,
    P_SUCCESS,
    P_TASK_PARAM,
    P_TCELL,
    Layout,
    static_team_size,
)
from .physics import ACTION_DIM, CONTACT_MARGIN, CUTOFF_MARGINS, num_actions
from .sim import FIELDS, INT32_MAX, ConfigError, Sim, check_float, check_int, one_of
from .tasks import COMMON_PARAMS, TASK_SPECS

ARRAYS = ("torch", "numpy")
DENSITY_TEAM = 10  # scale="density" keeps the agents per unit area of this team size in the 2 x 2 arena
# Taichi's CPU thread pool costs ~120-250 us per parallel loop; a step's work grows
# like B * M^2 (contact pairs, assignment). Below this much work one thread is faster
# (crossover measured at M = 3, 5, 10 on 2 cores: B*M^2 between ~13k and ~37k).
SERIAL_BELOW_WORK = 32768
# With neighbour lists, from this many agents per step the CPU steps them agent by agent too
# (step_wide_kernel): its passes cost a thread-pool dispatch each, which loses below it (time
# ratio against one thread per env on 2 threads: 3.6 at B x M = 120, 1.0-1.2 at 600-1000,
# 0.81-0.84 at 2500-5000, 0.54-0.95 at 10,000; docs/SWARM.md)
WIDE_CPU_AGENTS = 2048

LARGE_TEAM = 64  # from this team size, say that kernels are compiling (it takes a while)
_ANNOUNCED_CAPACITIES: set[int] = set()


assignment_capacity = assignment.capacity  # the module name is taken by a keyword below


class NaNActionsError(ValueError):
    """Actions holding NaN, refused by ``SwarmEnv.step``: from a trainer, a policy whose weights
    diverged (a ValueError, so callers that treat it as bad input still do)."""


class SwarmEnv:
    """A batch of ``num_envs`` teams of ``num_agents`` agents for ``task`` (``taichi_swarm.make``).

    task: one of ``TASKS`` (coverage, formation, line). comm: "uc" (every
    agent hears every agent) or "rc" (within ``comm_radius``). arch: "cpu",
    "cuda"/"gpu" or "auto". array: "torch" or "numpy" outputs (numpy needs no
    torch). action_space: "discrete" (the paper's 5 actions, int64 [B, M]), "fine" (9: the
    paper's 5, then -x, +x, -y, +y at a quarter of the force, so an agent can park within
    0.035 of any point: physics.FINE) or "continuous" (MPE's continuous mode: float32
    [B, M, 2], force 5 clip(u, -1, 1) per axis). task_params: ``max_steps`` (50) and
    ``success_threshold`` for all tasks; ``formation_radius`` (formation); ``line_length`` (line).

    neighbours: K, each agent's K nearest heard agents as index lists (obs["nbr"],
    obs["nbr_mask"]) found through a cell grid, which also finds the contacts; no M x M
    adjacency. "rc": those within comm_radius; "uc": the K nearest of all.
    landmark_neighbours (coverage; formation and line with scale="density", whose landmarks are
    then their M targets) with sense_radius: each agent's KL nearest landmarks within sense_radius
    (obs["entities"] [B, M, KL, 2], obs["entity_mask"]).
    landmark_occupancy (with neighbours and landmark_neighbours): obs["entities"] [B, M, KL, 3],
    the third feature each listed landmark's distance to its nearest agent other than the
    observer, capped at sense_radius: whether someone else already holds it.
    landmark_order (with landmark_occupancy): "nearest" (the default), the KL nearest landmarks
    within sense_radius; or "radio" (with assignment "free"), the landmark the agent
    holds in an auction the agents run by messages alone (radio.py), listed alone (its reading
    floored at success_threshold: free to it). Each keeps its own table (landmark id, epoch,
    price, holder) over its KL nearest landmarks within sense_radius and merges, each of
    auction_rounds R rounds a step (None: radio.DEFAULT_ROUNDS = 4; at most radio.MAX_ROUNDS = 64),
    the tables of the teammates on its neighbour list; no state is shared per landmark. An agent
    that holds nothing lists the ones its own table says another holds last, reading 0.
    info["radio"]: "messages" and "bytes" [B] float32, the tables (radio.ENTRY_BYTES per entry)
    each agent received in the step, env means.
    scale: None (the paper's geometry) or "density" (coverage: the spawn square grows as
    sqrt(M / 10), keeping the agents per unit area of M = 10). See docs/SWARM.md.
    assignment: "exact" (Jonker-Volgenant on the M x M costs, warm-started) or "free" (needs
    neighbours; no M x M block, which M = 10,000 needs; every per-step quantity local and exact:
    each target's nearest-agent distance d_t (DIST), in matched_dist [B, M] per target; success
    and covered from a maximum matching within success_threshold, in assignment [B, M], -1 where
    unmatched; each agent's reward from the target the matching gives it or, where it has none,
    from the nearest target the matching leaves free: a duplicate is paid for crossing to a free
    target; the team reward is their mean, as in every mode. nearest.py, docs/SWARM.md).
    agent_parallel (with neighbours): step every agent of every environment in parallel
    (kernels.step_wide_kernel), not one environment per thread; the same results bit for bit.
    None (default): on CUDA, where one thread per environment leaves the GPU idle at small B,
    and on the CPU from WIDE_CPU_AGENTS (2048) agents per step.
    """

    def __init__(
        self,
        sim: Sim,
        num_envs: int,
        arch: str = "cpu",
        seed: int | None = None,
        array: str = "torch",
        agent_parallel: bool | None = None,
        **task_params,
    ):
        if not isinstance(sim, Sim):
            raise ConfigError("sim", f"SwarmEnv takes a taichi_swarm.Sim, got {type(sim).__name__} (make() builds one)")
        spec = TASK_SPECS[sim.task]
        self.sim = sim
        self.task = sim.task
        self.num_envs = check_int("num_envs", num_envs, 1, INT32_MAX)
        self.num_agents = sim.team_size("the setting")
        self.comm, self.comm_radius = sim.comm, sim.comm_radius
        self.neighbours, self.landmark_neighbours, self.sense_radius = (
            sim.neighbours, sim.landmark_neighbours, sim.sense_radius,
        )  # fmt: skip
        self.scale, self.assignment_method = sim.scale, sim.assignment
        self.landmark_occupancy, self.landmark_order = sim.landmark_occupancy, sim.landmark_order
        self.auction_rounds = sim.rounds
        # the bid increment, recorded so equal runs share a key (None: no auction)
        self.auction_eps = None if self.auction_rounds is None else radio.ROUND_EPS
        self.num_landmarks = spec.num_landmarks(self.num_agents, listed=sim.landmark_neighbours is not None)
        one_of("array", array, ARRAYS)
        self.array = array
        self.action_space = sim.action_space
        self.continuous = sim.action_space == "continuous"
        self._seed = None if seed is None else check_int("seed", seed, 0)
        allowed = {**COMMON_PARAMS, **spec.params}
        unknown = sorted(set(task_params) - set(allowed))
        if unknown:
            raise ConfigError(
                unknown[0], f"unknown parameter(s) {unknown} for task {sim.task!r}; known: {sorted(allowed)}"
            )
        params = {**allowed, **task_params}
        self.params = {
            k: (check_int(k, v, 1, INT32_MAX) if k == "max_steps" else check_float(k, v, 0.0))
            for k, v in params.items()
        }
        self.num_actions = num_actions(sim.action_space)  # discrete actions per agent (0: continuous)
        self.action_dim = ACTION_DIM  # continuous: float32 [B, M, 2]
        self._task_id = spec.task_id
        # spawn square half-width: sqrt(M / 10) keeps the agents per unit area of M = 10 in [-1, 1]^2
        self.arena = (self.num_agents / DENSITY_TEAM) ** 0.5 if sim.scale == "density" else 1.0
        # compile-time M for small teams, else 0; with lists the kernels are the same code for
        # every M (cap 0: no stack arrays sized by M; the dense physics is not compiled)
        self._sm = static_team_size(self.num_agents) if self.neighbours is None else 0
        self._cap = assignment_capacity(self.num_agents) if self.neighbours is None else 0
        self._lists = (
            (kernels.AGENT_LISTS if self.neighbours is not None else 0)
            | (kernels.LANDMARK_LISTS if self.landmark_neighbours is not None else 0)
            | (kernels.FREE if sim.assignment == "free" else 0)
            | (kernels.OCCUPANCY if sim.landmark_occupancy else 0)
            | (kernels.RADIO if sim.landmark_order == "radio" else 0)
        )

        self.arch = runtime.init(arch)
        if self.arch == "cuda" and array == "numpy":
            raise ConfigError("array", "array='numpy' needs arch='cpu': CUDA buffers are torch tensors")
        self.device = "cuda" if self.arch == "cuda" else "cpu"
        self._parallel = self.arch == "cuda" or self.num_envs * self.num_agents**2 >= SERIAL_BELOW_WORK
        one_of("agent_parallel", agent_parallel, (None, True, False))
        if agent_parallel and self.neighbours is None:
            raise ConfigError(
                "agent_parallel", "agent_parallel needs neighbours (the dense layout's step is all pairs per team)"
            )
        self._agent_parallel = self.neighbours is not None and (
            agent_parallel
            if agent_parallel is not None
            else self.arch == "cuda" or self.num_envs * self.num_agents >= WIDE_CPU_AGENTS
        )
        self.reward_terms = spec.reward_terms
        self.layout = Layout(
            self.num_envs, self.num_agents, self.num_landmarks, RT=len(spec.reward_terms), **self._list_dims()
        )
        if self.neighbours is None and self.num_agents >= LARGE_TEAM and self._cap not in _ANNOUNCED_CAPACITIES:
            _ANNOUNCED_CAPACITIES.add(self._cap)
            print(
                f"taichi_swarm: compiling kernels for teams of up to {self._cap} agents (first use in this "
                f"process; up to a minute at M = 1000; neighbour lists compile once for every M: docs/SWARM.md)",
                file=sys.stderr,
                flush=True,
            )
        self._allocate()
        self._write_header()
        self._seeded = False

    def _list_dims(self) -> dict:
        """The layout's named dimensions (layout.DIMS) for the lists this env keeps."""
        M, dims = self.num_agents, {}
        if self.neighbours is not None:
            dims.update(MA=0, K=self.neighbours, N=M, G1=neighbours.buckets(M, neighbours.SPLIT) + 1)
        if self.landmark_neighbours is not None:
            L = self.num_landmarks
            dims.update(
                LE=self.landmark_neighbours,
                KL=self.landmark_neighbours,
                LN=L,
                GL1=neighbours.buckets(L, neighbours.SPLIT) + 1,
            )
            if self.landmark_occupancy:
                dims.update(EF=3, LO=L)
            if self.landmark_order == "radio":  # candidates and each agent's own table; no per-landmark state
                dims.update(BM=M, RM=M)
        # a grid of the targets instead of the M x M costs
        if self.assignment_method == "free":  # nearest.py's grids: no M x M block
            dims.update(MC=0, TN=M, GT1=neighbours.buckets(M) + 1)
        return dims

    # ------------------------------------------------------------------ buffers
    def _allocate(self) -> None:
        sizes = self.layout.sizes
        dtypes = {"f32": np.float32, "i32": np.int32, "u8": np.uint8}
        if self.arch == "cuda":
            import torch

            tdt = {"f32": torch.float32, "i32": torch.int32, "u8": torch.uint8}
            self._bufs = {k: torch.zeros(sizes[k], dtype=tdt[k], device="cuda") for k in sizes}
            self._host = None
        else:
            self._host = {k: np.zeros(sizes[k], dtype=dtypes[k]) for k in sizes}
            if self.array == "torch":
                import torch

                self._bufs = {k: torch.from_numpy(v) for k, v in self._host.items()}
            else:
                self._bufs = self._host
        # Kernel arguments: numpy arrays on the CPU (cheaper to launch than torch
        # tensors; same memory), torch tensors on CUDA.
        kbufs = self._host if self._host is not None else self._bufs
        self._f, self._i, self._u8 = kbufs["f32"], kbufs["i32"], kbufs["u8"]
        v = self._view
        # int32 [B, M] block that step() copies the actions into
        self._actions_in = v("actions")
        self._actions_host = self._actions_in if isinstance(self._actions_in, np.ndarray) else None
        if self._host is not None and self._actions_host is None:
            self._actions_host = self._actions_in.numpy()
        self.obs = {"self": v("obs_self"), "entities": v("obs_entities")}
        term = {"self": v("term_self"), "entities": v("term_entities")}
        if self.neighbours is None:
            self.obs["adj"], term["adj"] = v("adj", bool), v("term_adj", bool)
        else:
            self.obs["nbr"], term["nbr"] = v("nbr"), v("term_nbr")
            self.obs["nbr_mask"], term["nbr_mask"] = v("nbr_mask", bool), v("term_nbr_mask", bool)
        if self.landmark_neighbours is not None:
            self.obs["entity_mask"], term["entity_mask"] = v("entity_mask", bool), v("term_entity_mask", bool)
        self.reward = v("reward")
        self.done = v("done", bool)
        self.info = {
            # valid where ``done``: the episode that just ended
            "episode": {
                "success": v("ep_success", bool),  # terminated by success
                "truncated": v("ep_truncated", bool),  # hit the time limit
                "length": v("ep_length"),
                "return": v("ep_return"),
                "matched_dist": v("ep_matched_dist"),  # [B, M] final d*_i (assignment="free": d_t per target)
                "dist": v("ep_dist"),  # DIST: mean target -> closest agent distance
                "covered": v("ep_covered"),  # fraction of targets matched within success_threshold
            },
            "terminal_obs": term,
            # [B, M] each agent's own reward for the step just taken: the task's named
            # per-agent terms (Task.reward_terms) summed; the team reward is their mean
            "agent_reward": v("agent_reward"),
            # {term: [B, M]} each of those terms by name (views of one [B, M, T] block)
            "reward_terms": {name: v("reward_terms")[..., k] for k, name in enumerate(self.reward_terms)},
        }
        if self.neighbours is not None:
            # of the lists in ``obs`` (after an auto-reset: the new episode's first)
            self.info["neighbours"] = {
                "in_range": v("in_range"),  # [B, M] how many agents each agent hears
                "dropped": v("dropped"),  # [B] heard but not listed (more than K), summed over agents
            }
        if self.landmark_order == "radio":
            # [B] float32, of the step just taken: messages (tables heard, summed over the rounds) and
            # their bytes (radio.ENTRY_BYTES per table entry) each agent received, the env's mean
            self.info["radio"] = {"messages": v("radio_messages"), "bytes": v("radio_bytes")}
        # current state extras (targets for drawing, d*_i, who is matched to what)
        self.targets = v("targets")  # [B, M, 2]
        # assignment="free": matched_dist[b, t] = d_t, target t's distance to its nearest agent, and
        # assignment[b, i] = agent i's target in the maximum matching within success_threshold, -1 if none
        self.matched_dist = v("matched_dist")  # [B, M]
        self.assignment = v("assignment")  # [B, M] target index of agent i

    def _view(self, name: str, as_bool: bool = False):
        blk = self.layout.blocks[name]
        n = int(np.prod(blk.shape, dtype=np.int64))
        out = self._bufs[blk.buffer][blk.offset : blk.offset + n].reshape(blk.shape)
        if as_bool:
            if isinstance(out, np.ndarray):
                return out.view(np.bool_)
            import torch

            return out.view(torch.bool)
        return out

    def _write_header(self) -> None:
        header = self.layout.header.copy()
        header[H_COMM_RC] = 1 if self.comm == "rc" else 0
        header[H_DENSITY] = 1 if self.scale == "density" else 0
        header[H_MAX_STEPS] = self.params["max_steps"]
        header[H_ROUNDS] = self.auction_rounds or 0  # the radio's message rounds a step
        spec = TASK_SPECS[self.task]
        fparams = np.zeros(FLOAT_HEADER, dtype=np.float32)
        fparams[P_COMM_RADIUS] = self.comm_radius
        fparams[P_AGENT_RADIUS] = spec.agent_radius
        fparams[P_SUCCESS] = self.params["success_threshold"]
        fparams[P_TASK_PARAM] = self.params.get(spec.kernel_param, 0.0)
        # the agents' grid: cells hold everything an agent hears ("rc") and touches
        contact_reach = 2.0 * spec.agent_radius + CUTOFF_MARGINS * CONTACT_MARGIN
        heard = self.comm_radius if self.comm == "rc" else 0.0
        fparams[P_CELL] = max(neighbours.cell_side(heard, neighbours.SPLIT), neighbours.cell_side(contact_reach))
        fparams[P_SENSE] = self.sense_radius or 0.0
        fparams[P_LCELL] = neighbours.cell_side(self.sense_radius or 1.0, neighbours.SPLIT)
        fparams[P_ARENA] = self.arena
        fparams[P_TCELL] = nearest.target_cell(self.num_agents, self.arena)
        fparams[P_BID_EPS] = self.auction_eps or 0.0
        self._put(self._i, 0, header)
        self._put(self._f, 0, fparams)

    def _put(self, buf, offset: int, values: np.ndarray) -> None:
        if isinstance(buf, np.ndarray):
            buf[offset : offset + values.size] = values.reshape(-1)
        else:
            import torch

            buf[offset : offset + values.size] = torch.from_numpy(values.reshape(-1)).to(buf.device)

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None):
        """Start a fresh episode in every environment; returns ``obs``.

        ``seed`` restarts every environment's random stream (the same seed gives
        the same trajectories); without it the streams continue, or start from
        the ``seed`` given to ``make`` on the first reset.
        """
        if seed is not None:
            seed = check_int("seed", seed, 0)
        if seed is not None or not self._seeded:
            states = rng.seed_states(seed if seed is not None else self._seed, self.num_envs)
            self._put(self._i, self.layout.blocks["rng"].offset, states)
            self._seeded = True
        kernels.reset_kernel(
            self._f, self._i, self._u8, self._task_id, self._cap, self._sm, self._lists, self._parallel
        )
        return self.obs

    def warm_up(self) -> None:
        """Compile the kernels this env runs (a reset and a step) now rather than at their first
        use, and leave the env as it was: a process that must not stall mid-run calls it first
        (``swarm world``, before its agents start and take the CPU)."""
        seeded, snap = self._seeded, self.snapshot()
        self.reset()
        B, M = self.num_envs, self.num_agents
        self.step(np.zeros((B, M, self.action_dim), np.float32) if self.continuous else np.zeros((B, M), np.int64))
        self.restore(snap)
        self._seeded = seeded

    def reset_envs(self, mask):
        """Start a fresh episode in the environments where ``mask`` (bool [B], numpy
        or torch) is true; the others go on untouched. Returns ``obs``.

        The new episodes draw from each environment's random stream where it stands
        (no reseeding): what ``step`` does to an environment whose episode ends.
        """
        if not self._seeded:
            raise RuntimeError("call reset() before reset_envs()")
        host = _to_numpy(mask, "mask")
        if host.dtype != np.bool_:
            raise ValueError(f"mask must have dtype bool, got {host.dtype}")
        if host.shape != (self.num_envs,):
            raise ValueError(f"mask must have shape ({self.num_envs},) (num_envs,), got {host.shape}")
        if not host.any():
            return self.obs
        flags = np.ascontiguousarray(host, dtype=np.uint8)  # [B] 0/1, the kernel's exact dtype
        if self.arch == "cuda":
            import torch

            flags = torch.from_numpy(flags).to("cuda")
        kernels.reset_masked_kernel(
            self._f, self._i, self._u8, flags, self._task_id, self._cap, self._sm, self._lists, self._parallel
        )
        return self.obs

    def step(self, actions):
        """Advance every environment one step; returns ``(obs, reward, done, info)``.

        ``actions``, a contiguous tensor on the env's device (or a numpy array on
        the CPU): discrete (default) int64 [B, M], values 0..4 (no-op, -x, +x, -y,
        +y; "fine" also 5..8, those four at a quarter of the force); continuous
        (``action_space="continuous"``) float32 [B, M, 2], the force on each axis being
        5 clip(u, -1, 1) (NaN is refused).
        Finished environments restart inside this call: ``obs`` is then the
        first observation of the new episode, ``info["terminal_obs"]`` the last
        one of the old, ``info["episode"]`` its statistics.
        """
        if not self._seeded:
            raise RuntimeError("call reset() before step()")
        if self.continuous:
            u = self._check_continuous_actions(actions)  # 1-D float32 view, no copy
            if self._agent_parallel:
                kernels.step_wide_kernel(
                    self._f, self._i, self._u8, u, self._task_id, self._cap, self._sm, self._lists, True
                )
                return self.obs, self.reward, self.done, self.info
            kernels.step_continuous_kernel(
                self._f, self._i, self._u8, u, self._task_id, self._cap, self._sm, self._lists, self._parallel
            )
            return self.obs, self.reward, self.done, self.info
        host = self._check_actions(actions)
        if host is not None:  # numpy, or a CPU tensor seen through numpy (no torch dispatch)
            np.copyto(self._actions_host, host, casting="unsafe")  # int64 -> int32
        else:
            self._actions_in.copy_(actions)  # CUDA
        if self._agent_parallel:  # ``u`` unused (discrete): any float32 array will do
            kernels.step_wide_kernel(
                self._f, self._i, self._u8, self._f, self._task_id, self._cap, self._sm, self._lists, False
            )
        else:
            kernels.step_kernel(
                self._f, self._i, self._u8, self._task_id, self._cap, self._sm, self._lists, self._parallel
            )
        return self.obs, self.reward, self.done, self.info

    def _check_continuous_actions(self, actions):
        """Raise ValueError unless ``actions`` are float32 [B, M, 2], contiguous, on the env's
        device and free of NaN; returns them flattened to [B * M * 2] (a view): numpy on
        the CPU (a CPU tensor is seen through numpy), a torch tensor on CUDA."""
        shape = (self.num_envs, self.num_agents, ACTION_DIM)
        what = "continuous actions"
        if isinstance(actions, np.ndarray):
            if self.arch == "cuda":
                raise ValueError(f"{what} must be a torch tensor on cuda for a CUDA env, got a numpy array")
            if actions.dtype != np.float32:
                raise ValueError(f"{what} must have dtype float32, got {actions.dtype}")
            if actions.shape != shape:
                raise ValueError(f"{what} must have shape {shape} (num_envs, num_agents, 2), got {actions.shape}")
            if not actions.flags.c_contiguous:
                raise ValueError(f"{what} must be C-contiguous (use np.ascontiguousarray)")
            flat = actions.reshape(-1)
        else:
            import torch

            if not isinstance(actions, torch.Tensor):
                raise ValueError(f"{what} must be a torch tensor or numpy array, got {type(actions).__name__}")
            if actions.dtype != torch.float32:
                raise ValueError(f"{what} must have dtype torch.float32, got {actions.dtype}")
            if tuple(actions.shape) != shape:
                raise ValueError(
                    f"{what} must have shape {shape} (num_envs, num_agents, 2), got {tuple(actions.shape)}"
                )
            if actions.device.type != self.device:
                raise ValueError(f"{what} must be on device {self.device!r}, got {actions.device}")
            if not actions.is_contiguous():
                raise ValueError(f"{what} must be contiguous (call .contiguous())")
            if actions.device.type == "cuda":
                if bool(torch.isnan(actions).any()):
                    raise NaNActionsError(f"{what} must not contain NaN")
                return actions.detach().view(-1)
            flat = actions.detach().numpy().reshape(-1)
        if np.isnan(flat).any():
            raise NaNActionsError(f"{what} must not contain NaN")
        return flat

    def _check_actions(self, actions) -> np.ndarray | None:
        """Raise ValueError unless ``actions`` fit this env; returns them as a numpy
        array (a zero-copy view for a CPU tensor), or None for a CUDA tensor."""
        shape = (self.num_envs, self.num_agents)
        if isinstance(actions, np.ndarray):
            if self.arch == "cuda":
                raise ValueError("actions must be a torch tensor on cuda for a CUDA env, got a numpy array")
            if actions.dtype != np.int64:
                raise ValueError(f"actions must have dtype int64, got {actions.dtype}")
            if actions.shape != shape:
                raise ValueError(f"actions must have shape {shape} (num_envs, num_agents), got {actions.shape}")
            if not actions.flags.c_contiguous:
                raise ValueError("actions must be C-contiguous (use np.ascontiguousarray)")
            host = actions
        else:
            import torch

            if not isinstance(actions, torch.Tensor):
                raise ValueError(f"actions must be a torch tensor or numpy array, got {type(actions).__name__}")
            if actions.dtype != torch.int64:
                raise ValueError(f"actions must have dtype torch.int64, got {actions.dtype}")
            if tuple(actions.shape) != shape:
                raise ValueError(f"actions must have shape {shape} (num_envs, num_agents), got {tuple(actions.shape)}")
            if actions.device.type != self.device:
                raise ValueError(f"actions must be on device {self.device!r}, got {actions.device}")
            if not actions.is_contiguous():
                raise ValueError("actions must be contiguous (call .contiguous())")
            if actions.device.type == "cuda":
                lo, hi = (int(x) for x in torch.aminmax(actions))
                if lo < 0 or hi >= self.num_actions:
                    raise ValueError(f"actions must be in 0..{self.num_actions - 1}, got values in [{lo}, {hi}]")
                return None
            host = actions.detach().numpy()
        # one pass: seen as unsigned, a negative value is huge, so max < A <=> all in 0..A-1
        if host.size and host.view(np.uint64).max() >= self.num_actions:
            lo, hi = int(host.min()), int(host.max())
            raise ValueError(f"actions must be in 0..{self.num_actions - 1}, got values in [{lo}, {hi}]")
        return host

    def snapshot(self) -> dict:
        """A copy of everything the environments carry from step to step (the three packed
        buffers: state, random streams, episode statistics, warm starts, observations);
        ``restore`` continues from it bit-identically. numpy arrays, any arch."""
        bufs = {}
        for k, buf in self._bufs.items():
            bufs[k] = buf.detach().cpu().numpy().copy() if hasattr(buf, "detach") else buf.copy()
        return {"shape": self._snapshot_key(), "buffers": bufs}

    def restore(self, snapshot: dict) -> dict:
        """Continue from ``snapshot()`` of an env built with the same arguments; returns ``obs``."""
        if not isinstance(snapshot, dict) or "buffers" not in snapshot:
            raise ValueError("restore() takes what snapshot() returned")
        if tuple(snapshot.get("shape", ())) != self._snapshot_key():
            raise ValueError(f"snapshot of {tuple(snapshot.get('shape', ()))} cannot restore {self._snapshot_key()}")
        arrays = {}
        for k, buf in self._bufs.items():  # every buffer checked before any is written
            if k not in snapshot["buffers"]:
                raise ValueError(f"snapshot lacks buffer {k}")
            arr = arrays[k] = np.asarray(snapshot["buffers"][k])
            if arr.shape != tuple(buf.shape) or arr.dtype != self._host_dtype(k):
                raise ValueError(
                    f"snapshot buffer {k} has shape {arr.shape} / {arr.dtype}, expected {tuple(buf.shape)}"
                )
        if not np.isfinite(arrays["f32"]).all():
            raise ValueError("snapshot buffer f32 holds NaN or inf")
        from .layout import FLOAT_HEADER

        live = self.snapshot()["buffers"]  # the headers (offsets, sizes, parameters) the kernels trust
        for k, n in (("i32", self.layout.header.size), ("f32", FLOAT_HEADER)):
            if not np.array_equal(arrays[k][:n], live[k][:n]):
                raise ValueError(f"snapshot buffer {k}'s header differs from this environment's")
        for k, buf in self._bufs.items():
            arr = arrays[k]
            if self._host is not None:
                self._host[k][...] = arr
            else:
                import torch

                buf.copy_(torch.from_numpy(arr))
        self._seeded = True
        return self.obs

    def _snapshot_key(self) -> tuple:
        return (
            self.task,
            self.num_envs,
            self.num_agents,
            self.num_landmarks,
            self.comm,
            self.comm_radius,
            *self._list_key(),
        )

    def _list_key(self) -> tuple:
        """The list and scale options, only where set (snapshots of dense envs keep their key)."""
        opts = (
            ("neighbours", self.neighbours),
            ("landmark_neighbours", self.landmark_neighbours),
            ("sense_radius", self.sense_radius),
            ("scale", self.scale),
            ("assignment", None if self.assignment_method == "exact" else self.assignment_method),
            ("landmark_occupancy", True if self.landmark_occupancy else None),
            ("landmark_order", None if self.landmark_order == "nearest" else self.landmark_order),
            ("auction_rounds", self.auction_rounds),
            ("auction_eps", self.auction_eps),
        )
        return tuple(f"{k}={v}" for k, v in opts if v is not None)

    @staticmethod
    def _host_dtype(kind: str):
        return {"f32": np.float32, "i32": np.int32, "u8": np.uint8}[kind]

    def get_state(self) -> dict:
        """Copies of pos [B, M, 2], vel [B, M, 2], landmarks [B, L, 2], step [B]."""
        names = {"pos": "pos", "vel": "vel", "landmarks": "landmarks", "step": "step"}
        return {k: _copy(self._view(n)) for k, n in names.items()}

    def set_state(self, pos=None, vel=None, landmarks=None, step=None):
        """Overwrite parts of the state (all environments); returns the new ``obs``.

        Targets, assignment and observations are recomputed from the new state. With the radio
        auction, that includes another step's message rounds (the agents' tables carry over, as in
        a step; ``step=0`` starts them afresh).
        """
        if not self._seeded:
            self.reset()
        for name, value in (("pos", pos), ("vel", vel), ("landmarks", landmarks), ("step", step)):
            if value is None:
                continue
            blk = self.layout.blocks[name]
            arr = _to_numpy(value, name)
            if arr.shape != blk.shape:
                raise ValueError(f"{name} must have shape {blk.shape}, got {arr.shape}")
            # checked on the values as stored (int32 / float32), not before narrowing them
            if name == "step":
                if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer) or (arr < 0).any():
                    raise ValueError("step must hold non-negative integers")
                if (arr > np.iinfo(np.int32).max).any():
                    raise ValueError(f"step must be <= {np.iinfo(np.int32).max}, got {arr.max()}")
                arr = arr.astype(np.int32)
            else:
                if arr.dtype == np.bool_ or not (
                    np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
                ):
                    raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
                with np.errstate(over="ignore"):
                    arr = arr.astype(np.float32)
                if not np.isfinite(arr).all():
                    raise ValueError(f"{name} must be finite as float32 (|x| < 3.4e38)")
            self._put(self._bufs[blk.buffer], blk.offset, arr)
        kernels.refresh_kernel(
            self._f, self._i, self._u8, self._task_id, self._cap, self._sm, self._lists, self._parallel
        )
        return self.obs

    def __repr__(self) -> str:
        return (
            f"SwarmEnv(task={self.task!r}, num_envs={self.num_envs}, num_agents={self.num_agents}, "
            f"num_landmarks={self.num_landmarks}, comm={self.comm!r}, comm_radius={self.comm_radius}, "
            f"arch={self.arch!r}, array={self.array!r}"
            + (f", action_space={self.action_space!r}" if self.action_space != "discrete" else "")
            + "".join(f", {kv}" for kv in self._list_key())
            + ")"
        )


def _copy(x):
    return x.copy() if isinstance(x, np.ndarray) else x.clone()


def _to_numpy(value, name: str) -> np.ndarray:
    if isinstance(value, np.ndarray):
        return value
    if hasattr(value, "detach"):  # torch tensor, any device
        return value.detach().cpu().numpy()
    try:
        return np.asarray(value)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"{name} must be array-like") from exc


def make(
    task: Sim | str,
    num_envs: int,
    num_agents: int | None = None,
    *,
    arch: str = "cpu",
    seed: int | None = None,
    array: str = "torch",
    agent_parallel: bool | None = None,
    **options,
) -> SwarmEnv:
    """The gym-style entry point: ``make(sim, num_envs)`` builds a ``SwarmEnv`` for a ``Sim``;
    ``make("coverage", 1024, 3, comm="rc", ...)`` builds the Sim from the task, the team size and
    its options first. The other keywords are the task's parameters (max_steps, success_threshold,
    formation_radius, line_length)."""
    setting = {k: options.pop(k) for k in list(options) if k in FIELDS}
    if isinstance(task, Sim):
        if num_agents is not None or setting:
            given = ["num_agents"] if num_agents is not None else sorted(setting)
            raise ConfigError(given[0], f"make(sim, ...) takes the setting from the Sim: {given} belong in it")
        sim = task
    else:
        if "agents" in setting:
            raise ConfigError("agents", "make() takes the team size as num_agents")
        if num_agents is None:
            raise ConfigError("agents", "make() needs num_agents (or a Sim)")
        sim = Sim(task, num_agents, **setting)
    return SwarmEnv(sim, num_envs, arch=arch, seed=seed, array=array, agent_parallel=agent_parallel, **options)
