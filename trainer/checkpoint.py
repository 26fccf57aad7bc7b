"""Checkpoints: written atomically, loaded with ``weights_only=True``, checked
before use so a wrong file gives a clear error instead of a torch traceback."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import math
import os
import zipfile

import torch

from taichi_swarm.files import (  # noqa: F401
    MAX_CHECKPOINT_BYTES,
    InputFileError,
    atomic_write_bytes,
    atomic_write_json,
    check_input,
    clean_leftovers,
    ensure_writable,
)
from trainer import rundir, zoo
from trainer.config import to_dict, train_config_from_dict
from trainer.model import MAX_HIDDEN, MAX_ROUNDS, ModelConfig, SwarmPolicy
from trainer.ppo import NonFiniteTraining, all_finite
from trainer.rundir import CHECKPOINT, POLICY
from trainer.zoo import file_sha256

MAX_LANDMARKS = 1024  # of a "concat" network
MAX_UPDATES = 10**9  # PPO updates of one run: at one update a second, 30 years

FORMAT = "taichi-swarm-checkpoint"
# 3: one sha256 over the whole payload ("sha256"), one reward normaliser per team size
#    ("reward_scalers"), the counters and RNG states always present;
# 2: the same sha256, beside the weights-only "model_sha256" and a copy of the first
#    normaliser ("reward_scaler"); 1: "model_sha256" only, or no digest at all.
# ``load`` checks a file as it was written, then ``migrate`` brings it to version 3.
VERSION = 3
READABLE_VERSIONS = (1, 2, 3)


class CheckpointError(ValueError):
    """A checkpoint file is missing, unreadable, unsigned or does not fit."""


class UnsignedCheckpoint(CheckpointError):
    """A checkpoint without a digest: its contents cannot be checked (``trust_unsigned``)."""


class CheckpointArgumentError(CheckpointError, TypeError):
    """An argument of ``load`` / ``load_policy`` of the wrong kind (a path of None, a
    ``trust_unsigned`` that is not a bool): caught as the ValueError every caller handles,
    and as the TypeError it is."""


def _check_arguments(path, trust_unsigned, expected_sha256) -> str:
    """``path`` as a str, once the arguments are of the kinds ``load`` takes."""
    if not isinstance(path, (str, os.PathLike)):
        raise CheckpointArgumentError(
            f"checkpoint path must be a file, a run directory or a model zoo name, got {path!r}"
        )
    path = os.fspath(path)
    if not isinstance(path, str) or not path:
        raise CheckpointArgumentError(f"checkpoint path must be a non-empty str, got {path!r}")
    # a truthy string ('no') must not count as consent to load a file that cannot be checked
    if not isinstance(trust_unsigned, bool):
        raise CheckpointArgumentError(f"trust_unsigned must be True or False, got {trust_unsigned!r}")
    if expected_sha256 is not None and not (
        isinstance(expected_sha256, str)
        and len(expected_sha256) == 64
        and all(c in "0123456789abcdef" for c in expected_sha256.lower())
    ):
        raise CheckpointArgumentError(f"expected_sha256 must be 64 hex digits or None, got {expected_sha256!r}")
    return path


def check_device(device) -> torch.device:
    """``device`` as a torch.device this machine has; one CheckpointError line otherwise (torch
    itself fails with an AssertionError deep in ``.to``)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise CheckpointArgumentError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}") from None
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise CheckpointError(f"device {device!r}: this machine has no CUDA device (use device='cpu')")
        if dev.index is not None and dev.index >= count:
            raise CheckpointError(f"device {device!r}: this machine has {count} CUDA device(s), 0..{count - 1}")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise CheckpointError(f"device {device!r}: MPS is not available on this machine (use device='cpu')")
    return dev


def _tensor_bytes(t: torch.Tensor) -> bytes:
    t = t.detach().cpu().contiguous().reshape(-1)
    return t.view(torch.uint8).numpy().tobytes() if t.numel() else b""


def weights_digest(state_dict: dict) -> str:
    """sha256 over the names, dtypes, shapes and bytes of every tensor of a state dict."""
    h = hashlib.sha256()
    for name in sorted(state_dict):
        t = state_dict[name]
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(_tensor_bytes(t))
    return h.hexdigest()


