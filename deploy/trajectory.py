"""The trajectory record: a rollout recorded once, as per-step state (``--record FILE.npz``).

``TrajectoryRecorder`` is the one recorder the rollout loops feed (``log_step`` /
``log_episode_ends``, see ``taichi_swarm.metrics.run_first_episodes``); the Rerun
recording (deploy/recording.py) and the GIF/MP4 (deploy/video.py) are both rendered from
the ``Trajectory`` it collects, and ``swarm replay FILE.npz`` loads the same record. Neither
torch, Rerun nor matplotlib is imported here.

The file is an .npz (numpy's zip of arrays, read without pickle), written atomically:
    header                  JSON text: format, schema, task, agents M, envs B, drawn D, comm,
                            comm_radius, attention (bool)
    step [T]                the step each state was logged at (the state the agents act on)
    pos, vel [T, D, M, 2]   of the first D (drawn) environments
    landmarks [T, D, L, 2], targets [T, D, N, 2], actions [T, D, M], arena [T] (half side)
    reward [T, B]           team reward of the step that led to this state, every env
    assignment, matched_dist [T, D, M]   where the task has them
    graph_index [E, 3], graph_offsets [T + 1]
                            the communication graph (i hears j) as (b, i, j) rows, step t's
                            rows graph_index[graph_offsets[t]:graph_offsets[t + 1]]
    attention_index [A, 3], attention_weights [A], attention_offsets [T + 1]
                            last-round attention i <- j, the same way (only with attention)
    end_step, success, length, dist [B]  each env's first episode (end_step -1: it did not end)
    end_pos [D, M, 2]       where the drawn envs' agents stood when their first episode ended
                            (the env restarts inside that step, so no logged state holds it;
                            NaN where it did not end; absent from older records)
"""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass

import numpy as np

FORMAT = "taichi-swarm trajectory"
SCHEMA = 1
SUFFIX = ".npz"
PER_STEP = ("pos", "vel", "landmarks", "targets", "actions", "arena", "reward")
OPTIONAL = ("assignment", "matched_dist")
MAX_ACTIONS = 9  # the fine action space's (taichi_swarm.physics.NUM_FINE_ACTIONS); the paper's is 5


class TrajectoryError(ValueError):
    """A file that is not a trajectory record this version can read."""


def to_numpy(x) -> np.ndarray:
    """torch tensor (any device) or array-like -> numpy array."""
    if hasattr(x, "cpu"):
        x = x.cpu()
    return np.asarray(x)


def comm_graph(obs: dict, D: int) -> np.ndarray:
    """The communication graph of the first ``D`` envs as [D, M, M] bool (i hears j), from
    ``obs["adj"]`` or from the neighbour lists (``obs["nbr"]``, ``obs["nbr_mask"]``)."""
    if "adj" in obs:
        return to_numpy(obs["adj"])[:D].astype(bool)  # (astype copies)
    nbr, mask = to_numpy(obs["nbr"])[:D].astype(np.int64), to_numpy(obs["nbr_mask"])[:D].astype(bool)
    D, M, _ = nbr.shape
    adj = np.zeros((D, M, M), bool)
    adj[:, np.arange(M), np.arange(M)] = True
    d, i, k = np.nonzero(mask & (nbr >= 0) & (nbr < M))
    adj[d, i, nbr[d, i, k]] = True
    return adj


