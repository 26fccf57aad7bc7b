"""landmark_order: a run trained on the radio auction's landmark lists records them, and its
policy is evaluated and exported on them; the option is refused where it cannot apply, and a
stored run on an order that left (the shared-price auction, claim-zero) is refused naming the tag."""

import dataclasses
import json
import os

import pytest
from test_train_lists import tiny

from deploy.export import export
from taichi_swarm.sim import ConfigError
from trainer import checkpoint
from trainer.config import train_config_from_dict
from trainer.evaluate import evaluate
from trainer.train import train

LISTS = dict(neighbours=3, landmark_neighbours=3, sense_radius=1.5, scale="density")


def test_a_radio_run_carries_its_lists_to_evaluation_and_export(tmp_path, capsys):
    rounds = 2
    cfg = tiny(
        tmp_path, "radio", agents=6, updates=1, landmark_occupancy=True, landmark_order="radio", assignment="free",
        auction_rounds=rounds, **LISTS,
    )  # fmt: skip
    train(cfg)
    policy, payload = checkpoint.load_policy(os.path.join(cfg.run_dir, "policy.pt"))
    assert payload["swarm"]["landmark_order"] == "radio" and payload["swarm"]["auction_rounds"] == rounds
    out = evaluate(policy, episodes=2, seed=9)  # its own setting, as load_policy records it
    assert 0 <= out["success_rate"] <= 1 and out["messages_per_agent_step"] > 0
    export(os.path.join(cfg.run_dir, "policy.pt"), str(tmp_path / "export"))
    manifest = json.load(open(tmp_path / "export" / "manifest.json"))
    assert manifest["contract"]["swarm"]["landmark_order"] == "radio"
    with pytest.raises(ConfigError) as refused:
        dataclasses.replace(cfg.sim, landmark_occupancy=False)
    assert refused.value.field == "landmark_order"
    # another --landmark-order drops the trained rounds, on eval and execute alike
    from deploy.executor import ExportedModel, resolve_settings
    from swarm_cli.options import EvalOptions, ExecuteOptions, parse
    from swarm_cli.train import run_sim

    for argv, kept in (([], rounds), (["--landmark-order", "nearest"], None)):
        opts = parse(EvalOptions, ["policy.pt", *argv], "swarm eval")
        assert run_sim(opts, payload).auction_rounds == kept
        opts = parse(ExecuteOptions, [str(tmp_path / "export"), *argv], "swarm execute")
        s = resolve_settings(ExportedModel(str(tmp_path / "export")), swarm=opts.swarm_kwargs())
        assert s.sim.auction_rounds == kept
    for argv, line in (
        (["--auction-rounds", "0"], "--auction-rounds"),
        (["--landmark-order", "auction"], "--landmark-order"),
        (["--assignment", "auction"], "--assignment"),
    ):
        with pytest.raises(SystemExit):
            parse(EvalOptions, ["policy.pt", *argv], "swarm eval")
        assert line in capsys.readouterr().err
    # a stored run made on an order or assignment that left this version names the tag
    stored = json.load(open(os.path.join(cfg.run_dir, "config.json")))
    for key, value in (("landmark_order", "auction"), ("landmark_order", "claim-zero"), ("assignment", "auction")):
        with pytest.raises(ValueError, match=rf"^{key}: .*swarm-chains"):
            train_config_from_dict({**stored, key: value})
