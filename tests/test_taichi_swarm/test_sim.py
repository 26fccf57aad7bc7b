"""The simulated setting (``taichi_swarm.Sim``): one declaration, checked once, the field named."""

import dataclasses

import pytest

from taichi_swarm.sim import ConfigError, Sim

RADIO = dict(
    comm="rc", neighbours=12, landmark_neighbours=64, sense_radius=6.0, landmark_occupancy=True,
    landmark_order="radio", auction_rounds=8, scale="density", assignment="free", action_space="fine",
)  # fmt: skip


def test_records_round_trip_and_leave_the_defaults_out():
    sim = Sim("coverage", 100, **RADIO)
    assert sim.task_record() == {"task": "coverage", "agents": 100, "comm": "rc", "comm_radius": 1.0}
    assert "comm" not in sim.swarm_record() and sim.swarm_record()["auction_rounds"] == 8
    assert Sim.from_record(sim.task_record(), sim.swarm_record()) == sim
    assert Sim("coverage", 3).swarm_record() == {}  # the paper's setting: nothing recorded
    assert Sim("coverage", 3, landmark_order="nearest", assignment="exact").swarm_record() == {}
    assert Sim.from_record({"task": "line"}).agents is None  # not recorded: None, not a default


def test_override_keeps_what_is_unset_and_drops_the_radios_rounds_with_its_order():
    sim = Sim("coverage", 100, **RADIO)
    assert sim.override(agents=1000, comm=None) == dataclasses.replace(sim, agents=1000)
    nearest = sim.override(landmark_order="nearest")
    assert nearest.auction_rounds is None and nearest.rounds is None
    assert sim.rounds == 8 and sim.override(auction_rounds=None).rounds == 8  # None: keep
    assert Sim("coverage", 10, **{**RADIO, "auction_rounds": None}).rounds == 4  # the radio's default
    assert Sim.resolve(None, None, "the manifest", task="line", agents=6) == Sim("line", 6)


@pytest.mark.parametrize(
    ("options", "field"),
    [
        (dict(task="soccer"), "task"),
        (dict(task="formation", agents=1), "agents"),
        (dict(agents=0), "agents"),
        (dict(agents=True), "agents"),
        (dict(agents=2**40), "agents"),
        (dict(comm="xx"), "comm"),
        (dict(comm_radius=-1.0), "comm_radius"),
        (dict(comm_radius=float("nan")), "comm_radius"),
        (dict(comm_radius=1e39), "comm_radius"),
        (dict(action_space="box"), "action_space"),
        (dict(neighbours=0), "neighbours"),
        (dict(neighbours=2000), "neighbours"),
        (dict(landmark_neighbours=4), "sense_radius"),
        (dict(landmark_neighbours=4, sense_radius=0.0), "sense_radius"),
        (dict(sense_radius=1.0), "sense_radius"),
        (dict(task="formation", neighbours=4, landmark_neighbours=4, sense_radius=1.0), "scale"),
        (dict(task="line", neighbours=4, landmark_neighbours=4, sense_radius=1.0), "scale"),
        (dict(scale="huge"), "scale"),
        (dict(assignment="free"), "assignment"),
        (dict(assignment="auction"), "assignment"),
        (dict(landmark_occupancy=1), "landmark_occupancy"),
        (dict(landmark_occupancy=True, neighbours=4), "landmark_occupancy"),
        (dict(landmark_order="claim"), "landmark_order"),
        (dict(RADIO, assignment="exact"), "landmark_order"),
        (dict(RADIO, landmark_occupancy=False), "landmark_order"),
        (dict(auction_rounds=4), "auction_rounds"),
        (dict(RADIO, auction_rounds=0), "auction_rounds"),
        (dict(RADIO, auction_rounds=65), "auction_rounds"),
    ],
)
def test_each_bad_value_is_refused_by_its_field(options, field):
    options = {"task": "coverage", "agents": 3, **options}
    with pytest.raises(ConfigError) as refused:
        Sim(**options)
    assert refused.value.field == field
    assert isinstance(refused.value, ValueError)  # (callers that treat bad input as a ValueError still do)


@pytest.mark.parametrize(
    ("recorded", "swarm", "overrides", "field"),
    [
        ({}, {}, {}, "task"),
        ({"task": "coverage", "bogus": 1}, {}, {}, "bogus"),
        ({"task": "coverage"}, {"auction_eps": 0.5}, {}, "auction_eps"),
        ({"task": "coverage", "agents": 3}, {}, {"task": "line"}, "task"),  # another task's observations
        ({"task": "coverage", "agents": 3}, {}, {"neighbour": 4}, "neighbour"),
    ],
)
def test_records_and_overrides_are_checked_like_a_new_setting(recorded, swarm, overrides, field):
    with pytest.raises(ConfigError) as refused:
        Sim.resolve(recorded, swarm, "the checkpoint", **overrides)
    assert refused.value.field == field


def test_team_size_must_be_recorded_or_given():
    with pytest.raises(ConfigError, match="the manifest does not say its team size: pass --agents"):
        Sim("coverage").team_size("the manifest")


def test_each_field_is_an_option_of_every_surface_with_no_other_declaration():
    """A field added to the Sim is, with no other change: a `swarm train` option (in its
    "large teams" group unless another names it), an option of eval / zero-shot / execute (those
    a command may set over a policy's own), a spec key, and stored and restored by a checkpoint."""
    from reproduce.spec import _keys
    from swarm_cli.options import EvaluationOptions, ExecuteOptions
    from swarm_cli.train import config_from_argv
    from taichi_swarm.sim import FIELDS, RUN_TIME_KEYS
    from trainer.config import to_dict, train_config_from_dict

    options = {"task": "line", "agents": 7, **RADIO}
    argv = [a for k, v in options.items() for a in (f"--{k.replace('_', '-')}", str(v))]
    argv = [a for a in argv if a != "True"]  # (a flag takes no value)
    cfg = config_from_argv(argv, "swarm train")
    assert cfg.sim == Sim(**options)
    assert train_config_from_dict(to_dict(cfg)) == cfg and set(FIELDS) <= set(to_dict(cfg))
    assert set(FIELDS) <= _keys("train")
    assert set(RUN_TIME_KEYS) == set(FIELDS) - {"task", "agents", "comm", "comm_radius", "action_space",
                                                "landmark_occupancy"}  # fmt: skip
    for cls in (EvaluationOptions, ExecuteOptions):
        assert set(RUN_TIME_KEYS) <= {f.name for f in dataclasses.fields(cls)}
