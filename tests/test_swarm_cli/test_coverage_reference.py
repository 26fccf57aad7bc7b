"""tools/coverage_reference.py: the hand-written coverage controllers docs/SWARM.md compares the
learned policies with. The steering hovers within the success radius of a goal that lies
between the lattice points an agent can park on, and the central plan covers at small M."""

import importlib.util
import os

import numpy as np

from taichi_swarm.physics import DAMPING, DT, MASS, SENSITIVITY

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
PATH = os.path.join(ROOT, "tools", "coverage_reference.py")
spec = importlib.util.spec_from_file_location("coverage_reference", PATH)
ref = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ref)


def test_steering_hovers_within_the_success_radius_between_lattice_points():
    # from rest an agent parks only on a lattice of side 0.2; (0.1, 0.1) is the farthest point
    # from it (0.141 > 0.1): a controller that only parks stays out of reach there
    rng = np.random.default_rng(0)
    goals = np.concatenate([[[0.1, 0.1], [0.1, -0.1], [0.3, 0.1]], rng.uniform(-0.6, 0.6, (40, 2))]).astype(np.float32)
    pos, vel = np.zeros_like(goals), np.zeros_like(goals)
    worst = []
    for t in range(40):
        a = ref.steer(pos, vel, goals)
        vel = vel * (1 - DAMPING) + ref.DIRECTIONS[a] * (SENSITIVITY / MASS) * DT
        pos = pos + vel * DT
        if t >= 30:
            worst.append(np.linalg.norm(pos - goals, axis=-1).max())
    assert max(worst) < 0.1, worst


def test_the_central_plan_covers_small_teams_and_the_greedy_one_runs():
    planned = ref.run("planned", agents=5, episodes=10, seed=777, batch=10)
    assert planned["episodes"] == 10 and planned["success_rate"] >= 0.7 and planned["covered"] >= 0.9, planned
    greedy = ref.run("greedy", agents=5, episodes=10, seed=777, batch=10)
    assert greedy["episodes"] == 10 and 0.0 < greedy["covered"] <= 1.0 and greedy["dist"] > 0, greedy


def test_claim_never_heads_for_a_landmark_read_held_and_covers_small_teams():
    # one env, two agents far apart (neither hears the other); each lists two landmarks
    state = {"pos": np.array([[[0.0, 0.0], [5.0, 5.0]]], np.float32)}
    ent = np.zeros((1, 2, 2, 3), np.float32)
    ent[0, :, 0] = [0.05, 0.0, 0.02]  # the nearest reads held: a teammate 0.02 from it
    ent[0, :, 1] = [0.0, 0.5, 0.3]  # the next reads free
    obs = {
        "entities": ent,
        "entity_mask": np.ones((1, 2, 2), bool),
        "nbr": np.array([[[0], [1]]], np.int32),
        "nbr_mask": np.zeros((1, 2, 1), bool),
    }
    goals = ref.claim_goals(state, obs, threshold=0.1)
    np.testing.assert_allclose(goals[0], [[0.0, 0.5], [5.0, 5.5]])
    ent[0, 0, 0, 2] = 0.1  # at the threshold it reads free (claim floors free readings there)
    assert np.allclose(ref.claim_goals(state, obs, threshold=0.1)[0, 0], [0.05, 0.0])
    claim = ref.run("claim", agents=10, episodes=5, seed=777, batch=5, assignment="nearest")
    assert claim["success_rate"] >= 0.8 and claim["covered"] >= 0.95, claim


def test_steps_set_the_episode_length_and_are_never_saved(capsys):
    import pytest

    short = ref.run("greedy", agents=5, episodes=2, seed=777, batch=2, steps=5)
    assert short["length"] <= 5, short
    with pytest.raises(SystemExit):
        ref.main(["--steps", "80", "--save", "--sizes", "10"])
    assert "--steps goes without --save" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # claim lists come from the threshold matching
        ref.main(["--controllers", "claim", "--sizes", "10"])
    assert "claim reads claim lists" in capsys.readouterr().err


def test_save_merges_rows_by_size_and_refuses_another_seed(tmp_path):
    import json

    import pytest

    row = dict(controller="greedy", agents=10, episodes=5, success_rate=0.2, covered=0.7, dist=0.1, length=50.0)
    ref.save([row, dict(row, agents=20)], seed=777, directory=str(tmp_path))
    ref.save([dict(row, agents=10, covered=0.8)], seed=777, directory=str(tmp_path))
    data = json.loads((tmp_path / "reference-greedy.json").read_text())
    assert [(r["agents"], r["covered"]) for r in data["results"]] == [(10, 0.8), (20, 0.7)]
    assert data["controller"] == "greedy" and data["checkpoint"] == "reference: greedy"
    with pytest.raises(SystemExit, match="seed 777, not 1"):
        ref.save([row], seed=1, directory=str(tmp_path))


def test_save_keeps_the_max_matching_rows_apart(tmp_path):
    row = dict(controller="planned", agents=10, episodes=5, success_rate=1.0, covered=1.0, dist=0.03, length=10.0)
    ref.save([row, dict(row, assignment="nearest")], seed=777, directory=str(tmp_path))
    assert sorted(os.listdir(tmp_path)) == ["reference-planned-nearest.json", "reference-planned.json"]


