"""Offline videos: a short GIF rendered from a real rollout and read back."""

import numpy as np
import pytest
from PIL import Image

from taichi_swarm.cli import main as swarm


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
