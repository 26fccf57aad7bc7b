"""The export manifest (``manifest.json``): its schema, its seal, and the checks made
against the ONNX files themselves. One definition, used when ``swarm export`` writes
it and when the executor reads it (no torch here).

- Schema: jsonschema (draft 2020-12); an error names the field.
- Seal: ``manifest_sha256`` is the sha256 of the manifest's canonical JSON without
  that key, so an edited field (``rounds: 2``) is refused like an edited .onnx file.
- ONNX: each file's graph inputs and outputs must be the ones the manifest lists, and
  the width of the hidden state the graphs take must be the manifest's ``hidden``.
- edge_position ("none" | "relative"; absent in manifests older than it: "none"): the
  round pieces take ``offsets`` exactly when it is "relative".
- Consistency: the top-level fields, ``model_config``, ``task`` and ``contract`` agree; every
  static dimension of the graphs is the one the manifest implies (self_obs [4], entities
  [L, F], message [2, H], logits [A], ...).
- ONNX metadata (``metadata_props``, exports since it was added): each graph carries the
  model config and task setting it was exported with; a manifest resealed to claim other
  rounds or another task is refused, since the shapes alone do not pin K or the task.
- Size: a manifest is parsed only at most MAX_DEPTH levels deep (100,000 nested arrays
  would exhaust Python's recursion in the parser or the schema check).
"""

from __future__ import annotations

import hashlib
import json

import jsonschema

from taichi_swarm.constants import COMMS, EDGE_POSITIONS, ENTITY_MODES, NUM_ACTIONS, NUM_FINE_ACTIONS

MANIFEST = "manifest.json"
FORMAT = "taichi-swarm-onnx"
VERSION = 1
PIECES = ("encode", "round", "round_heads", "heads")
MAX_DEPTH = 32  # a manifest nests about 5 deep
META_MODEL = "taichi_swarm.model_config"  # ONNX metadata_props keys: canonical JSON of each
META_TASK = "taichi_swarm.task"
SELF_DIM = 4  # self_obs: vx, vy, px, py (taichi_swarm.layout.SELF_DIM)