def _feed(h, x, where: str) -> None:
    """Every value, its type and its place in the structure into ``h`` (dict keys sorted)."""
    if isinstance(x, torch.Tensor):
        h.update(f"T{x.dtype}|{tuple(x.shape)}|".encode())
        h.update(_tensor_bytes(x))
    elif isinstance(x, dict):
        h.update(f"D{len(x)}|".encode())
        for k in sorted(x, key=lambda k: (type(k).__name__, repr(k))):
            _feed(h, k, where)
            _feed(h, x[k], f"{where}.{k}")
    elif isinstance(x, (list, tuple)):
        h.update(f"{'L' if isinstance(x, list) else 'U'}{len(x)}|".encode())
        for i, v in enumerate(x):
            _feed(h, v, f"{where}[{i}]")
    elif isinstance(x, bool) or x is None:
        h.update(f"B{x}|".encode())
    elif isinstance(x, int):
        h.update(f"I{x}|".encode())
    elif isinstance(x, float):
        h.update(f"F{x.hex()}|".encode())
    elif isinstance(x, str):
        data = x.encode()
        h.update(f"S{len(data)}|".encode() + data)
    else:
        raise CheckpointError(f"checkpoint entry {where} is a {type(x).__name__}, which a checkpoint cannot hold")


def payload_digest(payload: dict) -> str:
    """sha256 over everything a payload holds but its own digest: weights, Adam's moments,
    environment buffers, reward normalisers, RNG states, counters, configs."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in payload.items() if k != "sha256"}, "payload")
    return h.hexdigest()


def save(path: str, payload: dict) -> None:
    """Save ``payload`` (must hold "model_config" and "model") atomically, signed with one
    sha256 over the whole of it (checked by ``load``)."""
    payload = {k: v for k, v in payload.items() if k not in ("format", "version", "sha256", "model_sha256")}
    payload = {"format": FORMAT, "version": VERSION, **payload}
    payload["sha256"] = payload_digest(payload)
    data = io.BytesIO()
    torch.save(payload, data)  # in memory first: a full disk then fails as OSError(ENOSPC), not inside torch
    atomic_write_bytes(path, lambda f: f.write(data.getbuffer()))


def resolve_path(path: str) -> str:
    """A checkpoint file, or a run directory's checkpoint.pt, else its policy.pt."""
    if os.path.isdir(path):  # a run directory: its full checkpoint, else its final weights
        found = [p for p in (os.path.join(path, n) for n in (CHECKPOINT, POLICY)) if os.path.exists(p)]
        if not found:
            raise CheckpointError(f"{path} is a directory without {CHECKPOINT} or {POLICY}")
        path = found[0]
    try:  # a FIFO would block torch.load, a device never end; a bounded size
        check_input(path, "checkpoint", MAX_CHECKPOINT_BYTES)
    except InputFileError as exc:
        raise CheckpointError(str(exc)) from None
    return path


