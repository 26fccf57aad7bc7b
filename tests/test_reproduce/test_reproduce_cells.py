"""`swarm reproduce`: the spec as data, one cell resumable without Ray, the tables
rendered from results, and (through local Ray) a killed worker that loses nothing."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from reproduce import cells as cells_mod
from reproduce.spec import SpecError, load_spec
from reproduce.tables import DOC_BEGIN, DOC_END, doc_markers, render_all, update_doc
from trainer.config import PRESETS

TINY = """
name = "tiny"
[defaults]
preset = "fast"
ppo = {{ num_envs = 4, num_steps = 8, minibatches = 1, epochs = 1 }}
eval_every = {eval_every}
eval_episodes = 10
final_episodes = 12
checkpoint_every = 1
compile = false

[[cells]]
id = "train-cov"
table = 1
kind = "train"
task = "coverage"
agents = 2
updates = {updates}
paper = {{ "2" = {{ S = 99, T = 10.0 }} }}

[[cells]]
id = "zs-cov"
table = 4
kind = "zero-shot"
task = "coverage"
source = "train-cov"
sizes = [1, 2, 3]
paper = {{ "3" = {{ S = 50 }} }}
"""


def write_spec(tmp_path, updates=3, eval_every=2, text=None) -> str:
    path = tmp_path / "tiny.toml"
    path.write_text(text if text is not None else TINY.format(updates=updates, eval_every=eval_every))
    return str(path)


# --- the spec ------------------------------------------------------------------------


def test_shipped_paper_spec_has_every_table_and_the_papers_numbers():
    spec = load_spec("paper")
    assert spec.tables() == [1, 2, 3, 4]
    t1 = [c for c in spec.cells if c.table == 1 and c.kind == "train"]
    assert len(t1) == 12 and {c.run.agents for c in t1} == {3, 6}
    baselines = [c for c in spec.cells if c.kind == "baseline"]
    assert {c.run.config.algorithm for c in baselines} == {"maddpg", "mappo", "ippo", "qmix", "vdn", "iql"}
    assert all(c.table == 1 and c.run.config.obs_mode == "full" and c.run.config.frames <= 4_500_000 for c in baselines)
    assert spec.cell("t1-coverage-maddpg-m3").paper["3"] == {"S": 95, "T": 17.89, "DIST": 0.065}
    assert spec.cell("t1-coverage-qmix-m6").paper["6"] == {"S": 0}
    assert spec.cell("t1-coverage-rc-m6").paper["6"] == {"S": 5, "T": 48.32, "DIST": 0.17}
    assert spec.cell("t2-coverage-emp-rc").paper["10"] == {"S": 85, "N": 3250}
    assert spec.cell("t2-coverage-noemp-uc").run.config.model.entity_mode == "padded"
    zs = spec.cell("t4-line-rc")
    assert zs.needs == "t3-line-rc" and zs.run.source_agents == 5 and zs.paper["3"]["S"] == 16
    # every reported number comes from 500 fresh episodes at a seed training never uses
    assert all(c.run.final_episodes >= 500 and c.run.eval_seed < 2**40 for c in spec.cells)


def test_shipped_recipe_spec_is_the_paper_spec_with_our_recipes():
    """`recipe` has the paper spec's tables of our method, with the paper's numbers, run by
    what reproduced them here: fast preset, never-reset return, a polish after every run
    and stage, and the coverage curricula started from Table 1's UC M = 3 run; line M = 6
    with the reset return, as the runs that reproduced it; the line curricula started from Table 1's line M = 3
    run of their mode; formation's curricula with the landmark offset concatenated, whose M = 5 policy carries
    to M = 4 and 6."""
    paper, recipe = load_spec("paper"), load_spec("recipe")
    ours = [c for c in paper.cells if c.kind != "baseline"]
    # (and beyond the paper, table 11: policies trained on from the zoo's through a lossy radio)
    assert sorted(c.id for c in recipe.cells if c.table != 11) == sorted(c.id for c in ours)
    assert all(recipe.cell(c.id).paper == c.paper for c in ours)
    trained = [c for c in recipe.cells if c.kind in ("train", "curriculum") and c.table != 11]
    # with the never-reset return line UC M = 6 read 0-1% in 1550 updates
    reset = {"t1-line-uc-m6", "t1-line-rc-m6"}
    fast = PRESETS["fast"]
    assert all(c.run.config.preset == "fast" and c.run.config.ppo.reset_return is (c.id in reset) for c in trained)
    # the coverage and line curricula are fine-tunes throughout: a constant 1e-4 (at 7e-4 coverage RC
    # collapsed at M = 7; line stalled at UC M = 7 or 10 and RC M = 5 or 7, with either return)
    fine_tunes = {"t2-coverage-emp-uc", "t2-coverage-emp-rc", "t3-line-uc", "t3-line-rc"}
    tune = dataclasses.replace(fast, reset_return=False, lr=1e-4, lr_end=1e-4)
    assert all(c.run.config.ppo == tune for c in trained if c.id in fine_tunes)
    assert all(
        c.run.config.ppo == dataclasses.replace(fast, reset_return=c.id in reset)
        for c in trained
        if c.id not in fine_tunes
    )
    assert all(c.transfer_offsets == (2,) for c in trained)  # the next stage's size, logged while training
    assert all(c.run.polish_updates == 300 and c.run.polish_lr == 3e-5 for c in trained)
    assert all(c.run.config.updates * 2048 >= 4_500_000 for c in trained if c.kind == "train")  # the paper's budget
    for cid in ("t2-coverage-emp-uc", "t2-coverage-emp-rc"):
        assert recipe.cell(cid).needs == "t1-coverage-uc-m3"
    assert recipe.cell("t2-coverage-emp-rc").run.sizes == (3, 5, 7, 10)
    for mode in ("uc", "rc"):  # line's M = 3 stage is Table 1's line M = 3 run of the same mode
        line = recipe.cell(f"t3-line-{mode}")
        assert line.needs == f"t1-line-{mode}-m3" and line.run.sizes == (5, 7, 10) and "3" in line.paper
    # formation's chains with the authors' network for formation: EMP's M = 5 policy did not carry
    concat = {c.id for c in recipe.cells if c.kind != "zero-shot" and c.run.config.model.entity_mode == "concat"}
    assert concat == {"t3-formation-uc", "t3-formation-rc"}
    assert [c.id for c in recipe.select(cell_ids=["t4-coverage-rc"])] == [
        "t1-coverage-uc-m3", "t2-coverage-emp-rc", "t4-coverage-rc"
    ]  # fmt: skip
    assert all(c.run.final_episodes >= 500 and c.run.eval_seed == 777 for c in recipe.cells)


def test_shipped_beyond_spec_sets_one_team_size_against_two():
    """`beyond`: the 10-minute coverage recipe (1100 updates, fast preset, never-reset
    return) on M = 3 alone against M = 3 and 4 together, each evaluated at M = 3..6 and
    each the start of the recipe spec's coverage UC curriculum."""
    beyond = load_spec("beyond")
    alone, mixed = beyond.cell("x-coverage-uc-m3"), beyond.cell("x-coverage-uc-m34")
    assert (alone.run.config.team_sizes, mixed.run.config.team_sizes) == ((), (3, 4))
    assert {**mixed.definition()["config"], "team_sizes": []} == alone.definition()["config"]  # nothing else differs
    assert alone.run.config.preset == "fast" and alone.run.config.ppo == dataclasses.replace(
        PRESETS["fast"], reset_return=False
    )
    assert alone.run.config.updates == 1100 and alone.run.polish_updates == 0 and alone.run.agents == 3
    for cid, source in (("x-zs-coverage-uc-m3", alone), ("x-zs-coverage-uc-m34", mixed)):
        assert beyond.cell(cid).needs == source.id and beyond.cell(cid).run.sizes == (3, 4, 5, 6)
    # the curriculum from each: the recipe spec's coverage UC chain, only the start differs
    chain = load_spec("recipe").cell("t2-coverage-emp-uc")
    for cid, start in (("x-cur-coverage-uc-from-m3", alone), ("x-cur-coverage-uc-from-m34", mixed)):
        cur = beyond.cell(cid)
        assert cur.needs == start.id and cur.kind == "curriculum"
        same = ("sizes", "ppo", "threshold", "max_updates_per_stage", "polish_updates", "polish_lr", "preset")
        assert {k: getattr(cur.run.config, k) for k in same} == {k: getattr(chain.run.config, k) for k in same}
    # formation 3 -> 5 with EMP against concat: nothing else differs, the recipe's chain settings
    emp, concat = beyond.cell("x-cur-formation-uc-emp"), beyond.cell("x-cur-formation-uc-concat")
    assert (emp.run.config.model.entity_mode, concat.run.config.model.entity_mode) == ("emp", "concat")
    assert emp.run.sizes == (3, 5)
    concat_config = concat.definition()["config"]
    assert {**concat_config, "model": {**concat_config["model"], "entity_mode": "emp"}} == emp.definition()["config"]
    formation = load_spec("recipe").cell("t3-formation-uc")
    alike = ("ppo", "threshold", "max_updates_per_stage", "polish_updates", "polish_lr", "preset", "eval_every")
    assert {k: getattr(emp.run.config, k) for k in alike} == {k: getattr(formation.run.config, k) for k in alike}
    assert (emp.run.final_episodes, emp.run.eval_seed) == (formation.run.final_episodes, formation.run.eval_seed)
    assert beyond.tables() == [5, 6, 7, 8, 9]  # numbered after the paper's four
    assert all(c.run.final_episodes >= 500 and c.run.eval_seed == 777 for c in beyond.cells)


