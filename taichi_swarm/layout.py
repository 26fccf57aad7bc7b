"""Packed state: every per-step array lives in one of three flat buffers.

A Taichi launch costs ~30 us plus ~20-45 us per torch-tensor argument
(docs/PAPER.md s.8), so the step kernel takes exactly three
buffers (float32, int32, uint8) plus the actions. Each named array is a
contiguous block ``[B, ...]`` inside its buffer; the public arrays
(``obs["self"]``, ``reward``, ...) are zero-copy views of those blocks.

The block offsets and strides are written into a small header at the start of the
int32 buffer (and the float parameters at the start of the float32 buffer), and the
kernels reach every block through its named accessor (``blocks.pos.env(ib, b)``,
generated from ``BLOCKS``) instead of being recompiled for each (B, M, L).

Block shapes are written in named dimensions (``DIMS``): the dense layout has
``MA = M`` (the adjacency) and no neighbour blocks; with neighbour lists
(``make(..., neighbours=K)``) ``MA = 0`` (no M x M block) and the list and grid
blocks get their sizes (K slots, N = M agents in the grid, G + 1 bucket starts).
"""

import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

# --- int32 header: sizes and switches -------------------------------------------------
# H_ROUNDS: the radio auction's message rounds per step (auction_rounds; 0: no radio)
H_B, H_M, H_L, H_COMM_RC, H_MAX_STEPS, H_K, H_KL, H_G, H_GL, H_GT, H_DENSITY, H_ROUNDS = range(12)
SIZE_SLOTS = 12
SELF_DIM = 4  # an agent's own observation: vx, vy, px, py (the kernels write exactly these)


@dataclass(frozen=True)
class BlockSpec:
    """One named array: its buffer and its per-environment shape ("M", "L" or numbers)."""

    name: str
    buffer: str  # "f32" | "i32" | "u8"
    per_env: tuple = ()

    def shape(self, M: int, L: int, dims: dict | None = None) -> tuple:
        sizes = {**dense_dims(M, L), **(dims or {})}
        return tuple(sizes[d] if isinstance(d, str) else int(d) for d in self.per_env)


def dense_dims(M: int, L: int) -> dict:
    """The named dimensions of the dense layout (no neighbour or landmark lists)."""
    return {
        "M": M,
        "L": L,
        "MA": M,
        "LE": L,
        "EF": 2,
        "MC": M,
        "K": 0,
        "KL": 0,
        "N": 0,
        "G1": 0,
        "LN": 0,
        "GL1": 0,
        "TN": 0,
        "GT1": 0,
        "LO": 0,
        "BM": 0,
        "RM": 0,
        "RT": 1,
    }


DIMS = tuple(dense_dims(0, 0))


