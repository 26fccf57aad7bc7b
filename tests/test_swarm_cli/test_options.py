"""The typed options of the commands (swarm_cli/options.py), at parse time only."""

import pytest

from swarm_cli import options
from swarm_cli.main import main as swarm


@pytest.mark.parametrize(
    "argv",
    [
        ["reproduce", "--cells"],  # an empty selection must not mean "every cell"
        ["reproduce", "--tables"],
        ["execute", "somewhere", "--drop"],
        ["bench", "train", "--threads"],
        ["bench", "sim", "--batch-sizes"],
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
        (["bench", "train", "--minibatches", "0"], "--minibatches must be >= 1"),
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
    assert opts.video == "a.gif" and opts.checkpoint == "c.pt" and opts.seed == 12345
    assert options.parse(options.ReproduceOptions, ["--tables", "2", "3"], "x").tables == (2, 3)
