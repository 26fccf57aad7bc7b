"""Export a trained ``SwarmPolicy`` as the per-agent ONNX pieces (``swarm export``).

This module imports torch; the executor (deploy/executor.py) never imports it.

Pieces (one agent, no batch axis; H hidden, L landmarks, n messages heard):
    encode.onnx       self_obs [4], entities [L, 2]  -> h [H], message [2, H]
    round.onnx        h [H], heard [n, 2, H]         -> h [H], message [2, H], weights [n + 1]
    heads.onnx        h [H]                          -> logits [5], value []
    round_heads.onnx  h [H], heard [n, 2, H]         -> logits [5], value [], weights [n + 1], h [H]
With edge_position "relative" both round pieces also take offsets [n, 2]: p_j - p_i of
each sender j of heard, as the receiver i measures it (row k of offsets goes with row k
of heard; the agent's own message gets offset 0 inside the graph).
``round_heads`` is the last round fused with the heads (one call fewer per step);
``heads`` alone serves K = 0 and anyone who wants the pieces unfused.

A message is the sender's attention key and value (``policy.message(h)``, stacked
[2, H]), so a receiver only applies its query: the projection of h is done once, by
the sender. An agent always hears itself (s.3): the round graphs recompute the
agent's own message from h inside the graph and attend over [own; heard], so the
caller passes only what arrived from others (weights[0] is the self weight).
L (EMP and padded modes) and n are dynamic, n = 0 included (nothing arrived: the
agent attends to itself alone, as an isolated agent does in the batched policy).
"""

from __future__ import annotations

import os
import platform
import warnings

import torch
from torch import nn

from deploy.manifest import FORMAT, MANIFEST, VERSION, ManifestError, integrator_contract, metadata, seal
from taichi_swarm.files import atomic_write_json
from taichi_swarm.physics import ACTION_MEANINGS
from taichi_swarm.sim import Sim
from trainer.checkpoint import CheckpointError, load_policy
from trainer.model import PADDED_SLOTS, SELF_DIM, SwarmPolicy
from trainer.zoo import file_sha256

OPSET = 18
EDGE_DOC = (
    "edge_position relative: offsets [n, 2] (float32, world units, world frame) is p_j - p_i for "
    "each sender j of heard, in the same order: where receiver i measures j, at the step it uses j's "
    "message (also for a delayed one); the true positions, whatever self_position"
)


class EncodePiece(nn.Module):
    """self_obs [4], entities [L, 2] -> h [H] and the first message [2, H] (key; value)."""

    def __init__(self, policy: SwarmPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, self_obs: torch.Tensor, entities: torch.Tensor):
        if self.policy.config.entity_mode == "padded":
            # NOTE: zero-fill to the 10 slots with a concat (not F.pad) so L stays symbolic.
            pad = entities.new_zeros(PADDED_SLOTS - entities.shape[0], entities.shape[1])
            entities = torch.cat([entities, pad], dim=0)
        h = self.policy.encode(self_obs, entities)  # [H]
        return h, torch.stack(self.policy.message(h))


def round_update(policy: SwarmPolicy, h: torch.Tensor, heard: torch.Tensor, offsets: torch.Tensor | None):
    """h [H] attends over its own message (recomputed from h: an agent always hears itself) and the
    n messages heard [n, 2, H] (and their senders' offsets [n, 2], relative edges)
    -> (new h [H], weights [n + 1], own first)."""
    own = torch.stack(policy.message(h))  # [2, H]
    msgs = torch.cat([own[None], heard], dim=0)  # [n + 1, 2, H]
    if offsets is not None:  # [1, n + 1, 2]: its own offset p_i - p_i = 0, as the model's self edge
        offsets = torch.cat([offsets.new_zeros(1, 2), offsets], dim=0)[None]
    h_new, weights = policy.update(h[None], msgs[:, 0], msgs[:, 1], None, offsets)  # [1, H], [1, n + 1]
    return h_new[0], weights[0]