def _check_records(path: str) -> None:
    """Every record of the zip archive torch wrote against its CRC-32: a flipped byte in any of
    them (pickle, tensor data, version) is refused here, before torch reads it."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except Exception as exc:  # noqa: BLE001 - not a zip, torn, or a header flipped
        raise CheckpointError(
            f"cannot read checkpoint {path}: it is corrupted, truncated or not a "
            f"taichi-swarm checkpoint ({type(exc).__name__})"
        ) from None
    if bad is not None:
        raise CheckpointError(f"checkpoint {path} is corrupted: its record {bad} fails its CRC-32")


def load(path: str, map_location="cpu", *, trust_unsigned: bool = False, expected_sha256: str | None = None) -> dict:
    """Load and check a checkpoint file or run directory; raises CheckpointError with the reason.
    The payload comes back in the current layout (``migrate``); its "version" says what the
    file was written as.

    A file must be signed: its stored sha256 over the whole payload (written by ``save``),
    or for files from before it existed, over the weights (``model_sha256``), must match.
    ``expected_sha256``: the sha256 of the file's bytes as a model index records it; a
    match counts as signed, a mismatch is refused; given with a zoo name, it is checked in
    place of the entry's own. A file with no digest at all is refused (``UnsignedCheckpoint``)
    unless ``trust_unsigned`` (a bool). A digest that does not match is always refused."""
    path = _check_arguments(path, trust_unsigned, expected_sha256)
    if not os.path.exists(path) and zoo.looks_like_name(path):  # a model zoo name: its entry's file and sha256
        entry = zoo.get(path)
        # the caller's digest wins: it pins the bytes they measured, whatever the index says now
        path, expected_sha256 = entry.path, expected_sha256 if expected_sha256 is not None else entry.sha256
    path = resolve_path(path)
    if expected_sha256 is not None:
        actual = file_sha256(path)
        if actual != expected_sha256.lower():
            raise CheckpointError(
                f"{path} has sha256 {actual[:12]}..., its index entry says {expected_sha256[:12]}...: "
                "the file was changed or corrupted"
            )
    _check_records(path)
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupted, truncated or not a torch file
        raise CheckpointError(
            f"cannot read checkpoint {path}: it is corrupted, truncated or not a "
            f"taichi-swarm checkpoint ({type(exc).__name__})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a taichi-swarm checkpoint")
    version = payload.get("version")
    if version not in READABLE_VERSIONS:
        raise CheckpointError(f"{path} has checkpoint version {version!r}, expected one of {READABLE_VERSIONS}")
    for key in ("model_config", "model"):
        if key not in payload:
            raise CheckpointError(f"{path} lacks {key!r}")
    if not isinstance(payload["model"], dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in payload["model"].items()
    ):
        raise CheckpointError(f"{path}: 'model' is not a dict of tensors")
    if version >= 2:
        if not isinstance(payload.get("sha256"), str):
            raise CheckpointError(f"{path} lacks its sha256 (a version {version} checkpoint always carries one)")
        if payload["sha256"] != payload_digest(payload):
            raise CheckpointError(f"{path}: the contents do not match their stored sha256 (the file was corrupted)")
    digest = payload.get("model_sha256")
    if digest is not None and digest != weights_digest(payload["model"]):
        raise CheckpointError(f"{path}: the weights do not match their stored sha256 (the file was corrupted)")
    signed = version >= 2 or digest is not None  # (version 1: the weights' digest, if any)
    if not signed and expected_sha256 is None and not trust_unsigned:
        raise UnsignedCheckpoint(
            f"{path} carries no sha256, so corruption in it cannot be detected; pass --trust-unsigned to load it anyway"
        )
    return migrate(payload)


def migrate(payload: dict) -> dict:
    """The one migration: a version 1 or 2 payload (its digests already checked) in version
    3's layout, so that no reader needs to know older keys. The committed zoo weights are
    version 1 policy files; checkpoints of runs started before version 3 resume through it."""
    if payload["version"] >= 3:
        return payload
    payload = dict(payload)
    payload.pop("model_sha256", None)  # checked by load; version 3's sha256 covers the weights
    first = payload.pop("reward_scaler", None)  # before several team sizes: the one normaliser
    if first is not None and "reward_scalers" not in payload:
        payload["reward_scalers"] = [first]
    payload.setdefault("swarm", {})  # before neighbour lists: the dense graph
    payload.setdefault("evals", [])
    if isinstance(payload.get("counters"), dict):
        payload["counters"] = {"skipped_minibatches": 0, **payload["counters"]}
    if "optimizer" in payload:  # a training checkpoint: from before GPU training, no CUDA generators
        payload.setdefault("cuda_rng", [])
    return payload


def check_tensor(where: str, t, *, shape=None, dtype=None, finite: bool = True, nonnegative: bool = False):
    """``t`` if it is a tensor of ``shape`` / ``dtype``, finite (floats) and >= 0 where asked;
    else CheckpointError naming ``where``."""
    if not isinstance(t, torch.Tensor):
        raise CheckpointError(f"checkpoint entry {where} is a {type(t).__name__}, expected a tensor")
    if shape is not None and tuple(t.shape) != tuple(shape):
        raise CheckpointError(f"checkpoint entry {where} has shape {tuple(t.shape)}, expected {tuple(shape)}")
    if dtype is not None and t.dtype != dtype:
        raise CheckpointError(f"checkpoint entry {where} has dtype {t.dtype}, expected {dtype}")
    if finite and (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
        raise CheckpointError(f"checkpoint entry {where} holds NaN or inf: refusing to use it")
    if nonnegative and bool((t < 0).any()):
        raise CheckpointError(f"checkpoint entry {where} holds negative values")
    return t


def check_number(where: str, x, *, minimum: float = 0.0, integer: bool = False):
    """``x`` if it is a finite number >= ``minimum`` (an int where ``integer``)."""
    kinds = (int,) if integer else (int, float)
    if isinstance(x, bool) or not isinstance(x, kinds) or not math.isfinite(x) or x < minimum:
        kind = "an integer" if integer else "a finite number"
        raise CheckpointError(f"checkpoint entry {where} is {x!r}, expected {kind} >= {minimum:g}")
    return x


POLICY_KEYS = ("model_config", "model", "task", "swarm", "counters", "evals")  # swarm: make()'s list options


def save_policy_only(payload: dict, path: str) -> None:
    """Save the inference part of a training checkpoint (no optimiser state): ~1 MB."""
    save(path, {k: payload[k] for k in POLICY_KEYS if k in payload})


def check_model_config(config: ModelConfig, where: str = "checkpoint") -> ModelConfig:
    """Refuse a network too large to build or too slow to run (a crafted file's 10^9 rounds
    would hang every forward): the bounds the export schema and training share."""
    if config.rounds > MAX_ROUNDS:
        raise CheckpointError(f"{where} has {config.rounds} message rounds; at most {MAX_ROUNDS} are supported")
    if config.hidden > MAX_HIDDEN:
        raise CheckpointError(f"{where} has hidden width {config.hidden}; at most {MAX_HIDDEN} is supported")
    if config.num_landmarks > MAX_LANDMARKS:
        raise CheckpointError(f"{where} has {config.num_landmarks} landmarks; at most {MAX_LANDMARKS} are supported")
    return config


def model_config_from_payload(payload: dict, where: str = "checkpoint") -> ModelConfig:
    """The payload's "model_config", every field of its type and within the bounds."""
    raw = payload["model_config"]
    if not isinstance(raw, dict) or not all(isinstance(k, str) for k in raw):
        raise CheckpointError(f"{where} entry model_config is a {type(raw).__name__}, expected a dict of fields")
    try:
        config = ModelConfig.from_dict(raw)  # (its __post_init__ checks every field's type and range)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{where} has an invalid model config: {exc}") from None
    return check_model_config(config, where)


