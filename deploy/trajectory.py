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
import os
import zipfile
from dataclasses import dataclass

import numpy as np

FORMAT = "taichi-swarm trajectory"
SCHEMA = 1
SUFFIX = ".npz"
PER_STEP = ("pos", "vel", "landmarks", "targets", "actions", "arena", "reward")
OPTIONAL = ("assignment", "matched_dist")


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
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise TrajectoryError(
                f"cannot read {path} as a trajectory record (.npz written by --record): {exc}"
            ) from None
        try:
            header = json.loads(str(arrays.pop("header")))
            assert isinstance(header, dict) and header.get("format") == FORMAT
        except (KeyError, ValueError, AssertionError):
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
        T = len(arrays["step"])
        D, M, B = (int(header.get(k, -1)) for k in ("drawn", "agents", "envs"))
        bad = [k for k in PER_STEP if len(arrays[k]) != T]
        bad += [k for k in ("pos", "vel") if arrays[k].shape[1:] != (D, M, 2)]
        bad += [k for k in ("end_step", "success", "length", "dist") if arrays[k].shape != (B,)]
        bad += [k for k in ("graph_offsets",) if arrays[k].shape != (T + 1,)]
        bad += [k for k in ("end_pos",) if k in arrays and arrays[k].shape != (D, M, 2)]
        if T == 0 or bad:
            raise TrajectoryError(
                f"{path}: the trajectory record's arrays do not fit its header ({', '.join(bad) or 'no steps'})"
            )
        return cls(header, arrays)


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
