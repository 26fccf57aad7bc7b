"""scale="density": coverage's spawn square grows as sqrt(M / 10) (the agents per unit area
of the paper's M = 10), formation's targets are a filled hexagonal lattice; scale=None
stays the paper's geometry. And the episode's fraction of targets covered."""

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


def _hex_spiral(M, spacing):
    """Reference: the first M points of the hexagonal spiral (axial coordinates, ring n from
    the corner n * (-1, 1), sides along (1, 0), (1, -1), (0, -1), (-1, 0), (-1, 1), (0, 1))."""
    dirs = [(1, 0), (1, -1), (0, -1), (-1, 0), (-1, 1), (0, 1)]
    pts, n = [(0, 0)], 1
    while len(pts) < M:
        q, r = -n, n
        for dq, dr in dirs:
            for _ in range(n):
                pts.append((q, r))
                q, r = q + dq, r + dr
        n += 1
    pts = np.asarray(pts[:M], dtype=np.float64)
    return spacing * np.stack([pts[:, 0] + 0.5 * pts[:, 1], np.sqrt(3) / 2 * pts[:, 1]], axis=1)


@pytest.mark.parametrize("M", [2, 7, 10, 50, 400])
def test_density_formation_is_a_filled_hexagonal_lattice(M):
    from taichi_swarm.tasks import formation

    B = 3
    env = taichi_swarm.make("formation", B, M, scale="density", seed=M, array="numpy")
    env.reset()
    rng = np.random.default_rng(0)
    spacing = 2 * 0.5 * np.sin(np.pi / 10)
    ref = _hex_spiral(M, spacing)
    for t in range(3):
        s = env.get_state()
        centre = s["landmarks"][:, 0]
        if t == 0:  # agents spawned over the lattice's disc round the landmark
            r = np.linalg.norm(s["pos"] - centre[:, None], axis=-1)
            assert r.max() <= formation.lattice_disc_radius(M) + 1e-5
        for b in range(B):
            np.testing.assert_allclose(env.targets[b] - centre[b], ref, atol=2e-5)
        env.step(rng.integers(0, 5, size=(B, M)))
    if M >= 3:  # every target has a neighbour one spacing away, none closer
        gaps = np.linalg.norm(ref[:, None] - ref[None], axis=-1) + 9 * np.eye(M)
        np.testing.assert_allclose(gaps.min(axis=1), spacing, rtol=1e-9)


@pytest.mark.parametrize(("task", "M"), [("formation", 2), ("formation", 7), ("formation", 50), ("line", 2),
                                         ("line", 9), ("line", 61)])  # fmt: skip
def test_density_shapes_list_their_targets_as_landmarks(task, M):
    """With landmark lists every target is a landmark, landmark k target k (formation: landmark 0
    the lattice's centre; line: landmark 0 the first row's start, which with landmark 1 its end
    is what the plain task stores), the episode is otherwise the plain task's draw for draw, and
    each agent senses the nearest targets, as coverage's agents sense their landmarks. (line at
    M = 61: three rows, the last short.)"""
    from scipy.spatial import cKDTree

    from taichi_swarm.tasks import line

    B, KL, sense = 3, 6, 0.8
    kw = dict(comm="rc", neighbours=6, scale="density", seed=M, array="numpy")
    listed = taichi_swarm.make(task, B, M, landmark_neighbours=KL, sense_radius=sense, **kw)
    plain = taichi_swarm.make(task, B, M, **kw)
    L = plain.num_landmarks
    assert listed.num_landmarks == M and L == {"formation": 1, "line": 2}[task]
    obs, _ = listed.reset(), plain.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        a, b = listed.get_state(), plain.get_state()
        np.testing.assert_array_equal(a["pos"], b["pos"])
        np.testing.assert_array_equal(a["landmarks"][:, 0], b["landmarks"][:, 0])
        np.testing.assert_array_equal(a["landmarks"], listed.targets)  # landmark k is target k
        if task == "line" and M > 2:  # the plain task's landmark 1 is the first row's end
            np.testing.assert_allclose(b["landmarks"][:, 1], listed.targets[:, line.per_row(M) - 1], atol=1e-5)
        np.testing.assert_allclose(listed.targets, plain.targets, atol=1e-5)
        np.testing.assert_allclose(listed.matched_dist, plain.matched_dist, atol=1e-5)
        for e in range(B):
            tree = cKDTree(a["landmarks"][e].astype(np.float64))
            for i in range(M):
                d, _ = tree.query(a["pos"][e, i], k=min(KL, M), distance_upper_bound=sense)
                d = np.atleast_1d(d)
                want = np.sort(d[np.isfinite(d)])
                got = np.linalg.norm(obs["entities"][e, i][obs["entity_mask"][e, i] > 0], axis=-1)
                np.testing.assert_allclose(np.sort(got), want, atol=1e-4)
        actions = rng.integers(0, 5, size=(B, M))
        obs, *_ = listed.step(actions)
        plain.step(actions)