def policy_from_payload(payload: dict, device="cpu") -> SwarmPolicy:
    config = model_config_from_payload(payload)
    check_device(device)
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
    # load_state_dict would cast silently: int64 weights become whole-number floats, a network
    # that runs and fails at its task
    odd = sorted(k for k in own if state_dict[k].dtype != own[k].dtype)
    if odd:
        k = odd[0]
        raise CheckpointError(
            f"checkpoint weights must be {own[k].dtype}; {', '.join(odd[:4])} "
            f"{'is' if len(odd) == 1 else 'are'} {state_dict[k].dtype}: refusing to convert them"
        )
    bad = sorted(k for k, v in state_dict.items() if v.is_floating_point() and not torch.isfinite(v).all())
    if bad:
        raise CheckpointError(f"checkpoint weights hold NaN or inf ({', '.join(bad[:4])}): refusing to use them")
    policy.load_state_dict(state_dict)


def recorded_sim(payload: dict, what: str = "the checkpoint"):
    """The ``taichi_swarm.Sim`` a payload records (None: it records no task)."""
    from taichi_swarm.sim import Sim

    if not (payload.get("task") or {}).get("task"):
        return None
    swarm = payload.get("swarm") or {}
    if not isinstance(swarm, dict):
        raise CheckpointError(f"{what}'s swarm setting is not a dict: {swarm!r}")
    return Sim.from_record(payload["task"], swarm, what)


