"""The model zoo: every entry of models/index.toml exists, matches its sha256, loads by name,
and was trained in the setting its card states; a name that is not an entry, a changed file
and a malformed index are refused with one line."""

import os
import shutil

import pytest

from trainer import zoo
from trainer.checkpoint import CheckpointError, load_policy

ENTRIES = zoo.load_index()


def test_the_zoo_covers_every_published_setting():
    names = {e.name for e in ENTRIES}
    for task in ("coverage", "formation", "line"):
        for comm in ("uc", "rc"):
            for m in (3, 5, 6, 7, 10):
                assert f"{task}-{comm}-m{m}" in names
    assert "coverage-uc-m3-transfer" in names


@pytest.mark.parametrize("entry", ENTRIES, ids=lambda e: e.name)
def test_entry_exists_loads_by_name_and_matches_its_card(entry):
    zoo.verify(entry)  # the file is there and its bytes are the ones measured
    policy, payload = load_policy(entry.name)
    setting = payload["task"]
    assert (setting["task"], setting["comm"], setting["agents"]) == (entry.task, entry.comm, entry.agents)
    assert setting["comm_radius"] == entry.comm_radius
    assert payload["model_config"]["entity_mode"] == entry.entity_mode
    # 500 fresh episodes; from M = 100, 100 do (each reports the fraction covered beside S%)
    assert 0 <= entry.success <= 1 and entry.episodes >= (100 if entry.agents >= 100 else 500)
    assert entry.eval_seed == 777 and (entry.agents < 100 or entry.covered is not None or entry.task != "coverage")
    assert entry.curves == "" or os.path.exists(os.path.join(zoo.ROOT, entry.curves))


def test_a_name_not_in_the_zoo_is_refused_with_suggestions():
    with pytest.raises(zoo.ZooError, match="did you mean coverage-rc-m10"):
        load_policy("coverage-rc-m1")
    with pytest.raises(CheckpointError, match="does not exist"):
        load_policy("runs/no/such/policy.pt")  # a path stays a path


def test_a_changed_file_is_refused(tmp_path, monkeypatch):
    entry = zoo.get("formation-uc-m3")
    copy = tmp_path / "policy.pt"
    shutil.copy(entry.path, copy)
    data = bytearray(copy.read_bytes())
    data[len(data) // 2] ^= 0xFF
    copy.write_bytes(bytes(data))
    index = tmp_path / "index.toml"
    index.write_text(
        open(zoo.INDEX).read().replace(f'weights = "{entry.weights}"', f'weights = "{os.path.relpath(copy, zoo.ROOT)}"')
    )
    monkeypatch.setattr(zoo, "INDEX", str(index))
    monkeypatch.setattr(zoo.load_index, "__defaults__", (str(index),))
    with pytest.raises(ValueError, match="sha256"):
        load_policy("formation-uc-m3")


def test_a_malformed_index_is_refused(tmp_path):
    bad = tmp_path / "index.toml"
    bad.write_text('[[model]]\nname = "x"\nweights = 3\nunknown_key = 1\n')
    with pytest.raises(zoo.ZooError, match="unknown keys"):
        zoo.load_index(str(bad))
    bad.write_text("[[model]\n")
    with pytest.raises(zoo.ZooError, match="not valid TOML"):
        zoo.load_index(str(bad))


def test_models_names_the_entry_to_use_for_a_team_size(capsys):
    """`swarm models --task line --agents 50`: one entry per comm, the one trained nearest 50; every
    card opens with when to use it."""
    from swarm_cli.models import models_main

    entries = zoo.load_index()
    picked = {(e.task, e.comm): e.name for e in zoo.select(entries, "line", None, 50)}
    assert picked == {("line", "uc"): "line-uc-m10", ("line", "rc"): "line-rc-m100-radio"}
    assert [e.name for e in zoo.select(entries, "coverage", "uc", 4)] == ["coverage-uc-m5"]  # 5/4 is nearer than 4/3
    assert models_main(["--task", "line", "--agents", "50"]) == 0
    out = capsys.readouterr().out
    assert "line-rc-m100-radio" in out and "line-rc-m10`" not in out
    for e in entries:
        assert e.when().startswith("Use it")
        if e.spec == "radio":  # the large-team cards say how each agent's landmark is chosen and what it senses
            assert "auction the agents run by messages" in e.when() and "senses the landmarks within" in e.when()


def test_a_large_team_policy_evaluates_in_its_own_setting_as_loaded():
    """README's Python use: load_policy(NAME) then evaluate(...) runs a large-team policy on the
    lists it was trained on, with no setting passed; the dense layout is one it cannot take."""
    from taichi_swarm import Sim
    from trainer.evaluate import evaluate

    policy, payload = load_policy("coverage-rc-m100-radio")
    assert policy.sim.swarm_record() == payload["swarm"] and policy.sim.auction_rounds == 8
    out = evaluate(policy, policy.sim.override(agents=12), episodes=2, seed=777)
    assert 0 <= out["success_rate"] <= 1 and out["agents"] == 12
    with pytest.raises(ValueError, match="entities"):
        evaluate(policy, Sim("coverage", 12, "rc", 1.0), episodes=2, seed=777)
