"""landmark_order="auction" (auction.local_solve): each agent lists only the landmark it wins in
the agents' own auction over the landmarks each senses. Pinned here: the winners form the
eps-optimal min-sum matching of agents to their KL nearest landmarks within sense_radius (scipy
over the same candidates), under both step kernels alike, and list their landmark alone; an
agent priced out of a crowd wins nothing and reads the claim-zero lists; and the order needs
the threshold matching. With a budget of bid rounds a step (auction_rounds), the auction carries
over from step to step, spends no more rounds than the budget, and ends at the same optimum."""

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import taichi_swarm
from taichi_swarm import auction

KL, SENSE = 8, 1.5


def _make(M, B=2, task="line", wide=False, order="auction", rounds=None):
    return taichi_swarm.make(
        task, B, M, comm="rc", comm_radius=1.0, neighbours=8, assignment="free", seed=7, array="numpy",
        scale="density", landmark_neighbours=KL, sense_radius=SENSE, landmark_occupancy=True,
        landmark_order=order, agent_parallel=wide, auction_rounds=rounds,
    )  # fmt: skip


def _won(env):
    """The auction's answer as the kernels left it: each agent's landmark (-1: none)."""
    return np.asarray(env._view("bid_won")).copy()


def _check_winners_list_their_landmark_alone(obs, won, pos, landmarks, thr):
    mask, ent = np.asarray(obs["entity_mask"]), np.asarray(obs["entities"])
    for b in range(won.shape[0]):
        w = won[b] >= 0
        assert (mask[b, w].sum(-1) == 1).all() and mask[b, w, 0].all()
        np.testing.assert_allclose(ent[b, w, 0, :2], landmarks[b, won[b, w]] - pos[b, w], atol=1e-5)
        assert (ent[b, w, 0, 2] >= thr - 1e-6).all()  # read free: the occupancy floored at the threshold


def test_the_winners_are_the_min_sum_matching_over_what_each_agent_senses():
    """After a step, under both step kernels alike (step_kernel and the per-agent passes of
    step_wide_kernel), bit for bit."""
    M, B = 60, 2
    envs = [_make(M, B, wide=wide) for wide in (False, True)]
    rng = np.random.default_rng(3)
    for env in envs:
        env.reset()
    lmk = envs[0].get_state()["landmarks"]
    start = lmk + rng.normal(0.0, 0.4, size=(B, M, 2))  # near their rows, scrambled
    obs = []
    for env in envs:
        env.set_state(pos=start, vel=np.zeros((B, M, 2)), landmarks=lmk, step=np.zeros(B, dtype=np.int64))
        obs.append(env.step(np.zeros((B, M), dtype=np.int64))[0])
    for key in ("entities", "entity_mask"):
        np.testing.assert_array_equal(np.asarray(obs[0][key]), np.asarray(obs[1][key]))
    pos = envs[0].get_state()["pos"]
    won = _won(envs[0])
    np.testing.assert_array_equal(won, _won(envs[1]))
    thr = envs[0].params["success_threshold"]
    _check_winners_list_their_landmark_alone(obs[0], won, pos, lmk, thr)
    for b in range(B):
        got, best = _cost_and_optimum(won[b], pos[b], lmk[b])
        assert best - 1e-3 <= got <= best + M * auction.LOCAL_EPS
        assert (won[b] >= 0).mean() > 0.9


def _cost_and_optimum(won, pos, lmk):
    """The auction's total cost (a winner's distance to its landmark, OUT sense radii for staying
    out) and scipy's optimum over the same choices: the KL nearest within SENSE, or staying out."""
    winners = won[won >= 0]
    assert len(set(winners.tolist())) == len(winners), "two agents won one landmark"
    M, out = len(won), auction.OUT * SENSE
    d = np.linalg.norm(pos[:, None] - lmk[None], axis=-1)
    cand = np.full((M, len(lmk) + M), 1e3)
    cand[:, len(lmk) :] = out
    for i in range(M):
        near = np.argsort(d[i])[:KL]
        near = near[d[i, near] <= SENSE]
        cand[i, near] = d[i, near]
    rows, cols = linear_sum_assignment(cand)
    got = np.where(won >= 0, d[np.arange(M), np.maximum(won, 0)], out).sum()
    return got, cand[rows, cols].sum()


def _scrambled(env, B, M, seed=3):
    """Env reset, its agents placed near their landmarks, scrambled; returns (pos, landmarks)."""
    env.reset()
    lmk = env.get_state()["landmarks"]
    pos = lmk + np.random.default_rng(seed).normal(0.0, 0.4, size=(B, M, 2))
    return pos, lmk


def test_a_budget_of_rounds_carries_the_auction_over_to_the_same_optimum():
    """Agents unmoved (zero velocity, set each step): with two rounds a step the auction is not
    done at the first step, goes on from where it stopped until a round places no bid, and ends
    within its increment per agent of the optimum; the budget's state stays consistent (one holder
    per landmark, the holder's landmark among what it senses, a landmark nobody holds at price 0)."""
    M, B, eps = 60, 2, auction.ROUND_EPS
    env = _make(M, B, rounds=2)
    pos, lmk = _scrambled(env, B, M)
    prices = []
    for step in range(150):
        env.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=lmk, step=np.full(B, step, dtype=np.int64))
        prices.append(np.asarray(env._view("bid_price")).copy())
    assert (prices[1] != prices[0]).any(axis=-1).all(), "two rounds settled the auction"
    np.testing.assert_array_equal(prices[-1], prices[-2])  # settled: the last rounds placed no bid
    won = _won(env)
    for b in range(B):
        got, best = _cost_and_optimum(won[b], pos[b], lmk[b])
        assert best - 1e-3 <= got <= best + M * eps
    holder, price = np.asarray(env._view("bid_holder")), np.asarray(env._view("bid_price"))
    cand, count = np.asarray(env._view("bid_cand")), np.asarray(env._view("bid_count"))
    for b in range(B):
        held, winners = np.flatnonzero(holder[b] >= 0), np.flatnonzero(won[b] >= 0)
        np.testing.assert_array_equal(won[b, holder[b, held]], held)  # each side names the other
        np.testing.assert_array_equal(holder[b, won[b, winners]], winners)
        assert (price[b, holder[b] < 0] == 0).all()
        for i in np.flatnonzero(won[b] >= 0):
            assert won[b, i] in cand[b, i, : count[b, i]]


