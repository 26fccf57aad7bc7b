"""tools/coverage_misses.py: the classification of a coverage policy's misses docs/SWARM.md
reports (duplicate, near miss, far), on hand-made layouts, and the tool end to end."""

import importlib.util
import os

import numpy as np

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
PATH = os.path.join(ROOT, "tools", "coverage_misses.py")
spec = importlib.util.spec_from_file_location("coverage_misses", PATH)
misses = importlib.util.module_from_spec(spec)
spec.loader.exec_module(misses)


def test_each_uncovered_landmark_is_one_duplicate_near_or_far_agent():
    landmarks = np.array([[0, 0], [1, 0], [2, 0], [3, 0]], np.float32)
    # two agents on landmark 0 (one a duplicate), one on landmark 1, one 5 away from everything
    pos = np.array([[0.02, 0], [-0.03, 0], [1.0, 0.05], [3.0, 5.0]], np.float32)
    r = misses.classify(pos, landmarks, 0.1)
    assert r == {"covered": 0.5, "duplicate": 0.25, "near": 0.0, "far": 0.25}
    # the far agent moved next to landmark 3, 0.15 off: a near miss
    pos[3] = [3.0, 0.15]
    assert misses.classify(pos, landmarks, 0.1) == {"covered": 0.5, "duplicate": 0.25, "near": 0.25, "far": 0.0}
    # an agent within reach of two landmarks lets the matching move the other one: both covered
    landmarks2 = np.array([[0, 0], [0.12, 0]], np.float32)
    pos2 = np.array([[0.06, 0], [-0.05, 0]], np.float32)
    assert misses.classify(pos2, landmarks2, 0.1)["covered"] == 1.0


def test_a_duplicates_nearest_free_landmark_and_whether_it_is_in_sight():
    landmarks = np.array([[0, 0], [0.5, 0], [3, 0], [0, 0.8]], np.float32)
    # agents 0 and 1 share landmark 0, agent 2 holds landmark 1; landmarks 2 (3 away) and 3
    # (0.8 away, beyond the two nearest) are free
    pos = np.array([[0.02, 0], [-0.03, 0], [0.5, 0.05], [9, 9]], np.float32)
    dist, sight = misses.duplicates_reach(pos, landmarks, 0.1, kl=2, radius=1.0)
    assert len(dist) == 1 and abs(dist[0] - np.hypot(0.03, 0.8)) < 1e-5 and not sight[0]
    _, sight = misses.duplicates_reach(pos, landmarks, 0.1, kl=3, radius=1.0)
    assert sight[0]  # landmark 3 is its third nearest
    _, sight = misses.duplicates_reach(pos, landmarks, 0.1, kl=3, radius=0.5)
    assert not sight[0]  # ... but outside the radius
    # free-first lists hold the free landmark 3 before the held landmark 1, nearer: in sight at KL = 2
    _, sight = misses.duplicates_reach(pos, landmarks, 0.1, kl=2, radius=1.0, free_first=True)
    assert sight[0]
    _, sight = misses.duplicates_reach(pos, landmarks, 0.1, kl=2, radius=0.5, free_first=True)
    assert not sight[0]  # the radius still bounds them
    none = misses.duplicates_reach(pos[[0, 2, 3]], landmarks[[0, 1, 2]], 0.1, kl=2, radius=1.0)
    assert len(none[0]) == 0 and len(none[1]) == 0  # no duplicate


def test_the_tool_runs_a_zoo_policy(capsys):
    misses.main(["coverage-rc-m5-swarm", "--agents", "5", "--episodes", "3"])
    out = capsys.readouterr().out.splitlines()
    head = ["M", "episodes", "succeeded", "covered", "duplicate", "near", "far", "held", "hover", "best"]
    head += ["free_distance", "free_in_sight"]
    assert out[0].split() == head
    cells = out[1].split()
    assert cells[:2] == ["5", "3"] and 0 <= int(cells[2]) <= 3
    if len(cells) == 12:  # (every episode may succeed early at M = 5)
        covered, dup, near, far = map(float, cells[3:7])
        assert abs(covered + dup + near + far - 1.0) < 2e-3


def test_the_tool_runs_a_formation_policy_on_its_sensed_lattice(capsys):
    """Formation's sensed lattice: its landmarks are its targets, the threshold formation's 0.05."""
    misses.main(["formation-rc-m50-lattice", "--agents", "12", "--episodes", "3", "--steps", "4"])
    cells = capsys.readouterr().out.splitlines()[1].split()
    assert cells[:3] == ["12", "3", "0"] and len(cells) == 12  # no lattice is filled in 4 steps
    covered, dup, near, far, held, hover, best = map(float, cells[3:10])
    assert abs(covered + dup + near + far - 1.0) < 2e-3 and far > 0
    assert held + hover <= 1.0 and held <= best <= 1.0


def test_held_hover_and_best_over_the_window():
    inside = np.array(
        [[1, 1, 0, 0], [1, 0, 1, 0], [1, 1, 1, 0]], bool
    )  # agent 0 held, 1 and 2 hover, 3 never in; at most 3 of 4 at once
    assert misses.hovering(inside) == {"held": 0.25, "hover": 0.5, "best": 0.75}


def test_a_bad_sense_option_is_one_line(capsys):
    import pytest

    for bad in (["x", "1"], ["0", "1"], ["4", "-1"]):
        with pytest.raises(SystemExit) as exc:
            misses.main(["coverage-rc-m5-swarm", "--sense", *bad])
        assert exc.value.code == 2 and "--sense takes" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        misses.main(["coverage-rc-m5-swarm", "--steps", "1"])
    assert exc.value.code == 2 and "--steps must be >= 2" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        misses.main(["coverage-rc-m5-swarm", "--window", "0"])
    assert exc.value.code == 2 and "--window must be >= 1" in capsys.readouterr().err


def test_jostling_counts_a_pairs_swaps_and_full_pushes():
    landmarks = np.array([[0, 0], [1, 0], [3, 0]], np.float32)
    # agents 0 and 1 share landmark 0, the nearer swapping at every step, both pushing at full
    # force; agent 2 alone on landmark 1, parked (no-op, then a quarter push); landmark 2 free
    pos = np.array(
        [
            [[0.01, 0], [0.03, 0], [1.0, 0.01]],
            [[0.04, 0], [0.02, 0], [1.0, 0.01]],
            [[0.02, 0], [0.05, 0], [1.0, 0.01]],
        ],
        np.float32,
    )
    actions = np.array([[1, 2, 0], [3, 4, 5], [2, 0, 0]])
    r = misses.jostling(pos, actions, landmarks, 0.1)
    assert r["pairs"] == 1 and r["swaps"] == 2  # nearer: 0, then 1, then 0
    assert (r["pair_full"], r["pair_actions"]) == (5, 6) and (r["lone_full"], r["lone_actions"]) == (0, 3)


def test_the_tool_adds_the_jostle_columns(capsys):
    misses.main(["coverage-rc-m5-swarm", "--agents", "8", "--episodes", "2", "--jostle"])
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[-3:] == ["swaps", "pair_push", "lone_push"]
    cells = out[1].split()
    assert len(cells) in (4, 15)  # (every episode may succeed early)