# THE declaration of every block, in buffer order; its index here (after the size slots)
# is its slot in the int32 header, which holds the block's offset.
BLOCKS = (
    BlockSpec("pos", "f32", ("M", 2)),
    BlockSpec("vel", "f32", ("M", 2)),
    BlockSpec("landmarks", "f32", ("L", 2)),
    BlockSpec("targets", "f32", ("M", 2)),
    BlockSpec("obs_self", "f32", ("M", SELF_DIM)),
    # LE: L, or KL with landmark lists; EF: 2 (the offset), 3 with landmark occupancy
    BlockSpec("obs_entities", "f32", ("M", "LE", "EF")),
    BlockSpec("reward", "f32"),
    BlockSpec("agent_reward", "f32", ("M",)),  # each agent's own terms summed (the team reward is their mean)
    BlockSpec("reward_terms", "f32", ("M", "RT")),  # ... each of the task's RT named terms
    BlockSpec("contacts", "f32", ("M",)),  # the teammates each agent touched this step (the terms' context)
    BlockSpec("matched_dist", "f32", ("M",)),
    BlockSpec("ep_matched_dist", "f32", ("M",)),
    BlockSpec("ep_dist", "f32"),
    BlockSpec("ep_return", "f32"),
    BlockSpec("return_acc", "f32"),
    BlockSpec("term_self", "f32", ("M", SELF_DIM)),
    BlockSpec("term_entities", "f32", ("M", "LE", "EF")),
    BlockSpec("assign_cost", "f32", ("M", "MC")),  # exact assignment's cost matrix (M > SMALL_M)
    BlockSpec("prices", "f32", ("M",)),  # assignment column prices, the next solve's warm start
    BlockSpec("lap_dist", "f32", ("M",)),  # assignment work array: path lengths to each column
    BlockSpec("ep_covered", "f32"),  # fraction of targets matched within success_threshold
    BlockSpec("nbr_d2", "f32", ("M", "K")),  # squared distances of the listed neighbours
    BlockSpec("ent_d2", "f32", ("M", "KL")),  # squared distances of the listed landmarks
    BlockSpec("occ_d2", "f32", ("LO", 2)),  # each landmark's two nearest agents (occupancy), d^2
    # the radio auction's candidates (radio.candidates): the landmarks each agent senses, their d^2
    BlockSpec("bid_d2", "f32", ("BM", "KL")),
    # the radio auction (landmark_order="radio", radio.py): each agent's own table of up to KL
    # entries, keyed by landmark id, and the next round's (double buffer: every agent merges the
    # tables of the round before); the messages and bytes each agent received per step (env means)
    BlockSpec("radio_price", "f32", ("RM", "KL")),
    BlockSpec("radio_next_price", "f32", ("RM", "KL")),
    BlockSpec("radio_messages", "f32"),
    BlockSpec("radio_bytes", "f32"),
    BlockSpec("step", "i32"),
    BlockSpec("rng", "i32"),
    BlockSpec("ep_length", "i32"),
    BlockSpec("assignment", "i32", ("M",)),
    BlockSpec("actions", "i32", ("M",)),  # the step's actions, copied in (one kernel argument less)
    # assignment work arrays: row -> column, column -> row, column order, path predecessor
    BlockSpec("lap_x", "i32", ("M",)),
    BlockSpec("lap_y", "i32", ("M",)),
    BlockSpec("lap_cols", "i32", ("M",)),
    BlockSpec("lap_pred", "i32", ("M",)),
    BlockSpec("nbr", "i32", ("M", "K")),  # the K nearest heard agents, nearest first
    BlockSpec("term_nbr", "i32", ("M", "K")),
    BlockSpec("ent_idx", "i32", ("M", "KL")),  # scratch: each agent's landmark list being built (agents search at once)
    BlockSpec("occ_idx", "i32", ("LO", 2)),  # ... and their indices
    BlockSpec("occ_found", "i32", ("LO",)),  # ... how many of the two are within sense_radius
    # ... and their ids and how many
    BlockSpec("bid_cand", "i32", ("BM", "KL")),
    BlockSpec("bid_count", "i32", ("BM",)),
    # the radio auction's tables (landmark id ascending, epoch, holder -1: none), their lengths, and
    # the landmark each agent believes it holds (-1: none)
    BlockSpec("radio_lid", "i32", ("RM", "KL")),
    BlockSpec("radio_epoch", "i32", ("RM", "KL")),
    BlockSpec("radio_holder", "i32", ("RM", "KL")),
    BlockSpec("radio_next_lid", "i32", ("RM", "KL")),
    BlockSpec("radio_next_epoch", "i32", ("RM", "KL")),
    BlockSpec("radio_next_holder", "i32", ("RM", "KL")),
    BlockSpec("radio_count", "i32", ("RM",)),
    BlockSpec("radio_won", "i32", ("RM",)),
    # whether an agent's table changed since its teammates last merged it (radio.rounds)
    BlockSpec("radio_changed", "i32", ("RM",)),
    BlockSpec("in_range", "i32", ("N",)),  # how many agents each agent hears
    BlockSpec("dropped", "i32"),  # heard but cut from the lists (more than K), summed over agents
    BlockSpec("grid_start", "i32", ("G1",)),  # agents' cell grid: bucket g holds items[start[g]:start[g+1]]
    BlockSpec("grid_items", "i32", ("N",)),
    BlockSpec("grid_cell", "i32", ("N", 2)),  # each agent's integer cell coordinates
    BlockSpec("lgrid_start", "i32", ("GL1",)),  # the landmarks' cell grid (landmark lists)
    BlockSpec("lgrid_items", "i32", ("LN",)),
    BlockSpec("lgrid_cell", "i32", ("LN", 2)),
    BlockSpec("tgrid_start", "i32", ("GT1",)),  # the targets' cell grid (assignment free)
    BlockSpec("tgrid_items", "i32", ("TN",)),
    BlockSpec("tgrid_cell", "i32", ("TN", 2)),
    BlockSpec("adj", "u8", ("M", "MA")),
    BlockSpec("done", "u8"),
    BlockSpec("ep_success", "u8"),
    BlockSpec("ep_truncated", "u8"),
    BlockSpec("term_adj", "u8", ("M", "MA")),
    BlockSpec("nbr_mask", "u8", ("M", "K")),
    BlockSpec("term_nbr_mask", "u8", ("M", "K")),
    BlockSpec("entity_mask", "u8", ("M", "KL")),
    BlockSpec("term_entity_mask", "u8", ("M", "KL")),
)
SLOT = {spec.name: SIZE_SLOTS + i for i, spec in enumerate(BLOCKS)}  # header slot of each block's offset
# the header holds three entries per block: its offset, its entries per env and per row
# (per index of its first dimension), so that one compiled kernel serves every (B, M, L, K)
ENV_STRIDE, ROW_STRIDE = len(BLOCKS), 2 * len(BLOCKS)  # added to a block's SLOT
INT_HEADER = SIZE_SLOTS + 3 * len(BLOCKS)


