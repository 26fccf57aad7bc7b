"""assignment="free" (nearest.py): each target's nearest-agent distance d_t against a scipy
cKDTree, each agent's own d (to its matched target, else the nearest free one), the rewards
against their formulas, and
success / covered against scipy's maximum bipartite matching on the threshold graph, at M =
200 and 1000, from steps, warm starts and arbitrary states (agents far from every target,
so the full scan runs; agents on a permutation of the landmarks; one agent within the
threshold of two landmarks). One compiled variant for coverage (lists compile once for every
M), one for line."""

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching
from scipy.spatial import cKDTree

import taichi_swarm


def _make(M, B=2, task="coverage", assignment="free", **kw):
    opts = {"scale": "density"} if task == "coverage" else {}
    return taichi_swarm.make(
        task, B, M, comm="rc", comm_radius=1.0, neighbours=16, assignment=assignment, seed=M, array="numpy",
        **opts, **kw,
    )  # fmt: skip


def _reference(pos, targets, thr):
    """d_t per target, the maximum threshold matching's size."""
    pos, targets = pos.astype(np.float64), targets.astype(np.float64)
    d_t, _ = cKDTree(pos).query(targets)
    pairs = cKDTree(targets).query_ball_point(pos, r=thr * (1 + 1e-4))  # candidates, then the strict rule
    rows, cols = [], []
    for i, ts in enumerate(pairs):
        for t in ts:
            if np.linalg.norm(pos[i] - targets[t]) < thr:
                rows.append(i)
                cols.append(t)
    M = len(pos)
    graph = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(M, M))
    size = int((maximum_bipartite_matching(graph, perm_type="column") >= 0).sum()) if rows else 0
    return d_t, size


def _free_reference(pos, targets, a):
    """assignment="free"'s d per agent: to its matched target, else to the nearest unmatched one."""
    pos, targets = pos.astype(np.float64), targets.astype(np.float64)
    free = np.setdiff1d(np.arange(len(targets)), a[a >= 0])
    d = np.empty(len(pos))
    on = a >= 0
    d[on] = np.linalg.norm(pos[on] - targets[a[on]], axis=-1)
    if (~on).any():
        d[~on] = cKDTree(targets[free]).query(pos[~on])[0]
    return d


def _check_matching(env, b, pos, targets):
    """env.assignment[b] is a matching of threshold edges (distinct targets) of the maximum size."""
    thr = env.params["success_threshold"]
    a = env.assignment[b]
    matched = a[a >= 0]
    assert len(set(matched.tolist())) == len(matched), "two agents on one target"
    d = np.linalg.norm(pos[a >= 0].astype(np.float64) - targets[matched], axis=-1)
    assert (d < thr + 1e-6).all()
    _, size = _reference(pos, targets, thr)
    assert len(matched) == size
    return size