class RoundPiece(nn.Module):
    """One communication round -> new h [H], the next message [2, H], weights [n + 1]."""

    def __init__(self, policy: SwarmPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, h: torch.Tensor, heard: torch.Tensor, offsets: torch.Tensor | None = None):
        h_new, weights = round_update(self.policy, h, heard, offsets)
        return h_new, torch.stack(self.policy.message(h_new)), weights


class HeadsPiece(nn.Module):
    """h [H] -> logits [5], value []."""

    def __init__(self, policy: SwarmPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, h: torch.Tensor):
        return self.policy.heads(h)


class RoundHeadsPiece(nn.Module):
    """The last round fused with the heads -> logits [5], value [], weights [n + 1], h [H]."""

    def __init__(self, policy: SwarmPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, h: torch.Tensor, heard: torch.Tensor, offsets: torch.Tensor | None = None):
        h_new, weights = round_update(self.policy, h, heard, offsets)
        logits, value = self.policy.heads(h_new)
        return logits, value, weights, h_new


PIECES = {
    # name -> (module class, input names, output names)
    "encode": (EncodePiece, ("self_obs", "entities"), ("h", "message")),
    "round": (RoundPiece, ("h", "heard"), ("h_out", "message", "weights")),
    "heads": (HeadsPiece, ("h",), ("logits", "value")),
    "round_heads": (RoundHeadsPiece, ("h", "heard"), ("logits", "value", "weights", "h_out")),
}


def piece_inputs(name: str, cfg) -> tuple[str, ...]:
    """The input names of piece ``name``: with relative edges the rounds take ``offsets`` too."""
    inputs = PIECES[name][1]
    return (*inputs, "offsets") if cfg.edge_position == "relative" and "heard" in inputs else inputs


def _example_inputs(name: str, policy: SwarmPolicy) -> tuple[tuple[torch.Tensor, ...], dict]:
    """Example inputs (dynamic sizes >= 2 so nothing specialises) and their dynamic_shapes."""
    cfg = policy.config
    H = cfg.hidden
    n = torch.export.Dim("n", min=0, max=4096)
    if name == "encode":
        if cfg.entity_mode == "concat":
            L_ex, dyn = cfg.num_landmarks, None
        else:
            L_ex = 3
            dyn = torch.export.Dim("L", min=1, max=PADDED_SLOTS if cfg.entity_mode == "padded" else 4096)
        return (torch.randn(SELF_DIM), torch.randn(L_ex, cfg.entity_features)), {
            "self_obs": None,
            "entities": {0: dyn} if dyn else None,
        }
    if name == "heads":
        return (torch.randn(H),), {"h": None}
    args, dynamic = (torch.randn(H), torch.randn(3, 2, H)), {"h": None, "heard": {0: n}}
    if cfg.edge_position == "relative":
        args, dynamic = (*args, torch.randn(3, 2)), {**dynamic, "offsets": {0: n}}
    return args, dynamic