@ti.data_oriented
class BlockRef:
    """The kernels' accessor of one block of ``BLOCKS``: ``blocks.pos.env(ib, b)`` is the
    index of env b's first entry of pos, ``blocks.pos.row(ib, base, i)`` that of agent i's
    row (its entries follow it), ``get2`` / ``set2`` read and write a row of two.

    A row's width is a compile-time constant when the block's trailing dimensions are
    numbers (pos: 2, obs_self: SELF_DIM), so the specialised small-M kernels keep constant
    strides; otherwise (nbr: K) it is read from the header."""

    def __init__(self, spec: BlockSpec):
        self.name, self.buffer = spec.name, spec.buffer
        self.slot = SLOT[spec.name]
        trailing = spec.per_env[1:]
        self.width = math.prod(trailing) if all(isinstance(d, int) for d in trailing) else 0

    @ti.func
    def env(self, ib: ti.template(), b: ti.i32) -> ti.i32:
        return ib[self.slot] + b * ib[self.slot + ENV_STRIDE]

    @ti.func
    def row_width(self, ib: ti.template()) -> ti.i32:
        """Entries per row (hoist it out of an inner loop when it is read from the header)."""
        width = 0
        if ti.static(self.width > 0):
            width = self.width
        else:
            width = ib[self.slot + ROW_STRIDE]
        return width

    @ti.func
    def row(self, ib: ti.template(), base: ti.i32, i: ti.i32) -> ti.i32:
        return base + i * self.row_width(ib)

    @ti.func
    def at(self, ib: ti.template(), b: ti.i32, i: ti.i32) -> ti.i32:
        """Row i of env b (one access; in a loop, take ``env`` once and ``row`` per i)."""
        return self.row(ib, self.env(ib, b), i)

    @ti.func
    def get2(self, buf: ti.template(), ib: ti.template(), base: ti.i32, i: ti.i32):
        """Row i's two entries, as a vector of the buffer's type (vec2 or ivec2)."""
        k = self.row(ib, base, i)
        return ti.Vector([buf[k], buf[k + 1]])

    @ti.func
    def set2(self, buf: ti.template(), ib: ti.template(), base: ti.i32, i: ti.i32, v: ti.template()):
        k = self.row(ib, base, i)
        buf[k] = v[0]
        buf[k + 1] = v[1]

    @ti.func
    def load(self, buf: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32):
        """``get2`` of row i of env b (the tasks' one-off reads)."""
        return self.get2(buf, ib, self.env(ib, b), i)

    @ti.func
    def store(self, buf: ti.template(), ib: ti.template(), b: ti.i32, i: ti.i32, v: ti.template()):
        """``set2`` of row i of env b."""
        self.set2(buf, ib, self.env(ib, b), i, v)


class Blocks:
    """One ``BlockRef`` per block of ``BLOCKS``, by name: ``blocks.pos``, ``blocks.nbr``, ..."""

    def __init__(self):
        for spec in BLOCKS:
            setattr(self, spec.name, BlockRef(spec))


