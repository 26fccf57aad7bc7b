"""Training on the simulator's neighbour lists: the rollout stores them, PPO trains over
them, a run resumes on them; with lists that hold everyone it is the dense run."""

import json
import os

import pytest
import torch

from trainer import checkpoint
from trainer.config import PPOConfig, TrainConfig
from trainer.model import ModelConfig
from trainer.ppo import Rollout
from trainer.train import train

TINY_PPO = PPOConfig(num_envs=4, num_steps=8, epochs=1, minibatches=2)


def tiny(tmp_path, name, **kw):
    base = dict(
        task="coverage",
        agents=4,
        comm="rc",
        comm_radius=0.9,
        updates=2,
        eval_every=100,
        eval_episodes=4,
        checkpoint_every=1,
        run_dir=str(tmp_path / name),
        progress=False,
        torch_threads=1,
        model=ModelConfig(hidden=16, rounds=2),
        ppo=TINY_PPO,
        compile=False,
        transfer_offsets=(),
    )
    return TrainConfig.of(**(base | kw))


def weights(run_dir):
    return checkpoint.load(os.path.join(run_dir, "checkpoint.pt"))["model"]


def test_rollout_takes_the_layout_of_the_observation():
    import taichi_swarm

    env = taichi_swarm.make("coverage", 3, 5, comm="rc", comm_radius=0.8, neighbours=3, seed=0)
    buf = Rollout.for_env(4, env)
    assert buf.adj is None and buf.nbr.shape == (4, 3, 5, 3) and buf.nbr.dtype == torch.int32
    assert buf.input_names() == ("self_obs", "entities", "nbr", "nbr_mask")
    inputs = buf.store(2, env.reset())
    assert torch.equal(buf.nbr[2], env.obs["nbr"]) and torch.equal(inputs["nbr_mask"], env.obs["nbr_mask"])
    dense = Rollout.for_env(4, taichi_swarm.make("coverage", 3, 5, seed=0))
    assert dense.nbr is None and dense.adj.shape == (4, 3, 5, 5)
    assert dense.input_names() == ("self_obs", "entities", "adj")


def test_training_on_full_lists_is_the_dense_run(tmp_path):
    """K = M - 1: every heard agent is listed, so the lists run makes the same episodes and
    the same updates as the dense run (to float rounding)."""
    dense = tiny(tmp_path, "dense")
    lists = tiny(tmp_path, "lists", neighbours=3)
    train(dense)
    train(lists)
    a, b = weights(dense.run_dir), weights(lists.run_dir)
    for k in a:
        torch.testing.assert_close(b[k], a[k], atol=1e-5, rtol=1e-4)
    one = tiny(tmp_path, "one", neighbours=3, updates=1)
    train(one)
    assert not torch.allclose(weights(one.run_dir)["agent_encoder.weight"], b["agent_encoder.weight"])  # it trained


def test_a_run_on_lists_resumes_bit_identically(tmp_path):
    whole = tiny(tmp_path, "whole", neighbours=2, updates=3)
    part = tiny(tmp_path, "part", neighbours=2, updates=2)
    train(whole)
    train(part)
    train(resume=part.run_dir, updates=3)
    a, b = weights(whole.run_dir), weights(part.run_dir)
    for k in a:
        assert torch.equal(a[k], b[k]), k
    saved = checkpoint.load(os.path.join(part.run_dir, "checkpoint.pt"))
    assert saved["train_config"]["neighbours"] == 2


def test_swarm_train_takes_the_list_options(tmp_path):
    from swarm_cli.main import main as swarm_main

    run = str(tmp_path / "cli")
    args = ["train", "--task", "coverage", "--agents", "3", "--comm", "rc", "--neighbours", "2", "--updates", "1"]
    args += ["--ppo.num-envs", "2", "--ppo.num-steps", "4", "--ppo.minibatches", "1", "--eval-every", "100"]
    args += ["--model.hidden", "8", "--run-dir", run, "--no-progress", "--transfer-offsets"]
    assert swarm_main(args) == 0
    assert checkpoint.load(os.path.join(run, "checkpoint.pt"))["train_config"]["neighbours"] == 2
    # the policy records the lists it trained on, and swarm eval runs on them unless told otherwise
    policy = os.path.join(run, "policy.pt")
    assert checkpoint.load(policy)["swarm"] == {"neighbours": 2}
    for extra, K in (([], 2), (["--neighbours", "3"], 3)):
        out = str(tmp_path / f"eval{K}.json")
        assert swarm_main(["eval", policy, "--episodes", "2", "--json", out, *extra]) == 0
        with open(out) as f:
            assert json.load(f)["neighbours"] == K


@pytest.mark.parametrize("bad,match", [(dict(neighbours=0), "neighbours"), (dict(scale="area"), "scale")])
def test_bad_list_options_are_refused(tmp_path, bad, match):
    with pytest.raises(ValueError, match=match):
        tiny(tmp_path, "bad", **bad).validate()


def test_a_run_trains_and_evaluates_on_the_assignment_it_names(tmp_path):
    """--assignment flows from the CLI to the simulator, into the policy's record and back to
    swarm eval (whose --assignment overrides it); "exact", the default, is recorded as unset.
    "free" (nearest.py's searches, each agent paid by its matched or nearest free target) is the
    newest of the local ones."""
    from swarm_cli.main import main as swarm_main

    run = str(tmp_path / "near")
    args = ["train", "--task", "coverage", "--agents", "3", "--comm", "rc", "--neighbours", "2", "--updates", "1"]
    args += ["--assignment", "free", "--ppo.num-envs", "2", "--ppo.num-steps", "4", "--ppo.minibatches", "1"]
    args += ["--eval-every", "100", "--model.hidden", "8", "--run-dir", run, "--no-progress", "--transfer-offsets"]
    assert swarm_main(args) == 0
    policy = os.path.join(run, "policy.pt")
    assert checkpoint.load(policy)["swarm"] == {"neighbours": 2, "assignment": "free"}
    for extra, want in (([], "free"), (["--assignment", "exact"], None)):  # (each another kernel variant)
        out = str(tmp_path / f"eval-{want}.json")
        assert swarm_main(["eval", policy, "--episodes", "2", "--json", out, *extra]) == 0
        with open(out) as f:
            assert json.load(f).get("assignment") == want


@pytest.mark.parametrize(
    "bad,match",
    [
        (dict(assignment="greedy"), "assignment must be one of"),
        (dict(assignment="auction"), "assignment must be one of"),
        (dict(assignment="nearest"), "assignment must be one of"),
        (dict(assignment="free"), "needs neighbours=K"),
    ],
)
def test_bad_assignments_are_refused(tmp_path, bad, match):
    with pytest.raises(ValueError, match=match):
        tiny(tmp_path, "bad", **bad).validate()