def _check_step(env, pos, targets):
    """After a step: d_t, the agents' rewards, the team reward and the matching."""
    thr = env.params["success_threshold"]
    for b in range(env.num_envs):
        d_t, size = _reference(pos[b], targets[b], thr)
        d_i = _free_reference(pos[b], targets[b], env.assignment[b])
        np.testing.assert_allclose(env.matched_dist[b], d_t, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(env.info["agent_reward"][b], np.clip(-d_i, -15, 15), rtol=1e-5, atol=1e-5)
        assert env.reward[b] == pytest.approx(np.clip(-d_i, -15, 15).mean(), rel=1e-5, abs=1e-5)  # their mean
        assert _check_matching(env, b, pos[b], targets[b]) == size


@pytest.mark.parametrize("M", [200, 1000])
def test_nearest_distances_rewards_and_matching_like_scipy(M):
    env = _make(M)
    B = env.num_envs
    env.reset()
    for b in range(B):  # after a reset: d_t and the matching (the rewards of a reset are 0)
        d_t, _ = _reference(env.get_state()["pos"][b], env.targets[b], 0.1)
        np.testing.assert_allclose(env.matched_dist[b], d_t, rtol=1e-5, atol=1e-5)
        _check_matching(env, b, env.get_state()["pos"][b], env.targets[b])
    rng = np.random.default_rng(M)
    for _ in range(3):  # random steps
        env.step(rng.integers(0, 5, size=(B, M)))
        _check_step(env, env.get_state()["pos"], env.targets)
    w = env.arena
    lmk = env.get_state()["landmarks"]
    states = [
        rng.uniform(-w, w, size=(B, M, 2)),  # an arbitrary spread
        rng.uniform(-w, w, size=(B, M, 2)) + 6 * w,  # far from every target: the full scan
        lmk + rng.normal(0, 0.06, size=lmk.shape),  # near the targets: many edges, contention
    ]
    for pos in states:
        env.set_state(pos=pos, vel=np.zeros((B, M, 2)))
        s = env.get_state()
        for b in range(B):
            d_t, _ = _reference(s["pos"][b], env.targets[b], 0.1)
            np.testing.assert_allclose(env.matched_dist[b], d_t, rtol=1e-5, atol=1e-5)
            _check_matching(env, b, s["pos"][b], env.targets[b])
        for _ in range(2):  # warm-started steps from there
            env.step(rng.integers(0, 5, size=(B, M)))
            _check_step(env, env.get_state()["pos"], env.targets)


def test_far_agents_scan_every_agent():
    """Every agent 200 cells from every target: no ring holds one, the answer is the full scan's."""
    M, B = 200, 2
    env = _make(M, B)
    env.reset()
    rng = np.random.default_rng(3)
    pos = rng.uniform(-1, 1, size=(B, M, 2)) + 200.0
    pos[:, 0] = 180.0  # one agent nearer than the rest
    env.set_state(pos=pos, vel=np.zeros((B, M, 2)))
    env.step(np.zeros((B, M), dtype=np.int64))
    s = env.get_state()
    _check_step(env, s["pos"], env.targets)
    assert (env.assignment == -1).all()


def test_small_cells_under_uc():
    """Under "uc" the agents' cells are the contact reach (0.12): the searches walk several
    rings and often end in the full scan."""
    M, B = 200, 2
    env = taichi_swarm.make(
        "coverage", B, M, comm="uc", neighbours=16, assignment="free", scale="density", seed=2, array="numpy"
    )
    env.reset()
    rng = np.random.default_rng(2)
    lmk = env.get_state()["landmarks"]
    env.set_state(pos=lmk + rng.normal(0, 0.06, size=lmk.shape))
    for _ in range(3):
        env.step(rng.integers(0, 5, size=(B, M)))
        _check_step(env, env.get_state()["pos"], env.targets)


def _lattice(M, spacing=0.6):
    side = int(np.ceil(np.sqrt(M)))
    k = np.arange(M)
    return np.stack([k % side, k // side], axis=-1) * spacing - 0.5 * side * spacing


def test_success_tempting_landmarks_and_warm_start():
    """Agents exactly on a permutation of the landmarks: success, done, covered 1. Then one
    agent within the threshold of two landmarks 0.15 apart, nearer the one another agent can
    reach too: covering both needs the augmenting path through the warm-started pair."""
    M, B = 200, 2
    env = _make(M, B, max_steps=50)
    env.reset()
    rng = np.random.default_rng(5)
    lmk = np.broadcast_to(_lattice(M), (B, M, 2)).copy()
    perm = rng.permutation(M)
    env.set_state(pos=lmk[:, perm], vel=np.zeros((B, M, 2)), landmarks=lmk, step=np.zeros(B, dtype=np.int64))
    assert (env.assignment >= 0).all()
    env.step(np.zeros((B, M), dtype=np.int64))  # no action, no contact (0.6 apart): nobody moves
    ep = env.info["episode"]
    assert env.done.all() and ep["success"].all() and not ep["truncated"].any()
    np.testing.assert_allclose(ep["covered"], 1.0)
    np.testing.assert_allclose(ep["dist"], 0.0, atol=1e-6)

    # landmarks 0 and 1 0.15 apart, far from the rest; agent a at 0.07 / 0.08 from them
    lmk[:, 0], lmk[:, 1] = (-40.0, -40.0), (-39.85, -40.0)
    a, c = np.argsort(perm)[:2]  # the agents sitting on landmarks 0 and 1
    pos = lmk[:, perm].copy()
    pos[:, a] = (-39.93, -40.0)
    pos[:, c] = (40.0, 40.0)  # away: only a can cover 0 or 1
    env.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=lmk, step=np.zeros(B, dtype=np.int64))
    s = env.get_state()
    for b in range(B):
        assert _check_matching(env, b, s["pos"][b], env.targets[b]) == M - 1
        assert env.assignment[b, a] in (0, 1)
    pos[:, c] = (-40.06, -40.0)  # c back, within the threshold of landmark 0 only
    for b in range(B):  # a on landmark 0 (its nearer): the warm start then needs the augmenting path
        env.assignment[b, a] = 0
    env.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=lmk)
    s = env.get_state()
    for b in range(B):
        assert _check_matching(env, b, s["pos"][b], env.targets[b]) == M
        assert env.assignment[b, a] == 1 and env.assignment[b, c] == 0
        d_t, _ = _reference(s["pos"][b], env.targets[b], 0.1)
        np.testing.assert_allclose(env.matched_dist[b], d_t, rtol=1e-5, atol=1e-5)
    env.step(np.zeros((B, M), dtype=np.int64))
    assert env.done.all() and env.info["episode"]["success"].all()


def test_truncated_episode_statistics_are_the_terminal_states():
    """At the time limit: covered = the terminal matching's size / M, DIST = mean d_t, the
    final matched_dist = the terminal d_t (from the terminal observation's positions)."""
    M, B = 200, 2
    env = _make(M, B, max_steps=50)
    env.reset()
    rng = np.random.default_rng(7)
    lmk = env.get_state()["landmarks"]
    env.set_state(pos=lmk + rng.normal(0, 0.05, size=lmk.shape), step=np.full(B, 49))
    env.step(rng.integers(0, 5, size=(B, M)))
    ep, term = env.info["episode"], env.info["terminal_obs"]
    assert env.done.all() and ep["truncated"].all()
    for b in range(B):
        pos = term["self"][b, :, 2:4]
        d_t, size = _reference(pos, lmk[b], 0.1)
        np.testing.assert_allclose(ep["matched_dist"][b], d_t, rtol=1e-5, atol=1e-5)
        assert ep["dist"][b] == pytest.approx(d_t.mean(), rel=1e-5)
        assert ep["covered"][b] == pytest.approx(size / M)
        assert 0 < size < M
    assert not ep["success"].any()


def test_line_targets():
    """Line's targets are per-agent points too: the same code."""
    M, B = 30, 3
    env = _make(M, B, task="line", max_steps=6)
    env.reset()
    rng = np.random.default_rng(1)
    for _ in range(8):  # an episode end included
        env.step(rng.integers(0, 5, size=(B, M)))
        s = env.get_state()
        thr = env.params["success_threshold"]
        for b in range(B):
            d_t, size = _reference(s["pos"][b], env.targets[b], thr)
            d_i = _free_reference(s["pos"][b], env.targets[b], env.assignment[b])
            np.testing.assert_allclose(env.matched_dist[b], d_t, rtol=1e-5, atol=1e-5)
            if env.done[b]:
                continue  # rewards of the old episode, state of the new
            np.testing.assert_allclose(env.info["agent_reward"][b], -np.clip(d_i, 0, 2), rtol=1e-5, atol=1e-5)
            assert env.reward[b] == pytest.approx(-np.clip(d_i, 0, 2).mean(), rel=1e-5, abs=1e-5)
            assert _check_matching(env, b, s["pos"][b], env.targets[b]) == size


@pytest.mark.parametrize("wide", [False, True])
def test_free_rewards_each_agent_by_its_matched_or_nearest_free_target(wide):
    """An agent the threshold matching holds is measured to its target, an unmatched one to the
    nearest target the matching leaves free (scipy over the free targets), on both kernels (one
    env per thread and every agent in parallel). A duplicate on a held landmark is measured to the
    free one across the arena, not paid for staying."""
    M, B = 200, 2
    free = _make(M, B, max_steps=50, agent_parallel=wide)
    rng = np.random.default_rng(11)
    free.reset()
    lmk = free.get_state()["landmarks"]
    near_targets = lmk + rng.normal(0, 0.06, size=lmk.shape)  # many threshold edges, duplicates among them
    free.set_state(pos=near_targets, vel=np.zeros((B, M, 2)))
    for _ in range(4):
        free.step(rng.integers(0, 5, size=(B, M)))
        s = free.get_state()
        for b in range(B):
            assert (free.assignment[b] < 0).any()  # some agents unmatched: the free search runs
            want = np.clip(-_free_reference(s["pos"][b], free.targets[b], free.assignment[b]), -15, 15)
            np.testing.assert_allclose(free.info["agent_reward"][b], want, rtol=1e-5, atol=1e-5)

    # every agent on its own landmark of a lattice, then agent a moved onto c's landmark
    lat = np.broadcast_to(_lattice(M), (B, M, 2)).copy()
    pos = lat.copy()
    a, c = 3, 150
    pos[:, a] = lat[:, c] + (0.02, 0.0)
    # the lattice held first: c keeps its landmark (held, and nearer than a)
    free.set_state(pos=lat, vel=np.zeros((B, M, 2)), landmarks=lat, step=np.zeros(B, dtype=np.int64))
    free.set_state(pos=pos, vel=np.zeros((B, M, 2)))
    free.step(np.zeros((B, M), dtype=np.int64))
    s = free.get_state()  # the step's contact pushed a and c apart a little
    for b in range(B):
        assert free.assignment[b, a] == -1 and free.assignment[b, c] == c  # c, the nearer, holds it
        far, own = np.linalg.norm(s["pos"][b, a] - lat[b, a]), np.linalg.norm(s["pos"][b, a] - lat[b, c])
        assert far > 6 and own < 0.1
        assert free.info["agent_reward"][b, a] == pytest.approx(-far, rel=1e-4)  # a's own landmark, the one free


@pytest.mark.parametrize("wide", [False, True])
def test_the_nearer_of_two_agents_on_a_target_holds_it(wide):
    """Of two agents within the threshold of one target the nearer holds it, whichever came
    first: an incumbent that a newcomer gets nearer than loses the target, and under "free" it is
    the one paid for crossing to a free target. On random near-target scatters every matched
    agent that is its target's nearest agent stays matched to it (unless another target's
    nearest it is), and the matching stays maximum (scipy)."""
    M, B = 200, 2
    env = _make(M, B, max_steps=50, agent_parallel=wide)
    env.reset()
    lat = np.broadcast_to(_lattice(M), (B, M, 2)).copy()
    a, c = 3, 150
    env.set_state(pos=lat, vel=np.zeros((B, M, 2)), landmarks=lat, step=np.zeros(B, dtype=np.int64))
    assert (env.assignment == np.arange(M)).all()  # everyone on its own landmark
    pos = lat.copy()
    pos[:, c] = lat[:, c] + (0.06, 0.0)  # c, the incumbent, 0.06 off its landmark
    pos[:, a] = lat[:, c] - (0.03, 0.0)  # a arrives nearer: 0.03 from it
    env.set_state(pos=pos, vel=np.zeros((B, M, 2)))
    for b in range(B):
        assert env.assignment[b, a] == c and env.assignment[b, c] == -1  # the nearer holds it
        assert _check_matching(env, b, pos[b], env.targets[b]) == M - 1
    env.step(np.zeros((B, M), dtype=np.int64))
    s = env.get_state()
    for b in range(B):
        assert env.assignment[b, a] == c and env.assignment[b, c] == -1
        far = np.linalg.norm(s["pos"][b, c] - lat[b, a])  # c is paid by a's landmark, the one free
        assert far > 6 and env.info["agent_reward"][b, c] == pytest.approx(-far, rel=1e-4)

    rng = np.random.default_rng(4)
    env.reset()
    lmk = env.get_state()["landmarks"]
    pos = lmk + rng.normal(0, 0.06, size=lmk.shape)
    env.set_state(pos=pos, vel=np.zeros((B, M, 2)))
    for b in range(B):
        assign, targets = env.assignment[b], env.targets[b]
        _check_matching(env, b, pos[b], targets)
        d = np.linalg.norm(pos[b][:, None] - targets[None], axis=-1)
        thr = env.params["success_threshold"]
        for t in np.flatnonzero(d.min(0) < thr):
            i = int(d[:, t].argmin())  # the target's nearest agent
            if (d[i] < thr).sum() == 1:  # an edge to this target only: it holds the target
                assert assign[i] == t


def test_radio_needs_the_threshold_matching():
    with pytest.raises(ValueError, match="landmark_order='radio' needs assignment"):
        _make(20, assignment="exact", landmark_neighbours=4, sense_radius=1.0, landmark_occupancy=True,
              landmark_order="radio")  # fmt: skip


def test_free_needs_neighbour_lists():
    with pytest.raises(ValueError, match="assignment='free' needs neighbours=K"):
        taichi_swarm.make("coverage", 2, 5, assignment="free", array="numpy")
    for retired in ("greedy", "nearest"):
        with pytest.raises(ValueError, match="assignment must be one of"):
            taichi_swarm.make("coverage", 2, 5, assignment=retired, array="numpy")