blocks = Blocks()

# --- float32 header: physical and task parameters ------------------------------------
# P_CELL / P_LCELL / P_TCELL: cell sides of the agents', landmarks' and targets' grids;
# P_ARENA: the spawn square's half-width (1, or sqrt(M / 10) with scale="density");
# P_BID_EPS: the radio auction's bid increment (radio.ROUND_EPS)
(P_COMM_RADIUS, P_AGENT_RADIUS, P_SUCCESS, P_TASK_PARAM, P_CELL, P_SENSE, P_LCELL, P_ARENA, P_TCELL,
 P_BID_EPS) = range(10)  # fmt: skip
FLOAT_HEADER = 10


# Teams up to this size get kernels compiled for their exact M: every loop over agents
# then has a constant trip count, unrolls, and keeps its values in registers.
STATIC_M_MAX = 4


def static_team_size(num_agents: int) -> int:
    """The kernels' compile-time ``sm`` argument: M itself if M <= STATIC_M_MAX, else 0."""
    return num_agents if num_agents <= STATIC_M_MAX else 0


@ti.func
def team_size(sm: ti.template(), ib: ti.template()) -> ti.i32:
    """M: the compile-time ``sm`` when the kernels are specialised (> 0), else the header's."""
    m = 0
    if ti.static(sm > 0):
        m = sm
    else:
        m = ib[H_M]
    return m


@dataclass(frozen=True)
class Block:
    buffer: str  # "f32" | "i32" | "u8"
    offset: int
    shape: tuple  # full shape, batch first: (B, *per_env)


class Layout:
    """Offsets of every named block for one (B, M, L); ``dims`` overrides the dense
    layout's named dimensions (``dense_dims``)."""

    def __init__(self, num_envs: int, num_agents: int, num_landmarks: int, **dims: int):
        self.B, self.M, self.L = num_envs, num_agents, num_landmarks
        unknown = sorted(set(dims) - set(DIMS))
        if unknown:
            raise ValueError(f"unknown layout dimension(s) {unknown}; known: {list(DIMS)}")
        self.dims = {**dense_dims(num_agents, num_landmarks), **dims}
        self.blocks: dict[str, Block] = {}
        # offsets in Python integers first: the int32 header is filled only once they fit
        offset = {"f32": FLOAT_HEADER, "i32": INT_HEADER, "u8": 0}
        for spec in BLOCKS:
            per_env = spec.shape(num_agents, num_landmarks, self.dims)
            self.blocks[spec.name] = Block(spec.buffer, offset[spec.buffer], (num_envs, *per_env))
            offset[spec.buffer] += int(num_envs) * math.prod(int(x) for x in per_env)
        self.sizes = dict(offset)
        if max(self.sizes.values()) >= 2**31:
            need = 4 * self.sizes["f32"] + 4 * self.sizes["i32"] + self.sizes["u8"]
            raise ValueError(
                f"num_envs={num_envs} x num_agents={num_agents} needs {max(self.sizes.values()):,} entries in one "
                f"buffer (the kernels index with int32: at most 2^31) and {need / 2**30:.1f} GiB of memory; "
                "use fewer environments per SwarmEnv"
            )
        self.header = np.zeros(INT_HEADER, dtype=np.int32)
        self.header[[H_B, H_M, H_L]] = (num_envs, num_agents, num_landmarks)
        d = self.dims
        self.header[[H_K, H_KL, H_G, H_GL, H_GT]] = (
            d["K"],
            d["KL"],
            max(d["G1"] - 1, 0),
            max(d["GL1"] - 1, 0),
            max(d["GT1"] - 1, 0),
        )
        for name, block in self.blocks.items():
            per_env = block.shape[1:]
            self.header[SLOT[name]] = block.offset
            self.header[SLOT[name] + ENV_STRIDE] = math.prod(per_env)
            self.header[SLOT[name] + ROW_STRIDE] = math.prod(per_env[1:])

    @property
    def nbytes(self) -> int:
        """Memory of the three buffers."""
        return 4 * self.sizes["f32"] + 4 * self.sizes["i32"] + self.sizes["u8"]
