"""Checkpoints: written atomically, loaded with ``weights_only=True``, checked
before use so a wrong file gives a clear error instead of a torch traceback."""

from __future__ import annotations

import hashlib
import io
import os

import torch

from taichi_swarm.files import atomic_write_bytes, atomic_write_json, clean_leftovers, ensure_writable  # noqa: F401
from trainer.model import ModelConfig, SwarmPolicy

FORMAT = "taichi-swarm-checkpoint"
VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint file is missing, unreadable or does not fit."""


def weights_digest(state_dict: dict) -> str:
    """sha256 over the names, dtypes, shapes and bytes of every tensor of a state dict."""
    h = hashlib.sha256()
    for name in sorted(state_dict):
        t = state_dict[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def save(path: str, payload: dict) -> None:
    """Save ``payload`` (must hold "model_config" and "model") atomically, with the
    digest of its weights (checked by ``load``)."""
    payload = {"format": FORMAT, "version": VERSION, **payload, "model_sha256": weights_digest(payload["model"])}
    data = io.BytesIO()
    torch.save(payload, data)  # in memory first: a full disk then fails as OSError(ENOSPC), not inside torch
    atomic_write_bytes(path, lambda f: f.write(data.getbuffer()))


def load(path: str, map_location="cpu") -> dict:
    """Load and sanity-check a checkpoint; raises CheckpointError with the reason."""
    if os.path.isdir(path):  # a run directory: its full checkpoint, else its final weights
        found = [p for p in (os.path.join(path, n) for n in ("checkpoint.pt", "policy.pt")) if os.path.exists(p)]
        if not found:
            raise CheckpointError(f"{path} is a directory without checkpoint.pt or policy.pt")
        path = found[0]
    if not os.path.exists(path):
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupted, truncated or not a torch file
        raise CheckpointError(
            f"cannot read checkpoint {path}: it is corrupted, truncated or not a "
            f"taichi-swarm checkpoint ({type(exc).__name__})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a taichi-swarm checkpoint")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"{path} has checkpoint version {payload.get('version')}, expected {VERSION}")
    for key in ("model_config", "model"):
        if key not in payload:
            raise CheckpointError(f"{path} lacks {key!r}")
    if not isinstance(payload["model"], dict) or not all(
        isinstance(v, torch.Tensor) for v in payload["model"].values()
    ):
        raise CheckpointError(f"{path}: 'model' is not a dict of tensors")
    digest = payload.get("model_sha256")  # absent in checkpoints written before it existed
    if digest is not None and digest != weights_digest(payload["model"]):
        raise CheckpointError(f"{path}: the weights do not match their stored sha256 (the file was corrupted)")
    return payload


POLICY_KEYS = ("model_config", "model", "task", "counters", "evals")


def save_policy_only(payload: dict, path: str) -> None:
    """Save the inference part of a training checkpoint (no optimiser state): ~1 MB."""
    save(path, {k: payload[k] for k in POLICY_KEYS if k in payload})


def policy_from_payload(payload: dict, device="cpu") -> SwarmPolicy:
    try:
        config = ModelConfig(**payload["model_config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint has an invalid model config: {exc}") from None
    policy = SwarmPolicy(config)
    load_weights(policy, payload["model"])
    return policy.to(device)


def load_weights(policy: SwarmPolicy, state_dict: dict) -> None:
    """Load weights, naming the mismatching tensors instead of torch's error dump."""
    own = policy.state_dict()
    missing = sorted(set(own) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(own))
    wrong = sorted(k for k in set(own) & set(state_dict) if own[k].shape != state_dict[k].shape)
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"missing {missing[:4]}")
        if unexpected:
            parts.append(f"unexpected {unexpected[:4]}")
        if wrong:
            parts.append(
                "shape mismatch "
                + ", ".join(f"{k}: {tuple(state_dict[k].shape)} vs {tuple(own[k].shape)}" for k in wrong[:4])
            )
        raise CheckpointError(
            "checkpoint weights do not fit this network ("
            + "; ".join(parts)
            + "): was it trained with another --model configuration?"
        )
    bad = sorted(k for k, v in state_dict.items() if v.is_floating_point() and not torch.isfinite(v).all())
    if bad:
        raise CheckpointError(f"checkpoint weights hold NaN or inf ({', '.join(bad[:4])}): refusing to use them")
    policy.load_state_dict(state_dict)


def load_policy(path: str, device="cpu") -> tuple[SwarmPolicy, dict]:
    """(policy in eval mode, payload) from a checkpoint file or run directory."""
    payload = load(path)
    policy = policy_from_payload(payload, device)
    policy.eval()
    return policy, payload
