"""Offline videos: a short GIF rendered from a real rollout and read back."""

import numpy as np
import pytest
from PIL import Image

from swarm_cli.main import main as swarm


def test_eval_renders_a_gif_that_reads_back(tmp_path, capsys):
    import torch

    from trainer.checkpoint import save
    from trainer.model import ModelConfig, SwarmPolicy

    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=16, rounds=1))
    ckpt = tmp_path / "p.pt"
    save(
        str(ckpt),
        {
            "model_config": policy.config.to_dict(),
            "model": policy.state_dict(),
            "task": {"task": "coverage", "agents": 3, "comm": "rc", "comm_radius": 1.0},
        },
    )
    gif = tmp_path / "out.gif"
    assert swarm(["eval", str(ckpt), "--episodes", "3", "--video", str(gif), "--record-envs", "2"]) == 0
    im = Image.open(gif)
    assert im.n_frames == 51  # 50 steps (an untrained policy never succeeds) + the outcome frame
    assert im.size[0] > 200 and im.size[1] > 100
    im.seek(1)
    pixels = np.asarray(im.convert("RGB"))
    assert pixels.std() > 5  # not blank
    assert (np.abs(pixels.astype(int) - [31, 119, 180]).sum(-1) < 60).any()  # agent 0 is drawn (tab:blue)
    assert "video:" in capsys.readouterr().out


def test_bad_video_paths_are_refused_before_the_work(tmp_path, capsys):
    from deploy.video import check_video_path

    with pytest.raises(ValueError, match=".gif or .mp4"):
        check_video_path(str(tmp_path / "x.avi"))
    assert swarm(["eval", str(tmp_path / "none.pt"), "--video", str(tmp_path / "x.avi")]) == 2


def test_record_and_video_come_from_one_trajectory_record(tmp_path, capsys):
    """--record FILE.npz and --video of one evaluation are rendered from the same record;
    `swarm replay FILE.npz --video` renders the same frames again from the file (the record
    copies the env's buffers: a view would be overwritten by the next step)."""
    import torch

    from deploy.trajectory import Trajectory, TrajectoryRecorder
    from deploy.video import frames
    from taichi_swarm import Sim
    from trainer.evaluate import evaluate
    from trainer.model import ModelConfig, SwarmPolicy

    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=16, rounds=1)).eval()
    rec = TrajectoryRecorder("coverage", 5, 3, 3)
    evaluate(policy, Sim("coverage", 3), episodes=5, seed=3, recorder=rec)
    live = rec.trajectory()
    path, gif = str(tmp_path / "r.npz"), str(tmp_path / "r.gif")
    live.save(path)
    back = Trajectory.load(path)
    got, want = frames(back), frames(live)
    assert len(got) == len(want) == live.num_steps + 1  # every step, and the last one with the outcomes
    for g, w in zip(got, want, strict=True):
        assert g["step"] == w["step"]
        for key in ("pos", "targets", "adj", "live"):
            np.testing.assert_array_equal(g[key], w[key])
    assert not np.array_equal(got[0]["pos"], got[5]["pos"])  # the agents moved: no aliased buffers
    assert swarm(["replay", path, "--video", gif]) == 0
    assert Image.open(gif).n_frames == len(got)


def test_mp4_when_an_ffmpeg_is_available(tmp_path):
    from deploy.video import ffmpeg_path, render

    if ffmpeg_path() is None:
        pytest.skip("no ffmpeg (pip install -e '.[video]')")
    frames = [
        {
            "step": k,
            "pos": np.full((1, 2, 2), 0.1 * k, np.float32),
            "landmarks": np.zeros((1, 2, 2), np.float32),
            "targets": np.zeros((1, 2, 2), np.float32),
            "adj": np.ones((1, 2, 2), bool),
            "assignment": None,
            "live": np.ones(1, bool),
        }
        for k in range(5)
    ]
    out = render(frames, str(tmp_path / "v.mp4"), "coverage", 2)
    assert open(out, "rb").read(12)[4:8] == b"ftyp"  # an MP4 container


def test_targets_reached_counts_a_target_with_an_agent_strictly_within_the_threshold():
    from deploy.video import _success_threshold, targets_reached

    targets = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], np.float32)
    pos = np.array([[0.05, 0.0], [1.1, 0.0], [0.0, 0.02]], np.float32)  # two on the first, one 0.1 off the second
    assert targets_reached(targets, pos, 0.1).tolist() == [True, False, False]
    assert targets_reached(targets, pos[:0], 0.1).tolist() == [False, False, False]
    assert _success_threshold("coverage") == pytest.approx(0.1)
    assert _success_threshold("no-such-task") is None
