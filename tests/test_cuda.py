"""GPU path: run the suite with TAICHI_SWARM_TEST_ARCH=cuda on a machine with CUDA."""

import numpy as np
import pytest
from mpe_reference import mpe_step

import taichi_swarm
from taichi_swarm import runtime

pytestmark = pytest.mark.cuda


def test_cuda_env_steps_torch_tensors_on_the_gpu():
    import torch

    if runtime.current_arch() != "cuda":
        pytest.skip("Taichi runs on the CPU in this session (set TAICHI_SWARM_TEST_ARCH=cuda)")
    env = taichi_swarm.make("coverage", 64, 5, arch="cuda", seed=0)
    obs = env.reset()
    assert obs["self"].device.type == "cuda"
    state = env.get_state()
    actions = torch.randint(0, 5, (64, 5), device="cuda")
    env.step(actions)
    new = env.get_state()
    for b in range(8):
        if env.done[b]:
            continue
        ref_pos, ref_vel = mpe_step(
            state["pos"][b].cpu().numpy(), state["vel"][b].cpu().numpy(), actions[b].cpu().numpy(), 0.05
        )
        np.testing.assert_allclose(new["pos"][b].cpu().numpy(), ref_pos, atol=2e-5)


def test_cuda_training_end_to_end(tmp_path):
    """--device cuda --arch cuda: Taichi steps on the GPU into torch CUDA tensors, the
    policy and PPO run there (a few updates of a small configuration)."""
    import torch

    if runtime.current_arch() != "cuda" or not torch.cuda.is_available():
        pytest.skip("needs Taichi and torch on CUDA (TAICHI_SWARM_TEST_ARCH=cuda)")
    from trainer.config import PPOConfig, TrainConfig
    from trainer.train import train

    cfg = TrainConfig(
        agents=3,
        updates=2,
        eval_every=2,
        eval_episodes=16,
        run_dir=str(tmp_path / "run"),
        progress=False,
        device="cuda",
        arch="cuda",
        compile=False,
        ppo=PPOConfig(num_envs=256, num_steps=8, minibatches=2, epochs=1),
    )
    summary = train(cfg)
    assert summary["update"] == 2 and summary["last_eval"]["success_rate"] >= 0