def test_selection_pulls_in_the_source_of_a_zero_shot_row():
    spec = load_spec("paper")
    chosen = [c.id for c in spec.select(cell_ids=["t4-coverage-rc"])]
    assert chosen == ["t2-coverage-emp-rc", "t4-coverage-rc"]
    assert {c.table for c in spec.select(tables=[1])} == {1}
    with pytest.raises(SpecError, match="no cell 'nope'"):
        spec.select(cell_ids=["nope"])
    with pytest.raises(SpecError, match=r"--tables \[9\]"):
        spec.select(tables=[9])


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace('kind = "train"', 'kind = "trian"'), "kind must be one of"),
        (lambda t: t.replace("agents = 2", "agents = 2\nbogus = 1"), r"unknown keys \['bogus'\]"),
        (lambda t: t.replace('source = "train-cov"', 'source = "missing"'), "must be a cell declared before it"),
        (lambda t: t.replace("sizes = [1, 2, 3]", "sizes = [0, 2]"), "sizes must be team sizes"),
        (lambda t: t.replace('id = "zs-cov"', 'id = "train-cov"'), "two cells named 'train-cov'"),
        (lambda t: t.replace('task = "coverage"\nagents', 'task = "covrage"\nagents'), "task must be one of"),
        (lambda t: t + "\n[[cells]]\nid = 'x'\n", "missing 'table'"),
        (lambda t: t.replace("name =", "nmae ="), "unknown top-level keys"),
        (lambda t: t + "\n[[cells", "not valid TOML"),
        (lambda t: t.replace('kind = "train"', 'kind = "baseline"\nframes = 9'), "needs algorithm"),
        (lambda t: t.replace('preset = "fast"', 'preset = "papr"'), "preset must be one of"),
        (lambda t: t.replace("epochs = 1 }", "epochs = 1, epocs = 2 }"), r"ppo has unknown options \['epocs'\]"),
        (lambda t: t.replace('source = "train-cov"', 'source = "train-cov"\ncomm = "rc"'), "differ from its source"),
        # a zero-shot row's setting, by the Sim's own checks
        (
            lambda t: t.replace('source = "train-cov"', 'source = "train-cov"\ncomm_radius = -1.0'),
            "comm_radius must be >= 0",
        ),
        (lambda t: t.replace('kind = "train"', 'kind = "baseline"\nalgorithm = "mappo"'), "needs frames"),
        (lambda t: t.replace("agents = 2", "agents = 2\ntransfer_offsets = [0, 1]"), "small non-zero team-size"),
        (lambda t: t.replace("agents = 2", "agents = 2\ntransfer_offsets = 1"), "transfer_offsets must be a list"),
        (lambda t: t.replace("agents = 2", "agents = 2\ntransfer_offsets = [2, 2]"), "repeated offset"),
        (lambda t: t.replace("sizes = [1, 2, 3]", "sizes = 3"), "sizes must be a list of integers"),
        (
            lambda t: t.replace("sizes = [1, 2, 3]", "sizes = [1]\nteam_sizes = [1, 2]"),
            r"unknown keys \['team_sizes'\] for a zero-shot",
        ),
        (
            lambda t: t.replace("agents = 2", "agents = 2\nteam_sizes = [0, 2]"),
            r"team_sizes must be team sizes in \[1, ",
        ),
        (lambda t: t.replace("agents = 2", "agents = 2\nteam_sizes = [2, 2]"), "team_sizes repeats a size"),
        (lambda t: t.replace("agents = 2", "agents = 2\nteam_sizes = 2"), "team_sizes must be a list of integers"),
        (
            lambda t: t.replace("agents = 2", "agents = 2\nteam_sizes = [2, 3]"),
            r"'train-cov': ppo.minibatches \(1\) must be >= the number of team_sizes \(2\)",
        ),
        # values of the wrong type name the key, not a traceback
        (lambda t: t.replace("agents = 2", 'agents = "2"'), "agents must be an integer, got '2'"),
        (lambda t: t.replace("agents = 2", "agents = true"), "agents must be an integer, got True"),
        (lambda t: t.replace("sizes = [1, 2, 3]", "sizes = [true, 3]"), "sizes must be a list of integers"),
        (lambda t: t.replace("compile = false", 'compile = "no"'), "compile must be true or false"),
        (lambda t: t.replace('paper = { "2" = { S = 99, T = 10.0 } }', "paper = 5"), "paper must be a table, got 5"),
        (lambda t: "defaults = 3\n" + t[t.index("[[cells]]") :], r"\[defaults\] must be a table"),
        (lambda t: t.replace("sizes = [1, 2, 3]", "sizes = [1, 2, 1]"), r"sizes repeats a size: \[1, 2, 1\]"),
        # the trainer's own checks of the values, at load time: not after the cell has written its definition
        (lambda t: t.replace("epochs = 1 }", "epochs = 0 }"), "'train-cov': ppo.epochs must be >= 1"),
        (lambda t: t.replace("epochs = 1 }", 'epochs = "1" }'), "'train-cov': ppo.epochs must be an integer, got '1'"),
        (lambda t: t.replace('source = "train-cov"', 'source = "train-cov"\nsource_agents = 3'), "leave source_agents"),
        (lambda t: t.replace("table = 4", "table = 1"), "a zero-shot cell in table 1, whose cell 'train-cov'"),
    ],
)
def test_bad_specs_name_the_cell_and_the_key(tmp_path, edit, message):
    path = write_spec(tmp_path, text=edit(TINY.format(updates=3, eval_every=2)))
    with pytest.raises(SpecError, match=message):
        load_spec(path)


