"""Packed state: every per-step array lives in one of three flat buffers.

A Taichi launch costs ~30 us plus ~20-45 us per torch-tensor argument
(docs/PAPER.md s.8), so the step kernel takes exactly three
buffers (float32, int32, uint8) plus the actions. Each named array is a
contiguous block ``[B, ...]`` inside its buffer; the public arrays
(``obs["self"]``, ``reward``, ...) are zero-copy views of those blocks.

The block offsets are written into a small header at the start of the int32
buffer (and the float parameters at the start of the float32 buffer), so the
kernels read ``ib[O_POS]`` instead of being recompiled for each (B, M, L).
"""

import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

# --- int32 header: sizes and switches -------------------------------------------------
H_B, H_M, H_L, H_COMM_RC, H_MAX_STEPS = range(5)
SELF_DIM = 4  # an agent's own observation: vx, vy, px, py (the kernels write exactly these)
# --- int32 header: where each block starts (in its own buffer) -----------------------
(
    # float32 blocks
    O_POS,
    O_VEL,
    O_LMK,
    O_TGT,
    O_OBS_SELF,
    O_OBS_ENT,
    O_REWARD,
    O_MATCHED,
    O_EP_MATCHED,
    O_EP_DIST,
    O_EP_RETURN,
    O_RET_ACC,
    O_TERM_SELF,
    O_TERM_ENT,
    O_COST,
    O_PRICES,
    # int32 blocks
    O_STEP,
    O_RNG,
    O_EP_LEN,
    O_ASSIGN,
    O_ACTIONS,
    # uint8 blocks
    O_ADJ,
    O_DONE,
    O_EP_SUCCESS,
    O_EP_TRUNC,
    O_TERM_ADJ,
) = range(5, 5 + 26)
INT_HEADER = 5 + 26
# --- float32 header: physical and task parameters ------------------------------------
P_COMM_RADIUS, P_AGENT_RADIUS, P_SUCCESS, P_TASK_PARAM = range(4)
FLOAT_HEADER = 4


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


def _blocks(M: int, L: int):
    """(header slot, name, per-env shape) of every block, per buffer dtype."""
    f32 = [
        (O_POS, "pos", (M, 2)),
        (O_VEL, "vel", (M, 2)),
        (O_LMK, "landmarks", (L, 2)),
        (O_TGT, "targets", (M, 2)),
        (O_OBS_SELF, "obs_self", (M, SELF_DIM)),
        (O_OBS_ENT, "obs_entities", (M, L, 2)),
        (O_REWARD, "reward", ()),
        (O_MATCHED, "matched_dist", (M,)),
        (O_EP_MATCHED, "ep_matched_dist", (M,)),
        (O_EP_DIST, "ep_dist", ()),
        (O_EP_RETURN, "ep_return", ()),
        (O_RET_ACC, "return_acc", ()),
        (O_TERM_SELF, "term_self", (M, SELF_DIM)),
        (O_TERM_ENT, "term_entities", (M, L, 2)),
        (O_COST, "assign_cost", (M, M)),  # assignment cost matrix (M > SMALL_M)
        (O_PRICES, "prices", (M,)),  # assignment column prices, the next solve's warm start
    ]
    i32 = [
        (O_STEP, "step", ()),
        (O_RNG, "rng", ()),
        (O_EP_LEN, "ep_length", ()),
        (O_ASSIGN, "assignment", (M,)),
        (O_ACTIONS, "actions", (M,)),  # the step's actions, copied in (one kernel argument less)
    ]
    u8 = [
        (O_ADJ, "adj", (M, M)),
        (O_DONE, "done", ()),
        (O_EP_SUCCESS, "ep_success", ()),
        (O_EP_TRUNC, "ep_truncated", ()),
        (O_TERM_ADJ, "term_adj", (M, M)),
    ]
    return {"f32": f32, "i32": i32, "u8": u8}


@dataclass(frozen=True)
class Block:
    buffer: str  # "f32" | "i32" | "u8"
    offset: int
    shape: tuple  # full shape, batch first: (B, *per_env)


class Layout:
    """Offsets of every named block for one (B, M, L)."""

    def __init__(self, num_envs: int, num_agents: int, num_landmarks: int):
        self.B, self.M, self.L = num_envs, num_agents, num_landmarks
        self.blocks: dict[str, Block] = {}
        self.sizes = {}
        slots = {}
        # offsets in Python integers first: the int32 header is filled only once they fit
        for buf, entries in _blocks(num_agents, num_landmarks).items():
            offset = INT_HEADER if buf == "i32" else FLOAT_HEADER if buf == "f32" else 0
            for slot, name, per_env in entries:
                self.blocks[name] = Block(buf, offset, (num_envs, *per_env))
                slots[slot] = offset
                offset += int(num_envs) * math.prod(int(x) for x in per_env)
            self.sizes[buf] = offset
        if max(self.sizes.values()) >= 2**31:
            need = 4 * self.sizes["f32"] + 4 * self.sizes["i32"] + self.sizes["u8"]
            raise ValueError(
                f"num_envs={num_envs} x num_agents={num_agents} needs {max(self.sizes.values()):,} entries in one "
                f"buffer (the kernels index with int32: at most 2^31) and {need / 2**30:.1f} GiB of memory; "
                "use fewer environments per SwarmEnv"
            )
        self.header = np.zeros(INT_HEADER, dtype=np.int32)
        self.header[[H_B, H_M, H_L]] = (num_envs, num_agents, num_landmarks)
        for slot, offset in slots.items():
            self.header[slot] = offset

    @property
    def nbytes(self) -> int:
        """Memory of the three buffers."""
        return 4 * self.sizes["f32"] + 4 * self.sizes["i32"] + self.sizes["u8"]
