"""The packed buffer layout: blocks never overlap, fill their buffers exactly, and the
header the kernels read points at each block."""

import math

import pytest

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
    assert sorted(lay.SLOT.values()) == list(range(lay.SIZE_SLOTS, lay.INT_HEADER))  # each slot once
    for name, slot in lay.SLOT.items():
        assert lo.header[slot] == lo.blocks[name].offset, name
    assert (lo.header[[lay.H_B, lay.H_M, lay.H_L]] == (B, M, L)).all()


def test_every_kernel_slot_constant_names_a_declared_block():
    constants = {name: value for name, value in vars(lay).items() if name.startswith("O_")}
    assert sorted(constants.values()) == sorted(lay.SLOT.values())  # one constant per block, none twice
