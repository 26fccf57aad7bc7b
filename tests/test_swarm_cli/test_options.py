"""The typed options of the commands (swarm_cli/options.py), at parse time only."""

import re

import pytest

from swarm_cli import options
from swarm_cli.main import main as swarm


@pytest.mark.parametrize(
    "argv",
    [
        ["reproduce", "--cells"],  # an empty selection must not mean "every cell"
        ["reproduce", "--tables"],
        ["execute", "somewhere", "--drop"],
        ["zero-shot", "x.pt", "--sizes"],
    ],
)
def test_a_list_option_without_values_is_refused(argv, capsys):
    assert swarm(argv) == 2
    assert "needs at least one value" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, says",
    [
        (["eval", "x.pt", "--episodes", "0"], "--episodes must be >= 1"),
        (["eval", "x.pt", "--record-envs", "0"], "--record-envs must be >= 1"),
        (["execute", "d", "--threads", "0"], "--threads must be >= 1"),
        (["eval", "x.pt", "--comm-radius", "-1"], "--comm-radius must be >= 0"),
        (["eval", "x.pt", "--comm", "xx"], "--comm"),
        (["replay", "f.rrd", "--port", "70000"], "--port must be in 1..65535"),
        (["plot", "--zero-shot", "a.json"], "--zero-shot needs --out"),
        (["reproduce", "--progress-every", "nan"], "--progress-every must be a positive finite number"),
    ],
)
def test_bad_values_are_refused_naming_the_option(argv, says, capsys):
    assert swarm(argv) == 2
    assert says in " ".join(capsys.readouterr().err.split())  # tyro wraps its message in a box


def test_values_parse_into_typed_fields():
    opts = options.parse(
        options.ExecuteOptions, ["d", "--drop", "0", "0.25", "--comm", "rc", "--comm-radius", "0"], "x"
    )
    assert opts.drop == (0.0, 0.25) and opts.comm == "rc" and opts.comm_radius == 0.0  # radius 0: nobody heard
    assert opts.directory == "d" and opts.agents is None and opts.record_envs == 4
    opts = options.parse(options.EvalOptions, ["c.pt", "--gif", "a.gif"], "x")
    assert opts.video == "a.gif" and opts.checkpoint == "c.pt" and opts.seed == 777
    assert options.parse(options.ReproduceOptions, ["--tables", "2", "3"], "x").tables == (2, 3)


PAPER_LR4 = {"num_envs": 32, "num_steps": 128, "lr": 1e-4, "lr_end": None, "minibatches": 32}


@pytest.mark.parametrize(
    "argv, preset, updates, ppo",
    [
        ([], "fast", 2200, {}),
        (["--preset", "paper", "--ppo.lr", "1e-4"], "paper", 1100, PAPER_LR4),
        (["--ppo.lr", "1e-4", "--preset", "paper"], "paper", 1100, PAPER_LR4),  # in any order
        (["--preset", "gpu"], "gpu", 300, {"num_envs": 4096, "num_steps": 16, "lr": 7e-4, "minibatches": 16}),
        (["--preset", "gpu", "--updates", "5", "--ppo.lr", "7e-4"], "gpu", 5, {"num_envs": 4096, "lr": 7e-4}),
        (["--preset", "paper", "--ppo.lr", "7e-4", "--ppo.bootstrap-time-limit"], "paper", 1100,
         {"lr": 7e-4, "num_envs": 32, "bootstrap_time_limit": True}),
        (["--ppo.no-bootstrap-time-limit", "--ppo.lr-end", "None"], "fast", 2200,
         {"lr": 7e-4, "lr_end": None, "num_envs": 64, "bootstrap_time_limit": False}),
    ],
)  # fmt: skip
def test_a_preset_gives_the_values_not_given(argv, preset, updates, ppo):
    """The preset is a value of the config: the PPO options and --updates not on the command line
    are its, those given win (whatever the preset's value and the order of the flags)."""
    import dataclasses

    from swarm_cli.train import config_from_argv
    from trainer.config import PRESETS, CurriculumConfig, TrainConfig, to_dict

    # (a curriculum's stages set its updates: not an option of its own)
    for config_type in (TrainConfig,) if "--updates" in argv else (TrainConfig, CurriculumConfig):
        cfg = config_from_argv(argv, "swarm train", config_type)
        assert type(cfg) is config_type and cfg.preset == preset and cfg.updates == updates
        assert {k: getattr(cfg.ppo, k) for k in ppo} == ppo
        given = {k: v for k, v in ppo.items() if getattr(PRESETS[preset], k) != v}
        want = config_type(preset=preset, updates=updates, ppo=dataclasses.replace(PRESETS[preset], **given))
        assert to_dict(cfg) == to_dict(want)


