"""One real learning check: a tiny configuration must improve within a bounded
number of updates (it fails if PPO, GAE, the network or the env are broken)."""

import pytest
import torch

from trainer.config import PPOConfig, TrainConfig
from trainer.model import ModelConfig
from trainer.train import train


@pytest.mark.slow  # 40 PPO updates and 200 evaluation episodes: a learning test
def test_single_agent_coverage_learns(tmp_path):
    cfg = TrainConfig.of(
        task="coverage",
        agents=1,
        updates=40,
        eval_every=40,
        eval_episodes=200,
        seed=1,
        run_dir=str(tmp_path / "run"),
        progress=False,
        torch_threads=1,
        checkpoint_every=40,
        compile=False,
        model=ModelConfig(hidden=32, rounds=1),
        ppo=PPOConfig(num_envs=32, num_steps=32, lr=3e-3, epochs=4, minibatches=2),
    )
    rewards = []
    summary = train(cfg, on_update=lambda r: rewards.append(r["reward"]))
    first, last = sum(rewards[:5]) / 5, sum(rewards[-5:]) / 5
    # random walk: ~0% success within 50 steps and mean distance ~0.8
    assert last > first + 0.2, f"reward did not improve: {first:.3f} -> {last:.3f}"
    assert summary["last_eval"]["success_rate"] >= 0.5, summary["last_eval"]
    assert torch.isfinite(torch.tensor(rewards)).all()
