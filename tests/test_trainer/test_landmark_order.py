"""landmark_order: a run trained on auction landmark lists records them, and its policy is
evaluated and exported on them; the option is refused where it cannot apply."""

import dataclasses
import json
import os

import pytest
from test_train_lists import tiny

from deploy.export import export
from trainer import checkpoint
from trainer.evaluate import evaluate, swarm_options
from trainer.train import train

LISTS = dict(neighbours=3, landmark_neighbours=3, sense_radius=1.5, scale="density")


def test_swarm_options_take_the_landmark_order():
    assert swarm_options(landmark_occupancy=True, landmark_order="nearest", **LISTS) == {
        **LISTS,
        "landmark_occupancy": True,
    }  # the default, "nearest", is recorded as unset
    claim = swarm_options(landmark_occupancy=True, landmark_order="claim-zero", **LISTS)
    assert claim["landmark_order"] == "claim-zero"
    with pytest.raises(ValueError, match="landmark_order 'claim-zero' needs landmark occupancy"):
        swarm_options(landmark_order="claim-zero", **LISTS)
    for retired in ("free", "open", "claim", "held"):
        with pytest.raises(ValueError, match="landmark_order must be one of"):
            swarm_options(landmark_occupancy=True, landmark_order=retired, **LISTS)
    budget = swarm_options(landmark_occupancy=True, landmark_order="auction", auction_rounds=8, **LISTS)
    assert budget["auction_rounds"] == 8
    with pytest.raises(ValueError, match="auction_rounds is the budget of the agents' own auction: it needs"):
        swarm_options(landmark_occupancy=True, landmark_order="claim-zero", auction_rounds=8, **LISTS)
    with pytest.raises(ValueError, match="auction_rounds must be an integer >= 1, got 0"):
        swarm_options(landmark_occupancy=True, landmark_order="auction", auction_rounds=0, **LISTS)


# "auction" lists (the agents' own auction) need the threshold matching: assignment "free"; and
# may have a budget of bid rounds a step
@pytest.mark.parametrize("order, assignment, rounds", [("auction", "free", None), ("auction", "free", 2)])
def test_an_auction_run_carries_its_lists_to_evaluation_and_export(tmp_path, capsys, order, assignment, rounds):
    extra = {"assignment": assignment} if assignment else {}
    extra.update({"auction_rounds": rounds} if rounds else {})
    cfg = tiny(tmp_path, order, agents=6, updates=1, landmark_occupancy=True, landmark_order=order, **LISTS, **extra)
    train(cfg)
    policy, payload = checkpoint.load_policy(os.path.join(cfg.run_dir, "policy.pt"))
    assert payload["swarm"]["landmark_order"] == order
    assert payload["swarm"].get("auction_rounds") == rounds
    out = evaluate(policy, "coverage", 6, comm="rc", episodes=2, seed=9, swarm=payload["swarm"])
    assert 0 <= out["success_rate"] <= 1
    export(os.path.join(cfg.run_dir, "policy.pt"), str(tmp_path / "export"))
    manifest = json.load(open(tmp_path / "export" / "manifest.json"))
    assert manifest["contract"]["swarm"]["landmark_order"] == order
    with pytest.raises(ValueError, match=f"landmark_order '{order}' needs landmark occupancy"):
        dataclasses.replace(cfg, landmark_occupancy=False).validate()
    if rounds:  # --auction-rounds 0 clears the trained budget: the auction solved to the end each step
        from deploy.executor import ExportedModel, resolve_settings
        from swarm_cli.options import EvalOptions, ExecuteOptions, parse
        from swarm_cli.train import swarm_setting

        cleared = (["--auction-rounds", "0"], {}), (["--landmark-order", "claim-zero"], {})
        for argv, budget in (([], {"auction_rounds": rounds}), *cleared):
            opts = parse(EvalOptions, ["policy.pt", *argv], "swarm eval")
            setting = swarm_setting(opts, payload)
            assert {k: setting[k] for k in ("auction_rounds",) if k in setting} == budget
            opts = parse(ExecuteOptions, [str(tmp_path / "export"), *argv], "swarm execute")
            s = resolve_settings(ExportedModel(str(tmp_path / "export")), swarm=opts.swarm_kwargs())
            assert {k: v for k, v in s.swarm.items() if k.startswith("auction")} == budget
        for argv, line in ((["--auction-rounds", "-1"], "--auction-rounds"), (["--auction-eps", "0.3"], "auction-eps")):
            with pytest.raises(SystemExit):
                parse(EvalOptions, ["policy.pt", *argv], "swarm eval")
            assert line in capsys.readouterr().err