def test_train_help_groups_every_option(capsys):
    """swarm train --help: the options changed first at the top, every other in a named group
    (none left to "other"), each flag under its plain name."""
    assert swarm(["train", "--help"]) == 0
    text = capsys.readouterr().out
    top = text[: text.index("large teams options")]
    for flag in ("--task", "--agents", "--comm", "--preset", "--updates", "--seed", "--run-dir", "--device"):
        assert f"{flag} " in top, flag
    assert "other options" not in text
    for flag in ("--neighbours", "--scale", "--message-drop", "--resume"):
        assert f"{flag} " in text, flag
    flags = set(re.findall(r"^\W*(--[a-z][\w.-]*)", text, flags=re.M))  # each option's line
    assert "--ppo.lr" not in flags and "--help-all" in text and len(flags) <= 35, sorted(flags)  # a first screen
    assert swarm(["train", "--help-all"]) == 0  # every option: the network's, PPO's and the compute ones too
    text = capsys.readouterr().out
    for flag in ("--model.self-position", "--ppo.lr", "--torch-threads"):
        assert f"{flag} " in text, flag
    assert "(default: 0.0007; --preset paper: 0.0001)" in " ".join(text.split())
    assert swarm(["curriculum", "--help"]) == 0
    text = capsys.readouterr().out
    assert "curriculum options" in text and "other options" not in text and "--resume" not in text
    flags = set(re.findall(r"^\W*(--[a-z][\w.-]*)", text, flags=re.M))
    staged = {"--agents", "--updates", "--target-success", "--min-updates", "--team-sizes"}  # the stages set them
    assert not flags & staged and len(flags) <= 35, sorted(flags)


@pytest.mark.parametrize(
    "argv, says",
    [
        (["train", "--preset", "papr"], "invalid choice 'papr' for argument '--preset'"),
        (["curriculum", "--preset", "papr"], "invalid choice 'papr' for argument '--preset'"),
        (["train", "--resume", "r", "--task", "line", "--ppo.lr", "1"], "not --task --ppo.lr"),
        (["train", "--resume", "r", "--updates", "0"], "--updates must be >= 1"),
    ],
)
def test_bad_train_options_are_refused_in_one_line(argv, says, capsys):
    assert swarm(argv) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1, err


def test_fault_options_parse_into_the_fault_spec(capsys):
    """swarm agent / swarm world take deploy.net.faults.FaultSpec itself under its flags (--fault-seed:
    the world's --seed is its episodes'); FaultSpec.to_args gives the same spec back."""
    from deploy.net.faults import FaultSpec
    from swarm_cli.net import AgentOptions, WorldOptions

    argv = ["--drop", "0.1", "--burst-loss", "0.2", "--late-round", "1", "--fault-seed", "5"]
    agent = options.parse(AgentOptions, ["d", "--id", "2", *argv], "x")
    assert agent.faults == FaultSpec(drop=0.1, burst_loss=0.2, late_round=1, seed=5)
    assert options.parse(AgentOptions, ["d", "--id", "2", *agent.faults.to_args()], "x").faults == agent.faults
    world = options.parse(WorldOptions, ["--export", "d", "--seed", "3", *argv], "x")
    assert world.seed == 3 and world.faults == agent.faults
    assert options.parse(WorldOptions, ["--export", "d"], "x").faults == FaultSpec()
    assert swarm(["agent", "d", "--id", "0", "--drop", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("swarm agent: error: --drop must be a probability") and len(err.splitlines()) == 1
