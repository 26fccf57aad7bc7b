"""landmark_order: a run trained on the radio auction's landmark lists records them, and its
policy is evaluated and exported on them; the option is refused where it cannot apply, and a
stored run on an order that left (the shared-price auction, claim-zero) is refused naming the tag."""

import dataclasses
import json
import os

import pytest
from test_train_lists import tiny

from deploy.export import export
from trainer import checkpoint
from trainer.config import train_config_from_dict
from trainer.evaluate import evaluate, swarm_options
from trainer.train import train

LISTS = dict(neighbours=3, landmark_neighbours=3, sense_radius=1.5, scale="density")


def test_swarm_options_take_the_landmark_order():
    assert swarm_options(landmark_occupancy=True, landmark_order="nearest", **LISTS) == {
        **LISTS,
        "landmark_occupancy": True,
    }  # the default, "nearest", is recorded as unset
    radio = swarm_options(landmark_occupancy=True, landmark_order="radio", auction_rounds=8, **LISTS)
    assert radio["landmark_order"] == "radio" and radio["auction_rounds"] == 8
    with pytest.raises(ValueError, match="landmark_order 'radio' needs landmark occupancy"):
        swarm_options(landmark_order="radio", **LISTS)
    for retired in ("free", "open", "claim", "held", "claim-zero", "auction"):
        with pytest.raises(ValueError, match="landmark_order must be one of"):
            swarm_options(landmark_occupancy=True, landmark_order=retired, **LISTS)
    with pytest.raises(ValueError, match="auction_rounds is the radio auction's message rounds a step"):
        swarm_options(landmark_occupancy=True, landmark_order="nearest", auction_rounds=8, **LISTS)
    with pytest.raises(ValueError, match="auction_rounds must be an integer >= 1, got 0"):
        swarm_options(landmark_occupancy=True, landmark_order="radio", auction_rounds=0, **LISTS)


def test_a_radio_run_carries_its_lists_to_evaluation_and_export(tmp_path, capsys):
    rounds = 2
    cfg = tiny(
        tmp_path, "radio", agents=6, updates=1, landmark_occupancy=True, landmark_order="radio", assignment="free",
        auction_rounds=rounds, **LISTS,
    )  # fmt: skip
    train(cfg)
    policy, payload = checkpoint.load_policy(os.path.join(cfg.run_dir, "policy.pt"))
    assert payload["swarm"]["landmark_order"] == "radio" and payload["swarm"]["auction_rounds"] == rounds
    out = evaluate(policy, "coverage", 6, comm="rc", episodes=2, seed=9, swarm=payload["swarm"])
    assert 0 <= out["success_rate"] <= 1 and out["messages_per_agent_step"] > 0
    export(os.path.join(cfg.run_dir, "policy.pt"), str(tmp_path / "export"))
    manifest = json.load(open(tmp_path / "export" / "manifest.json"))
    assert manifest["contract"]["swarm"]["landmark_order"] == "radio"
    with pytest.raises(ValueError, match="landmark_order 'radio' needs landmark occupancy"):
        dataclasses.replace(cfg, landmark_occupancy=False).validate()
    # another --landmark-order drops the trained rounds, on eval and execute alike
    from deploy.executor import ExportedModel, resolve_settings
    from swarm_cli.options import EvalOptions, ExecuteOptions, parse
    from swarm_cli.train import swarm_setting

    for argv, kept in (([], {"auction_rounds": rounds}), (["--landmark-order", "nearest"], {})):
        opts = parse(EvalOptions, ["policy.pt", *argv], "swarm eval")
        setting = swarm_setting(opts, payload)
        assert {k: setting[k] for k in ("auction_rounds",) if k in setting} == kept
        opts = parse(ExecuteOptions, [str(tmp_path / "export"), *argv], "swarm execute")
        s = resolve_settings(ExportedModel(str(tmp_path / "export")), swarm=opts.swarm_kwargs())
        assert {k: v for k, v in s.swarm.items() if k.startswith("auction")} == kept
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
