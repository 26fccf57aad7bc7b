"""An exported policy, torch-free: the export directory read once and verified
(``ExportedModel``: its manifest, checked against itself and against the ONNX graphs, and the
bytes of every piece), and its ONNX pieces as onnxruntime sessions (``Pieces``). Both the
in-process executor (deploy/executor.py, ``swarm execute``) and each networked agent
(deploy/net/agent.py, ``swarm agent``) run a policy through these; neither imports torch.
"""

from __future__ import annotations

import hashlib
import os

import numpy as np
import onnxruntime as ort

from deploy.manifest import FORMAT, MANIFEST, ManifestError, check_onnx, edge_position, parse, validate
from taichi_swarm.files import MAX_ONNX_BYTES, InputFileError, read_input


class DeployError(ValueError):
    """An export directory, its manifest or the requested setting does not fit."""


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class ExportedModel:
    """An export directory, read once and verified: manifest plus the bytes of every .onnx file."""

    def __init__(self, directory: str):
        if not os.path.exists(directory):
            raise DeployError(f"export directory {directory} does not exist (run `swarm export CKPT --out DIR`)")
        if not os.path.isdir(directory):
            raise DeployError(f"{directory} is not a directory (pass the folder `swarm export` wrote)")
        path = os.path.join(directory, MANIFEST)
        if not os.path.exists(path):
            raise DeployError(f"{directory} has no {MANIFEST}: not a `swarm export` directory")
        try:  # a regular file of bounded size: a FIFO would block, /dev/zero fill the memory
            manifest = parse(read_input(path, "manifest"), path)  # (at most MAX_DEPTH deep)
        except (InputFileError, ManifestError) as exc:
            raise DeployError(str(exc)) from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise DeployError(f"{path} is not a taichi-swarm ONNX manifest")
        try:
            validate(manifest, path)
        except ManifestError as exc:
            raise DeployError(str(exc)) from None
        self.directory = directory
        self.manifest = manifest
        self.rounds: int = int(manifest["rounds"])
        self.hidden: int = int(manifest["hidden"])
        self.entity_mode: str = manifest["entity_mode"]
        self.edge_position: str = edge_position(manifest)
        self.task: dict = manifest["task"]
        self.models: dict[str, bytes] = {}
        self.sessions: dict = {}  # what the pieces run, on one thread
        files = {name: os.path.join(directory, entry["file"]) for name, entry in manifest["files"].items()}
        missing = [f for f in files.values() if not os.path.exists(f)]
        if missing:
            raise DeployError(f"{', '.join(missing)} missing (listed in {MANIFEST}): export again")
        for name, entry in manifest["files"].items():
            file = files[name]
            try:
                data = read_input(file, "ONNX model", MAX_ONNX_BYTES)
            except InputFileError as exc:
                raise DeployError(str(exc)) from None
            if _sha256(data) != entry["sha256"]:
                raise DeployError(
                    f"{file} does not match the sha256 in {MANIFEST}: the file is corrupted or "
                    "was changed after export; export again"
                )
            try:
                session = new_session(data)
            except Exception as exc:  # noqa: BLE001 - random bytes, truncated protobuf
                raise DeployError(f"{file} is not a readable ONNX model ({type(exc).__name__})") from None
            try:
                check_onnx(manifest, name, session, file)
            except ManifestError as exc:
                raise DeployError(str(exc)) from None
            self.models[name] = data
            if name in self.pieces():  # kept for Pieces (one thread); the others were checked only
                self.sessions[name] = session
            del session

    def pieces(self) -> tuple[str, ...]:
        """The ONNX pieces this network runs: encode, a round for each round before the last, then
        the last round with the heads (no rounds: the heads alone)."""
        return ("encode", *(("round",) if self.rounds > 1 else ()), "round_heads" if self.rounds >= 1 else "heads")

    def check_landmarks(self, task: str, num_landmarks: int) -> None:
        """Raise DeployError if this network cannot take ``num_landmarks`` landmark offsets."""
        if self.entity_mode == "concat" and num_landmarks != self.manifest["num_landmarks"]:
            raise DeployError(
                f"this model concatenates {self.manifest['num_landmarks']} landmark offsets (entity_mode 'concat', "
                f"trained on {self.task.get('task')!r}); task {task!r} has {num_landmarks} landmarks"
            )
        if self.entity_mode == "padded" and num_landmarks > int(self.manifest["max_landmarks"]):
            raise DeployError(
                f"this model holds at most {self.manifest['max_landmarks']} landmarks "
                f"(entity_mode 'padded'); task {task!r} has {num_landmarks}"
            )


def new_session(data: bytes, threads: int = 1) -> ort.InferenceSession:
    return ort.InferenceSession(data, session_options(threads), providers=["CPUExecutionProvider"])


def session_options(threads: int = 1) -> ort.SessionOptions:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    return opts


class Pieces:
    """The exported ONNX pieces, one onnxruntime session each. Sessions hold only weights, so
    they are stateless functions of the arrays passed in: one ``Pieces`` serves every agent of
    every environment (``Executor``), or the one agent of a process (``swarm agent``); an agent's
    state (h, its message) lives in the caller's arrays, and what it computes from is its own."""

    def __init__(self, model: ExportedModel, threads: int = 1):
        self.rounds = model.rounds
        self.relative = model.edge_position == "relative"

        def session(name):
            return model.sessions[name] if threads == 1 else new_session(model.models[name], threads)

        self._encode = session("encode")
        self._round = session("round") if self.rounds > 1 else None
        self._final = session("round_heads" if self.rounds >= 1 else "heads")
        self._encode_out = ["h", "message"]
        self._round_out = ["h_out", "message"]  # fetch only what is used: each output costs a copy

    def encode(self, self_obs: np.ndarray, entities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """self_obs [4], entities [L, 2] -> (h [H], the first message [2, H])."""
        return self._encode.run(self._encode_out, {"self_obs": self_obs, "entities": entities})

    def _heard(self, h, heard, offsets) -> dict:
        return {"h": h, "heard": heard, "offsets": offsets} if self.relative else {"h": h, "heard": heard}

    def round(self, h: np.ndarray, heard: np.ndarray, offsets: np.ndarray | None = None):
        """A round that is not the last: h [H], heard [n, 2, H] (from others; relative edges: their
        senders' offsets [n, 2]) -> (h, next message [2, H])."""
        return self._round.run(self._round_out, self._heard(h, heard, offsets))

    def decide(self, h: np.ndarray, heard: np.ndarray | None, offsets: np.ndarray | None = None):
        """The last round and the heads -> (logits [5], attention weights [n + 1], own first)."""
        if self.rounds == 0:
            logits, _ = self._final.run(None, {"h": h})
            return logits, np.ones(1, np.float32)
        logits, weights = self._final.run(["logits", "weights"], self._heard(h, heard, offsets))
        return logits, weights
