"""Neighbour and landmark lists (make(..., neighbours=K, landmark_neighbours=KL)): the same
simulation as the dense layout when the lists hold everyone, and the K nearest of a
scipy cKDTree otherwise, with what was cut counted."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

import taichi_swarm


def _heard_from_lists(nbr, mask):
    """[B, M, M] bool: agent i lists agent j."""
    B, M, _ = nbr.shape
    out = np.zeros((B, M, M), bool)
    b, i, _ = np.nonzero(mask)
    out[b, i, nbr[mask]] = True
    return out


def _check_lists_match_adj(nbr, mask, adj, pos):
    M = nbr.shape[1]
    heard = adj & ~np.eye(M, dtype=bool)  # the lists exclude the agent itself
    np.testing.assert_array_equal(_heard_from_lists(nbr, mask), heard)
    # nearest first; unused slots hold the agent's own index
    d2 = ((pos[:, :, None, :] - pos[:, None, :, :]) ** 2).sum(-1)
    listed_d2 = np.take_along_axis(d2, nbr.astype(np.int64), axis=2)
    listed_d2 = np.where(mask, listed_d2, 1e30)  # the listed slots come first
    assert (np.diff(listed_d2, axis=2) >= -1e-6).all()
    own = np.broadcast_to(np.arange(M)[None, :, None], nbr.shape)
    np.testing.assert_array_equal(nbr[~mask], own[~mask])


@pytest.mark.parametrize(
    ("task", "M", "comm", "action_space"),
    [
        ("coverage", 6, "rc", "discrete"),
        ("coverage", 12, "uc", "discrete"),
        ("formation", 7, "rc", "discrete"),
        ("line", 5, "uc", "discrete"),
        ("coverage", 9, "rc", "continuous"),
    ],
)
def test_lists_holding_everyone_are_the_dense_simulation(task, M, comm, action_space):
    """K >= M - 1: the lists are the adjacency (minus self), and the trajectories, rewards,
    episode ends, statistics and terminal observations are the dense layout's, bit for bit
    (contacts are summed in the same order)."""
    B = 6
    kw = dict(comm=comm, comm_radius=0.6, seed=4, array="numpy", action_space=action_space, max_steps=20)
    dense = taichi_swarm.make(task, B, M, **kw)
    lists = taichi_swarm.make(task, B, M, neighbours=M - 1 + (M % 2), assignment="exact", **kw)
    assert "adj" not in lists.obs and "adj" not in lists.info["terminal_obs"]
    od, ol = dense.reset(), lists.reset()
    rng = np.random.default_rng(1)
    ends = 0
    for _ in range(45):  # episodes end at 20 steps: auto-resets included
        if action_space == "continuous":
            a = rng.uniform(-1.5, 1.5, size=(B, M, 2)).astype(np.float32)
        else:
            a = rng.integers(0, 5, size=(B, M))
        od, rd, dd, idn = dense.step(a)
        ol, rl, dl, il = lists.step(a)
        for key in ("self", "entities"):
            np.testing.assert_array_equal(ol[key], od[key])
        np.testing.assert_array_equal(rl, rd)
        np.testing.assert_array_equal(dl, dd)
        _check_lists_match_adj(ol["nbr"], ol["nbr_mask"], od["adj"], od["self"][..., 2:])
        assert (lists.info["neighbours"]["dropped"] == 0).all()
        np.testing.assert_array_equal(lists.info["neighbours"]["in_range"], od["adj"].sum(-1) - 1)
        if dd.any():
            ends += int(dd.sum())
            for key in ("success", "length", "return", "matched_dist", "dist", "covered"):
                np.testing.assert_array_equal(il["episode"][key][dd], idn["episode"][key][dd])
            td, tl = idn["terminal_obs"], il["terminal_obs"]
            for key in ("self", "entities"):
                np.testing.assert_array_equal(tl[key][dd], td[key][dd])
            _check_lists_match_adj(tl["nbr"][dd], tl["nbr_mask"][dd], td["adj"][dd], td["self"][dd][..., 2:])
    assert ends > 0


def test_contacts_through_the_grid_in_a_crowd():
    """Agents packed so that many touch: the grid finds the same contact forces."""
    B, M = 2, 40
    kw = dict(comm="rc", comm_radius=0.3, seed=0, array="numpy")
    dense = taichi_swarm.make("coverage", B, M, **kw)
    lists = taichi_swarm.make("coverage", B, M, neighbours=8, **kw)
    rng = np.random.default_rng(2)
    pos = rng.uniform(-0.25, 0.25, size=(B, M, 2))  # 40 discs of radius 0.05 in a 0.5 x 0.5 square
    dense.set_state(pos=pos)
    lists.set_state(pos=pos)
    assert (lists.info["neighbours"]["dropped"] > 0).all()  # 8 slots, more heard
    touching = 0
    for _ in range(10):
        p = lists.get_state()["pos"]
        gaps = np.linalg.norm(p[:, :, None] - p[:, None], axis=-1) + 9 * np.eye(M)
        touching += int((gaps < 0.1).sum())
        a = rng.integers(0, 5, size=(B, M))
        od, *_ = dense.step(a)
        ol, *_ = lists.step(a)
        np.testing.assert_array_equal(ol["self"], od["self"])
    assert touching > 20


def _kdtree_lists(pos, radius, K, skip_self=True):
    """Reference: per point the K nearest within radius (float32 squared distances, ties
    by index), and how many were in range."""
    pos = pos.astype(np.float32)
    tree = cKDTree(pos.astype(np.float64))
    lists, counts = [], []
    for i, p in enumerate(pos):
        cand = tree.query_ball_point(p, radius * 1.001 + 1e-6)
        cand = [j for j in cand if not (skip_self and j == i)]
        d = pos[cand] - p
        d2 = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).astype(np.float32)
        keep = d2 <= np.float32(radius) * np.float32(radius)
        cand, d2 = np.asarray(cand)[keep], d2[keep]
        order = np.lexsort((cand, d2))
        lists.append(cand[order][:K].tolist())
        counts.append(len(cand))
    return lists, np.asarray(counts)


@pytest.mark.parametrize(("M", "half_width", "radius", "K"), [(200, 2.0, 0.5, 6), (1000, 5.0, 0.4, 16)])
def test_lists_are_the_k_nearest_of_a_kdtree(M, half_width, radius, K):
    B = 2
    env = taichi_swarm.make("coverage", B, M, comm="rc", comm_radius=radius, neighbours=K, seed=0, array="numpy")
    env.reset()
    rng = np.random.default_rng(M)
    pos = rng.uniform(-half_width, half_width, size=(B, M, 2))
    pos[:, : M // 10] = rng.normal(0.0, 0.1, size=(B, M // 10, 2))  # a crowd: more than K in range
    pos[1, -3:] = [[50.0, 50.0], [50.0 + radius, 50.0], [-77.0, 3.0]]  # far out, one exactly at the radius
    obs = env.set_state(pos=pos)
    pos32 = env.get_state()["pos"]
    for b in range(B):
        ref, counts = _kdtree_lists(pos32[b], radius, K)
        nbr, mask = obs["nbr"][b], obs["nbr_mask"][b]
        for i in range(M):
            got = nbr[i][mask[i]].tolist()
            assert got == ref[i], f"env {b} agent {i}: {got} != {ref[i]}"
        np.testing.assert_array_equal(env.info["neighbours"]["in_range"][b], counts)
        assert env.info["neighbours"]["dropped"][b] == np.maximum(counts - K, 0).sum()
        assert env.info["neighbours"]["dropped"][b] > 0
    assert obs["nbr_mask"][1, M - 1].sum() == 0  # the lone agent hears nobody


def test_uc_lists_are_the_k_nearest_of_all():
    B, M, K = 2, 30, 5
    env = taichi_swarm.make("coverage", B, M, comm="uc", neighbours=K, seed=1, array="numpy")
    obs = env.reset()
    pos = env.get_state()["pos"]
    for b in range(B):
        ref, _ = _kdtree_lists(pos[b], 100.0, K)
        for i in range(M):
            assert obs["nbr"][b, i].tolist() == ref[i]
    assert obs["nbr_mask"].all()
    assert (env.info["neighbours"]["in_range"] == M - 1).all()
    assert (env.info["neighbours"]["dropped"] == M * (M - 1 - K)).all()


@pytest.mark.parametrize(("M", "KL", "sense"), [(200, 4, 0.3), (1000, 8, 0.25)])
def test_landmark_lists_are_the_nearest_landmarks_of_a_kdtree(M, KL, sense):
    B = 2
    env = taichi_swarm.make(
        "coverage", B, M, comm="rc", comm_radius=0.3, neighbours=8, landmark_neighbours=KL, sense_radius=sense,
        scale="density", seed=3, array="numpy",
    )  # fmt: skip
    obs = env.reset()
    assert obs["entities"].shape == (B, M, KL, 2) and obs["entity_mask"].shape == (B, M, KL)
    s = env.get_state()
    for b in range(B):
        pos, lmk = s["pos"][b], s["landmarks"][b].astype(np.float32)
        tree = cKDTree(lmk.astype(np.float64))
        for i in range(M):
            cand = np.asarray(tree.query_ball_point(pos[i], sense * 1.001 + 1e-6), dtype=np.int64)
            off = lmk[cand] - pos[i]
            d2 = (off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1]).astype(np.float32)
            keep = d2 <= np.float32(sense) ** 2
            cand, d2 = cand[keep], d2[keep]
            ref = cand[np.lexsort((cand, d2))][:KL]
            mask = obs["entity_mask"][b, i]
            assert mask.sum() == len(ref)
            np.testing.assert_array_equal(obs["entities"][b, i][mask], lmk[ref] - pos[i])
            np.testing.assert_array_equal(obs["entities"][b, i][~mask], 0.0)
    assert obs["entity_mask"].any() and not obs["entity_mask"].all()


def test_landmark_lists_holding_everything_are_the_dense_entities():
    """KL = L and a sense radius beyond the arena: the same entities, reordered nearest first."""
    B, M = 3, 8
    kw = dict(comm="rc", comm_radius=0.5, seed=7, array="numpy")
    dense = taichi_swarm.make("coverage", B, M, **kw)
    lists = taichi_swarm.make("coverage", B, M, neighbours=M, landmark_neighbours=M, sense_radius=10.0, **kw)
    dense.reset(), lists.reset()
    rng = np.random.default_rng(0)
    for _ in range(5):
        a = rng.integers(0, 5, size=(B, M))
        od, *_ = dense.step(a)
        ol, *_ = lists.step(a)
        assert ol["entity_mask"].all()
        d = np.linalg.norm(od["entities"], axis=-1)
        order = np.argsort(d, axis=-1, kind="stable")
        np.testing.assert_array_equal(ol["entities"], np.take_along_axis(od["entities"], order[..., None], axis=2))


def test_list_snapshots_restore_bit_identically():
    env = taichi_swarm.make("coverage", 3, 20, comm="rc", comm_radius=0.5, neighbours=4, seed=0, array="numpy")
    env.reset()
    rng = np.random.default_rng(0)
    acts = rng.integers(0, 5, size=(8, 3, 20))
    snap = env.snapshot()
    first = [env.step(a)[0]["nbr"].copy() for a in acts]
    env.restore(snap)
    again = [env.step(a)[0]["nbr"].copy() for a in acts]
    np.testing.assert_array_equal(np.stack(first), np.stack(again))
    dense = taichi_swarm.make("coverage", 3, 20, comm="rc", comm_radius=0.5, seed=0, array="numpy")
    with pytest.raises(ValueError, match="cannot restore"):
        dense.restore(snap)


@pytest.mark.parametrize(
    ("task", "kwargs", "field"),
    [
        ("coverage", {"neighbours": 0}, "neighbours"),
        ("coverage", {"neighbours": 2.5}, "neighbours"),
        ("coverage", {"landmark_neighbours": 4}, "sense_radius"),  # (needs one)
        ("coverage", {"sense_radius": 0.5}, "sense_radius"),  # (only used with landmark_neighbours)
        ("coverage", {"landmark_neighbours": 0, "sense_radius": 0.5}, "landmark_neighbours"),
        ("coverage", {"landmark_neighbours": 2, "sense_radius": -1.0}, "sense_radius"),
        ("line", {"landmark_neighbours": 1, "sense_radius": 0.5}, "scale"),  # (its listed targets need density)
        ("formation", {"landmark_neighbours": 1, "sense_radius": 0.5}, "scale"),
        ("coverage", {"scale": "area"}, "scale"),
    ],
)
def test_bad_list_options_are_refused(task, kwargs, field):
    with pytest.raises(taichi_swarm.ConfigError) as refused:
        taichi_swarm.make(task, 2, 4, array="numpy", **kwargs)
    assert refused.value.field == field


def _occupancy_reference(pos, lmk, entities, mask, sense):
    """Each listed landmark's distance to its nearest agent other than the observer, capped at
    sense (float64 brute force over all agents; the landmark found from the listed offset)."""
    M = len(pos)
    out = np.zeros(mask.shape, dtype=np.float64)
    for i in range(M):
        for k in np.flatnonzero(mask[i]):
            lm = pos[i] + entities[i, k, :2]
            l = np.argmin(np.abs(lmk - lm).sum(-1))  # the landmark the offset points at
            d = np.linalg.norm(pos.astype(np.float64) - lmk[l].astype(np.float64), axis=-1)
            d[i] = np.inf
            out[i, k] = min(d.min(), sense)
    return out


@pytest.mark.parametrize(("M", "comm"), [(200, "rc"), (150, "uc")])
def test_landmark_occupancy_is_the_nearest_other_agents_distance(M, comm):
    """landmark_occupancy adds a third landmark feature, checked against a brute force over all
    agents after steps; the offsets, masks and the whole simulation are those without it."""
    B, sense = 2, 0.6
    kw = dict(comm=comm, comm_radius=0.8, neighbours=6, landmark_neighbours=5, sense_radius=sense)
    kw.update(scale="density", seed=4, array="numpy")
    occ = taichi_swarm.make("coverage", B, M, landmark_occupancy=True, **kw)
    plain = taichi_swarm.make("coverage", B, M, **kw)
    oo, op = occ.reset(), plain.reset()
    rng = np.random.default_rng(1)
    for step in range(4):
        if step:
            a = rng.integers(0, 5, size=(B, M))
            oo, ro, do, io = occ.step(a)
            op, rp, dp, ip = plain.step(a)
            np.testing.assert_array_equal(ro, rp)
            np.testing.assert_array_equal(do, dp)
        assert oo["entities"].shape == (B, M, 5, 3)
        np.testing.assert_array_equal(oo["entities"][..., :2], op["entities"])
        np.testing.assert_array_equal(oo["entity_mask"], op["entity_mask"])
        np.testing.assert_array_equal(oo["nbr"], op["nbr"])
        s = occ.get_state()
        for b in range(B):
            ref = _occupancy_reference(s["pos"][b], s["landmarks"][b], oo["entities"][b], oo["entity_mask"][b], sense)
            np.testing.assert_allclose(oo["entities"][b, ..., 2], ref, atol=2e-6)
            np.testing.assert_array_equal(oo["entities"][b, ..., 2][~oo["entity_mask"][b]], 0.0)
    third = oo["entities"][..., 2][oo["entity_mask"]]
    assert (third < sense).any() and (third == np.float32(sense)).any()  # both held and free landmarks seen


def test_an_observation_reads_nothing_beyond_its_sensing_and_hearing():
    """Locality of landmark_order "nearest" with occupancy (the radio's own: test_radio_auction.py):
    an agent's observation depends only on agents within its comm radius (whom it hears) or within
    the sense radius of a landmark it senses (the occupancy reading). Every other agent moved, by
    any amount within the arena's far side, changes nothing it reads; one moved onto a landmark
    it senses changes its reading (so the check can fail)."""
    M, sense, radius = 200, 0.6, 0.8
    kw = dict(comm="rc", comm_radius=radius, neighbours=6, landmark_neighbours=5, sense_radius=sense)
    env = taichi_swarm.make("coverage", 1, M, landmark_occupancy=True, scale="density", seed=4, array="numpy", **kw)
    env.reset()
    state = env.get_state()
    pos, lmk = state["pos"][0].astype(np.float64), state["landmarks"][0].astype(np.float64)
    counts = (np.linalg.norm(lmk[None] - pos[:, None], axis=-1) <= sense).sum(1)
    o = int(counts.argmax())  # the observer: the agent sensing the most landmarks
    sensed = lmk[np.linalg.norm(lmk - pos[o], axis=-1) <= sense]
    reach = np.linalg.norm(pos - pos[o], axis=-1) <= radius + 1e-6
    for q in sensed:
        reach |= np.linalg.norm(pos - q, axis=-1) <= sense + 1e-6
    far = np.flatnonzero(~reach)
    assert len(sensed) >= 2 and len(far) > M // 2

    def observe(p):
        obs = env.set_state(pos=p[None].astype(np.float32), vel=np.zeros((1, M, 2)), step=np.zeros(1, dtype=np.int64))
        return {k: np.asarray(v)[0, o].copy() for k, v in obs.items()}

    before = observe(pos)
    moved = pos.copy()
    corner = pos[o] - 3 * (radius + 2 * sense) * np.sign(pos[o] + 1e-9)  # the far side of the observer
    moved[far] = corner + np.random.default_rng(0).uniform(-0.5, 0.5, size=(len(far), 2))
    after = observe(moved)
    for k in before:
        np.testing.assert_array_equal(before[k], after[k], err_msg=k)
    near = moved.copy()
    near[far[0]] = sensed[0] + (0.01, 0.0)  # a stranger onto a landmark the observer senses
    assert not np.array_equal(observe(near)["entities"], before["entities"])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"landmark_order": "radio", "neighbours": 4, "landmark_neighbours": 2, "sense_radius": 0.5}, "landmark_order"),
        ({"landmark_order": "held"}, "landmark_order"),
        ({"landmark_order": "auction"}, "landmark_order"),
        ({"landmark_occupancy": True}, "landmark_occupancy"),  # (needs both lists)
        ({"landmark_occupancy": True, "neighbours": 4}, "landmark_occupancy"),
        (
            {"landmark_occupancy": 1, "neighbours": 4, "landmark_neighbours": 2, "sense_radius": 0.5},
            "landmark_occupancy",
        ),  # noqa: E501
    ],
)
def test_bad_occupancy_options_are_refused(kwargs, field):
    with pytest.raises(taichi_swarm.ConfigError) as refused:
        taichi_swarm.make("coverage", 2, 4, array="numpy", **kwargs)
    assert refused.value.field == field


def _assert_same(a, b, where):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, tuple | list):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        assert a == b, where


@pytest.mark.parametrize(
    ("task", "M", "kwargs"),
    [
        ("coverage", 40, dict(comm="rc", neighbours=6, landmark_neighbours=5, sense_radius=0.8,
                              landmark_occupancy=True, assignment="free", scale="density")),
        ("coverage", 12, dict(comm="uc", neighbours=4)),  # the exact assignment, every landmark seen
        ("formation", 20, dict(comm="rc", neighbours=5, landmark_neighbours=6, sense_radius=0.8, scale="density",
                               assignment="free")),
        ("line", 30, dict(comm="rc", neighbours=4, scale="density", action_space="continuous")),
    ],
)  # fmt: skip
def test_agent_parallel_step_is_the_env_step_bit_for_bit(task, M, kwargs):
    """The agent-parallel step (the default on CUDA) against one thread per environment: every
    observation, reward, done, episode statistic and dropped count equal, through auto-resets
    (episodes of 50 steps)."""
    B = 3
    envs = [taichi_swarm.make(task, B, M, seed=5, array="numpy", agent_parallel=w, **kwargs) for w in (False, True)]
    assert [e._agent_parallel for e in envs] == [False, True]
    out = [e.reset() for e in envs]
    _assert_same(out[0], out[1], "reset")
    rng = np.random.default_rng(1)
    for t in range(60):
        if kwargs.get("action_space") == "continuous":
            a = rng.uniform(-1.5, 1.5, size=(B, M, 2)).astype(np.float32)
        else:
            a = rng.integers(0, 5, size=(B, M))
        out = [e.step(a) for e in envs]
        _assert_same(out[0], out[1], f"step {t}")
    _assert_same(envs[0].get_state(), envs[1].get_state(), "state")


def test_agent_parallel_is_the_default_for_many_agents_on_the_cpu():
    """One thread per env below WIDE_CPU_AGENTS agents per step (each pass's dispatch would cost
    more than it saves), agent by agent from there; never without lists."""
    from taichi_swarm.env import WIDE_CPU_AGENTS

    def wide(B, M, **kw):
        return taichi_swarm.make("coverage", B, M, comm="rc", array="numpy", **kw)._agent_parallel

    assert not wide(WIDE_CPU_AGENTS // 64 - 1, 64, neighbours=4)
    assert wide(WIDE_CPU_AGENTS // 64, 64, neighbours=4)
    assert not wide(WIDE_CPU_AGENTS // 64, 64)  # the dense layout
    assert not wide(WIDE_CPU_AGENTS // 64, 64, neighbours=4, agent_parallel=False)


def test_agent_parallel_needs_lists():
    with pytest.raises(ValueError, match="agent_parallel needs neighbours"):
        taichi_swarm.make("coverage", 2, 3, agent_parallel=True)
    with pytest.raises(ValueError, match="agent_parallel must be one of"):
        taichi_swarm.make("coverage", 2, 3, neighbours=2, agent_parallel="yes")