def load_policy(
    path: str, device="cpu", *, trust_unsigned: bool = False, expected_sha256: str | None = None
) -> tuple[SwarmPolicy, dict]:
    """(policy in eval mode, payload) from a checkpoint file, run directory or zoo name
    (``load``'s checks); ``device`` one this machine has. The policy carries the simulator
    setting it was trained on (``policy.sim``, a ``taichi_swarm.Sim`` from the payload's "task"
    and "swarm" records; None where it records no task), which ``evaluate`` uses unless told
    otherwise."""
    _check_arguments(path, trust_unsigned, expected_sha256)
    check_device(device)  # before the file is read: a wrong device is no reason to read 100 MB
    payload = load(path, trust_unsigned=trust_unsigned, expected_sha256=expected_sha256)
    policy = policy_from_payload(payload, device)
    policy.eval()
    policy.sim = recorded_sim(payload, path)
    return policy, payload


def check_optimizer_state(where: str, state: dict, policy: SwarmPolicy) -> None:
    """An Adam state dict that fits ``policy``: one entry per parameter, moments of the
    parameter's shape and dtype, finite, the second moment >= 0, a finite step."""
    params = list(policy.parameters())
    if not isinstance(state, dict) or not isinstance(state.get("state"), dict):
        raise CheckpointError(f"{where}: 'optimizer' is not an optimiser state dict")
    groups = state.get("param_groups")
    if not isinstance(groups, list) or not groups or not all(isinstance(g, dict) for g in groups):
        raise CheckpointError(f"{where}: the optimiser state has no parameter groups")
    ids = [i for g in groups for i in g.get("params", [])]
    if sorted(ids) != list(range(len(params))):
        raise CheckpointError(f"{where}: the optimiser state holds {len(ids)} parameters, the network {len(params)}")
    for g in groups:
        for key in ("lr", "eps", "weight_decay"):
            if key in g:
                check_number(f"{where} optimizer.param_groups.{key}", g[key])
        betas = g.get("betas", (0.9, 0.999))
        if not isinstance(betas, (list, tuple)) or len(betas) != 2:
            raise CheckpointError(f"{where}: optimiser betas {betas!r} are not a pair")
        for b in betas:
            check_number(f"{where} optimizer.param_groups.betas", b)
    for key, entry in state["state"].items():
        if not isinstance(key, int) or not 0 <= key < len(params) or not isinstance(entry, dict):
            raise CheckpointError(f"{where}: optimiser state entry {key!r} does not fit the network")
        p = params[key]
        for name in ("exp_avg", "exp_avg_sq"):
            check_tensor(
                f"{where} optimizer.state.{key}.{name}",
                entry.get(name),
                shape=p.shape,
                dtype=p.dtype,
                nonnegative=name == "exp_avg_sq",
            )
        step = entry.get("step")
        if isinstance(step, torch.Tensor):
            check_tensor(f"{where} optimizer.state.{key}.step", step, shape=(), nonnegative=True)
        else:
            check_number(f"{where} optimizer.state.{key}.step", step)


def check_scaler_state(where: str, state: dict, num_envs: int | None) -> None:
    """A reward normaliser's state: the running returns [E] (any E where None) and a running variance."""
    if not isinstance(state, dict) or not isinstance(state.get("rms"), dict):
        raise CheckpointError(f"{where}: a reward normaliser state is not a dict with 'rms'")
    ret = check_tensor(f"{where} reward_scaler.ret", state.get("ret"), dtype=torch.float64)
    if ret.dim() != 1 or (num_envs is not None and ret.shape[0] != num_envs):
        raise CheckpointError(f"{where} reward_scaler.ret has shape {tuple(ret.shape)}, expected ({num_envs or 'E'},)")
    rms = state["rms"]
    check_tensor(f"{where} reward_scaler.rms.mean", rms.get("mean"), shape=(), dtype=torch.float64)
    check_tensor(f"{where} reward_scaler.rms.var", rms.get("var"), shape=(), dtype=torch.float64, nonnegative=True)
    check_number(f"{where} reward_scaler.rms.count", rms.get("count"), minimum=1e-300)


