"""The trajectory record (TrajectoryRecorder on numpy and torch envs, saved and loaded) and
the Rerun recordings rendered from it, read back with RrdReader, `rerun rrd verify`, and
`swarm replay`."""

from __future__ import annotations

import os
import subprocess

import numpy as np
import pytest
import torch

import taichi_swarm
from deploy.recording import write_rrd
from deploy.replay import rerun_command, summarize
from deploy.trajectory import Trajectory, TrajectoryError, TrajectoryRecorder
from swarm_cli.deploy import replay_main
from trainer import checkpoint
from trainer.model import ModelConfig, SwarmPolicy


def _record_numpy(path: str, B: int = 3, M: int = 3, steps: int = 5, drawn: int = 2) -> Trajectory:
    """A rollout recorded once; ``path`` (.npz: the record, .rrd: Rerun) rendered from it."""
    env = taichi_swarm.make("coverage", B, M, comm="rc", seed=0, array="numpy")
    env.reset()
    rec = TrajectoryRecorder("coverage", B, M, drawn, comm="rc", comm_radius=1.0)
    rng = np.random.default_rng(0)
    for t in range(steps):
        actions = rng.integers(0, 5, size=(B, M), dtype=np.int64)
        attention = np.full((B, M, M), 1.0 / M, np.float32)
        rec.log_step(t, env, actions, attention=attention)
        env.step(actions)
    ended = np.array([True, False, False])
    rec.log_episode_ends(
        steps,
        ended,
        {"success": np.array([True, False, False]), "length": np.full(B, steps), "dist": np.full(B, 0.5, np.float32)},
    )
    traj = rec.trajectory()
    traj.save(path) if path.endswith(".npz") else write_rrd(traj, path)
    return traj


def test_trajectory_record_round_trips(tmp_path):
    """Saved atomically (nothing but the record left), loaded to the same arrays; the graph and
    attention come back dense as they were logged."""
    path = str(tmp_path / "t.npz")
    traj = _record_numpy(path, B=3, M=4, steps=4)
    assert os.listdir(tmp_path) == ["t.npz"]
    back = Trajectory.load(path)
    assert back.header == traj.header and back.header["task"] == "coverage" and back.header["schema"] == 1
    assert set(back.arrays) == set(traj.arrays)
    for k, v in traj.arrays.items():
        np.testing.assert_array_equal(back.arrays[k], v, err_msg=k)
    assert back.arrays["pos"].shape == (4, 2, 4, 2) and back.arrays["reward"].shape == (4, 3)  # drawn 2 of B 3
    np.testing.assert_allclose(back.attention(0), np.full((2, 4, 4), 0.25))
    assert back.adj(0).dtype == bool and back.adj(0)[:, range(4), range(4)].all()
    assert back.outcomes() == {0: "success at step 4"}  # env 1 did not end
    assert back.live(3).tolist() == [True, True]


