"""scale="density": coverage's spawn square grows as sqrt(M / 10) (the agents per unit area
of the paper's M = 10); scale=None stays the paper's geometry. And the episode's
fraction of targets covered."""

import numpy as np
import pytest

import taichi_swarm


def test_density_scale_at_ten_agents_is_the_paper_geometry():
    kw = dict(comm="rc", comm_radius=0.5, seed=2, array="numpy")
    paper = taichi_swarm.make("coverage", 4, 10, **kw)
    dense = taichi_swarm.make("coverage", 4, 10, scale="density", **kw)
    assert dense.arena == 1.0
    op, od = paper.reset(), dense.reset()
    np.testing.assert_array_equal(op["self"], od["self"])
    np.testing.assert_array_equal(op["entities"], od["entities"])


@pytest.mark.parametrize(("M", "half_width"), [(40, 2.0), (250, 5.0), (1000, 10.0)])
def test_density_scale_spawn_square(M, half_width):
    B = 4
    env = taichi_swarm.make("coverage", B, M, neighbours=8, scale="density", seed=M, array="numpy")
    assert env.arena == pytest.approx(half_width)
    env.reset()
    s = env.get_state()
    for key in ("pos", "landmarks"):
        x = s[key]
        assert np.abs(x).max() <= half_width
        assert np.abs(x).max() > 0.95 * half_width  # fills the square, not the paper's [-1, 1]^2
        # uniform: a quarter of the points in each quadrant, about
        quadrant = (x[..., 0] > 0).astype(int) * 2 + (x[..., 1] > 0)
        share = np.bincount(quadrant.ravel(), minlength=4) / quadrant.size
        np.testing.assert_allclose(share, 0.25, atol=0.06)
    # the same number of agents per unit area as 10 agents in [-1, 1]^2
    assert M / (2 * half_width) ** 2 == pytest.approx(10 / 4)


def test_episode_reports_the_fraction_of_targets_covered():
    B, M = 64, 6
    env = taichi_swarm.make("coverage", B, M, seed=0, array="numpy", max_steps=5)
    env.reset()
    rng = np.random.default_rng(0)
    seen = 0
    for _ in range(5):
        _, _, done, info = env.step(rng.integers(0, 5, size=(B, M)))
    assert done.all()
    ep = info["episode"]
    want = (ep["matched_dist"] < 0.1).mean(axis=1)
    np.testing.assert_allclose(ep["covered"], want, atol=1e-6)
    seen = int((want > 0).sum())
    assert seen > 0  # some targets are covered by chance: the check is not all zeros
    np.testing.assert_array_equal(ep["success"], want == 1.0)