_POSITIVE_INT = {"type": "integer", "minimum": 1}
SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": [
        "format",
        "version",
        "task",
        "model_config",
        "rounds",
        "hidden",
        "entity_mode",
        "files",
        "num_actions",
        "manifest_sha256",
    ],
    "properties": {
        "format": {"const": FORMAT},
        "version": {"const": VERSION},
        "task": {
            "type": "object",
            "required": ["task", "comm", "comm_radius"],
            "properties": {
                "task": {"type": "string"},  # (a registered task: the simulator checks it, ``make``)
                "agents": {"anyOf": [_POSITIVE_INT, {"type": "null"}]},
                "comm": {"enum": list(COMMS)},
                "comm_radius": {"type": "number", "minimum": 0, "maximum": 1e6},
            },
        },
        "model_config": {
            "type": "object",
            "required": ["hidden", "rounds", "entity_mode", "num_landmarks"],
            "properties": {
                "hidden": _POSITIVE_INT,
                "rounds": {"type": "integer", "minimum": 0, "maximum": 64},
                "entity_mode": {"enum": list(ENTITY_MODES)},
                "num_landmarks": {"type": "integer", "minimum": 0},
                "self_position": {"enum": ["absolute", "none"]},
                "edge_position": {"enum": list(EDGE_POSITIONS)},
                "num_actions": {"enum": [NUM_ACTIONS, NUM_FINE_ACTIONS]},
            },
        },
        "rounds": {"type": "integer", "minimum": 0, "maximum": 64},
        "hidden": _POSITIVE_INT,
        "entity_mode": {"enum": list(ENTITY_MODES)},
        "edge_position": {"enum": list(EDGE_POSITIONS)},
        "num_landmarks": {"anyOf": [_POSITIVE_INT, {"type": "null"}]},
        "max_landmarks": {"anyOf": [_POSITIVE_INT, {"type": "null"}]},
        "num_actions": {"enum": [NUM_ACTIONS, NUM_FINE_ACTIONS]},
        "action_meanings": {"type": "array", "items": {"type": "string"}},
        "files": {
            "type": "object",
            "required": list(PIECES),
            "additionalProperties": False,
            "properties": {
                name: {
                    "type": "object",
                    "required": ["file", "sha256", "inputs", "outputs"],
                    "properties": {
                        "file": {"type": "string", "pattern": r"^[A-Za-z0-9_.-]+\.onnx$"},
                        "sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
                        "inputs": {"type": "array", "items": {"type": "string"}},
                        "outputs": {"type": "array", "items": {"type": "string"}},
                    },
                }
                for name in PIECES
            },
        },
        "manifest_sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
        "contract": {  # optional: exports made before it have none
            "type": "object",
            "required": ["control_period_s", "rounds", "comm", "comm_radius", "message_schema_version"],
            "properties": {
                "control_period_s": {"type": "number", "exclusiveMinimum": 0},
                "rounds": {"type": "integer", "minimum": 0, "maximum": 64},
                "comm": {"enum": list(COMMS)},
                "comm_radius": {"type": "number", "minimum": 0},
                "message_schema_version": _POSITIVE_INT,
                "radio": {  # a radio policy's auction, as each agent runs it (deploy/radio.py)
                    "type": "object",
                    "required": [
                        "rounds",
                        "table",
                        "sense_radius",
                        "success_threshold",
                        "increment",
                        "hold_slack",
                        "stay_out",
                    ],
                    "properties": {
                        "rounds": {"type": "integer", "minimum": 1, "maximum": 64},
                        "table": {"type": "integer", "minimum": 1, "maximum": 4096},
                        **{
                            k: {"type": "number", "exclusiveMinimum": 0, "maximum": 1e6}
                            for k in ("sense_radius", "success_threshold", "increment", "hold_slack", "stay_out")
                        },
                    },
                },
            },
        },
    },
}


def integrator_contract(task: dict, rounds: int, hidden: int) -> dict:
    """What a robot integrator needs beyond the ONNX files (``manifest["contract"]``; docs/DEPLOY.md):
    the control period the policy was trained at, K, the communication graph, the observation
    layout and units, the action and the wire format of the messages (deploy/net/protocol.py)."""
    from deploy.net.protocol import HEADER_BYTES, SCHEMA_VERSION
    from taichi_swarm.constants import DAMPING, DT, MASS, SENSITIVITY

    return {
        "control_period_s": DT,
        "rounds": rounds,
        "comm": task["comm"],
        "comm_radius": task["comm_radius"],
        "comm_doc": "uc: every agent hears every teammate; rc: it hears those within comm_radius "
        "(world units, centre to centre), decided each control step",
        "units": "world units (the arena: agents start uniformly in [-1, 1]^2) and seconds",
        "observation": {
            "self_obs": "float32 [4]: vx, vy (world units / s), px, py (world units), in the world frame",
            "entities": "float32 [L, 2]: each landmark's position minus the agent's own (world units), "
            "world frame, in the task's landmark order (coverage: M landmarks; formation: 1; line: 2)",
        },
        "action": "argmax of logits [5]: 0 noop, 1 -x, 2 +x, 3 -y, 4 +y; a force of "
        f"{SENSITIVITY} along the axis held for one control period (mass {MASS}, damping {DAMPING} per step)",
        "message_schema_version": SCHEMA_VERSION,
        "message": f"little-endian: a {HEADER_BYTES}-byte header (magic TSWM, schema version, kind, run, step, "
        f"worlds B, round, sender, nonce; deploy/net/protocol.py) then float32 [B, 2, {hidden}] (key; value per world)",
    }


class ManifestError(ValueError):
    """A manifest that does not follow the schema, was edited, or does not fit its files."""