def test_density_formation_travel_stays_bounded():
    """The mean matched distance at the start (what an agent must travel) does not grow with M."""
    means = []
    for M in (10, 100, 1000):
        env = taichi_swarm.make("formation", 8, M, scale="density", neighbours=8, seed=1, array="numpy")
        env.reset()
        means.append(float(env.matched_dist.mean()))
    assert max(means) < 0.45, means
    assert means[2] < 2.0 * means[0], means


@pytest.mark.parametrize("M", [2, 5, 10, 23, 90, 400])
def test_density_line_is_parallel_rows(M):
    from taichi_swarm.tasks import line

    B = 3
    env = taichi_swarm.make("line", B, M, scale="density", seed=M, array="numpy")
    env.reset()
    n, m = line.rows(M), line.per_row(M)
    assert n == max(1, round(np.sqrt(M / 10))) and n * m >= M > n * (m - 1) - 1
    gap, spacing = 1.25, 1.25 / 9
    s = env.get_state()
    for b in range(B):
        l0, l1 = s["landmarks"][b].astype(np.float64)
        along = (l1 - l0) / np.linalg.norm(l1 - l0)
        across = np.array([-along[1], along[0]])
        np.testing.assert_allclose(np.linalg.norm(l1 - l0), (m - 1) * spacing, rtol=1e-5)
        k = np.arange(M)
        ref = l0 + np.outer(k % m, along) * spacing + np.outer(k // m, across) * gap
        np.testing.assert_allclose(env.targets[b], ref, atol=2e-5 * max(1, m))
        # agents spawned over the block's footprint, in the line's frame
        rel = s["pos"][b] - l0
        a, c = rel @ along, rel @ across
        assert a.min() >= -0.5 * spacing - 1e-4 and a.max() <= (m - 0.5) * spacing + 1e-4
        assert c.min() >= -0.5 * gap - 1e-4 and c.max() <= (n - 0.5) * gap + 1e-4
        centre = l0 + 0.5 * (m - 1) * spacing * along + 0.5 * (n - 1) * gap * across
        assert np.abs(centre).max() <= 0.25 + 1e-4
    if M == 10:  # one row of the paper's length
        assert n == 1 and m == 10


def test_density_line_travel_stays_bounded():
    means = []
    for M in (10, 100, 1000):
        env = taichi_swarm.make("line", 8, M, scale="density", neighbours=8, seed=1, array="numpy")
        env.reset()
        means.append(float(env.matched_dist.mean()))
    assert max(means) < 0.6, means
    assert means[2] < 2.0 * means[0], means


def test_density_scale_is_refused_by_a_task_without_it():
    import dataclasses

    from taichi_swarm.tasks import TASK_SPECS, register, unregister

    plain = dataclasses.replace(TASK_SPECS["coverage"], name="plain", task_id=77, density_scale=False)
    register(plain)
    try:
        with pytest.raises(ValueError, match="scale='density' is not implemented for task 'plain'"):
            taichi_swarm.make("plain", 2, 4, scale="density", array="numpy")
    finally:
        unregister("plain")
