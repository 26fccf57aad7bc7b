"""landmark_order="radio" (radio.py): the agents' auction run by messages alone, each agent keeping
its own table and merging those of the teammates on its neighbour list, auction_rounds rounds a
step. Pinned here: both step kernels give the same results bit for bit (through an auto-reset,
which starts the tables afresh); agents held still settle on one landmark each, no two on the
same, within the increment per agent of scipy's optimum over what each senses; news moves one hop
per round, so an agent farther than R hops from a change sees nothing of it at that step; no state
is kept per landmark; and the option's refusals."""

from collections import deque

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import taichi_swarm
from taichi_swarm import radio
from taichi_swarm.layout import BLOCKS

TABLE = ("radio_won", "radio_count", "radio_lid", "radio_epoch", "radio_price", "radio_holder")
# every env here shares one compiled variant (B * M^2 below env.SERIAL_BELOW_WORK: serial env loop)


def _make(M, B=2, K=8, KL=12, sense=3.0, comm_radius=1.5, rounds=None, wide=False, **kw):
    return taichi_swarm.make(
        "coverage", B, M, comm="rc", comm_radius=comm_radius, neighbours=K, assignment="free", seed=7,
        array="numpy", scale="density", landmark_neighbours=KL, sense_radius=sense, landmark_occupancy=True,
        landmark_order="radio", auction_rounds=rounds, agent_parallel=wide, **kw,
    )  # fmt: skip


def _tables(env):
    """Each agent's won and table, the slots past its count blanked (left over, never read)."""
    out = {name: np.asarray(env._view(name)).copy() for name in TABLE}
    unused = np.arange(out["radio_lid"].shape[-1]) >= out["radio_count"][..., None]
    for name in TABLE[2:]:
        out[name][unused] = -9
    return out


def _hold(env, pos, lmk, step):
    """Agents placed at ``pos`` with zero velocity at episode step ``step``: one step of the radio."""
    B, M = pos.shape[:2]
    return env.set_state(pos=pos, vel=np.zeros((B, M, 2)), landmarks=lmk, step=np.full(B, step, dtype=np.int64))


def test_both_step_kernels_agree_bit_for_bit_through_an_auto_reset():
    """Random actions for 60 steps (coverage's episodes end at 50): step_kernel and step_wide_kernel
    give the same observations, tables and message counts; at the auto-reset the tables start
    afresh (those of set_state at step 0 on the new episode's state); no per-landmark state."""
    M, B = 30, 2
    envs = [_make(M, B, K=6, KL=8, sense=2.0, comm_radius=1.0, wide=wide) for wide in (False, True)]
    fresh = _make(M, B, K=6, KL=8, sense=2.0, comm_radius=1.0)
    for env in (*envs, fresh):
        env.reset()
    assert envs[0].auction_rounds == radio.DEFAULT_ROUNDS
    for spec in BLOCKS:  # the radio keeps nothing per landmark: its blocks are per agent (or per env)
        if spec.name.startswith(("radio", "bid")):
            assert spec.per_env[:1] in ((), ("BM",), ("RM",)), spec
    rng = np.random.default_rng(1)
    restarted, held = 0, []
    for _ in range(60):
        actions = rng.integers(0, 5, size=(B, M))
        obs = [env.step(actions)[0] for env in envs]
        for key in obs[0]:
            np.testing.assert_array_equal(np.asarray(obs[0][key]), np.asarray(obs[1][key]), err_msg=key)
        tables = [_tables(env) for env in envs]
        for name in TABLE:
            np.testing.assert_array_equal(tables[0][name], tables[1][name], err_msg=name)
        for key in ("messages", "bytes"):
            np.testing.assert_array_equal(envs[0].info["radio"][key], envs[1].info["radio"][key])
        state = envs[0].get_state()
        if (state["step"] == 0).all():
            _hold(fresh, state["pos"], state["landmarks"], 0)
            for name in TABLE:
                np.testing.assert_array_equal(tables[0][name], _tables(fresh)[name], err_msg=name)
            restarted += 1
        held.append((tables[0]["radio_won"] >= 0).mean())
    assert restarted == 1
    assert np.mean(held) > 0.5  # the auction does something under motion


def _sensed_optimum(pos, lmk, KL, sense):
    """scipy's min-sum matching over what each agent senses (its KL nearest within sense), each
    agent free to stay out at OUT sense radii (a dummy column per agent)."""
    M, L = len(pos), len(lmk)
    d = np.linalg.norm(pos[:, None] - lmk[None], axis=-1)
    out = radio.OUT * sense
    cost = np.full((M, L + M), 1e3)
    cost[:, L:] = out
    for i in range(M):
        near = np.argsort(d[i], kind="stable")[:KL]
        near = near[d[i, near] <= sense]
        cost[i, near] = d[i, near]
    rows, cols = linear_sum_assignment(cost)
    return cost[rows, cols].sum(), d