def test_formation_on_its_sensed_lattice_is_planned_and_saved_apart(tmp_path):
    """--task formation: every agent on one point of the lattice (its landmarks here), success
    within 0.05 under the same steering; its rows go to a file of their own."""
    planned = ref.run("planned", agents=5, episodes=10, seed=777, batch=10, task="formation")
    assert planned["task"] == "formation" and planned["dist"] is None
    assert planned["success_rate"] >= 0.7 and planned["covered"] >= 0.9, planned
    ref.save([planned], seed=777, directory=str(tmp_path))
    assert os.listdir(tmp_path) == ["reference-formation-planned.json"]
    import json

    assert json.loads((tmp_path / "reference-formation-planned.json").read_text())["checkpoint"] == (
        "reference: formation planned"
    )


def _sorted_scan(cost):
    """the greedy matching by its definition: every pair in increasing cost, kept where both ends are free"""
    match, used = np.full(len(cost), -1), set()
    for flat in np.argsort(cost, axis=None, kind="stable"):
        i, j = divmod(int(flat), cost.shape[1])
        if match[i] < 0 and j not in used:
            match[i] = j
            used.add(j)
    return match


def test_nearest_first_is_the_greedy_matching_and_bounds_coverage_below_the_plan():
    rng = np.random.default_rng(1)
    for n in (1, 2, 7, 40, 150):
        pos, lmk = rng.uniform(-3, 3, (n, 2)), rng.uniform(-3, 3, (n, 2))
        cost = np.linalg.norm(pos[:, None] - lmk[None], axis=-1)
        np.testing.assert_array_equal(ref.nearest_first(cost), _sorted_scan(cost))
    # a chain where nearest-first is not min-sum: agent 0 takes landmark 0, agent 1 the far one
    cost = np.array([[1.0, 2.0], [1.1, 10.0]])
    np.testing.assert_array_equal(ref.nearest_first(cost), [0, 1])
    # ties (a grid of equal distances) still end, every row matched once
    tied = np.abs(np.arange(6)[:, None] - np.arange(6)[None]).astype(float)
    assert sorted(ref.nearest_first(tied)) == list(range(6))
    run = ref.run("nearest-first", agents=10, episodes=5, seed=777, batch=5, assignment="nearest")
    assert run["controller"] == "nearest-first" and run["success_rate"] >= 0.6 and run["covered"] >= 0.95, run


def test_line_rows_are_sensed_and_planned():
    planned = ref.run("nearest-first", agents=20, episodes=5, seed=777, batch=5, task="line")
    assert planned["task"] == "line" and planned["dist"] is None and planned["success_rate"] >= 0.6, planned


def test_window_plans_like_the_central_plan_when_it_sees_everyone_and_locally_when_not(tmp_path):
    rng = np.random.default_rng(2)
    pos, lmk = rng.uniform(-2, 2, (2, 30, 2)), rng.uniform(-2, 2, (2, 30, 2))
    state = {"pos": pos, "landmarks": lmk}
    # a window wider than the arena holds every agent and landmark: the min-sum matching itself
    np.testing.assert_allclose(ref.window_goals(state, radius=10.0), ref.planned_goals(state))
    # a window holding no landmark: the nearest one
    far = {"pos": np.zeros((1, 2, 2)), "landmarks": np.array([[[3.0, 0.0], [0.0, 4.0]]])}
    np.testing.assert_allclose(ref.window_goals(far, radius=1.0)[0], [[3.0, 0.0], [3.0, 0.0]])
    # two agents, one landmark in both windows: the nearer takes it, the other its nearest (the same)
    # unless another lies within its window: here agent 1 sees landmark 1 too and takes it
    pair = {"pos": np.array([[[0.0, 0.0], [0.5, 0.0]]]), "landmarks": np.array([[[0.1, 0.0], [1.3, 0.0]]])}
    np.testing.assert_allclose(ref.window_goals(pair, radius=1.0)[0], [[0.1, 0.0], [1.3, 0.0]])
    run = ref.run("window", agents=10, episodes=5, seed=777, batch=5, assignment="nearest", window_radius=2.0)
    assert run["window_radius"] == 2.0 and run["success_rate"] >= 0.6 and run["covered"] >= 0.95, run
    ref.save([run, dict(run, window_radius=3.0)], seed=777, directory=str(tmp_path))
    assert sorted(os.listdir(tmp_path)) == ["reference-window-r2-nearest.json", "reference-window-r3-nearest.json"]


def test_window_radius_must_be_positive(capsys):
    import pytest

    with pytest.raises(SystemExit):
        ref.main(["--controllers", "window", "--window-radius", "0", "--sizes", "5"])
    assert "--window-radius must be > 0, got 0" in capsys.readouterr().err


def test_fine_steering_parks_on_goals_between_the_lattice_points():
    # with the quarter pushes of action_space="fine" an agent holds a point within formation's 0.05
    rng = np.random.default_rng(3)
    goals = rng.uniform(-0.6, 0.6, (40, 2)).astype(np.float32)
    pos, vel = np.zeros_like(goals), np.zeros_like(goals)
    worst = []
    for t in range(40):
        a = ref.steer(pos, vel, goals, "fine")
        assert a.min() >= 0 and a.max() <= 8
        vel = vel * (1 - DAMPING) + ref.FORCES["fine"][a] * (SENSITIVITY / MASS) * DT
        pos = pos + vel * DT
        if t >= 30:
            worst.append(np.linalg.norm(pos - goals, axis=-1).max())
    assert max(worst) < 0.05, worst
