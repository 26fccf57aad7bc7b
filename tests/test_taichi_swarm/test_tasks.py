"""Assignment, targets, rewards, episode ends and auto-reset, every task."""

import numpy as np
import pytest
from mpe_reference import formation_targets, line_targets, matched_distances

import taichi_swarm


@pytest.mark.parametrize("M", [1, 2, 3, 4, 7, 10, 13, 20])
def test_assignment_is_optimal_like_scipy(M):
    B = 24
    env = taichi_swarm.make("coverage", B, M, seed=M, array="numpy")
    env.reset()
    rng = np.random.default_rng(100 + M)
    for trial in range(3):
        pos = rng.uniform(-1, 1, size=(B, M, 2))
        lmk = rng.uniform(-1, 1, size=(B, M, 2))
        if trial == 2:  # ties: several agents on the same spot
            pos[:, : (M + 1) // 2] = pos[:, :1]
        env.set_state(pos=pos, landmarks=lmk)
        for b in range(B):
            ref_d, ref_cost = matched_distances(pos[b].astype(np.float32), lmk[b].astype(np.float32))
            assign = env.assignment[b]
            assert sorted(assign.tolist()) == list(range(M)), "not a permutation"
            np.testing.assert_allclose(env.matched_dist[b].sum(), ref_cost, rtol=1e-5, atol=1e-5)
            # d*_i is the distance to the target the assignment gives agent i
            own = np.linalg.norm(pos[b] - lmk[b][assign], axis=-1)
            np.testing.assert_allclose(env.matched_dist[b], own, rtol=1e-5, atol=1e-5)


def test_formation_targets_reanchor_on_smallest_angle_agent():
    M = 5
    env = taichi_swarm.make("formation", 4, M, seed=3, array="numpy")
    env.reset()
    rng = np.random.default_rng(0)
    for _ in range(4):
        env.step(rng.integers(0, 5, size=(4, M)))
        s = env.get_state()
        for b in range(4):
            ref = formation_targets(s["pos"][b], s["landmarks"][b, 0])
            np.testing.assert_allclose(env.targets[b], ref, atol=1e-5)
            d, _ = matched_distances(s["pos"][b], ref)
            reward = -np.clip(d, 0, 2).mean()
            if not env.done[b]:
                assert env.reward[b] == pytest.approx(reward, abs=1e-5)


def test_line_landmarks_and_targets():
    M = 6
    env = taichi_swarm.make("line", 256, M, seed=5, array="numpy")
    env.reset()
    s = env.get_state()
    l0, l1 = s["landmarks"][:, 0], s["landmarks"][:, 1]
    assert np.all(np.abs(l0) <= 0.25)
    assert np.all(np.abs(l1) < 1.0)
    np.testing.assert_allclose(np.linalg.norm(l1 - l0, axis=-1), 1.25, atol=1e-5)
    for b in range(0, 256, 37):
        np.testing.assert_allclose(env.targets[b], line_targets(l0[b], l1[b], M), atol=1e-5)


def test_coverage_reward_and_success_threshold():
    M = 3
    env = taichi_swarm.make("coverage", 2, M, seed=0, array="numpy")
    env.reset()
    lmk = np.array([[[0.5, 0.5], [-0.5, 0.5], [0.0, -0.5]]] * 2)
    # env 0: every agent 0.05 from a landmark (success, < 0.1); env 1: one agent 0.15 away
    pos = lmk + np.array(
        [
            [
                [
                    0.05,
                    0,
                ],
                [0, 0.05],
                [-0.05, 0],
            ],
            [[0.05, 0], [0, 0.05], [-0.15, 0]],
        ]
    )
    env.set_state(pos=pos, vel=np.zeros((2, M, 2)), landmarks=lmk, step=np.zeros(2, dtype=np.int32))
    env.step(np.zeros((2, M), dtype=np.int64))  # no-op: nobody moves
    assert env.done.tolist() == [True, False]
    ep = env.info["episode"]
    assert ep["success"][0] and not ep["truncated"][0] and ep["length"][0] == 1
    np.testing.assert_allclose(ep["matched_dist"][0], 0.05, atol=1e-6)
    assert env.reward[0] == pytest.approx(-0.05, abs=1e-6)
    assert env.reward[1] == pytest.approx(-(0.05 + 0.05 + 0.15) / 3, abs=1e-6)
    # coverage DIST: mean distance from each landmark to its closest agent
    assert ep["dist"][0] == pytest.approx(0.05, abs=1e-6)


@pytest.mark.parametrize("task", taichi_swarm.TASKS)
def test_episodes_end_at_time_limit_and_reset_fresh(task):
    B, M = 8, 3
    env = taichi_swarm.make(task, B, M, seed=11, array="numpy")
    obs = env.reset()
    first = env.get_state()
    for t in range(1, 51):
        last_obs = {k: v.copy() for k, v in obs.items()}
        obs, reward, done, info = env.step(np.zeros((B, M), dtype=np.int64))  # agents stay put
        if t < 50:
            assert not done.any()
    assert done.all()
    ep = info["episode"]
    assert (ep["length"] == 50).all() and ep["truncated"].all() and not ep["success"].any()
    # terminal observation = the state after the 50th step, not the reset one
    np.testing.assert_allclose(info["terminal_obs"]["self"][:, :, 2:], first["pos"], atol=1e-6)
    np.testing.assert_allclose(info["terminal_obs"]["entities"], last_obs["entities"], atol=1e-6)
    new = env.get_state()
    assert (new["step"] == 0).all()
    assert not np.allclose(new["pos"], first["pos"]), "auto-reset replayed the first state"
    assert not np.allclose(new["landmarks"], first["landmarks"])
    np.testing.assert_allclose(obs["self"][:, :, 2:], new["pos"])


def test_success_thresholds_and_task_params():
    assert taichi_swarm.make("coverage", 1, 2).params["success_threshold"] == 0.1
    assert taichi_swarm.make("formation", 1, 2).params["success_threshold"] == 0.05
    assert taichi_swarm.make("line", 1, 2).params["success_threshold"] == 0.05
    env = taichi_swarm.make("coverage", 2, 2, max_steps=5, seed=0, array="numpy")
    env.reset()
    for _ in range(5):
        _, _, done, info = env.step(np.zeros((2, 2), dtype=np.int64))
    assert done.all() and (info["episode"]["length"] == 5).all()


@pytest.mark.parametrize("task", taichi_swarm.TASKS)
def test_observation_layout_and_graph(task):
    B, M = 4, 5
    env = taichi_swarm.make(task, B, M, comm="rc", comm_radius=0.6, seed=2, array="numpy")
    obs = env.reset()
    s = env.get_state()
    L = env.num_landmarks
    assert obs["self"].shape == (B, M, 4) and obs["entities"].shape == (B, M, L, 2)
    np.testing.assert_allclose(obs["self"][..., 2:], s["pos"])
    np.testing.assert_allclose(obs["entities"], s["landmarks"][:, None] - s["pos"][:, :, None], atol=1e-6)
    dist = np.linalg.norm(s["pos"][:, :, None] - s["pos"][:, None], axis=-1)
    np.testing.assert_array_equal(obs["adj"], dist <= 0.6)
    assert obs["adj"][:, np.arange(M), np.arange(M)].all()
    uc = taichi_swarm.make(task, B, M, comm="uc", seed=2, array="numpy").reset()
    assert uc["adj"].all()


def test_same_seed_same_trajectory_and_envs_differ():
    def rollout(seed):
        env = taichi_swarm.make("coverage", 16, 4, seed=seed, array="numpy")
        env.reset()
        rng = np.random.default_rng(0)
        out = []
        for _ in range(60):  # crosses an auto-reset
            obs, r, d, _ = env.step(rng.integers(0, 5, size=(16, 4)))
            out.append(obs["self"].copy())
        return np.stack(out)

    a, b, c = rollout(7), rollout(7), rollout(8)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    # different environments of one batch start differently
    env = taichi_swarm.make("coverage", 16, 4, seed=7, array="numpy")
    pos = env.reset()["self"][..., 2:]
    assert len({tuple(np.round(p.ravel(), 6)) for p in pos}) == 16
    # reset(seed) restarts the streams
    first = env.reset(seed=3)["self"].copy()
    env.reset()
    np.testing.assert_array_equal(env.reset(seed=3)["self"], first)


def test_torch_outputs_share_memory_with_the_env():
    import torch

    env = taichi_swarm.make("coverage", 4, 3, seed=0)
    obs = env.reset()
    assert isinstance(obs["self"], torch.Tensor) and obs["adj"].dtype == torch.bool
    before = obs["self"].clone()
    obs2, reward, done, info = env.step(torch.full((4, 3), 2, dtype=torch.int64))
    assert obs2["self"] is obs["self"] and not torch.equal(before, obs["self"])
    assert reward.dtype == torch.float32 and reward.shape == (4,) and done.dtype == torch.bool


@pytest.mark.slow
@pytest.mark.parametrize("M", [50, 100])
def test_large_teams_run(M):
    env = taichi_swarm.make("coverage", 2, M, seed=0, array="numpy")
    env.reset()
    obs, r, d, _ = env.step(np.random.default_rng(0).integers(0, 5, size=(2, M)))
    assert np.isfinite(obs["self"]).all() and np.isfinite(r).all()
    assert sorted(env.assignment[0].tolist()) == list(range(M))


@pytest.mark.parametrize("M", [3, 5, 10, 20])
def test_assignment_stays_optimal_while_agents_move(M):
    """Step after step (episodes resetting inside too) the assignment stays scipy's optimum."""
    B = 16
    env = taichi_swarm.make("coverage", B, M, seed=M, array="numpy", max_steps=12)
    env.reset()
    rng = np.random.default_rng(M)
    for _ in range(30):
        env.step(rng.integers(0, 5, size=(B, M)))
        s = env.get_state()
        for b in range(B):
            _, ref_cost = matched_distances(s["pos"][b], s["landmarks"][b])
            assert sorted(env.assignment[b].tolist()) == list(range(M))
            np.testing.assert_allclose(env.matched_dist[b].sum(), ref_cost, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(("task", "M"), [("coverage", 1), ("coverage", 3), ("formation", 4), ("line", 2)])
def test_kernels_specialised_for_small_teams_match_the_generic_ones(task, M):
    """M <= 4 runs kernels compiled for that exact M (and enumerates the assignments);
    forcing the generic kernels (M read at run time, Jonker-Volgenant) must agree."""
    B = 8
    envs = [taichi_swarm.make(task, B, M, comm="rc", seed=11, array="numpy") for _ in range(2)]
    assert envs[0]._sm == M
    envs[1]._sm = 0  # the generic kernels
    for env in envs:
        env.reset()
    rng = np.random.default_rng(0)
    for _ in range(60):  # episodes end at 50 steps: resets included
        actions = rng.integers(0, 5, size=(B, M))
        out = [env.step(actions) for env in envs]
        (obs0, r0, d0, _), (obs1, r1, d1, _) = out
        for key in ("self", "entities"):
            np.testing.assert_allclose(obs0[key], obs1[key], atol=1e-5)
        np.testing.assert_array_equal(obs0["adj"], obs1["adj"])
        np.testing.assert_array_equal(d0, d1)
        # equal optimal cost; the assignments may differ where the optimum is tied
        np.testing.assert_allclose(envs[0].matched_dist.sum(1), envs[1].matched_dist.sum(1), atol=1e-5)
        if task == "coverage":  # -mean(d): the same for every optimal assignment
            np.testing.assert_allclose(r0, r1, atol=1e-5)
        else:  # -mean(clip(d, 0, 2)) can tell tied optima apart (formation: the anchor agent
            # is in line with two opposite targets); each env is consistent with its own
            for env, r in zip(envs, (r0, r1), strict=True):
                live = ~env.done
                want = -np.clip(env.matched_dist, 0, 2).mean(1)
                np.testing.assert_allclose(r[live], want[live], atol=1e-5)