def export_piece(name: str, policy: SwarmPolicy, path: str, props: dict[str, str] | None = None) -> None:
    """Export one piece to a single self-contained .onnx file (no external data), carrying
    ``props`` as its metadata_props (deploy.manifest.metadata: what the manifest must claim)."""
    cls, _, output_names = PIECES[name]
    input_names = piece_inputs(name, policy.config)
    module = cls(policy).eval()
    args, dynamic_shapes = _example_inputs(name, policy)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            module,
            args,
            dynamo=True,
            dynamic_shapes=dynamic_shapes,
            opset_version=OPSET,
            input_names=list(input_names),
            output_names=list(output_names),
            verbose=False,
        )
    import onnx

    tmp = path + ".tmp"
    try:
        program.save(tmp, external_data=False)
        if props:  # K and the task are not in any shape: the graph names them itself
            model = onnx.load(tmp)
            for key, value in props.items():
                entry = model.metadata_props.add()
                entry.key, entry.value = key, value
            onnx.save(model, tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _versions() -> dict:
    import onnx
    import onnxruntime

    try:
        from importlib.metadata import version

        swarm_version = version("taichi-swarm")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        swarm_version = "unknown"
    return {
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "taichi-swarm": swarm_version,
        "python": platform.python_version(),
    }


def _check_landmarks_fit(cfg, setting) -> None:
    """Refuse a task setting the network cannot take (its manifest would name a task no
    ``swarm execute`` of it could run)."""
    from taichi_swarm import TASK_SPECS

    if setting.agents is None:
        return
    L = TASK_SPECS[setting.task].num_landmarks(setting.agents)
    misfit = cfg.landmark_misfit(L)
    if misfit:
        raise CheckpointError(f"{misfit} ({setting.task} with {setting.agents} agents has {L} landmarks)")


def export(checkpoint: str, out_dir: str, task: dict | None = None, trust_unsigned: bool = False) -> dict:
    """Export ``checkpoint`` (file or run dir) into ``out_dir``; returns the manifest.

    ``task`` overrides/complements the checkpoint's ``payload["task"]``
    ({"task", "agents", "comm", "comm_radius"}; None values keep the checkpoint's): one
    ``taichi_swarm.Sim`` with the checkpoint's "swarm" record, checked.
    """
    import onnx

    policy, payload = load_policy(checkpoint, trust_unsigned=trust_unsigned)
    policy = policy.float().eval()
    cfg = policy.config
    try:
        setting = Sim.resolve(payload.get("task"), payload.get("swarm"), "the checkpoint", **(task or {}))
    except ValueError as exc:
        raise CheckpointError(str(exc)) from None
    _check_landmarks_fit(cfg, setting)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise FileExistsError(f"--out {out_dir} exists and is not a directory")
    os.makedirs(out_dir, exist_ok=True)

    files = {}
    props = metadata({"model_config": cfg.to_dict(), "task": setting.task_record()})
    for name, (_, _, outputs) in PIECES.items():
        path = os.path.join(out_dir, f"{name}.onnx")
        export_piece(name, policy, path, props)
        onnx.checker.check_model(path, full_check=True)
        files[name] = {
            "file": f"{name}.onnx",
            "sha256": file_sha256(path),
            "inputs": list(piece_inputs(name, cfg)),
            "outputs": list(outputs),
        }
    H = cfg.hidden
    edge = ["offsets [n, 2]"] if cfg.edge_position == "relative" else []
    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "task": setting.task_record(),
        "model_config": cfg.to_dict(),
        "rounds": cfg.rounds,
        "hidden": H,
        "entity_mode": cfg.entity_mode,
        "edge_position": cfg.edge_position,
        "num_landmarks": cfg.num_landmarks if cfg.entity_mode == "concat" else None,
        "max_landmarks": PADDED_SLOTS if cfg.entity_mode == "padded" else None,
        "observation": {
            "self_obs": {"shape": [SELF_DIM], "layout": ["vx", "vy", "px", "py"], "dtype": "float32"},
            "entities": {
                "shape": ["L", cfg.entity_features],
                "layout": "landmark position - own position, per landmark"
                + (
                    "; then its occupancy: its distance to the nearest agent other than this one, capped at "
                    "sense_radius"
                    if cfg.landmark_occupancy
                    else ""
                ),
                "dtype": "float32",
                "L": "coverage: M; formation: 1; line: 2; with landmark lists the KL listed",
            },
        },
        "message": {
            "kind": "key_value",
            "shape": [2, H],
            "doc": "policy.message(h): the sender's attention key (row 0) and value (row 1). A receiver stacks "
            "the n messages that arrived from others into heard [n, 2, H]; the round graphs add the "
            "agent's own message (recomputed from h: it always hears itself), so n = 0 is valid. "
            "weights [n + 1]: attention on [own; heard].",
        },
        "schedule": {
            "doc": "per step: encode -> send message; rounds 1..K-1: round(h, heard) -> send message; "
            "round K: round_heads(h, heard) -> logits (K = 0: heads(h)); action = argmax(logits)",
            "calls_per_step": 1 + max(cfg.rounds, 1),
            "inputs": {
                "encode": ["self_obs [4]", f"entities [L, {cfg.entity_features}]"],
                "round": ["h [H]", "heard [n, 2, H]", *edge],
                "round_heads": ["h [H]", "heard [n, 2, H]", *edge],
                "heads": ["h [H]"],
            },
            **({"offsets": EDGE_DOC} if edge else {}),
        },
        "contract": {**integrator_contract(setting.task_record(), cfg.rounds, H), **swarm_contract(setting)},
        "action_meanings": list(ACTION_MEANINGS[: cfg.num_actions]),
        "num_actions": cfg.num_actions,
        "opset": OPSET,
        "files": files,
        "versions": _versions(),
        "source_checkpoint": os.path.abspath(checkpoint),
    }
    try:
        manifest = seal(manifest)  # validated against the schema before it is written
    except ManifestError as exc:
        raise ValueError(f"refusing to export: {exc}") from None
    atomic_write_json(os.path.join(out_dir, MANIFEST), manifest)
    return manifest