def test_table_numbers_are_the_mean_and_95_interval_over_seeds_and_say_how_many_ran():
    from reproduce import tables

    # half-width of the 95% t-interval: t(0.975, n-1) * sd / sqrt(n)
    assert tables._stat([0.5, 0.7], 100) == "60.0 ± 127.1 (2)"  # 12.706 * 14.14 / 1.414
    assert tables._stat([0.5, 0.7, 0.9], 100) == "70.0 ± 49.7 (3)"  # 4.303 * 20 / 1.732
    assert tables._stat([2200.0, 2200.0], digits=0) == "2200 (2)"  # every seed the same: no interval
    assert tables._stat([None, float("nan")]) == "-"
    assert tables._stat([0.5], 100) == "50.0"  # one seed: the number alone


def test_a_zero_shot_table_marks_sizes_a_row_does_not_evaluate(tmp_path):
    extra = '\n[[cells]]\nid = "zs-cov-2"\ntable = 4\nkind = "zero-shot"\ntask = "coverage"\n'
    extra += 'source = "train-cov"\nsizes = [2]\n'
    spec = load_spec(write_spec(tmp_path, text=TINY.format(updates=3, eval_every=2) + extra))
    md = render_all(spec.cells, [0], str(tmp_path / "root"), "tiny")
    assert "| coverage UC | train-cov | not run (-) | not run (-) | not run (50) |" in md
    assert "| coverage UC | train-cov | - (-) | not run (-) | - (-) |" in md  # sizes 1 and 3: not this row's


def test_transfer_offsets_are_logged_and_leave_the_definition_alone(tmp_path):
    """A cell's transfer_offsets make its evaluations during training report S% at those
    neighbouring sizes; they decide nothing that is trained, so results from before stay valid."""
    text = TINY.format(updates=2, eval_every=2)
    plain = load_spec(write_spec(tmp_path, text=text)).cell("train-cov")
    spec = load_spec(write_spec(tmp_path, text=text.replace("agents = 2", "agents = 2\ntransfer_offsets = [1]")))
    cell = spec.cell("train-cov")
    assert cell.transfer_offsets == (1,) and cell.digest() == plain.digest()
    root = str(tmp_path / "root")
    cells_mod.run_cell(cell, 0, root)
    with open(os.path.join(cells_mod.cell_dir(root, cell, 0), "metrics.jsonl")) as f:
        evals = [r for r in map(json.loads, f) if "eval_success_rate" in r]
    assert evals and set(evals[-1]["eval_transfer"]) == {"3"}


def test_a_cell_trains_on_several_team_sizes_at_once(tmp_path, capsys):
    """team_sizes: one group of environments per size in every rollout (the trainer's
    --team-sizes); part of the definition, so the run differs from the one-size cell."""
    text = TINY.format(updates=2, eval_every=2).replace("minibatches = 1", "minibatches = 2")
    plain = load_spec(write_spec(tmp_path, text=text)).cell("train-cov")
    spec = load_spec(write_spec(tmp_path, text=text.replace("agents = 2", "agents = 2\nteam_sizes = [2, 3]")))
    cell = spec.cell("train-cov")
    assert cell.run.config.team_sizes == (2, 3) and cell.definition()["config"]["team_sizes"] == [2, 3]
    assert cell.digest() != plain.digest()
    root = str(tmp_path / "root")
    (row,) = cells_mod.run_cell(cell, 0, root)["rows"]
    assert row["agents"] == 2 and row["env_steps"] == 2 * 4 * 8  # reported at agents; 2 envs per size
    with open(os.path.join(cells_mod.cell_dir(root, cell, 0), "config.json")) as f:
        assert json.load(f)["team_sizes"] == [2, 3]
    md = render_all(spec.cells, [0], root, "tiny")
    assert "| coverage UC | 2 | " in md and "not run" not in md.split("### Table 4")[0]
    from swarm_cli.main import main

    assert main(["reproduce", "--spec", spec.path, "--root", root, "--dry-run"]) == 0
    assert re.search(r"train-cov +train +coverage +uc +emp +2 \(on 2 3\) ", capsys.readouterr().out)


def test_unknown_spec_name_lists_the_shipped_ones():
    with pytest.raises(SpecError, match=r"\(beyond, paper, quick, recipe, smoke\)"):
        load_spec("no-such-spec")