def _sparse(mats: list[np.ndarray | None]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step [D, M, M] (None: nothing) -> (index [E, 3] int32 of (b, i, j), values [E], offsets [T + 1]):
    a swarm's graph has O(M K) edges, not M^2 cells."""
    index, values, offsets = [], [], [0]
    for m in mats:
        if m is not None:
            nz = np.nonzero(m)
            index.append(np.stack(nz, axis=1).astype(np.int32))
            values.append(m[nz].astype(np.float32))
        offsets.append(offsets[-1] + (0 if m is None else len(index[-1])))
    if not index:
        return np.zeros((0, 3), np.int32), np.zeros(0, np.float32), np.asarray(offsets, np.int64)
    return np.concatenate(index), np.concatenate(values), np.asarray(offsets, np.int64)


@dataclass
class Trajectory:
    header: dict
    arrays: dict[str, np.ndarray]

    @property
    def num_steps(self) -> int:
        return len(self.arrays["step"])

    @property
    def drawn(self) -> int:
        return int(self.header["drawn"])

    @property
    def comm_radius(self) -> float | None:
        """The radius drawn round each agent: under "rc" only."""
        return float(self.header["comm_radius"]) if self.header["comm"] == "rc" else None

    def live(self, t: int) -> np.ndarray:
        """[D] bool: the drawn envs whose first episode had not ended at step t."""
        end = self.arrays["end_step"][: self.drawn]
        return (end < 0) | (self.arrays["step"][t] < end)

    def _dense(self, name: str, t: int, dtype) -> np.ndarray:
        a = self.arrays
        lo, hi = a[f"{name}_offsets"][t], a[f"{name}_offsets"][t + 1]
        M = int(self.header["agents"])
        out = np.zeros((self.drawn, M, M), dtype)
        b, i, j = a[f"{name}_index"][lo:hi].T
        out[b, i, j] = True if name == "graph" else a["attention_weights"][lo:hi]
        return out

    def adj(self, t: int) -> np.ndarray:
        """[D, M, M] bool: i hears j at step t."""
        return self._dense("graph", t, bool)

    def attention(self, t: int) -> np.ndarray | None:
        """[D, M, M] float32 last-round attention at step t, or None if not recorded."""
        return self._dense("attention", t, np.float32) if self.header["attention"] else None

    def outcomes(self) -> dict[int, str]:
        """Drawn env -> "success at step T" / "failed at step T", for those whose episode ended."""
        a = self.arrays
        return {
            b: f"{'success' if a['success'][b] else 'failed'} at step {int(a['length'][b])}"
            for b in range(self.drawn)
            if a["end_step"][b] >= 0
        }

    def save(self, path: str) -> None:
        """Write ``path`` atomically: a temp file beside it, then os.replace (a failed or killed
        run never leaves a truncated record, nor replaces a good one)."""
        tmp = os.path.join(os.path.dirname(os.path.abspath(path)), f".tmp-{os.path.basename(path)}")
        try:
            with open(tmp, "wb") as f:  # a file object: savez would append .npz to the temp name
                np.savez_compressed(f, header=np.array(json.dumps(self.header)), **self.arrays)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path: str) -> Trajectory:
        """Read a record ``save`` wrote; TrajectoryError (one line) for anything else."""
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
            raise TrajectoryError(
                f"cannot read {path} as a trajectory record (.npz written by --record): {exc}"
            ) from None
        try:
            header = json.loads(str(arrays.pop("header")))
            assert isinstance(header, dict) and header.get("format") == FORMAT
        except (KeyError, ValueError, AssertionError, RecursionError):
            raise TrajectoryError(f"{path} is an .npz but not a taichi-swarm trajectory record (no header)") from None
        if header.get("schema") != SCHEMA:
            raise TrajectoryError(
                f"{path} is a trajectory record of schema {header.get('schema')}; this taichi-swarm reads schema "
                f"{SCHEMA}: record it again with this version"
            )
        need = ("step", *PER_STEP, "graph_index", "graph_offsets", "end_step", "success", "length", "dist")
        if header.get("attention"):
            need += ("attention_index", "attention_weights", "attention_offsets")
        missing = [k for k in need if k not in arrays]
        if missing:
            raise TrajectoryError(
                f"{path}: the trajectory record lacks {', '.join(missing)} (a truncated or edited file)"
            )
        problem = check_record(header, arrays)
        if problem:  # checked as a whole here, so no renderer meets an index out of range or a NaN
            raise TrajectoryError(f"{path}: not a valid trajectory record: {problem}")
        return cls(header, arrays)


def _int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _check_header(h: dict) -> str:
    """What is wrong with a record's header ("" if nothing)."""
    from taichi_swarm import COMMS, TASKS

    if h.get("task") not in TASKS:
        return f"header task {h.get('task')!r} is not one of {list(TASKS)}"
    for key in ("agents", "envs", "drawn"):
        if not _int(h.get(key)) or h[key] < 1:
            return f"header {key} {h.get(key)!r} is not an integer >= 1"
    if h["drawn"] > h["envs"]:
        return f"header drawn {h['drawn']} exceeds envs {h['envs']}"
    if h.get("comm") not in COMMS:
        return f"header comm {h.get('comm')!r} is not one of {list(COMMS)}"
    radius = h.get("comm_radius")
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not math.isfinite(radius) or radius < 0:
        return f"header comm_radius {radius!r} is not a finite number >= 0"
    if not isinstance(h.get("attention", False), bool):
        return f"header attention {h.get('attention')!r} is not true or false"
    return ""


