"""Counter-free per-environment random numbers (PCG-RXS-M-XS, O'Neill 2014).

Each environment owns one 32-bit state in the int32 buffer, so a batch is
reproducible for a seed regardless of thread scheduling, and every
environment draws from its own stream. ``ti.random`` is not used: its
per-thread streams depend on which thread ran which environment.
"""

import numpy as np
import taichi as ti

from .layout import blocks


@ti.func
def uniform(ib: ti.template(), b: ti.i32) -> ti.f32:
    """One U[0, 1) draw from environment b's stream (advances it)."""
    s = ti.cast(ib[blocks.rng.env(ib, b)], ti.u32) * ti.u32(747796405) + ti.u32(2891336453)
    ib[blocks.rng.env(ib, b)] = ti.cast(s, ti.i32)
    word = ((s >> ((s >> ti.u32(28)) + ti.u32(4))) ^ s) * ti.u32(277803737)
    word = (word >> ti.u32(22)) ^ word
    return ti.cast(word >> ti.u32(8), ti.f32) * (1.0 / 16777216.0)


@ti.func
def uniform2(ib: ti.template(), b: ti.i32, lo: ti.f32, hi: ti.f32) -> ti.math.vec2:
    x = lo + (hi - lo) * uniform(ib, b)
    y = lo + (hi - lo) * uniform(ib, b)
    return ti.math.vec2(x, y)


def seed_states(seed: int | None, num_envs: int) -> np.ndarray:
    """Distinct per-environment stream states for ``seed`` (int32 view of uint32)."""
    gen = np.random.default_rng(seed)
    return gen.integers(0, 2**32, size=num_envs, dtype=np.uint32).view(np.int32)