def check_counters(where: str, counters, steps_per_update: int | None = None) -> dict:
    """Counters of a run: integers >= 0, at most MAX_UPDATES updates, and consistent with each
    other (an update takes at least one environment step; with ``steps_per_update``, the
    run's num_steps x num_envs, exactly that many)."""
    if not isinstance(counters, dict):
        raise CheckpointError(f"{where}: 'counters' is not a dict")
    for key in ("update", "env_steps"):
        check_number(f"{where} counters.{key}", counters.get(key), integer=True)
    check_number(f"{where} counters.wall_time", counters.get("wall_time"))
    check_number(f"{where} counters.skipped_minibatches", counters.get("skipped_minibatches"), integer=True)
    update, env_steps = counters["update"], counters["env_steps"]
    if update > MAX_UPDATES:
        raise CheckpointError(f"{where} counters.update is {update}; a run holds at most {MAX_UPDATES} updates")
    if update > env_steps:
        raise CheckpointError(f"{where} counters.update {update} exceeds counters.env_steps {env_steps}")
    if steps_per_update is not None and env_steps != update * steps_per_update:
        raise CheckpointError(
            f"{where} counters.env_steps is {env_steps}; {update} updates of {steps_per_update} steps "
            f"(ppo.num_steps x ppo.num_envs) make {update * steps_per_update}"
        )
    return counters


def check_rng_state(where: str, state) -> torch.Tensor:
    """torch's CPU generator state: a uint8 vector of the size this torch uses."""
    return check_tensor(where, state, shape=torch.get_rng_state().shape, dtype=torch.uint8)


# ----------------------------------------------------------------------------- a run's checkpoints