def _strongly_connected(nbr, mask):
    """Whether news reaches every agent from every agent (j -> i where i lists j)."""
    M = len(nbr)
    edges = [(int(j), i) for i in range(M) for j in nbr[i][mask[i]]]

    def reach(pairs):
        seen, todo = {0}, [0]
        while todo:
            j = todo.pop()
            for a, b in pairs:
                if a == j and b not in seen:
                    seen.add(b)
                    todo.append(b)
        return len(seen) == M

    return reach(edges) and reach([(b, a) for a, b in edges])


def test_agents_held_still_settle_within_the_increment_of_the_optimum():
    """M = L, every agent's table covers every landmark within sense_radius (which holds most of the
    arena), the neighbour graph strongly connected, agents held still: after enough steps every
    landmark is held by exactly one agent, every agent's table agrees (a holder it names holds that
    landmark), and the total distance is within the increment per agent of scipy's optimum over
    the sensed pairs (measured 0.06 per agent, against the bound's 0.5). With small tables (KL = 12
    here) a duplicate claim can last: news of a landmark travels only through agents whose tables
    hold it, and the lists are directed (radio.py)."""
    M, B, KL, sense = 40, 2, 40, 3.0
    env = _make(M, B, K=12, KL=KL, sense=sense)
    env.reset()
    state = env.get_state()
    pos, lmk = state["pos"], state["landmarks"]
    obs = _hold(env, pos, lmk, 0)
    for b in range(B):
        assert _strongly_connected(np.asarray(obs["nbr"][b]), np.asarray(obs["nbr_mask"][b])), "pick another seed"
    settled = None
    last = _tables(env)
    for step in range(1, 200):
        obs = _hold(env, pos, lmk, step)
        now = _tables(env)
        if settled is None and all(np.array_equal(now[n], last[n]) for n in TABLE):
            settled = step
        last = now
    assert settled is not None, "the tables never stopped changing"
    won = last["radio_won"]
    gaps = []
    for b in range(B):
        assert sorted(won[b].tolist()) == list(range(M)), "a landmark held by none or by two"
        best, d = _sensed_optimum(pos[b], lmk[b], KL, sense)
        got = d[np.arange(M), won[b]].sum()
        assert best - 1e-3 <= got <= best + M * radio.ROUND_EPS
        gaps.append((got - best) / M)
        n, lid, holder = last["radio_count"][b], last["radio_lid"][b], last["radio_holder"][b]
        for i in range(M):
            for s in range(n[i]):
                h = holder[i, s]
                assert h < 0 or won[b, h] == lid[i, s], f"agent {i} believes {h} holds {lid[i, s]}"
    print(f"\nradio settled at step {settled} (R = {env.auction_rounds}); optimality gap per agent {gaps}")
    # the lists: a holder lists its landmark alone, read free
    mask, ent = np.asarray(obs["entity_mask"]), np.asarray(obs["entities"])
    assert (mask.sum(-1) == 1).all()
    np.testing.assert_allclose(ent[..., 0, :2], np.take_along_axis(lmk, won[..., None], 1) - pos, atol=1e-5)
    assert (ent[..., 0, 2] >= env.params["success_threshold"] - 1e-6).all()


# ---- locality: a chain of agents 0.6 apart (comm_radius 1: each hears the one on either side),
# a landmark beside each; agent P jumps far away. Each agent senses landmarks within SENSE.
CHAIN, P, SENSE, KL_CHAIN = 40, 15, 3.0, 12


def _chain():
    rng = np.random.default_rng(5)
    k = np.arange(CHAIN)
    pos = np.stack([0.6 * k + rng.uniform(-0.05, 0.05, CHAIN), rng.uniform(-0.05, 0.05, CHAIN)], -1)[None]
    lmk = np.stack([0.6 * k + 0.3 + rng.uniform(-0.1, 0.1, CHAIN), 0.25 + rng.uniform(-0.1, 0.1, CHAIN)], -1)[None]
    moved = pos.copy()
    moved[0, P] += (0.0, 40.0)
    return pos, lmk, moved


def _hops(sources, obs_pair):
    """Hops from the changed agents: news goes j -> i where i lists j, in either env's lists."""
    M = CHAIN
    hop = np.full(M, M + 1)
    queue = deque()
    for i in sources:
        hop[i] = 0 if i == P else 1
        queue.append(i)
    queue = deque(sorted(queue, key=lambda i: hop[i]))
    while queue:
        j = queue.popleft()
        for obs in obs_pair:
            nbr, mask = np.asarray(obs["nbr"][0]), np.asarray(obs["nbr_mask"][0])
            for i in np.flatnonzero((mask & (nbr == j)).any(-1)):
                if hop[i] > hop[j] + 1:
                    hop[i] = hop[j] + 1
                    queue.append(i)
    return hop


