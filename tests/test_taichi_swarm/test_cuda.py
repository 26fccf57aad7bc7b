"""GPU path: run the suite with TAICHI_SWARM_TEST_ARCH=cuda on a machine with CUDA."""

import numpy as np
import pytest
from mpe_reference import mpe_step, mpe_step_continuous

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


def test_cuda_continuous_actions_and_masked_reset():
    """action_space="continuous" and reset_envs on the GPU: torch CUDA tensors straight into the kernels."""
    import torch

    if runtime.current_arch() != "cuda":
        pytest.skip("Taichi runs on the CPU in this session (set TAICHI_SWARM_TEST_ARCH=cuda)")
    env = taichi_swarm.make("coverage", 64, 5, arch="cuda", seed=0, action_space="continuous")
    env.reset()
    state = env.get_state()
    u = torch.rand((64, 5, 2), device="cuda") * 4 - 2
    env.step(u)
    new = env.get_state()
    for b in range(8):
        if env.done[b]:
            continue
        ref_pos, _ = mpe_step_continuous(
            state["pos"][b].cpu().numpy(), state["vel"][b].cpu().numpy(), u[b].cpu().numpy(), 0.05
        )
        np.testing.assert_allclose(new["pos"][b].cpu().numpy(), ref_pos, atol=2e-5)
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.full_like(u, float("nan")))
    mask = torch.zeros(64, dtype=torch.bool, device="cuda")
    mask[::2] = True
    env.reset_envs(mask)
    steps = env.get_state()["step"].cpu()
    assert (steps[::2] == 0).all() and (steps[1::2] == 1).all()


def test_cuda_torchrl_adapter():
    """baselines/torchrl_env.py on the GPU: specs hold and the data stays on the device."""
    if runtime.current_arch() != "cuda":
        pytest.skip("Taichi runs on the CPU in this session (set TAICHI_SWARM_TEST_ARCH=cuda)")
    pytest.importorskip("torchrl")
    from torchrl.envs.utils import check_env_specs

    from baselines.torchrl_env import SwarmTorchRLEnv

    for continuous in (False, True):
        env = SwarmTorchRLEnv("formation", 32, 4, obs_mode="full", continuous_actions=continuous, device="cuda")
        check_env_specs(env, seed=0)
        td = env.rollout(60, break_when_any_done=False)
        assert td["next", "agents", "observation"].device.type == "cuda"
        assert td["next", "done"].sum() >= 32  # every env ended at least once (time limit 50)


def test_cuda_training_end_to_end(tmp_path):
    """--device cuda --arch cuda: Taichi steps on the GPU into torch CUDA tensors, the
    policy and PPO run there (a few updates of a small configuration)."""
    import torch

    if runtime.current_arch() != "cuda" or not torch.cuda.is_available():
        pytest.skip("needs Taichi and torch on CUDA (TAICHI_SWARM_TEST_ARCH=cuda)")
    from trainer.config import PPOConfig, TrainConfig
    from trainer.train import train

    cfg = TrainConfig.of(
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


def test_cuda_neighbour_lists():
    """Lists holding everyone match the dense layout on the GPU; lists at M = 1000 are a
    cKDTree's K nearest."""
    import torch
    from scipy.spatial import cKDTree

    if runtime.current_arch() != "cuda":
        pytest.skip("Taichi runs on the CPU in this session (set TAICHI_SWARM_TEST_ARCH=cuda)")
    B, M = 16, 9
    kw = dict(comm="rc", comm_radius=0.6, arch="cuda", seed=3)
    dense = taichi_swarm.make("coverage", B, M, **kw)
    lists = taichi_swarm.make("coverage", B, M, neighbours=M - 1, **kw)
    dense.reset(), lists.reset()
    for _ in range(60):
        a = torch.randint(0, 5, (B, M), device="cuda")
        od, *_ = dense.step(a)
        ol, *_ = lists.step(a)
        # on the CPU the two layouts are equal bit for bit (test_neighbours.py); on the GPU the
        # compiler contracts multiply-adds differently in each kernel, so the trajectories part
        # by float32 rounding (4e-5 after 60 steps on an H200): positions agree to 1e-3, and
        # each env's lists are checked against its own positions, pairs within 1e-5 of the
        # radius left out
        np.testing.assert_allclose(ol["self"].cpu().numpy(), od["self"].cpu().numpy(), atol=1e-3)
        pos = ol["self"].cpu().numpy()[..., 2:4].astype(np.float64)
        d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
        adj = (d <= kw["comm_radius"]) & ~np.eye(M, dtype=bool)
        clear = np.abs(d - kw["comm_radius"]) > 1e-5
        heard = np.zeros_like(adj)
        nbr, mask = ol["nbr"].cpu().numpy(), ol["nbr_mask"].cpu().numpy()
        b, i, _ = np.nonzero(mask)
        heard[b, i, nbr[mask]] = True
        np.testing.assert_array_equal(heard[clear], adj[clear])
    M, K, r = 1000, 16, 0.5
    env = taichi_swarm.make(
        "coverage", 2, M, comm="rc", comm_radius=r, neighbours=K, scale="density", assignment="free", arch="cuda"
    )
    env.reset(seed=0)
    env.step(torch.randint(0, 5, (2, M), device="cuda"))
    pos = env.get_state()["pos"].cpu().numpy()
    nbr, mask = env.obs["nbr"].cpu().numpy(), env.obs["nbr_mask"].cpu().numpy()
    for b in range(2):
        tree = cKDTree(pos[b].astype(np.float64))
        for i in range(0, M, 37):
            cand = [j for j in tree.query_ball_point(pos[b, i], r * 0.999) if j != i]
            listed = set(nbr[b, i][mask[b, i]].tolist())
            assert len(listed) == min(K, len(cand))
            if len(cand) <= K:
                assert listed == set(cand)