def parse(data: bytes | str, where: str = MANIFEST) -> dict:
    """A manifest's JSON text -> its object, refused (ManifestError) unless it is UTF-8 JSON
    nested at most MAX_DEPTH deep."""
    try:
        manifest = json.loads(data)
    except RecursionError:
        raise ManifestError(f"{where} is nested more than {MAX_DEPTH} levels deep: not a manifest") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ManifestError(f"cannot read {where}: {exc}") from None
    depth, level = 0, [manifest]
    while level:  # breadth first, no recursion: the check must not fail the way the parser does
        depth += 1
        if depth > MAX_DEPTH:
            raise ManifestError(f"{where} is nested more than {MAX_DEPTH} levels deep: not a manifest")
        level = [c for x in level for c in (x.values() if isinstance(x, dict) else x if isinstance(x, list) else ())]
    return manifest


def content_hash(manifest: dict) -> str:
    """sha256 of the canonical JSON of ``manifest`` without its own seal."""
    body = {k: v for k, v in manifest.items() if k != "manifest_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def seal(manifest: dict) -> dict:
    """``manifest`` with ``manifest_sha256`` set; validated before it is returned."""
    sealed = {**manifest, "manifest_sha256": content_hash(manifest)}
    validate(sealed)
    return sealed


def validate(manifest, where: str = MANIFEST) -> None:
    """Schema, seal and internal consistency; raises ManifestError naming the field."""
    if not isinstance(manifest, dict):
        raise ManifestError(f"{where} is not a JSON object")
    try:
        jsonschema.validate(manifest, SCHEMA)
    except jsonschema.ValidationError as exc:
        field = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ManifestError(f"{where}: field {field!r}: {exc.message}") from None
    if manifest["manifest_sha256"] != content_hash(manifest):
        raise ManifestError(
            f"{where} was changed after export (its manifest_sha256 does not match its content): export again"
        )
    own = {**manifest, "edge_position": edge_position(manifest)}
    # configs older than the fields: "none", the paper's 5 actions
    mc = {"edge_position": "none", "num_actions": NUM_ACTIONS, **manifest["model_config"]}
    for key in ("rounds", "hidden", "entity_mode", "edge_position", "num_actions"):
        if own[key] != mc[key]:
            raise ManifestError(f"{where}: {key} {own[key]!r} differs from model_config.{key} {mc[key]!r}")
    for name in ("round", "round_heads"):
        takes = "offsets" in manifest["files"][name]["inputs"]
        if takes != (own["edge_position"] == "relative"):
            raise ManifestError(
                f"{where}: edge_position {own['edge_position']!r}, but files.{name} "
                f"{'takes' if takes else 'does not take'} offsets (the senders' p_j - p_i)"
            )
    contract = manifest.get("contract")
    if contract is not None:  # what an integrator reads must be what the executor runs
        own_contract = {"rounds": manifest["rounds"], **{k: manifest["task"][k] for k in ("comm", "comm_radius")}}
        for key, value in own_contract.items():
            if contract[key] != value:
                where_from = "rounds" if key == "rounds" else f"task.{key}"
                raise ManifestError(f"{where}: contract.{key} {contract[key]!r} differs from {where_from} {value!r}")
    if manifest["entity_mode"] == "concat" and manifest.get("num_landmarks") != mc["num_landmarks"]:
        raise ManifestError(
            f"{where}: num_landmarks {manifest.get('num_landmarks')!r} differs from model_config.num_landmarks "
            f"{mc['num_landmarks']!r}"
        )
    meanings = manifest.get("action_meanings")
    if meanings is not None and len(meanings) != manifest["num_actions"]:
        raise ManifestError(f"{where}: {len(meanings)} action_meanings for num_actions {manifest['num_actions']}")
    if manifest["entity_mode"] == "concat" and not manifest.get("num_landmarks"):
        raise ManifestError(f"{where}: entity_mode 'concat' needs num_landmarks")


def edge_position(manifest: dict) -> str:
    """The manifest's edge_position, "none" | "relative" ("none" in manifests older than the field)."""
    return manifest.get("edge_position", "none")


def expected_shapes(manifest: dict) -> dict[str, list[int | None]]:
    """Every graph input and output name -> its shape as the manifest implies it (None: a
    dynamic axis, n heard or L landmarks)."""
    mc = manifest["model_config"]
    H, A = manifest["hidden"], manifest["num_actions"]
    L = manifest.get("num_landmarks") if manifest["entity_mode"] == "concat" else None
    features = 3 if mc.get("landmark_occupancy") else 2
    return {
        "self_obs": [SELF_DIM],
        "entities": [L, features],
        "h": [H],
        "h_out": [H],
        "message": [2, H],
        "heard": [None, 2, H],
        "offsets": [None, 2],
        "logits": [A],
        "value": [],
        "weights": [None],
    }


def metadata(manifest: dict) -> dict[str, str]:
    """The metadata_props export writes into every graph: what the manifest must keep claiming."""
    return {
        META_MODEL: json.dumps(manifest["model_config"], sort_keys=True, separators=(",", ":")),
        META_TASK: json.dumps(manifest["task"], sort_keys=True, separators=(",", ":")),
    }


# ModelConfig fields added after the first manifests, at the value the network had without them
LATER_MODEL_FIELDS = {
    "edge_position": "none",
    "self_position": "absolute",
    "landmark_occupancy": False,
    "num_actions": 5,
}


def check_onnx(manifest: dict, name: str, session, where: str) -> None:
    """The graph of ``session`` (an onnxruntime InferenceSession of the piece: read with the
    runtime the agents run, not the ``onnx`` package, which would cost an agent process 12 MB)
    takes and gives what the manifest says, every static dimension the one the manifest
    implies, and (where it carries them) was exported with the manifest's model config and task."""
    entry = manifest["files"][name]
    inputs = [i.name for i in session.get_inputs()]
    outputs = [o.name for o in session.get_outputs()]
    if inputs != entry["inputs"] or outputs != entry["outputs"]:
        raise ManifestError(
            f"{where} takes {inputs} and gives {outputs}; the manifest lists {entry['inputs']} -> {entry['outputs']}"
        )
    want = expected_shapes(manifest)
    for value in list(session.get_inputs()) + list(session.get_outputs()):
        if value.name not in want or value.shape is None:
            continue
        dims = [d if isinstance(d, int) else None for d in value.shape]  # (a named or unknown dimension: None)
        shape = want[value.name]
        if len(dims) != len(shape) or any(d != s for d, s in zip(dims, shape, strict=True) if None not in (d, s)):
            shown, implied = (["?" if d is None else d for d in x] for x in (dims, shape))
            raise ManifestError(
                f"{where}: {value.name} has shape {shown}, the manifest implies {implied} "
                f"(hidden {manifest['hidden']}, num_actions {manifest['num_actions']})"
            )
    props = dict(session.get_modelmeta().custom_metadata_map)
    for key, field in ((META_MODEL, "model_config"), (META_TASK, "task")):
        if key not in props:  # (an export from before the metadata: its shapes are all there is)
            continue
        try:
            recorded = json.loads(props[key])
        except (ValueError, RecursionError):
            recorded = None
        # a field a manifest older than it lacks reads as the value it had before the field existed
        claimed = {**(LATER_MODEL_FIELDS if field == "model_config" else {}), **manifest[field]}
        if not isinstance(recorded, dict):
            raise ManifestError(f"{where}: its metadata {key} is not a JSON object")
        for name in sorted(set(recorded) | set(claimed)):
            if recorded.get(name) != claimed.get(name):
                raise ManifestError(
                    f"{where} was exported with {field}.{name} {recorded.get(name)!r}; "
                    f"the manifest says {claimed.get(name)!r}"
                )
