"""The packed buffer layout: blocks never overlap, fill their buffers exactly, and the
header the kernels read points at each block."""

import math

import numpy as np
import pytest
import taichi as ti

from taichi_swarm import layout as lay


@pytest.mark.parametrize(("B", "M", "L"), [(1, 1, 1), (3, 2, 2), (7, 5, 1), (64, 10, 10), (5, 100, 100)])
def test_blocks_tile_their_buffers_and_the_header_points_at_them(B, M, L):
    lo = lay.Layout(B, M, L)
    starts = {"f32": lay.FLOAT_HEADER, "i32": lay.INT_HEADER, "u8": 0}
    for buf in ("f32", "i32", "u8"):
        # empty blocks (lists off) sit at the offset of the block after them
        blocks = sorted((b.offset, math.prod(b.shape), name, b) for name, b in lo.blocks.items() if b.buffer == buf)
        end = starts[buf]
        for offset, _, name, block in blocks:
            assert block.shape[0] == B, name
            assert offset == end, f"{name} starts at {offset}, the previous block ends at {end}"
            end = offset + math.prod(block.shape)
        assert end == lo.sizes[buf]
    # each block's three header entries (offset, per env, per row), each slot once
    slots = [s + k for s in lay.SLOT.values() for k in (0, lay.ENV_STRIDE, lay.ROW_STRIDE)]
    assert sorted(slots) == list(range(lay.SIZE_SLOTS, lay.INT_HEADER))
    for name, slot in lay.SLOT.items():
        block = lo.blocks[name]
        assert lo.header[slot] == block.offset, name
        assert lo.header[slot + lay.ENV_STRIDE] == math.prod(block.shape[1:]), name
        assert lo.header[slot + lay.ROW_STRIDE] == math.prod(block.shape[2:]), name
    assert (lo.header[[lay.H_B, lay.H_M, lay.H_L]] == (B, M, L)).all()


def test_every_block_has_its_named_accessor():
    assert sorted(vars(lay.blocks)) == sorted(spec.name for spec in lay.BLOCKS)
    for spec in lay.BLOCKS:
        ref = getattr(lay.blocks, spec.name)
        assert (ref.name, ref.buffer, ref.slot) == (spec.name, spec.buffer, lay.SLOT[spec.name])


@ti.kernel
def _mark_rows(
    buf: ti.types.ndarray(dtype=ti.i32, ndim=1), ib: ti.types.ndarray(dtype=ti.i32, ndim=1), ref: ti.template()
):
    for b in range(ib[lay.H_B]):
        base = ref.env(ib, b)
        for i in range(ib[ref.slot + lay.ENV_STRIDE] // ti.max(ib[ref.slot + lay.ROW_STRIDE], 1)):
            k = ref.row(ib, base, i)
            if i % 2 == 1:  # ``at`` is ``row`` of ``env``
                k = ref.at(ib, b, i)
            buf[k] = 1000 * b + i + 1


@pytest.mark.parametrize("name", ["pos", "obs_self", "obs_entities", "nbr", "assign_cost", "reward", "grid_start"])
def test_accessors_reach_row_i_of_env_b(name):
    """The kernels' accessors land where the Python views of the same layout put [b, i, 0],
    for compile-time row widths (pos, obs_self) and header-read ones (nbr: K)."""
    B, M, L = 3, 5, 4
    lo = lay.Layout(B, M, L, K=3, N=M, G1=17, KL=2, LE=2)
    block = lo.blocks[name]
    buf = np.zeros(max(lo.sizes.values()), dtype=np.int32)
    buf[: lay.INT_HEADER] = lo.header
    _mark_rows(buf, lo.header.copy(), getattr(lay.blocks, name))
    view = buf[block.offset : block.offset + math.prod(block.shape)].reshape(block.shape)
    rows = view.reshape(B, block.shape[1] if len(block.shape) > 1 else 1, -1)[:, :, 0]
    want = 1000 * np.arange(B)[:, None] + np.arange(rows.shape[1])[None, :] + 1
    np.testing.assert_array_equal(rows, want)