def test_a_budget_of_rounds_under_motion_stays_within_its_slack_in_both_step_kernels():
    """Random actions through auto-resets: both step kernels give the same lists and the same
    winners bit for bit, and a budget large enough to finish each step's bidding keeps the
    matching within HOLD_SLACK increments per agent of the optimum (a holder keeps its landmark
    until another option is better by that much)."""
    M, B, eps = 40, 2, auction.ROUND_EPS
    envs = [_make(M, B, wide=wide, rounds=rounds) for rounds in (10_000, 2) for wide in (False, True)]
    for env in envs:
        env.reset()
    rng = np.random.default_rng(1)
    for _ in range(60):  # line's episodes end at 50 steps: one auto-reset each
        actions = rng.integers(0, 5, size=(B, M))
        obs = [env.step(actions)[0] for env in envs]
        for one, wide in ((0, 1), (2, 3)):  # the budget's carried state too, where 2 rounds bind
            for key in ("entities", "entity_mask"):
                np.testing.assert_array_equal(np.asarray(obs[one][key]), np.asarray(obs[wide][key]))
            for name in ("bid_won", "bid_holder", "bid_price"):
                np.testing.assert_array_equal(np.asarray(envs[one]._view(name)), np.asarray(envs[wide]._view(name)))
        state = envs[0].get_state()
        for b in range(B):
            got, best = _cost_and_optimum(_won(envs[0])[b], state["pos"][b], state["landmarks"][b])
            assert best - 1e-3 <= got <= best + M * auction.HOLD_SLACK * eps
    assert (_won(envs[2]) >= 0).any()


def test_a_budgets_auction_starts_afresh_with_each_episode():
    """At an auto-reset the carried auction is dropped: the new episode's first rounds are those of
    a fresh start at its positions (set_state with step 0)."""
    M, B = 40, 2
    env, fresh = _make(M, B, rounds=2), _make(M, B, rounds=2)
    env.reset()
    fresh.reset()
    rng = np.random.default_rng(2)
    restarted = 0
    for _ in range(55):  # line's episodes end at 50 steps
        env.step(rng.integers(0, 5, size=(B, M)))
        state = env.get_state()
        if (state["step"] == 0).all():
            fresh.set_state(pos=state["pos"], vel=state["vel"], landmarks=state["landmarks"], step=state["step"])
            for name in ("bid_won", "bid_holder", "bid_price"):
                np.testing.assert_array_equal(np.asarray(env._view(name)), np.asarray(fresh._view(name)))
            restarted += 1
    assert restarted == 1


def test_auction_rounds_needs_the_auction_order_and_a_positive_budget():
    with pytest.raises(ValueError, match="auction_rounds is the budget of the agents' own auction"):
        _make(20, order="claim-zero", rounds=4)
    with pytest.raises(ValueError, match="auction_rounds must be >= 1, got 0"):
        _make(20, rounds=0)


def test_an_agent_priced_out_of_a_crowd_wins_nothing_and_reads_claim_zero_lists():
    """All M agents crowd round 4 landmarks: 4 win one each, the rest stay out (staying out costs
    OUT sense radii, which bounds every price, so the bidding ends) and read exactly the
    claim-zero lists of the same state."""
    M, B = 20, 1
    env = _make(M, B, task="coverage")
    env.reset()
    lmk = env.get_state()["landmarks"]
    centre = lmk[0, :4].mean(0)
    near = np.argsort(np.linalg.norm(lmk[0] - centre, axis=-1))
    rng = np.random.default_rng(0)
    # the four landmarks nearest a point stay, every other is moved out of everyone's sensing
    crowd = lmk.copy()
    crowd[0, near[4:]] = centre + 50.0 + rng.uniform(0, 5, size=(M - 4, 2))
    pos = centre + rng.uniform(-0.3, 0.3, size=(B, M, 2))
    obs = env.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=crowd)
    won = _won(env)[0]
    winners = np.flatnonzero(won >= 0)
    assert len(winners) == 4 and sorted(won[winners].tolist()) == sorted(near[:4].tolist())
    _check_winners_list_their_landmark_alone(obs, won[None], pos, crowd, env.params["success_threshold"])
    plain = _make(M, B, task="coverage", order="claim-zero")
    plain.reset()
    other = plain.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=crowd)
    losers = np.setdiff1d(np.arange(M), winners)
    for key in ("entities", "entity_mask"):
        np.testing.assert_array_equal(np.asarray(obs[key])[0, losers], np.asarray(other[key])[0, losers])
    assert (np.asarray(obs["entity_mask"])[0, losers].sum(-1) == 4).all()


def test_the_auction_order_needs_the_threshold_matching():
    with pytest.raises(ValueError, match="landmark_order='auction' needs assignment 'nearest' or 'free'"):
        taichi_swarm.make(
            "coverage", 2, 20, comm="rc", neighbours=8, landmark_neighbours=4, sense_radius=1.0,
            landmark_occupancy=True, landmark_order="auction", array="numpy",
        )  # fmt: skip