def open_run(cfg, resume: str | None, overrides: dict | None = None):
    """The run directory of a new run, or of one to resume (its checkpoint checked, its
    config read back, leftovers of a killed write repaired; ``overrides``: the config fields a
    resume changes, e.g. updates, progress). Returns (run, cfg, payload: None for a new run)."""

    if resume is None:
        if cfg is None:
            raise ValueError("train() needs a config or a run directory to resume")
        run = rundir.RunDir(cfg.default_run_dir())
        if os.path.exists(run.checkpoint):
            raise FileExistsError(
                f"{run.path} already holds a run; continue it with --resume {run.path} or pick another --run-dir"
            )
        os.makedirs(run.path, exist_ok=True)
        cfg.validate()
        run.truncate_metrics(0)  # lines a run killed before its first checkpoint left behind
        run.write_config(to_dict(cfg))
        return run, cfg, None
    run = rundir.RunDir(resume)
    clean_leftovers(run.path)  # a kill during a write leaves a .tmp-* file
    payload = load(run.checkpoint)
    if "train_config" not in payload:
        raise CheckpointError(f"{run.checkpoint} is not a training checkpoint (no train_config)")
    lacking = [k for k in rundir.RESUME_KEYS if k not in payload]
    if lacking:
        raise CheckpointError(f"{run.checkpoint} cannot resume a run: it lacks {lacking}")
    check_counters(run.checkpoint, payload["counters"])  # (before policy.pt is repaired from them)
    try:
        cfg = train_config_from_dict(payload["train_config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{run.checkpoint} holds a training config this version cannot read: {exc}") from None
    check_counters(run.checkpoint, payload["counters"], cfg.ppo.num_steps * cfg.ppo.num_envs)
    model_config_from_payload(payload, run.checkpoint)  # (policy.pt is written from it)
    if os.path.exists(run.policy):  # a kill between the two writes leaves policy.pt one behind
        if load(run.policy)["counters"] != payload["counters"]:
            save_policy_only(payload, run.policy)
    cfg = dataclasses.replace(cfg, **(overrides or {}))
    run.truncate_metrics(payload["counters"]["update"])
    cfg.validate()
    run.write_config(to_dict(cfg))
    return run, cfg, payload


# ----------------------------------------------------------------------------- checkpoints


def env_state(env) -> dict:
    """``env.snapshot()`` as torch tensors (checkpoints load with weights_only=True)."""
    snap = env.snapshot()
    return {"shape": list(snap["shape"]), "buffers": {k: torch.from_numpy(v) for k, v in snap["buffers"].items()}}


def save_checkpoint(run: rundir.RunDir, state, cfg) -> None:
    """pt (everything to resume bit-identically), then policy.pt (weights only).
    A state holding NaN/inf is never written: the last good checkpoint stays."""

    moments = [t for entry in state.optimizer.state.values() for t in entry.values() if isinstance(t, torch.Tensor)]
    if not all_finite(list(state.policy.parameters()) + moments):
        raise NonFiniteTraining(
            f"the weights or Adam's moments hold NaN/inf: not written (last good checkpoint: {run.checkpoint})"
        )
    payload = {
        "model_config": state.policy.config.to_dict(),
        "model": state.policy.state_dict(),
        "task": cfg.sim.task_record(),
        "swarm": cfg.sim.swarm_record(),  # the neighbour lists / density scaling it trained on ({}: dense)
        "counters": dict(state.counters),
        "evals": list(state.evals),
        "optimizer": state.optimizer.state_dict(),
        "env_states": [env_state(g.env) for g in state.groups],
        "reward_scalers": [g.scaler.state_dict() for g in state.groups],
        "torch_rng": torch.get_rng_state(),
        # on a GPU, sampling and minibatch shuffles draw from CUDA's generators
        "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else [],
        "train_config": to_dict(cfg),
    }
    save(run.checkpoint, payload)
    save_policy_only(payload, run.policy)


def restore_env(env, saved, where: str) -> dict:
    """``env.restore`` from a checkpoint's entry (its buffers checked by ``restore``)."""

    if not isinstance(saved, dict) or not isinstance(saved.get("buffers"), dict):
        raise CheckpointError(f"checkpoint {where} is not an environment state")
    buffers = {}
    for name, t in saved["buffers"].items():
        buffers[name] = check_tensor(f"{where}.buffers.{name}", t, finite=False).numpy()
    try:
        return env.restore({"shape": tuple(saved.get("shape", ())), "buffers": buffers})
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {where}: {exc}") from None


def restore(state, payload: dict, device: str) -> None:
    """Put a training state (trainer.ppo.TrainingState, freshly built for the run's config)
    back as the checkpoint ``payload`` holds it: weights, Adam, reward normalisers, RNG
    states, counters, evaluations and every environment's buffers. Every piece is checked
    (shape, dtype, finite) before it is used."""
    import torch

    groups = state.groups
    sizes = [g.agents for g in groups]
    load_weights(state.policy, payload["model"])
    check_optimizer_state("checkpoint", payload["optimizer"], state.policy)
    state.optimizer.load_state_dict(payload["optimizer"])
    scaler_states = payload["reward_scalers"]
    if not isinstance(scaler_states, list) or len(scaler_states) != len(groups):
        raise CheckpointError(f"the checkpoint does not hold one reward scaler per team size {sizes}")
    for g, scaler_state in zip(groups, scaler_states, strict=True):
        check_scaler_state("checkpoint", scaler_state, g.scaler.ret.shape[0])
        g.scaler.load_state_dict(scaler_state)
    torch.set_rng_state(check_rng_state("checkpoint torch_rng", payload["torch_rng"]))
    cuda_rng = payload["cuda_rng"]
    for i, t in enumerate(cuda_rng):
        check_tensor(f"checkpoint cuda_rng[{i}]", t, dtype=torch.uint8)
    if device.startswith("cuda") and len(cuda_rng) == torch.cuda.device_count():  # (not: another machine)
        torch.cuda.set_rng_state_all(cuda_rng)
    state.counters = dict(check_counters("checkpoint", payload["counters"]))
    state.evals = list(payload["evals"])
    env_states = payload["env_states"]
    if not isinstance(env_states, list) or len(env_states) != len(groups):
        raise CheckpointError(f"the checkpoint's env_states do not hold one state per team size {sizes}")
    for k, g in enumerate(groups):  # resume bit-identically: the environments' buffers as they were
        g.obs = restore_env(g.env, env_states[k], f"env_states[{k}]")