def _check_sparse(name: str, a: dict, T: int, D: int, M: int) -> str:
    """``{name}_index`` [E, 3] rows (b, i, j) in range, ``{name}_offsets`` [T + 1] from 0 to E,
    never decreasing."""
    index, offsets = a[f"{name}_index"], a[f"{name}_offsets"]
    if offsets.shape != (T + 1,) or offsets.dtype.kind not in "iu":
        return f"{name}_offsets has shape {offsets.shape} ({offsets.dtype}), expected ({T + 1},) integers"
    if index.ndim != 2 or index.shape[1] != 3 or index.dtype.kind not in "iu":
        return f"{name}_index has shape {index.shape} ({index.dtype}), expected (E, 3) integers"
    if offsets[0] != 0 or offsets[-1] != len(index) or (np.diff(offsets) < 0).any():
        return f"{name}_offsets must rise from 0 to {len(index)} (the rows of {name}_index), never decreasing"
    for col, (what, n) in enumerate((("env", D), ("agent i", M), ("agent j", M))):
        if len(index) and (index[:, col].min() < 0 or index[:, col].max() >= n):
            return f"{name}_index holds an {what} index outside 0..{n - 1}"
    return ""


def check_record(header: dict, a: dict) -> str:
    """What is wrong with a record (header and arrays, as ``Trajectory.load`` reads them),
    one line, naming the field; "" if nothing: every index in range, offsets monotone,
    positions finite, counts and shapes consistent with the header and with each other."""
    from taichi_swarm import TASK_SPECS

    problem = _check_header(header)
    if problem:
        return problem
    T = len(a["step"])
    D, M, B = header["drawn"], header["agents"], header["envs"]
    if T == 0:
        return "no steps"
    if "steps" in header and header["steps"] != T:
        return f"header steps {header['steps']!r}, but {T} steps recorded"
    spec = TASK_SPECS[header["task"]]
    L = {spec.num_landmarks(M), spec.num_landmarks(M, listed=True)}
    shapes = {
        "step": ((T,), "iu"),
        "pos": ((T, D, M, 2), "f"),
        "vel": ((T, D, M, 2), "f"),
        "targets": ((T, D, M, 2), "f"),
        "actions": ((T, D, M), "iu"),
        "arena": ((T,), "f"),
        "reward": ((T, B), "f"),
        "assignment": ((T, D, M), "iu"),
        "matched_dist": ((T, D, M), "f"),
        "end_step": ((B,), "iu"),
        "success": ((B,), "b"),
        "length": ((B,), "iu"),
        "dist": ((B,), "f"),
        "end_pos": ((D, M, 2), "f"),
    }
    for name, (shape, kinds) in shapes.items():
        if name in a and (a[name].shape != shape or a[name].dtype.kind not in kinds):
            kind = {"iu": "integers", "f": "floats", "b": "booleans"}[kinds]
            return f"{name} has shape {a[name].shape} ({a[name].dtype}), expected {shape} {kind}"
    lm = a["landmarks"]
    if lm.ndim != 4 or lm.shape[:2] != (T, D) or lm.shape[2] not in L or lm.shape[3] != 2 or lm.dtype.kind != "f":
        return f"landmarks has shape {lm.shape} ({lm.dtype}), expected ({T}, {D}, L, 2) floats, L in {sorted(L)}"
    for name in ("pos", "vel", "landmarks", "targets", "reward"):
        if not np.isfinite(a[name]).all():
            return f"{name} holds NaN or inf"
    if (np.diff(a["step"]) <= 0).any() or a["step"][0] < 0:
        return "step must rise from >= 0, one entry per logged state"
    if not (np.isfinite(a["arena"]).all() and (a["arena"] > 0).all()):
        return "arena (the half side) must be finite and > 0 at every step"
    if a["actions"].min() < 0 or a["actions"].max() >= MAX_ACTIONS:
        return f"actions must lie in 0..{MAX_ACTIONS - 1}"
    if "assignment" in a and (a["assignment"].min() < -1 or a["assignment"].max() >= M):
        return f"assignment must lie in -1..{M - 1} (a target index, -1: none)"
    end, first, last = a["end_step"], int(a["step"][0]), int(a["step"][-1])
    if ((end != -1) & ((end <= first) | (end > last + 1))).any():
        return f"end_step must be -1 (not ended) or in {first + 1}..{last + 1}, the steps recorded"
    if (a["length"] < 0).any():
        return "length holds a negative episode length"
    for name in ("dist", "end_pos"):  # NaN where an episode did not end (or its task has no DIST)
        if name in a and np.isinf(a[name]).any():
            return f"{name} holds inf"
    if "end_pos" in a:
        nan = np.isnan(a["end_pos"]).reshape(D, -1)
        if (nan.any(1) & ~nan.all(1)).any():  # a drawn env's end is known for every agent or for none
            return "end_pos holds NaN for some agents of an env and not for others"
    for name in ("graph", "attention") if header.get("attention") else ("graph",):
        problem = _check_sparse(name, a, T, D, M)
        if problem:
            return problem
    if header.get("attention"):
        w = a["attention_weights"]
        if w.shape != a["attention_index"].shape[:1] or w.dtype.kind != "f":
            return f"attention_weights has shape {w.shape}, expected one per attention_index row"
        if not (np.isfinite(w).all() and (w >= 0).all() and (w <= 1 + 1e-5).all()):
            return "attention_weights must lie in 0..1"
    return ""