def test_bad_trajectory_records_are_refused_in_one_line(tmp_path, capsys):
    good = str(tmp_path / "t.npz")
    _record_numpy(good, steps=2)
    other = str(tmp_path / "other.npz")
    np.savez(other, x=np.zeros(3))
    with pytest.raises(TrajectoryError, match="not a taichi-swarm trajectory record"):
        Trajectory.load(other)
    z = dict(np.load(good))
    header = str(z.pop("header")).replace('"schema": 1', '"schema": 99')
    newer = str(tmp_path / "newer.npz")
    np.savez(newer, header=np.array(header), **z)
    with pytest.raises(TrajectoryError, match="schema 99"):
        Trajectory.load(newer)
    z = dict(np.load(good))
    del z["pos"]
    cut = str(tmp_path / "cut.npz")
    np.savez(cut, **z)
    with pytest.raises(TrajectoryError, match="lacks pos"):
        Trajectory.load(cut)
    broken = tmp_path / "broken.npz"
    broken.write_bytes(open(good, "rb").read()[:200])  # starts like a zip, is cut short
    for path in (other, newer, cut, str(broken)):
        assert replay_main([path, "--stats"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "swarm replay: error:" in err and "Traceback" not in err, err


def test_replay_renders_a_trajectory_record(tmp_path, capsys):
    path = str(tmp_path / "t.npz")
    _record_numpy(path, steps=3)
    rrd = str(tmp_path / "t.rrd")
    assert replay_main([path, "--stats", "--rrd", rrd]) == 0
    out = capsys.readouterr().out
    assert "trajectory record (schema 1), coverage, M=3" in out and "env 0: success at step 3" in out
    assert summarize(rrd)["entities"]["/env_0/agents"]["steps"] == (0, 2)
    assert replay_main([rrd, "--video", str(tmp_path / "x.gif")]) == 2  # nothing is parsed back from a .rrd
    assert "record one with --record FILE.npz" in capsys.readouterr().err and not (tmp_path / "x.gif").exists()


def test_recording_has_entities_and_steps(tmp_path):
    path = str(tmp_path / "rollout.rrd")
    _record_numpy(path)
    summary = summarize(path)
    ents = summary["entities"]
    for b in (0, 1):
        for name in ("agents", "landmarks", "targets", "comm", "attention", "reward"):
            assert ents[f"/env_{b}/{name}"]["steps"][0] == 0, name
        assert ents[f"/env_{b}/arena"]["static"]
    assert ents["/env_0/agents"]["steps"] == (0, 4)  # steps 0..4 drawn; the last state stays (no Clear)
    assert ents["/env_0/episode/success"]["steps"] == (5, 5)
    assert "/env_1/episode/success" not in ents  # env 1 did not end
    assert not any(name.startswith("/env_2") for name in ents)  # max_envs_drawn = 2
    assert ents["/all/reward_mean"]["rows"] == 5 and "/all/success_rate" in ents
    assert summary["steps"] == (0, 5)


def test_rrd_verify(tmp_path):
    path = str(tmp_path / "rollout.rrd")
    _record_numpy(path, steps=2)
    try:
        proc = subprocess.run(rerun_command() + ["rrd", "verify", path], capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"rerun binary not usable here: {exc}")
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_eval_record_with_torch_env(tmp_path, capsys):
    """`swarm eval --record` (torch env, torch actions) uses the same recorder interface."""
    from swarm_cli.train import eval_main

    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=32, rounds=1))
    ckpt = str(tmp_path / "ckpt.pt")
    checkpoint.save(
        ckpt,
        {
            "model_config": policy.config.to_dict(),
            "model": policy.state_dict(),
            "task": {"task": "coverage", "agents": 3, "comm": "uc", "comm_radius": 1.0},
        },
    )
    rrd = str(tmp_path / "eval.rrd")
    assert eval_main([ckpt, "--episodes", "2", "--record", rrd]) == 0
    ents = summarize(rrd)["entities"]
    assert "/env_1/agents" in ents and "/env_0/episode/length" in ents


def test_replay_stats_and_no_display(tmp_path, capsys, monkeypatch):
    path = str(tmp_path / "rollout.rrd")
    _record_numpy(path, steps=2)
    assert replay_main([path, "--stats"]) == 0
    out = capsys.readouterr().out
    assert "/env_0/agents" in out and "entity paths" in out
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert replay_main([path]) == 2
    assert "--serve-web" in capsys.readouterr().err
    assert replay_main([str(tmp_path / "missing.rrd"), "--stats"]) == 2
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not an rrd")
    assert replay_main([str(bad), "--stats"]) == 2
    assert "swarm replay: error:" in capsys.readouterr().err
    assert os.path.exists(path)


def test_recordings_carry_a_grid_layout_one_view_per_environment(tmp_path):
    import subprocess

    from deploy.recording import layout
    from deploy.replay import rerun_command

    grid, plots = layout(5).root_container.contents
    assert [v.origin for v in grid.contents] == [f"env_{b}" for b in range(5)]  # never overlaid
    assert type(plots).__name__ == "TimeSeriesView"
    env = taichi_swarm.make("coverage", 3, 3, array="numpy", seed=0)
    env.reset()
    path = str(tmp_path / "r.rrd")
    rec = TrajectoryRecorder("coverage", 3, 3, 2)
    rec.log_step(0, env, np.zeros((3, 3), dtype=np.int64))
    write_rrd(rec.trajectory(), path)
    printed = subprocess.run(rerun_command() + ["rrd", "print", path], capture_output=True, text=True).stdout
    assert printed.count("ViewBlueprint:space_origin") >= 3  # 2 environment views and the plot


