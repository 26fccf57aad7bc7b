"""The exact assignment at large M: Jonker-Volgenant with its work arrays in the packed buffers
gives scipy's optimum; the shared-price auction assignment is gone and refused by name."""

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import taichi_swarm


@pytest.mark.parametrize("name", ["greedy", "auction"])
def test_unknown_assignments_are_refused_by_name(name):
    with pytest.raises(ValueError, match="assignment must be one of"):
        taichi_swarm.make("coverage", 2, 5, assignment=name, array="numpy")


@pytest.mark.parametrize(("M", "neighbours"), [(70, None), (300, 8)])
def test_exact_assignment_with_work_arrays_in_the_buffers_is_optimal(M, neighbours):
    """Past STACK_CAP (dense layout) and always with lists, Jonker-Volgenant keeps its work
    arrays in the packed buffers: the same optimum as scipy, cold and warm."""
    B = 2
    env = taichi_swarm.make("coverage", B, M, neighbours=neighbours, seed=M, array="numpy", comm="rc")
    assert env.assignment_method == "exact"
    env.reset()
    rng = np.random.default_rng(M)
    for t in range(4):
        if t > 0:
            env.step(rng.integers(0, 5, size=(B, M)))
        s = env.get_state()
        for b in range(B):
            cost = np.linalg.norm(s["pos"][b][:, None].astype(np.float64) - env.targets[b][None], axis=-1)
            rows, cols = linear_sum_assignment(cost)
            assert sorted(env.assignment[b].tolist()) == list(range(M))
            np.testing.assert_allclose(env.matched_dist[b].sum(), cost[rows, cols].sum(), rtol=1e-5, atol=1e-4)
