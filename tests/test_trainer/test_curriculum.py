"""The curriculum's polish: each stage trained on at a low constant learning rate, the
next stage started from the polished weights."""

import dataclasses
import json
import os

import pytest


def tiny_config(tmp_path, monkeypatch):
    import trainer.train as train_mod
    from trainer.config import PRESETS, ModelConfig, TrainConfig

    def perfect(policy, cfg, update, device):
        return {"success_rate": 1.0, "mean_length": 5.0, "dist": 0.0, "update": update}

    monkeypatch.setattr(train_mod, "evaluate_during_training", perfect)
    ppo = dataclasses.replace(PRESETS["fast"], num_envs=4, num_steps=8, minibatches=1, epochs=1)
    return TrainConfig.of(
        agents=2, updates=4, eval_every=2, run_dir=str(tmp_path / "cur"), compile=False, progress=False,
        transfer_offsets=(), ppo=ppo, model=ModelConfig(hidden=16, rounds=1),
    )  # fmt: skip


def curriculum(base, sizes, threshold, max_updates_per_stage, run_dir, **options):
    from trainer.config import CurriculumConfig

    return CurriculumConfig.over(
        base, run_dir=run_dir, sizes=tuple(sizes), threshold=threshold, max_updates_per_stage=max_updates_per_stage,
        **options,
    )  # fmt: skip


def read_config(path):
    with open(os.path.join(path, "config.json")) as f:
        return json.load(f)


def test_polish_trains_each_stage_on_and_the_next_stage_starts_from_it(tmp_path, monkeypatch):
    from trainer.curriculum import format_stages, run_curriculum

    cfg = tiny_config(tmp_path, monkeypatch)
    run_dir = str(tmp_path / "cur")
    cur = curriculum(cfg, [2, 3], 0.5, 4, run_dir, fresh_eval_episodes=3, polish_updates=4, polish_lr=1e-5)
    stages = run_curriculum(cur)
    assert [s["updates"] for s in stages] == [2, 2]  # each stage stopped at its first evaluation
    assert [s["polish"]["updates"] for s in stages] == [4, 4]  # the polish has no target: evaluations at 2 and 4
    polish = read_config(os.path.join(run_dir, "stage-m2-polish"))
    assert polish["ppo"]["lr"] == 1e-5 and polish["ppo"]["lr_end"] is None
    assert polish["target_success"] == 0.0
    assert polish["init_from"] == os.path.join(run_dir, "stage-m2", "checkpoint.pt")
    assert read_config(os.path.join(run_dir, "stage-m3"))["init_from"] == os.path.join(
        run_dir, "stage-m2-polish", "checkpoint.pt"
    )
    fresh = stages[1]["polish"]["fresh_eval"]  # the polished policy on fresh episodes
    assert (fresh["agents"], fresh["episodes"], fresh["update"]) == (3, 3, 4)
    with open(os.path.join(run_dir, "curriculum.json")) as f:
        assert json.load(f)["stages"][0]["polish"]["run_dir"] == os.path.join(run_dir, "stage-m2-polish")
    table = format_stages(stages)
    assert "polished S%" in table and "+N" in table

    summary = os.path.join(run_dir, "stage-m3-polish", "summary.json")
    before = os.stat(summary).st_mtime_ns
    again = run_curriculum(cur)  # resumed: all done
    assert os.stat(summary).st_mtime_ns == before
    assert [s["polish"]["fresh_eval"] for s in again] == [s["polish"]["fresh_eval"] for s in stages]
    # a polish of the stage as it ended before (a stage trained on since) is never reused
    marker = os.path.join(run_dir, "stage-m2-polish", "polish-of.json")
    with open(marker) as f:
        assert json.load(f)["stage_update"] == 2
    with open(marker, "w") as f:
        json.dump({"stage": os.path.join(run_dir, "stage-m2"), "stage_update": 1}, f)
    with pytest.raises(ValueError, match="as it was at update 1; it now ends at update 2: move .* away"):
        run_curriculum(cur)


def test_without_polish_the_table_has_no_polish_columns(tmp_path, monkeypatch):
    from trainer.curriculum import format_stages, run_curriculum

    stages = run_curriculum(curriculum(tiny_config(tmp_path, monkeypatch), [2], 0.5, 4, str(tmp_path / "cur")))
    assert "polish" not in stages[0] and "polished" not in format_stages(stages)
    assert not os.path.exists(tmp_path / "cur" / "stage-m2-polish")


@pytest.mark.parametrize(
    "kwargs, message", [({"polish_updates": -1}, "--polish-updates"), ({"polish_lr": 0.0}, "--polish-lr")]
)
def test_bad_polish_options_are_named(tmp_path, monkeypatch, kwargs, message):
    from trainer.curriculum import run_curriculum

    with pytest.raises(ValueError, match=message):
        run_curriculum(curriculum(tiny_config(tmp_path, monkeypatch), [2], 0.5, 4, str(tmp_path / "cur"), **kwargs))


def test_a_curriculum_refuses_several_team_sizes_at_once(tmp_path, monkeypatch):
    """Every stage would train on --team-sizes and be judged at its own size: refused, named."""
    import dataclasses

    from trainer.curriculum import run_curriculum

    cfg = dataclasses.replace(tiny_config(tmp_path, monkeypatch), team_sizes=(2, 3))
    with pytest.raises(ValueError, match=r"--team-sizes \[2, 3\] cannot go with a curriculum"):
        run_curriculum(curriculum(cfg, [2, 3], 0.5, 4, str(tmp_path / "cur")))
    assert not os.path.exists(tmp_path / "cur")  # refused before anything was written


def test_a_stage_trained_from_an_earlier_state_of_the_stage_before_is_refused(tmp_path, monkeypatch):
    """The same command with a larger --max-updates-per-stage continues a stage that ran out
    below the threshold; the stages after it had started from its old weights and must not
    be read back as if they came from the new ones."""
    from trainer.curriculum import STARTED_FROM, run_curriculum

    cfg = tiny_config(tmp_path, monkeypatch)
    run_dir = str(tmp_path / "cur")
    run_curriculum(curriculum(cfg, [2, 3], 0.5, 4, run_dir))
    marker = os.path.join(run_dir, "stage-m3", STARTED_FROM)
    with open(marker) as f:
        assert json.load(f) == {"run": os.path.join(run_dir, "stage-m2"), "update": 2}
    assert not os.path.exists(os.path.join(run_dir, "stage-m2", STARTED_FROM))  # the first stage: --init-from
    run_curriculum(curriculum(cfg, [2, 3], 0.5, 4, run_dir))  # unchanged: read back
    with open(marker, "w") as f:
        json.dump({"run": os.path.join(run_dir, "stage-m2"), "update": 1}, f)  # as if stage M = 2 had grown since
    with pytest.raises(ValueError, match=r"stage-m3 started from .*stage-m2 as it was at update 1; it now ends at"):
        run_curriculum(curriculum(cfg, [2, 3], 0.5, 4, run_dir))