def test_replay_names_directories_and_non_recordings(tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    assert replay_main([str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert replay_main([str(text)]) == 2
    assert "neither a trajectory record (.npz) nor a Rerun recording" in capsys.readouterr().err
    garbage = tmp_path / "garbage.rrd"  # starts like a recording, is not one
    garbage.write_bytes(b"RRF2" + bytes(range(256)) * 4)
    assert replay_main([str(garbage), "--stats"]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_the_record_keeps_where_each_finished_env_ended(tmp_path):
    """An env restarts inside the step that ends it, so the last logged state is the one its
    agents acted on; the record keeps where they stood at the end (the terminal observation),
    the video's outcome frame draws that, and a record without it still renders as before."""
    from deploy.video import frames
    from taichi_swarm.metrics import run_first_episodes

    B, M = 3, 3
    env = taichi_swarm.make("coverage", B, M, comm="rc", seed=0, array="numpy", max_steps=6)
    rec = TrajectoryRecorder("coverage", B, M, 2, comm="rc", comm_radius=1.0)
    rng = np.random.default_rng(0)
    seen = {}

    def on_done(done):
        seen["end"] = env.info["terminal_obs"]["self"][..., 2:4].copy()

    run_first_episodes(env, lambda obs: (rng.integers(0, 5, size=(B, M)), None), recorder=rec, on_done=on_done)
    traj = rec.trajectory()
    assert (traj.arrays["end_step"] == 6).all()
    np.testing.assert_array_equal(traj.arrays["end_pos"], seen["end"][:2])
    last = frames(traj)[-1]
    np.testing.assert_array_equal(last["pos"], seen["end"][:2])
    assert not np.allclose(last["pos"], traj.arrays["pos"][-1])  # one step later than the last logged state
    path = str(tmp_path / "t.npz")
    traj.save(path)
    np.testing.assert_array_equal(Trajectory.load(path).arrays["end_pos"], seen["end"][:2])
    older = Trajectory(traj.header, {k: v for k, v in traj.arrays.items() if k != "end_pos"})
    np.testing.assert_array_equal(frames(older)[-1]["pos"], traj.arrays["pos"][-1])
    rrd = str(tmp_path / "t.rrd")
    write_rrd(traj, rrd)  # the agents logged once more, at the end step: the last logged state is step 5
    assert summarize(rrd)["entities"]["/env_0/agents"]["steps"] == (0, 6)
    write_rrd(older, rrd)
    assert summarize(rrd)["entities"]["/env_0/agents"]["steps"] == (0, 5)


# ------------------------------------------------------------------------------ crafted records
def _header(key, value):
    def edit(h, a):
        h[key] = value

    return edit


def _array(name, change):
    def edit(h, a):
        a[name] = change(a[name].copy())

    return edit


def _set(index, value):
    def change(x):
        x[index] = value
        return x

    return change


CRAFTED = {
    # header
    "drawn > envs": (_header("drawn", 5), "drawn"),
    "drawn 0": (_header("drawn", 0), "drawn"),
    "agents float": (_header("agents", 3.0), "agents"),
    "task soccer": (_header("task", "soccer"), "task"),
    "comm": (_header("comm", "telepathy"), "comm"),
    "comm_radius NaN": (_header("comm_radius", float("nan")), "comm_radius"),
    "steps": (_header("steps", 99), "steps"),
    # per-step arrays
    "pos NaN": (_array("pos", _set((0, 0, 0, 0), np.nan)), "pos"),
    "vel inf": (_array("vel", _set((1, 0, 0, 1), np.inf)), "vel"),
    "reward NaN": (_array("reward", _set((0, 0), np.nan)), "reward"),
    "landmarks shape": (_array("landmarks", lambda x: x[:, :, :1]), "landmarks"),
    "landmarks NaN": (_array("landmarks", _set((0, 0, 0, 0), np.nan)), "landmarks"),
    "targets shape": (_array("targets", lambda x: x[:, :, :, :1]), "targets"),
    "actions 100": (_array("actions", _set((0, 0, 0), 100)), "actions"),
    "actions -1": (_array("actions", _set((0, 0, 0), -1)), "actions"),
    "actions float": (_array("actions", lambda x: x.astype(np.float32)), "actions"),
    "arena 0": (_array("arena", _set(0, 0.0)), "arena"),
    "step decreasing": (_array("step", _set(1, 0)), "step"),
    "assignment": (_array("assignment", _set((0, 0, 0), 7)), "assignment"),
    # the sparse graph and attention
    "graph offsets decreasing": (_array("graph_offsets", _set(1, 100)), "graph_offsets"),
    "graph offsets short": (_array("graph_offsets", lambda x: x[:-1]), "graph_offsets"),
    "graph env index": (_array("graph_index", _set((0, 0), 2)), "graph_index"),
    "graph agent index": (_array("graph_index", _set((0, 2), 3)), "graph_index"),
    "graph index negative": (_array("graph_index", _set((0, 1), -4)), "graph_index"),
    "attention index": (_array("attention_index", _set((0, 1), 9)), "attention_index"),
    "attention weights": (_array("attention_weights", _set(0, 5.0)), "attention_weights"),
    # outcomes
    "end_step past the record": (_array("end_step", _set(0, 50)), "end_step"),
    "end_step 0": (_array("end_step", _set(0, 0)), "end_step"),
    "length negative": (_array("length", _set(0, -3)), "length"),
    "success shape": (_array("success", lambda x: x[:2]), "success"),
    "end_pos partly NaN": (_array("end_pos", _set((0, 0, 0), np.nan)), "end_pos"),
}


@pytest.fixture(scope="module")
def good_record(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("good") / "t.npz")
    traj = _record_numpy(path, steps=3)
    # (the record's env 0 ended: its end_pos is known for every agent)
    traj.arrays["end_pos"][0] = 0.0
    traj.arrays["assignment"] = np.zeros((3, 2, 3), np.int32)
    traj.save(path)
    Trajectory.load(path)  # the unedited record is valid
    return path


@pytest.mark.parametrize("what", list(CRAFTED))
def test_a_crafted_record_is_refused_in_one_line_naming_the_field(good_record, tmp_path, capsys, what):
    import json

    edit, field = CRAFTED[what]
    z = dict(np.load(good_record))
    header = json.loads(str(z.pop("header")))
    edit(header, z)
    path = str(tmp_path / "crafted.npz")
    np.savez(path, header=np.array(json.dumps(header)), **z)
    with pytest.raises(TrajectoryError, match=field):
        Trajectory.load(path)
    rrd, gif = str(tmp_path / "out.rrd"), str(tmp_path / "out.gif")
    assert replay_main([path, "--stats", "--rrd", rrd, "--video", gif]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and field in err and "Traceback" not in err, err
    assert sorted(os.listdir(tmp_path)) == ["crafted.npz"]  # no recording, video or temp file


def test_a_failed_rrd_leaves_no_temp_file(good_record, tmp_path, capsys, monkeypatch):
    import deploy.recording

    def fail(*args):
        raise IndexError("drawing failed")

    monkeypatch.setattr(deploy.recording, "_log", fail)
    rrd = tmp_path / "out.rrd"
    with pytest.raises(IndexError):
        write_rrd(Trajectory.load(good_record), str(rrd))
    assert os.listdir(tmp_path) == []
    monkeypatch.setattr(deploy.recording, "_log", lambda *args: (_ for _ in ()).throw(OSError("disk full")))
    assert replay_main([good_record, "--rrd", str(rrd)]) == 2
    assert "disk full" in capsys.readouterr().err and os.listdir(tmp_path) == []
