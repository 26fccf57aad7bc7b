"""Importing the paper authors' published checkpoints (``swarm import``).

A checkpoint in the published layout is built here from one of our networks, so the
conversion is checked anywhere; the real files are checked when
../shared/published-models exists (skipped otherwise; never committed)."""

import os

import pytest
import torch

from swarm_cli.main import main as swarm
from taichi_swarm import Sim
from trainer.checkpoint import CheckpointError, load_policy
from trainer.evaluate import evaluate
from trainer.model import ModelConfig, SwarmPolicy
from trainer.published import convert_state_dict, import_published

PUBLISHED = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "published-models")


def published_layout(policy: SwarmPolicy) -> dict:
    """What marl_transfer's MPNN state dict looks like for these weights."""
    sd = policy.state_dict()
    out = {}
    rename = {
        "agent_encoder": "encoder.0",
        "entity_encoder": "entity_encoder.0",
        "entity_update": "entity_update.0",
        "comm_update": "update.0",
        "policy_head.0": "policy_head.0",
        "policy_head.2": "dist.linear",
        "value_head.0": "value_head.0",
        "value_head.2": "value_head.2",
    }
    for ours, theirs in rename.items():
        for part in ("weight", "bias"):
            if f"{ours}.{part}" in sd:
                out[f"{theirs}.{part}"] = sd[f"{ours}.{part}"].clone()
    for ours, theirs in (("entity_attention", "entity_messages"), ("comm_attention", "messages")):
        for a, b in (("w_q", "W_query"), ("w_k", "W_key"), ("w_v", "W_val"), ("w_out", "W_out")):
            key = f"{ours}.{a}.weight"
            if key in sd:
                out[f"{theirs}.{b}"] = sd[key].t().unsqueeze(0).clone()  # used as x @ W[0]
    return out


@pytest.mark.parametrize("mode,L,task", [("emp", 0, "coverage"), ("concat", 1, "formation"), ("concat", 2, "line")])
def test_conversion_gives_back_the_same_network(tmp_path, mode, L, task):
    torch.manual_seed(0)
    ours = SwarmPolicy(ModelConfig(entity_mode=mode, num_landmarks=L)).eval()
    path = tmp_path / "na4_uc.pt"
    sd = published_layout(ours)
    torch.save({"models": [sd] * 4, "ob_rms": (None, None)}, path)
    payload = import_published(str(path))
    assert payload["task"] == {"task": task, "agents": 4, "comm": "uc", "comm_radius": 1.0}
    config, state = convert_state_dict(sd)
    back = SwarmPolicy(config)
    back.load_state_dict(state)
    Lr = L or 4
    s, e = torch.randn(3, 4, 4), torch.randn(3, 4, Lr, 2)
    adj = torch.ones(3, 4, 4, dtype=torch.bool)
    torch.testing.assert_close(back(s, e, adj)[0], ours(s, e, adj)[0])
    out = tmp_path / "converted.pt"
    assert swarm(["import", str(path), "--out", str(out)]) == 0
    policy, _ = load_policy(str(out))
    torch.testing.assert_close(policy(s, e, adj)[0], ours(s, e, adj)[0])


def test_bad_published_files_are_named(tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    torch.save({"something": 1}, bad)
    with pytest.raises(CheckpointError, match="published format"):
        import_published(str(bad))
    with pytest.raises(CheckpointError, match="does not exist"):
        import_published(str(tmp_path / "missing.pt"))
    sd = published_layout(SwarmPolicy())
    other = {k: v + 1 for k, v in sd.items()}
    torch.save({"models": [sd, other]}, bad)
    with pytest.raises(CheckpointError, match="differ"):
        import_published(str(bad))
    nan = dict(sd)
    nan["update.0.bias"] = torch.full_like(sd["update.0.bias"], float("nan"))
    torch.save({"models": [nan]}, bad)
    with pytest.raises(CheckpointError, match="NaN"):
        import_published(str(bad))
    assert swarm(["import", str(bad), "--out", str(tmp_path / "x.pt")]) == 2
    assert "NaN" in capsys.readouterr().err


needs_published = pytest.mark.skipif(not os.path.isdir(PUBLISHED), reason="../shared/published-models not present")


@needs_published
@pytest.mark.slow
def test_published_coverage_m3_succeeds():
    payload = import_published(os.path.join(PUBLISHED, "ss", "na3_uc.pt"))
    config, state = ModelConfig(**payload["model_config"]), payload["model"]
    policy = SwarmPolicy(config).eval()
    policy.load_state_dict(state)
    result = evaluate(policy, Sim("coverage", 3), episodes=500, seed=777)
    assert result["success_rate"] >= 0.95


@needs_published
@pytest.mark.slow
@pytest.mark.parametrize("M,readme", [(3, 0.940), (4, 0.926), (6, 0.842)])
def test_published_coverage_m5_zero_shot_row(M, readme):
    """Within 4 points of the folder README's zero-shot row (500 episodes each)."""
    payload = import_published(os.path.join(PUBLISHED, "ss", "na5_uc.pt"))
    policy = SwarmPolicy(ModelConfig(**payload["model_config"])).eval()
    policy.load_state_dict(payload["model"])
    result = evaluate(policy, Sim("coverage", M), episodes=500, seed=2024 + M)
    assert abs(result["success_rate"] - readme) <= 0.04