class TrajectoryRecorder:
    """Collects the state of the first ``num_drawn`` envs at every step (and every env's
    reward and first-episode outcome); ``trajectory()`` is the record."""

    def __init__(self, task: str, num_envs: int, num_agents: int, num_drawn: int = 4, comm="uc", comm_radius=1.0):
        self.num_envs, self.num_agents = int(num_envs), int(num_agents)
        self.drawn = max(1, min(int(num_drawn), self.num_envs))
        self.header = {
            "format": FORMAT,
            "schema": SCHEMA,
            "task": task,
            "agents": self.num_agents,
            "envs": self.num_envs,
            "drawn": self.drawn,
            "comm": comm,
            "comm_radius": float(comm_radius),
        }
        self.steps: list[dict] = []
        self.graphs: list[np.ndarray] = []
        self.attention: list[np.ndarray | None] = []
        self.end_step = np.full(self.num_envs, -1, np.int32)
        self.success = np.zeros(self.num_envs, bool)
        self.length = np.zeros(self.num_envs, np.int32)
        self.dist = np.full(self.num_envs, np.nan, np.float32)
        self.end_pos = np.full((self.drawn, self.num_agents, 2), np.nan, np.float32)

    def log_step(self, step: int, env, actions=None, attention=None) -> None:
        """The state the agents act on at ``step`` (before ``env.step(actions)``); actions [B, M]."""
        D, M = self.drawn, self.num_agents
        state = env.get_state()
        # copies: these are views of the env's buffers, which the next step overwrites
        row = {
            "step": int(step),
            "pos": to_numpy(state["pos"])[:D].astype(np.float32),
            "vel": to_numpy(state["vel"])[:D].astype(np.float32),
            "landmarks": to_numpy(state["landmarks"])[:D].astype(np.float32),
            "targets": to_numpy(env.targets)[:D].astype(np.float32),
            "actions": np.zeros((D, M), np.int8) if actions is None else to_numpy(actions)[:D].astype(np.int8),
            "arena": float(getattr(env, "arena", 1.0)),  # half side (scale="density" grows it)
            "reward": to_numpy(env.reward).astype(np.float32),
        }
        for name in OPTIONAL:
            if hasattr(env, name):
                row[name] = to_numpy(getattr(env, name))[:D].copy()
        self.steps.append(row)
        self.graphs.append(comm_graph(env.obs, D))
        self.attention.append(None if attention is None else to_numpy(attention)[:D].astype(np.float32))

    def log_episode_ends(self, step: int, mask, episode_info: dict, terminal_pos=None) -> None:
        """Envs in ``mask`` [B] just ended their first episode; success/length/dist [B] (valid where mask);
        ``terminal_pos`` [B, M, 2]: where their agents stood at the end (the env has restarted them)."""
        new = to_numpy(mask).astype(bool) & (self.end_step < 0)
        if terminal_pos is not None:
            drawn = new[: self.drawn]
            self.end_pos[drawn] = to_numpy(terminal_pos)[: self.drawn][drawn].astype(np.float32)
        self.end_step[new] = int(step)
        self.success[new] = to_numpy(episode_info["success"]).astype(bool)[new]
        self.length[new] = to_numpy(episode_info["length"])[new]
        if "dist" in episode_info:
            self.dist[new] = to_numpy(episode_info["dist"])[new]

    def trajectory(self) -> Trajectory:
        if not self.steps:
            raise ValueError("nothing to record: no steps were logged")
        arrays = {"step": np.array([s["step"] for s in self.steps], np.int32)}
        for name in (*PER_STEP, *OPTIONAL):
            if name in self.steps[0]:
                arrays[name] = np.stack([np.asarray(s[name]) for s in self.steps])
        arrays["graph_index"], _, arrays["graph_offsets"] = _sparse(self.graphs)
        has_attention = any(a is not None for a in self.attention)
        if has_attention:  # nonzero only where a message arrived (and on the diagonal): sparse too
            arrays["attention_index"], arrays["attention_weights"], arrays["attention_offsets"] = _sparse(
                self.attention
            )
        arrays.update(
            end_step=self.end_step, success=self.success, length=self.length, dist=self.dist, end_pos=self.end_pos
        )
        return Trajectory({**self.header, "attention": has_attention, "steps": len(self.steps)}, arrays)
