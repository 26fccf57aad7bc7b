"""The paper authors' published checkpoints (marl_transfer's ``models/naM_uc.pt``)
converted into this project's policy format.

A published file is ``{"models": [state_dict] * M, "ob_rms": (None, None)}``: one
identical state dict per agent. Its attention matrices are used as ``x @ W[0]``
(the transpose of an ``nn.Linear`` weight); everything else maps one to one:

    encoder.0             -> agent_encoder          (input 4: EMP; 4 + 2L: landmark offsets concatenated)
    entity_encoder.0      -> entity_encoder         (EMP only)
    entity_messages.W_*   -> entity_attention.w_*   (EMP only; transposed)
    entity_update.0       -> entity_update          (EMP only)
    messages.W_*          -> comm_attention.w_*     (transposed)
    update.0              -> comm_update
    policy_head.0, dist.linear  -> policy_head.0, policy_head.2
    value_head.0, value_head.2  -> value_head.0, value_head.2

The published input width tells the entity handling: 4 is EMP (coverage), 6 and 8
are one and two landmark offsets concatenated (formation, line).
"""

from __future__ import annotations

import os

import torch

from taichi_swarm import Sim
from taichi_swarm.files import MAX_CHECKPOINT_BYTES, InputFileError, check_input
from trainer.checkpoint import CheckpointError, save
from trainer.model import SELF_DIM, ModelConfig, SwarmPolicy

TASK_BY_INPUT = {SELF_DIM: "coverage", SELF_DIM + 2: "formation", SELF_DIM + 4: "line"}
_ATTENTION = {"W_query": "w_q", "W_key": "w_k", "W_val": "w_v", "W_out": "w_out"}
_LINEAR = {
    "encoder.0": "agent_encoder",
    "entity_encoder.0": "entity_encoder",
    "entity_update.0": "entity_update",
    "update.0": "comm_update",
    "policy_head.0": "policy_head.0",
    "dist.linear": "policy_head.2",
    "value_head.0": "value_head.0",
    "value_head.2": "value_head.2",
}


def _read(path: str) -> list[dict]:
    try:  # a regular file of bounded size (a FIFO would block torch.load)
        check_input(path, "published checkpoint", MAX_CHECKPOINT_BYTES)
    except InputFileError as exc:
        raise CheckpointError(str(exc)) from None
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupted, truncated or not a torch file
        raise CheckpointError(f"cannot read {path} as a published checkpoint ({type(exc).__name__})") from None
    models = raw.get("models") if isinstance(raw, dict) else None
    if not isinstance(models, (list, tuple)) or not models or not all(isinstance(m, dict) for m in models):
        raise CheckpointError(f"{path} is not in the published format (a dict with a list 'models' of state dicts)")
    ob_rms = raw.get("ob_rms", (None, None))
    if ob_rms not in (None, (None, None), [None, None]):
        raise CheckpointError(f"{path} uses observation normalisation (ob_rms), which this network does not have")
    for i, m in enumerate(models):
        bad = sorted(str(k) for k, v in m.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor))
        if bad:
            raise CheckpointError(f"{path}: agent {i}'s state dict holds non-tensor entries {bad[:4]}")
    first = models[0]
    for i, other in enumerate(models[1:], start=1):
        if other.keys() != first.keys() or any(not torch.equal(other[k], first[k]) for k in first):
            raise CheckpointError(f"{path}: agent {i}'s weights differ from agent 0's; only shared weights convert")
    return list(models)


def convert_state_dict(published: dict) -> tuple[ModelConfig, dict]:
    """One published state dict -> (ModelConfig, this project's state dict)."""
    if "encoder.0.weight" not in published:
        raise CheckpointError("not a published policy: no 'encoder.0.weight'")
    hidden, width = published["encoder.0.weight"].shape
    emp = "entity_encoder.0.weight" in published
    if emp:
        config = ModelConfig(hidden=hidden, rounds=3, entity_mode="emp")
    else:
        if width <= SELF_DIM or (width - SELF_DIM) % 2:
            raise CheckpointError(f"published agent encoder takes {width} inputs: expected 4 + 2 * landmarks")
        config = ModelConfig(hidden=hidden, rounds=3, entity_mode="concat", num_landmarks=(width - SELF_DIM) // 2)
    out: dict[str, torch.Tensor] = {}
    used: set[str] = set()
    for src, dst in _LINEAR.items():
        for part in ("weight", "bias"):
            key = f"{src}.{part}"
            if key in published:
                out[f"{dst}.{part}"] = published[key].float().clone()
                used.add(key)
    for block, dst in (("entity_messages", "entity_attention"), ("messages", "comm_attention")):
        for src, name in _ATTENTION.items():
            key = f"{block}.{src}"
            if key in published:
                w = published[key]
                if w.dim() != 3 or w.shape[0] != 1:
                    raise CheckpointError(f"{key} has shape {tuple(w.shape)}, expected (1, H, H)")
                out[f"{dst}.{name}.weight"] = w[0].t().float().contiguous()
                used.add(key)
    unknown = sorted(set(published) - used)
    if unknown:
        raise CheckpointError(f"published state dict has keys this converter does not know: {unknown[:4]}")
    policy = SwarmPolicy(config)
    own = policy.state_dict()
    missing = sorted(set(own) - set(out))
    wrong = sorted(k for k in out if k in own and own[k].shape != out[k].shape)
    if missing or wrong:
        raise CheckpointError(f"published weights do not fit the network: missing {missing[:4]}, shape {wrong[:4]}")
    for name, tensor in out.items():
        if not torch.isfinite(tensor).all():
            raise CheckpointError(f"published weight {name} holds NaN or inf")
    return config, out


def import_published(path: str, task: str | None = None, comm: str = "uc", comm_radius: float = 1.0) -> dict:
    """A policy payload (as ``checkpoint.save_policy_only`` writes) from a published file."""
    models = _read(path)
    config, state = convert_state_dict(models[0])
    guessed = TASK_BY_INPUT.get(SELF_DIM + 2 * config.num_landmarks if config.entity_mode == "concat" else SELF_DIM)
    task = task or guessed
    if task is None:
        raise CheckpointError(f"cannot tell the task of {path} from its input width: pass --task")
    return {
        "model_config": config.to_dict(),
        "model": state,
        "task": Sim(task, len(models), comm, comm_radius).task_record(),
        "counters": {"update": 0, "env_steps": 0, "wall_time": 0.0},
        "evals": [],
        "source": {"published": os.path.abspath(path)},
    }


def import_to(path: str, out: str, **kwargs) -> dict:
    """Convert ``path`` and write it atomically to ``out`` (a policy.pt file)."""
    payload = import_published(path, **kwargs)
    save(out, payload)
    return payload


__all__ = ["convert_state_dict", "import_published", "import_to"]
