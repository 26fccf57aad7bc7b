"""The task setting (task, team size, communication): one typed form, checked once."""

import pytest

from taichi_swarm import TaskSetting


def test_resolve_fills_unset_options_from_the_recorded_setting():
    recorded = {"task": "coverage", "agents": 3, "comm": "uc", "comm_radius": 1.0}
    s = TaskSetting.resolve(recorded, agents=5, comm="rc", comm_radius=None, task=None)
    assert s == TaskSetting("coverage", 5, "rc", 1.0)
    assert TaskSetting.from_dict(s.to_dict()) == s
    assert TaskSetting.resolve({"task": "line"}).agents is None  # not recorded: None, not a default


@pytest.mark.parametrize(
    ("recorded", "overrides", "message"),
    [
        ({}, {}, "does not say its task: pass --task"),
        ({"task": "soccer"}, {}, "--task must be one of"),
        ({"task": "coverage"}, {"comm": "xx"}, "--comm must be one of"),
        ({"task": "formation", "agents": 1}, {}, "--agents must be >= 2 for formation"),
        ({"task": "coverage", "agents": 0}, {}, "--agents must be >= 1"),
        ({"task": "coverage"}, {"comm_radius": -1.0}, "--comm-radius must be >= 0"),
        ({"task": "coverage"}, {"comm_radius": float("nan")}, "--comm-radius must be a finite number"),
        ({"task": "coverage", "bogus": 1}, {}, r"unknown keys \['bogus'\]"),
    ],
)
def test_bad_settings_are_named(recorded, overrides, message):
    with pytest.raises(ValueError, match=message):
        TaskSetting.resolve(recorded, **overrides)


def test_team_size_must_be_recorded_or_given():
    with pytest.raises(ValueError, match="the manifest does not say its team size: pass --agents"):
        TaskSetting("coverage").team_size("the manifest")