@pytest.mark.parametrize("before", [0, 3])
@pytest.mark.parametrize("rounds", [1, 2, 3])
def test_news_travels_one_hop_per_round(rounds, before):
    """Two envs in the same state for ``before`` steps of agents held still; then agent P jumps
    40 away in one of them. At that step, every agent more than R hops from the change (from P,
    or from an agent whose list changed with it) has the same table and won in both, and the same
    observation where P was and is farther than SENSE from every landmark it senses (the
    occupancy it reads). From a fresh start the change does reach R hops: the frontier is R."""
    pos, lmk, moved = _chain()
    envs = [_make(CHAIN, 1, K=4, KL=KL_CHAIN, sense=SENSE, comm_radius=1.0, rounds=rounds) for _ in range(2)]
    for env in envs:
        env.reset()
        for step in range(before):
            _hold(env, pos, lmk, step)
    obs = [_hold(envs[0], pos, lmk, before), _hold(envs[1], moved, lmk, before)]
    obs = [{k: np.asarray(v).copy() for k, v in o.items()} for o in obs]
    listed = [(o["nbr"][0], o["nbr_mask"][0]) for o in obs]
    changed = {P} | {
        i for i in range(CHAIN) if not (np.array_equal(listed[0][0][i], listed[1][0][i]) and
                                        np.array_equal(listed[0][1][i], listed[1][1][i]))
    }  # fmt: skip
    hop = _hops(changed, obs)
    assert hop.max() >= 2 * rounds + 2
    tables = [_tables(env) for env in envs]
    differs = np.zeros(CHAIN, bool)
    for name in TABLE:
        differs |= (tables[0][name][0] != tables[1][name][0]).reshape(CHAIN, -1).any(-1)
    far = hop > rounds
    assert not differs[far].any(), f"agents {np.flatnonzero(differs & far)} at hops {hop[differs & far]} > R"
    # observations, where the occupancy each reads cannot see P
    d_old = np.linalg.norm(lmk[0] - pos[0, P], axis=-1)
    d_new = np.linalg.norm(lmk[0] - moved[0, P], axis=-1)
    compared = 0
    for o in np.flatnonzero(far):
        sensed = np.linalg.norm(lmk[0] - pos[0, o], axis=-1) <= SENSE
        if (d_old[sensed] > SENSE).all() and (d_new[sensed] > SENSE).all():
            for key in obs[0]:
                np.testing.assert_array_equal(obs[0][key][0, o], obs[1][key][0, o], err_msg=f"{key} of agent {o}")
            compared += 1
    assert compared >= 10
    if before == 0:
        assert differs[hop == rounds].any(), "the change did not reach R hops"


def test_the_radio_counts_its_messages():
    """info["radio"]: each round every agent receives one table per teammate on its list, of
    radio.ENTRY_BYTES bytes per entry: exact on the chain."""
    pos, lmk, _ = _chain()
    env = _make(CHAIN, 1, K=4, KL=KL_CHAIN, sense=SENSE, comm_radius=1.0, rounds=3)
    env.reset()
    obs = _hold(env, pos, lmk, 0)
    nbr, mask, count = np.asarray(obs["nbr"][0]), np.asarray(obs["nbr_mask"][0]), _tables(env)["radio_count"][0]
    heard = mask.sum()
    entries = sum(count[j] for i in range(CHAIN) for j in nbr[i][mask[i]])
    assert env.info["radio"]["messages"][0] == pytest.approx(3 * heard / CHAIN)
    assert env.info["radio"]["bytes"][0] == pytest.approx(3 * radio.ENTRY_BYTES * entries / CHAIN)


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"neighbours": None}, "assignment"),  # (free's grid is the lists')
        ({"landmark_occupancy": False}, "landmark_order"),
        ({"landmark_neighbours": None, "sense_radius": None}, "landmark_occupancy"),
        ({"auction_rounds": 0}, "auction_rounds"),
        ({"auction_rounds": 65}, "auction_rounds"),
        ({"assignment": "exact"}, "landmark_order"),
    ],
)
def test_refusals(kw, field):
    args = dict(
        comm="rc", neighbours=8, assignment="free", array="numpy", scale="density", landmark_neighbours=8,
        sense_radius=2.0, landmark_occupancy=True, landmark_order="radio",
    )  # fmt: skip
    with pytest.raises(taichi_swarm.ConfigError) as refused:
        taichi_swarm.make("coverage", 2, 20, **{**args, **kw})
    assert refused.value.field == field
