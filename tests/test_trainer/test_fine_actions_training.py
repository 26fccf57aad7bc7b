"""Training on the fine action set (TrainConfig.action_space = "fine"): the head has 9 logits,
a 5-action policy grows into it greedily unchanged, and the policy carries its action set to
evaluation, export and execution."""

import dataclasses
import json
import os

import pytest
import torch

from taichi_swarm import Sim
from taichi_swarm.sim import ConfigError
from trainer import checkpoint
from trainer.config import PRESETS, TrainConfig
from trainer.evaluate import evaluate
from trainer.model import ModelConfig, SwarmPolicy, policy_inputs
from trainer.train import FINE_START_GAP, build_state, grow_actions, train


def config(tmp_path, name, **kw):
    return TrainConfig.of(
        task="formation",
        agents=3,
        updates=1,
        eval_every=1,
        eval_episodes=2,
        run_dir=str(tmp_path / name),
        progress=False,
        transfer_offsets=(),
        model=ModelConfig(hidden=16, rounds=1),
        ppo=dataclasses.replace(PRESETS["fast"], num_envs=2, num_steps=4, epochs=1, minibatches=1),
        compile=False,
        **kw,
    )


def test_a_five_action_policy_grows_into_the_fine_set_greedily_unchanged():
    from taichi_swarm import make, runtime

    runtime.init("cpu")
    torch.manual_seed(0)
    small = SwarmPolicy(ModelConfig(hidden=16, rounds=1))
    big = SwarmPolicy(ModelConfig(hidden=16, rounds=1, num_actions=9))
    big.load_state_dict(grow_actions(small.state_dict(), 9))
    env = make("formation", 4, 3, seed=1)
    inputs = policy_inputs(env.reset(), "cpu")
    with torch.no_grad():
        a, _ = small(**inputs)
        b, _ = big(**inputs)
    torch.testing.assert_close(b[..., :5], a)
    torch.testing.assert_close(b[..., 5:], a[..., 1:5] - FINE_START_GAP)
    assert torch.equal(b.argmax(-1), a.argmax(-1))
    weights = small.state_dict()
    assert grow_actions(weights, 5) is weights  # nothing to grow: the weights as given


def test_a_fine_run_records_its_action_set_and_everything_downstream_takes_it(tmp_path):
    base = config(tmp_path, "paper")
    train(base)
    cfg = config(tmp_path, "fine", action_space="fine", init_from=os.path.join(base.run_dir, "policy.pt"))
    assert build_state(cfg, None, "cpu").groups[0].env.num_actions == 9
    train(cfg)
    policy, payload = checkpoint.load_policy(os.path.join(cfg.run_dir, "policy.pt"))
    assert policy.config.num_actions == 9 and payload["swarm"] == {"action_space": "fine"}
    assert json.load(open(os.path.join(cfg.run_dir, "config.json")))["action_space"] == "fine"
    assert policy.sim.action_space == "fine"
    result = evaluate(policy, episodes=3)  # its own setting: a 5-action env would refuse 5..8
    assert result["action_space"] == "fine"

    from deploy.executor import ExecuteSettings, ExportedModel, run_episodes
    from deploy.export import export

    out = str(tmp_path / "export")
    export(os.path.join(cfg.run_dir, "policy.pt"), out)
    manifest = json.load(open(os.path.join(out, "manifest.json")))
    assert manifest["num_actions"] == 9 and len(manifest["action_meanings"]) == 9
    assert manifest["contract"]["swarm"] == {"action_space": "fine"}
    model = ExportedModel(out)
    s = ExecuteSettings(Sim("formation", 3, action_space="fine"), episodes=3, seed=4)
    assert 0 <= run_episodes(model, s)["success_rate"] <= 1


def test_fine_runs_refuse_what_they_cannot_take(tmp_path):
    with pytest.raises(ConfigError) as refused:
        evaluate(None, Sim("formation", 3, action_space="continuous"))
    assert refused.value.field == "action_space"
    assert Sim("formation", 3, action_space="discrete").swarm_record() == {}  # the paper's: recorded as unset
    with pytest.raises(ValueError, match="num_actions must be 5 or 9"):
        ModelConfig(num_actions=7)
    with pytest.raises(ValueError, match="model.num_actions follows action_space"):
        TrainConfig.of(model=ModelConfig(num_actions=9)).validate()
    fine = config(tmp_path, "fine", action_space="fine")
    train(fine)
    back = config(tmp_path, "back", init_from=os.path.join(fine.run_dir, "policy.pt"))
    with pytest.raises(checkpoint.CheckpointError, match="this run wants"):
        build_state(back, None, "cpu")