def swarm_contract(sim: Sim) -> dict:
    """The neighbour lists / density scaling the policy trained on, for ``manifest["contract"]``
    (``swarm execute`` runs on them unless told otherwise); {} for a dense policy."""
    swarm = sim.swarm_record()
    if not swarm:
        return {}
    return {
        **radio_contract(sim),
        "swarm": dict(swarm),
        "swarm_doc": "the simulator options it trained on: neighbours K: an agent hears its K nearest "
        "(within comm_radius under rc), never more; landmark_neighbours KL: entities holds the KL nearest "
        "landmarks within sense_radius, nearest first (unsensed slots left out of entities); "
        "landmark_occupancy: each landmark row adds its distance to the nearest other agent; "
        "landmark_order radio: only the landmark the agent holds in the auction the agents run by messages to "
        "the teammates they hear (its occupancy floored at the success threshold); holding none, the landmarks "
        "its own table says another holds listed last, reading 0; "
        "auction_rounds R: the radio's message rounds a step, each bid raising a price by at least 0.5; "
        "scale density: the arena's half side is sqrt(M / 10)",
    }


def radio_contract(sim: Sim) -> dict:
    """A radio policy's auction rules, what each agent process runs (deploy/radio.py): {} for another."""
    from taichi_swarm import TASK_SPECS, radio
    from taichi_swarm.tasks import COMMON_PARAMS

    if sim.landmark_order != "radio":
        return {}
    params = {**COMMON_PARAMS, **TASK_SPECS[sim.task].params}
    return {
        "radio": {
            "rounds": sim.rounds,
            "table": sim.landmark_neighbours,
            "sense_radius": sim.sense_radius,
            "success_threshold": float(params["success_threshold"]),
            "increment": radio.ROUND_EPS,
            "hold_slack": radio.HOLD_SLACK,
            "stay_out": radio.OUT,
        },
        "radio_doc": "the agents' auction (deploy/radio.py, docs/SWARM.md): before the network's rounds, R "
        "rounds a step, each agent bids (holding nothing) for its cheapest of the `table` nearest landmarks it "
        "senses (distance + price, against staying out at stay_out sense radii), raising the price by the gap "
        "to its second best + increment; sends its table (TABLE packets) to the teammates it hears and keeps "
        "the greatest entry of each (epoch, price, lower holder); lets its landmark go when another option is "
        "cheaper by hold_slack increments. Its landmark rows: the held one alone (occupancy floored at "
        "success_threshold), else the sensed ones with those another holds last, reading 0",
    }