# --- one cell, no Ray -------------------------------------------------------------------


def _metric_updates(run_dir: str) -> list[int]:
    with open(os.path.join(run_dir, "metrics.jsonl")) as f:
        return [json.loads(line)["update"] for line in f if line.strip()]


def test_a_killed_cell_resumes_and_a_finished_one_is_skipped(tmp_path, monkeypatch):
    spec = load_spec(write_spec(tmp_path, updates=4))
    train_cell, zs_cell = spec.cells
    root = str(tmp_path / "root")
    import trainer.train as train_mod

    real = train_mod.one_update

    stop_after = {"updates": 2}

    def interrupted(state, *args, **kwargs):  # Ctrl-C (or a kill) in the middle of update 3
        if state.counters["update"] == stop_after["updates"]:
            raise KeyboardInterrupt
        return real(state, *args, **kwargs)

    monkeypatch.setattr(train_mod, "one_update", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cells_mod.run_cell(train_cell, 0, root)
    other_root = str(tmp_path / "other")  # seed 0 stopped after 2 updates there, seed 1 after 1
    for seed, stop in ((0, 2), (1, 1)):
        stop_after["updates"] = stop
        with pytest.raises(KeyboardInterrupt):
            cells_mod.run_cell(train_cell, seed, other_root)
    assert cells_mod.cell_state(root, train_cell, 0) == "started"
    # the progress view shows how far it got and its latest evaluation (eval_every = 2)
    assert cells_mod.progress(root, train_cell, 0)["last_eval"]["update"] == 2
    from reproduce.runner import format_progress, submission_order

    status = format_progress([train_cell], [0], root, workers=1)
    assert "last eval S%" in status and " @2 " in status
    assert "stopped" in status.splitlines()[1]  # started, and no process holds it
    # a resumed run finishes what it had begun first, the nearest to done first; a source
    # still precedes its readers, even a started one (its source to run again)
    zs_dir = cells_mod.cell_dir(other_root, zs_cell, 1)
    os.makedirs(zs_dir)
    open(os.path.join(zs_dir, cells_mod.ATTEMPTS), "w").write("[]")
    order = submission_order(spec.cells, [1, 0], other_root, finished=set())
    assert [(c.id, s) for c, s in order] == [("train-cov", 0), ("train-cov", 1), ("zs-cov", 1), ("zs-cov", 0)]
    # a zero-shot row whose source has finished goes first: minutes of evaluation, numbers early
    order = submission_order(spec.cells, [1, 0], other_root, finished={("train-cov", 0)})
    assert [(c.id, s) for c, s in order] == [("zs-cov", 0), ("train-cov", 1), ("zs-cov", 1)]
    monkeypatch.setattr(train_mod, "one_update", real)
    # a started cell whose definition changed is refused, not resumed under the old one
    with pytest.raises(SpecError, match=r"differs in \['updates'\]"):
        cells_mod.run_cell(load_spec(write_spec(tmp_path, updates=6)).cells[0], 0, root)
    write_spec(tmp_path, updates=4)

    result = cells_mod.run_cell(train_cell, 0, root)
    run_dir = cells_mod.cell_dir(root, train_cell, 0)
    assert _metric_updates(run_dir) == [1, 2, 3, 4]  # nothing lost, nothing twice
    assert result["attempts"] == 2
    row = result["rows"][0]
    assert row["updates"] == 4 and row["episodes"] == 12 and row["seed"] == 777

    stamp = os.path.getmtime(os.path.join(run_dir, cells_mod.RESULT))
    assert cells_mod.run_cell(train_cell, 0, root) == result  # done: read back, not rerun
    assert os.path.getmtime(os.path.join(run_dir, cells_mod.RESULT)) == stamp

    with pytest.raises(SpecError, match="needs its source"):
        cells_mod.run_cell(zs_cell, 0, root)
    zs = cells_mod.run_cell(zs_cell, 0, root, source=train_cell)
    assert [r["agents"] for r in zs["rows"]] == [1, 2, 3]
    assert cells_mod.read_result(root, zs_cell, 0, train_cell) == zs
    # the source finished again (a new policy): its zero-shot row is stale and runs again
    source_json = os.path.join(run_dir, cells_mod.RESULT)
    redone = json.loads(open(source_json).read()) | {"finished": 1.0}
    open(source_json, "w").write(json.dumps(redone))
    assert cells_mod.read_result(root, zs_cell, 0, train_cell) is None
    assert cells_mod.run_cell(zs_cell, 0, root, source=train_cell)["source_finished"] == 1.0

    # a changed definition never mixes with old results
    changed = load_spec(write_spec(tmp_path, updates=5)).cells[0]
    with pytest.raises(SpecError, match=r"differs in \['updates'\]"):
        cells_mod.run_cell(changed, 0, root)

    # the tables: our numbers beside the paper's; a cell without results says so
    md = render_all(spec.cells, [0, 1], root, "tiny")
    assert re.search(r"\| coverage UC \| 2 \| \d+\.\d \| 99 \|", md)  # ours (one seed of the two ran), paper
    assert re.search(r"\| \d+\.\d \(50\) \|", md) and "curves-table-1.png" in md  # zero-shot at M = 3
    assert os.path.exists(os.path.join(root, "curves-table-1.png"))
    md_missing = render_all(spec.cells, [0], str(tmp_path / "empty"), "tiny")
    assert "not run" in md_missing
    # the source finished again after its zero-shot row ran: the row is left out, and named
    open(source_json, "w").write(json.dumps(redone | {"finished": 2.0}))
    md_stale = render_all(spec.cells, [0], root, "tiny")
    assert "Left out as stale" in md_stale and "zs-cov seed 0" in md_stale
    assert "| not run (50) |" in md_stale and "| not run (50) |" not in md  # its old numbers are not shown
    open(source_json, "w").write(json.dumps(redone))

    doc = tmp_path / "doc.md"
    doc.write_text(f"# Results\nbefore\n{DOC_BEGIN}\nold\n{DOC_END}\nafter\n")
    update_doc(str(doc), md)
    text = doc.read_text()
    assert "old" not in text and "before" in text and "after" in text and "| coverage UC | 2 |" in text
    # another spec's tables go between that spec's own markers, in the same document
    begin, end = doc_markers("recipe")
    doc.write_text(f"{text}\n{begin}\nold recipe\n{end}\n")
    update_doc(str(doc), "recipe tables", "recipe")
    both = doc.read_text()
    assert "old recipe" not in both and f"{begin}\nrecipe tables\n{end}" in both and "| coverage UC | 2 |" in both
    with pytest.raises(ValueError, match="--spec smoke"):
        update_doc(str(doc), md, "smoke")
    for bad in ("no markers", f"{DOC_END}\n{DOC_BEGIN}", f"{DOC_BEGIN}{DOC_END}{DOC_BEGIN}{DOC_END}"):
        doc.write_text(bad)
        with pytest.raises(ValueError, match="markers"):
            update_doc(str(doc), md)


def test_one_process_per_cell_and_the_status_says_which_is_running(tmp_path, lock_held_elsewhere):
    from reproduce.runner import format_progress
    from trainer.rundir import RunDirLocked

    spec = load_spec(write_spec(tmp_path, updates=2))
    train_cell, zs_cell = spec.cells
    root = str(tmp_path / "root")
    directory = cells_mod.cell_dir(root, train_cell, 0)

    def states(live=None):
        lines = format_progress(spec.cells, [0], root, workers=1, live=live).splitlines()[1:3]
        return [line.split()[2] for line in lines]

    assert states() == ["pending", "waits"]
    assert states(live={("train-cov", 0), ("zs-cov", 0)}) == ["queued", "waits"]
    with lock_held_elsewhere(directory, cells_mod.CELL_LOCK) as pid:  # another `swarm reproduce` on it
        assert states() == ["running", "waits"]
        with pytest.raises(RunDirLocked, match=rf"cell 'train-cov' \(seed 0\) \(pid {pid}"):
            cells_mod.run_cell(train_cell, 0, root)
    assert states() == ["pending", "waits"]  # refused before anything was written
    assert os.listdir(directory) == [cells_mod.CELL_LOCK]
    cells_mod.run_cell(train_cell, 0, root)  # the holder is gone: the cell runs
    assert states() == ["done", "pending"]


def test_cli_dry_run_status_and_errors(tmp_path, capsys):
    from swarm_cli.main import main

    def reproduce_main(argv):
        return main(["reproduce", *argv])

    path = write_spec(tmp_path)
    root = str(tmp_path / "root")
    assert reproduce_main(["--spec", path, "--root", root, "--dry-run"]) == 0
    assert reproduce_main(["--spec", path, "--root", root, "--dry-run", "--seeds", "2", "--first-seed", "3"]) == 0
    assert "seeds [3, 4]" in capsys.readouterr().out  # more seeds of a cell: --first-seed
    assert reproduce_main(["--spec", path, "--first-seed", "-1", "--dry-run"]) == 2
    assert reproduce_main(["--spec", path, "--root", root, "--status"]) == 0
    assert reproduce_main(["--spec", path, "--seeds", "0"]) == 2
    assert reproduce_main(["--spec", path, "--cells", "nope", "--dry-run"]) == 2
    assert reproduce_main(["--spec", path, "--root", root, "--render", "--update-doc", str(tmp_path / "x.md")]) == 2


# --- through Ray, with a worker killed mid-run ---------------------------------------


@pytest.mark.slow  # ~1-4 min: Ray's start, two workers' imports, the kill and the retry
def test_ray_run_survives_a_killed_worker(tmp_path):
    pytest.importorskip("ray")
    spec_path = write_spec(tmp_path, updates=10, eval_every=5)
    root = tmp_path / "root"
    run_dir = root / "train-cov" / "s0"
    cmd = [sys.executable, "-m", "swarm_cli", "reproduce", "--spec", spec_path, "--root", str(root)]
    proc = subprocess.Popen(
        [*cmd, "--workers", "1", "--progress-every", "2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    try:
        killed_pid = None
        deadline = time.time() + 480
        while time.time() < deadline and killed_pid is None:
            time.sleep(0.3)
            metrics = run_dir / "metrics.jsonl"
            if (run_dir / "attempts.json").exists() and metrics.exists() and len(_metric_updates(str(run_dir))) >= 2:
                killed_pid = json.loads((run_dir / "attempts.json").read_text())[-1]["pid"]
                # the cell runs at the driver's priority, not at Ray's worker niceness (15)
                assert os.getpriority(os.PRIO_PROCESS, killed_pid) == os.getpriority(os.PRIO_PROCESS, proc.pid)
                os.kill(killed_pid, signal.SIGKILL)  # the Ray worker running the cell
        assert killed_pid is not None, "the cell never got going"
        out, _ = proc.communicate(timeout=600)  # ~45 s on an idle 2-core machine
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert re.search(r"train-cov +0 +running", out), out  # the progress view saw its worker on it
    attempts = json.loads((run_dir / "attempts.json").read_text())
    assert len(attempts) == 2 and attempts[0]["pid"] == killed_pid != attempts[1]["pid"]
    assert _metric_updates(str(run_dir)) == list(range(1, 11))  # resumed from its checkpoint
    result = json.loads((run_dir / "result.json").read_text())
    assert result["rows"][0]["updates"] == 10
    assert (root / "zs-cov" / "s0" / "result.json").exists()  # the dependent row ran after it
    assert "| coverage UC | 2 |" in (root / "tables.md").read_text()
    # a second call finds everything done and runs nothing
    again = subprocess.run([*cmd, "--dry-run"], capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and again.stdout.count("s0 done") == 2


def test_a_benchmarl_baseline_cell_trains_evaluates_and_renders(tmp_path):
    pytest.importorskip("benchmarl")
    text = """
[[cells]]
id = "base-cov"
table = 1
kind = "baseline"
task = "coverage"
algorithm = "mappo"
agents = 2
frames = 256
actions = "discrete"
final_episodes = 16
num_envs = 4
frames_per_batch = 128
paper = { "2" = { S = 42 } }
"""
    spec = load_spec(write_spec(tmp_path, text=text))
    (cell,) = spec.cells
    assert cell.definition()["config"]["algorithm"] == "mappo"
    root = str(tmp_path / "root")
    result = cells_mod.run_cell(cell, 0, root)
    (row,) = result["rows"]
    assert row["episodes"] == 16 and row["env_steps"] >= 256 and row["algorithm"] == "mappo"
    assert 0.0 <= row["success_rate"] <= 1.0
    assert os.path.exists(os.path.join(cells_mod.cell_dir(root, cell, 0), "curves.png"))  # BenchMARL's csv drawn
    md = render_all(spec.cells, [0], root, "tiny")
    assert re.search(r"\| coverage MAPPO \(full obs\.\) \| 2 \| \d+\.\d \| 42 \|", md)
    with pytest.raises(SpecError, match=r"unknown keys \['bogus'\]"):
        load_spec(write_spec(tmp_path, text=text.replace("frames_per_batch = 128", "bogus = 1")))


def test_cuda_cells_need_a_gpu_share():
    from reproduce.runner import run_on_ray

    with pytest.raises(ValueError, match="--gpus-per-cell"):
        run_on_ray([], [0], "unused", arch="cuda")


def test_min_updates_holds_a_run_past_its_target(tmp_path, monkeypatch):
    """With min_updates, a run (and a curriculum stage) that reaches its target early
    trains on to min_updates, then stops at the next evaluation."""
    import trainer.train as train_mod
    from trainer.config import PRESETS, CurriculumConfig, TrainConfig
    from trainer.curriculum import run_curriculum

    def perfect(policy, cfg, update, device):
        return {"success_rate": 1.0, "mean_length": 5.0, "dist": 0.0, "update": update}

    monkeypatch.setattr(train_mod, "evaluate_during_training", perfect)
    ppo = PRESETS["fast"].__class__(**{**PRESETS["fast"].__dict__, "num_envs": 4, "num_steps": 8, "minibatches": 1})
    cfg = TrainConfig.of(
        agents=2, updates=8, eval_every=2, target_success=0.5, min_updates=3, run_dir=str(tmp_path / "run"),
        compile=False, progress=False, transfer_offsets=(), ppo=ppo,
    )  # fmt: skip
    summary = train_mod.train(cfg)
    assert summary["update"] == 4 and summary["reached_target"]  # evaluations at 2 (too early) and 4
    stages = run_curriculum(CurriculumConfig.over(
        cfg, min_updates=0, sizes=(2, 3), threshold=0.5, max_updates_per_stage=8, run_dir=str(tmp_path / "cur"),
        min_updates_per_stage=5,
    ))  # fmt: skip
    assert [s["updates"] for s in stages] == [6, 6]
    with pytest.raises(ValueError, match="min_updates"):
        dataclasses.replace(cfg, min_updates=9).validate()
    with pytest.raises(ValueError, match="min-updates-per-stage"):
        run_curriculum(CurriculumConfig.over(
            cfg, sizes=(2,), threshold=0.5, max_updates_per_stage=4, run_dir=str(tmp_path / "bad"),
            min_updates_per_stage=5,
        ))  # fmt: skip


def test_a_run_stopped_at_its_target_stays_stopped_after_a_kill(tmp_path, monkeypatch):
    """Killed between its last checkpoint and summary.json, a stage that had reached its
    threshold must not train on when resumed (N would be inflated)."""
    import trainer.train as train_mod
    from trainer.config import PRESETS, TrainConfig

    def perfect(policy, cfg, update, device):
        return {"success_rate": 1.0, "mean_length": 5.0, "dist": 0.0, "update": update}

    monkeypatch.setattr(train_mod, "evaluate_during_training", perfect)
    ppo = PRESETS["fast"].__class__(**{**PRESETS["fast"].__dict__, "num_envs": 4, "num_steps": 8, "minibatches": 1})
    cfg = TrainConfig.of(agents=2, updates=6, eval_every=2, target_success=0.5, run_dir=str(tmp_path / "run"),
                      compile=False, progress=False, transfer_offsets=(), ppo=ppo)  # fmt: skip
    assert train_mod.train(cfg)["update"] == 2
    os.unlink(tmp_path / "run" / "summary.json")  # the kill
    summary = train_mod.train_or_resume(cfg)
    assert summary["update"] == 2 and summary["reached_target"]


def test_a_larger_budget_extends_a_run_that_ran_out_short_of_its_target(tmp_path, monkeypatch):
    """train_or_resume with more updates than a finished run had continues it when it ran out
    of updates below its target (a curriculum given more updates per stage), never when it
    reached its target, and a smaller budget changes nothing."""
    import trainer.train as train_mod
    from trainer.config import PRESETS, TrainConfig

    rate = {"value": 0.0}

    def evaluation(policy, cfg, update, device):
        return {"success_rate": rate["value"], "mean_length": 5.0, "dist": 0.0, "update": update}

    monkeypatch.setattr(train_mod, "evaluate_during_training", evaluation)
    ppo = PRESETS["fast"].__class__(**{**PRESETS["fast"].__dict__, "num_envs": 4, "num_steps": 8, "minibatches": 1})
    cfg = TrainConfig.of(agents=2, updates=4, eval_every=2, target_success=0.5, run_dir=str(tmp_path / "run"),
                      compile=False, progress=False, transfer_offsets=(), ppo=ppo)  # fmt: skip
    first = train_mod.train(cfg)
    assert first["update"] == 4 and not first["reached_target"]
    assert train_mod.train_or_resume(dataclasses.replace(cfg, updates=3)) == first
    rate["value"] = 1.0  # reached at the first evaluation of the extension
    extended = train_mod.train_or_resume(dataclasses.replace(cfg, updates=10, arch="auto"))
    assert extended["update"] == 6 and extended["reached_target"]
    with open(tmp_path / "run" / "config.json") as f:
        assert json.load(f)["arch"] == "auto"  # resumed where the driver runs it now (cells: --arch, --device)
    assert train_mod.train_or_resume(dataclasses.replace(cfg, updates=20))["update"] == 6


# --- init_from and polish: a run started from another cell's policy, trained on after -----

CHAIN = (
    TINY.format(updates=2, eval_every=2).split('[[cells]]\nid = "zs-cov"')[0]
    + """
polish_updates = 2
polish_lr = 1e-5

[[cells]]
id = "train-cov3"
table = 1
kind = "train"
task = "coverage"
agents = 3
updates = 2

[[cells]]
id = "curr-cov-rc"
table = 2
kind = "curriculum"
task = "coverage"
comm = "rc"
sizes = [2, 3]
max_updates_per_stage = 2
init_from = "train-cov"
polish_updates = 1
paper = { "3" = { S = 96, N = 3700 } }

[[cells]]
id = "zs-cov-rc"
table = 4
kind = "zero-shot"
task = "coverage"
comm = "rc"
source = "curr-cov-rc"
source_agents = 3
sizes = [3, 4]
"""
)


def _fake_final_eval(policy_path, cell, agents, arch="cpu"):
    """S% 1.0 for a polished policy, 0.0 for any other: which one a row reports."""
    polished = os.path.basename(os.path.dirname(policy_path)).endswith("polish")
    return {"agents": agents, "success_rate": float(polished), "mean_length": 9.0, "dist": 0.1, "episodes": 12,
            "seed": 777}  # fmt: skip


def _table_is_aligned(md: str) -> None:
    """Every row of every table has as many cells as its header."""
    header = None
    for line in md.splitlines():
        if not line.startswith("|"):
            header = None
        elif header is None:
            header = line.count("|")
        else:
            assert line.count("|") == header, line


def test_a_curriculum_table_shows_the_start_the_chain_was_given(tmp_path):
    """A chain whose first stage is another cell (the paper's M = 3 stage is Table 1's run)
    shows that cell's number in its M = 3 row, beside the paper's."""
    text = TINY.format(updates=2, eval_every=2).split('[[cells]]\nid = "zs-cov"')[0] + (
        '[[cells]]\nid = "chain"\ntable = 2\nkind = "curriculum"\ntask = "coverage"\nsizes = [3]\n'
        'init_from = "train-cov"\npaper = { "2" = { S = 90, N = 100 }, "3" = { S = 80, N = 200 } }\n'
    )
    spec = load_spec(write_spec(tmp_path, text=text))
    start, chain = spec.cells
    root = str(tmp_path / "root")
    row = {"agents": 2, "success_rate": 0.95, "mean_length": 9.0, "dist": 0.1, "updates": 2, "env_steps": 64,
           "wall_time": 60.0}  # fmt: skip
    result = {"cell": start.id, "definition": start.definition(), "rows": [row], "finished": 1.0}
    os.makedirs(cells_mod.cell_dir(root, start, 0))
    with open(os.path.join(cells_mod.cell_dir(root, start, 0), cells_mod.RESULT), "w") as f:
        json.dump(result, f)
    md = render_all(spec.cells, [0], root, "tiny").split("### Table 2")[1]
    assert "| coverage UC | 2 | 95.0 (the start: train-cov) | 90 | 2 | 100 | 0.00 | 1.0 | - |" in md
    assert "| coverage UC | 3 | not run | 80 | - | 200 |" in md
    _table_is_aligned(md)


def test_a_cell_starts_from_another_cells_policy_and_polishes(tmp_path, monkeypatch):
    import trainer.train as train_mod

    monkeypatch.setattr(cells_mod, "final_eval", _fake_final_eval)
    spec = load_spec(write_spec(tmp_path, text=CHAIN))
    train_cell, _, curr_cell, zs_cell = spec.cells
    assert curr_cell.needs == "train-cov" and zs_cell.needs == "curr-cov-rc"
    assert [c.id for c in spec.select(cell_ids=["zs-cov-rc"])] == ["train-cov", "curr-cov-rc", "zs-cov-rc"]
    assert train_cell.budget_updates() == 4 and curr_cell.budget_updates() == 6
    root = str(tmp_path / "root")
    with pytest.raises(SpecError, match="needs its init_from cell 'train-cov'"):
        cells_mod.run_cell(curr_cell, 0, root)
    with pytest.raises(SpecError, match="init_from 'train-cov' .* has not finished"):
        cells_mod.run_cell(curr_cell, 0, root, source=train_cell)
    assert cells_mod.cell_state(root, curr_cell, 0) == "pending"  # the refusal wrote nothing

    real, calls = train_mod.one_update, []

    def killed_in_the_polish(state, *args, **kwargs):  # a kill in the polish's first update
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(state, *args, **kwargs)

    monkeypatch.setattr(train_mod, "one_update", killed_in_the_polish)
    with pytest.raises(KeyboardInterrupt):
        cells_mod.run_cell(train_cell, 0, root)
    assert cells_mod.progress(root, train_cell, 0)["updates"] == 2
    trained = cells_mod.run_cell(train_cell, 0, root)
    (row,) = trained["rows"]
    assert trained["attempts"] == 2
    assert row["updates"] == 4 and row["polish_updates"] == 2 and row["env_steps"] == 4 * 4 * 8
    assert row["success_rate"] == 1.0 and row["before_polish"]["success_rate"] == 0.0  # the polished policy reports
    polish_dir = os.path.join(cells_mod.cell_dir(root, train_cell, 0), "polish")
    assert _metric_updates(cells_mod.cell_dir(root, train_cell, 0)) == [1, 2]
    assert _metric_updates(polish_dir) == [1, 2]  # resumed: nothing lost, nothing twice
    polish_cfg = json.loads(open(os.path.join(polish_dir, "config.json")).read())
    assert polish_cfg["ppo"]["lr"] == 1e-5 and polish_cfg["ppo"]["lr_end"] is None

    chained = cells_mod.run_cell(curr_cell, 0, root, source=train_cell)
    assert [r["agents"] for r in chained["rows"]] == [2, 3]
    assert all(r["polish_updates"] == 1 and "before_polish" in r for r in chained["rows"])
    d = cells_mod.cell_dir(root, curr_cell, 0)
    first = json.loads(open(os.path.join(d, "stage-m2", "config.json")).read())
    assert first["init_from"] == cells_mod.policy_path(root, train_cell, 0) == os.path.join(polish_dir, "policy.pt")
    assert first["comm"] == "rc" and "init_carry" not in first
    second = json.loads(open(os.path.join(d, "stage-m3", "config.json")).read())
    assert second["init_from"] == os.path.join(d, "stage-m2-polish", "checkpoint.pt")
    assert cells_mod.run_dirs(root, curr_cell, 0) == [
        os.path.join(d, name) for name in ("stage-m2", "stage-m2-polish", "stage-m3", "stage-m3-polish")
    ]
    assert cells_mod.progress(root, curr_cell, 0)["updates"] == 6
    # the zero-shot row reads the polished M = 3 stage
    assert cells_mod.policy_path(root, curr_cell, 0, 3) == os.path.join(d, "stage-m3-polish", "policy.pt")
    assert [r["agents"] for r in cells_mod.run_cell(zs_cell, 0, root, source=curr_cell)["rows"]] == [3, 4]

    md = render_all(spec.cells, [0], root, "tiny")
    assert md.count("S% before polish (+updates)") == 2 and "| 0.0 (+1) | 2 | 3700 |" in md
    assert "| coverage UC | 2 | 100.0 | 99 | 0.0 (+2) |" in md and "| coverage UC | 3 | not run |" in md
    _table_is_aligned(md)

    # the upstream trained again: the cell trained from its old policy says so, never reads as done
    upstream_json = os.path.join(cells_mod.cell_dir(root, train_cell, 0), cells_mod.RESULT)
    redone = json.loads(open(upstream_json).read()) | {"finished": 1.0}
    open(upstream_json, "w").write(json.dumps(redone))
    with pytest.raises(SpecError, match="trained again since .* delete"):
        cells_mod.read_result(root, curr_cell, 0, train_cell)
    os.unlink(os.path.join(d, cells_mod.RESULT))  # (a run stopped half-way resumes from the same upstream only)
    with pytest.raises(SpecError, match="upstream.json: cell 'curr-cov-rc' was trained from a policy"):
        cells_mod.run_cell(curr_cell, 0, root, source=train_cell)
    assert (
        curr_cell.definition()["init_from"] == "train-cov" and curr_cell.definition()["config"]["polish_updates"] == 1
    )


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace('init_from = "train-cov"', 'init_from = "nope"'), "must be a cell declared before it"),
        (lambda t: t.replace('init_from = "train-cov"', 'init_from = "zs-cov-rc"'), "must be a cell declared"),
        (
            lambda t: t.replace('source = "curr-cov-rc"', 'source = "curr-cov-rc"\ninit_from = "train-cov"'),
            r"unknown keys \['init_from'\] for a zero-shot cell",
        ),
        (lambda t: t.replace("polish_updates = 1", "polish_updates = 1\ninit_agents = 5"), "leave init_agents out"),
        (
            lambda t: t.replace("polish_updates = 1", 'polish_updates = 1\nmodel = { entity_mode = "padded" }'),
            "the weights would not fit",
        ),
        (lambda t: t.replace("polish_updates = 1", "polish_updates = -1"), "polish.updates must be >= 0"),
        (lambda t: t.replace("polish_lr = 1e-5", "polish_lr = 0.0"), r"polish_lr must be in \(0, 1\]"),
        (lambda t: t.replace("sizes = [3, 4]", "sizes = [3, 4]\npolish_updates = 3"), r"unknown keys \['polish_u"),
        (lambda t: t.replace('init_from = "train-cov"\n', "init_agents = 2\n"), "set init_from too"),
    ],
)
def test_bad_init_from_and_polish_name_the_cell_and_the_key(tmp_path, edit, message):
    with pytest.raises(SpecError, match=message):
        load_spec(write_spec(tmp_path, text=edit(CHAIN)))


def test_init_from_crosses_tasks_only_where_the_inputs_fit(tmp_path):
    """Coverage's weights start a formation run on the same (entity message passing) inputs; a
    network that concatenates its task's landmarks fits only its own task."""
    chain = CHAIN.split('[[cells]]\nid = "zs-cov-rc"')[0]
    crossed = chain.replace('kind = "curriculum"\ntask = "coverage"', 'kind = "curriculum"\ntask = "formation"')
    assert crossed != chain
    spec = load_spec(write_spec(tmp_path, text=crossed))
    assert spec.cell("curr-cov-rc").run.task == "formation"
    concat = 'model = { entity_mode = "concat" }\n'
    both = crossed.replace("updates = 2\npaper", concat + "updates = 2\npaper", 1).replace(
        "polish_updates = 1\n", "polish_updates = 1\n" + concat
    )
    with pytest.raises(SpecError, match="the weights would not fit"):
        load_spec(write_spec(tmp_path, text=both))


# --- a cell's identity: the schema, its one migration, and fields added later ---------------

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
COMMITTED = {"paper": "results/reproduce", "recipe": "results/reproduce-recipe", "beyond": "results/reproduce-beyond"}


def test_every_committed_result_matches_its_cell():
    """The results under results/ (schema 1 definitions) read as done by today's cells."""
    import glob

    from reproduce.spec import canonical

    found = 0
    for name, rel in COMMITTED.items():
        spec, root = load_spec(name), os.path.join(ROOT, rel)
        for path in sorted(glob.glob(os.path.join(root, "*", "s*", cells_mod.RESULT))):
            cell = spec.cell(path.split(os.sep)[-3])
            seed = int(path.split(os.sep)[-2][1:])
            result = cells_mod.read_result(root, cell, seed, spec.cell(cell.needs) if cell.needs else None)
            assert result is not None, path
            assert canonical(result["definition"]) == cell.definition()
            found += 1
    assert found >= 50


def test_a_field_added_with_a_default_leaves_stored_definitions_valid(tmp_path, monkeypatch):
    """A stored definition lacks a field added since: it reads as the field's default (the
    behaviour before it), with no list of such fields kept anywhere; a cell that sets the new
    field to anything else is another experiment."""
    from reproduce import spec as spec_mod

    cell = load_spec(write_spec(tmp_path)).cell("train-cov")
    stored = cell.definition()

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class TrainPlus(spec_mod.Train):
        new_option: int = 0

    monkeypatch.setitem(spec_mod.RUNS, "train", TrainPlus)
    fields = {f.name: getattr(cell.run, f.name) for f in dataclasses.fields(cell.run)}
    now = dataclasses.replace(cell, run=TrainPlus(**fields))
    assert now.definition()["new_option"] == 0 and "new_option" not in stored
    cells_mod.check_same_definition("result.json", now, stored)  # still the same experiment
    other = dataclasses.replace(cell, run=TrainPlus(**fields, new_option=1))
    with pytest.raises(SpecError, match=r"differs in \['new_option'\]"):
        cells_mod.check_same_definition("result.json", other, stored)


def test_a_schema_1_definition_migrates_to_the_current_one(tmp_path):
    from reproduce.spec import SCHEMA_VERSION, canonical, migrate

    cell = load_spec(write_spec(tmp_path)).cell("train-cov")
    old = {  # what a version-1 Cell.definition() wrote for this cell
        "id": "train-cov", "kind": "train", "task": "coverage", "comm": "uc", "comm_radius": 1.0,
        "entity_mode": "emp", "preset": "fast", "ppo": {"num_envs": 4, "num_steps": 8, "minibatches": 1, "epochs": 1},
        "agents": 2, "updates": 3, "sizes": [], "threshold": 0.85, "max_updates_per_stage": 4000, "source": "",
        "source_agents": 0, "eval_every": 2, "eval_episodes": 10, "final_episodes": 12, "eval_seed": 777,
        "checkpoint_every": 1, "compile": False,
    }  # fmt: skip
    assert migrate(old, 1)["schema"] == SCHEMA_VERSION and canonical(old) == cell.definition()
    with pytest.raises(SpecError, match=r"differs in \['ppo.epochs'\]"):
        cells_mod.check_same_definition("result.json", cell, {**old, "ppo": {**old["ppo"], "epochs": 2}})
    with pytest.raises(SpecError, match="schemas 1 to"):
        canonical({**cell.definition(), "schema": SCHEMA_VERSION + 1})
