"""Rerun recordings of rollouts (``swarm eval --record``, ``swarm execute --record``).

``RolloutRecorder`` is only built when recording is asked for; the rollout loops
call it through ``if recorder is not None``, so nothing here runs (or is even
imported) on the hot path otherwise. Works with torch or numpy envs and never
imports torch itself.

Entity paths, per drawn env b (the first ``max_envs_drawn``), timeline "step":
    env_b/arena        the [-1, 1]^2 box (static)
    env_b/landmarks    Points2D [L]
    env_b/targets      Points2D [M]    where the task wants the agents
    env_b/assignment   LineStrips2D    agent -> its target in the optimal assignment
    env_b/agents       Points2D [M]    coloured by id, labelled with the id
    env_b/trails       LineStrips2D    the last few positions of each agent
    env_b/comm         LineStrips2D    the communication graph of the step (undirected i-j)
    env_b/comm_range   LineStrips2D    under RC, the communication radius round each agent
    env_b/attention    LineStrips2D    last-round attention i <- j, alpha = weight (when given)
    env_b/reward       Scalars         team reward of the step that led to this state
    env_b/matched_dist_mean  Scalars   mean matched distance d*_i
    env_b/episode/{success,length,dist}  Scalars at the step the env's first episode ended
    all/reward_mean, all/success_rate    Scalars over all B envs
"""

from __future__ import annotations

import os

import numpy as np
import rerun as rr

# tab10, RGB
PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    dtype=np.uint8,
)
LANDMARK_COLOR = (90, 90, 90)
TARGET_COLOR = (0, 0, 0)
EDGE_COLOR = (150, 150, 220, 140)
ARENA_HALF_SIZE = 1.0


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


TRAIL = 6  # steps of trail drawn behind each agent
MAX_TRAILS = 20  # larger teams are drawn as points (no trails, labels or radius circles)


def _circle(center: np.ndarray, radius: float, n: int = 48) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n)
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], axis=1)


def _edges(adj: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """adj [M, M] bool, pos [M, 2] -> segments [E, 2, 2] of the undirected graph, no self loops."""
    sym = np.triu(adj | adj.T, k=1)
    i, j = np.nonzero(sym)
    return np.stack([pos[i], pos[j]], axis=1)


def layout(num_drawn: int):
    """The viewer layout sent with every recording: one 2D view per recorded environment
    in a grid (never overlaid), the arena's bounds fixed, and below them the team reward
    and success rate on the step timeline."""
    import rerun.blueprint as rrb

    bounds = rrb.VisualBounds2D(x_range=[-1.2, 1.2], y_range=[-1.2, 1.2])
    views = [rrb.Spatial2DView(origin=f"env_{b}", name=f"env {b}", visual_bounds=bounds) for b in range(num_drawn)]
    contents = ["+ /all/**"] + [f"+ /env_{b}/{x}" for b in range(num_drawn) for x in ("reward", "matched_dist_mean")]
    plots = rrb.TimeSeriesView(
        origin="/", contents=contents, name="team reward and success rate; per env: reward, mean matched distance"
    )
    if not views:
        return rrb.Blueprint(plots, collapse_panels=True)
    grid = rrb.Grid(*views, grid_columns=max(1, int(np.ceil(np.sqrt(num_drawn)))))
    return rrb.Blueprint(rrb.Vertical(grid, plots, row_shares=[4, 1]), collapse_panels=True)


class RolloutRecorder:
    """Writes one .rrd file of a batched rollout; draw the first ``max_envs_drawn`` envs."""

    def __init__(
        self,
        path: str,
        task: str,
        num_envs: int,
        num_agents: int,
        max_envs_drawn: int = 8,
        app_id: str = "taichi_swarm",
        comm_radius: float | None = None,
    ):
        from taichi_swarm.tasks import TASK_SPECS

        self.path = path
        self.task = task
        self.num_envs, self.num_agents = int(num_envs), int(num_agents)
        self.drawn = max(0, min(int(max_envs_drawn), self.num_envs))
        spec = TASK_SPECS[task]
        self.agent_radius, self.landmark_radius = spec.agent_radius, spec.landmark_radius
        self.rec = rr.RecordingStream(app_id)
        self.rec.set_log_time_enabled(False)  # no wall clock: the same rollout gives the same data
        # written beside the target and moved there by close(): a run that fails or is killed
        # never leaves a truncated recording, nor replaces a good one
        self._partial = os.path.join(os.path.dirname(os.path.abspath(path)), f".tmp-{os.path.basename(path)}")
        try:
            self.rec.save(self._partial, default_blueprint=layout(self.drawn))
        except RuntimeError as exc:  # Rerun's own error (a path it cannot create): one line, nothing left
            self._remove_partial()
            raise OSError(f"cannot write the recording {path}: {exc}") from None
        self._ended = np.zeros(self.num_envs, bool)  # first episode of the env is over: stop drawing it
        self._successes: list[bool] = []
        self.colors = PALETTE[np.arange(self.num_agents) % len(PALETTE)]  # [M, 3]
        self.labels = [str(i) for i in range(self.num_agents)]
        self.comm_radius = comm_radius  # drawn as a circle round each agent (RC)
        self._trail: list[list[np.ndarray]] = [[] for _ in range(self.drawn)]  # last TRAIL positions
        self._arena = ARENA_HALF_SIZE  # the half side drawn (the env's, from the first step)
        for b in range(self.drawn):
            self.rec.log(
                f"env_{b}/arena",
                rr.Boxes2D(centers=[0.0, 0.0], half_sizes=[ARENA_HALF_SIZE] * 2, colors=[(60, 60, 60)]),
                static=True,
            )
            self.rec.log(f"env_{b}", rr.TextDocument(f"{task}, M={num_agents}, env {b}"), static=True)

    def log_step(self, step: int, env, actions, attention=None) -> None:
        """The state the agents act on at ``step`` (before ``env.step(actions)``); actions [B, M]."""
        rec = self.rec
        rec.set_time("step", sequence=int(step))
        reward = to_numpy(env.reward).astype(np.float64)  # [B]
        rec.log("all/reward_mean", rr.Scalars(float(reward.mean())))
        D = self.drawn
        if D == 0:
            return
        half = float(getattr(env, "arena", ARENA_HALF_SIZE))  # scale="density" grows the arena
        if half != self._arena:
            self._arena = half
            for b in range(D):
                box = rr.Boxes2D(centers=[0.0, 0.0], half_sizes=[half] * 2, colors=[(60, 60, 60)])
                rec.log(f"env_{b}/arena", box, static=True)
        swarm = self.num_agents > MAX_TRAILS  # a swarm reads better as points: no trails, labels or circles
        state = env.get_state()
        pos = to_numpy(state["pos"])[:D]  # [D, M, 2]
        landmarks = to_numpy(state["landmarks"])[:D]  # [D, L, 2]
        # copies: Rerun may encode arrays after log() returns, and these are views of the
        # env's buffers, which the next step overwrites (an auto-reset env's new targets)
        targets = to_numpy(env.targets)[:D].copy()  # [D, M, 2]
        adj = comm_graph(env.obs, D)  # [D, M, M]
        acts = to_numpy(actions)[:D].copy()  # [D, M]
        att = None if attention is None else to_numpy(attention)[:D].copy()  # [D, M, M]
        assign = to_numpy(env.assignment)[:D].copy() if hasattr(env, "assignment") else None  # [D, M]
        matched = to_numpy(env.matched_dist)[:D].copy() if hasattr(env, "matched_dist") else None  # [D, M]
        for b in range(D):
            if self._ended[b]:
                continue
            p = f"env_{b}"
            if not swarm:
                trail = self._trail[b]
                trail.append(pos[b].copy())
                del trail[:-TRAIL]
                strips = np.stack(trail, axis=1)  # [M, S, 2]
                rec.log(f"{p}/trails", rr.LineStrips2D(list(strips), colors=self.colors, radii=0.003))
            if assign is not None:
                lines = np.stack([pos[b], targets[b][assign[b]]], axis=1)  # agent -> its target
                rec.log(f"{p}/assignment", rr.LineStrips2D(lines, colors=(40, 40, 40, 120), radii=0.002))
            if matched is not None:
                rec.log(f"{p}/matched_dist_mean", rr.Scalars(float(matched[b].mean())))
            if self.comm_radius is not None and not swarm:  # RC: each agent's communication range
                circles = [_circle(q, self.comm_radius) for q in pos[b]]
                rec.log(f"{p}/comm_range", rr.LineStrips2D(circles, colors=(150, 150, 220, 60), radii=0.002))
            rec.log(f"{p}/landmarks", rr.Points2D(landmarks[b], radii=self.landmark_radius, colors=LANDMARK_COLOR))
            rec.log(f"{p}/targets", rr.Points2D(targets[b], radii=0.015, colors=TARGET_COLOR))
            rec.log(
                f"{p}/agents",
                rr.Points2D(
                    pos[b],
                    radii=self.agent_radius,
                    colors=self.colors,
                    labels=None if swarm else [f"{i}:{int(a)}" for i, a in enumerate(acts[b])],
                    class_ids=np.arange(self.num_agents),
                ),
            )
            rec.log(f"{p}/comm", rr.LineStrips2D(_edges(adj[b], pos[b]), colors=EDGE_COLOR, radii=0.004))
            if att is not None:
                i, j = np.nonzero(att[b] > 1e-3 * (1 - np.eye(self.num_agents)))
                keep = i != j
                i, j = i[keep], j[keep]
                alpha = np.clip(att[b][i, j] * 255, 0, 255).astype(np.uint8)
                colors = np.concatenate([self.colors[i], alpha[:, None]], axis=1)
                rec.log(
                    f"{p}/attention",
                    rr.LineStrips2D(np.stack([pos[b][j], pos[b][i]], axis=1), colors=colors, radii=0.008),
                )
            rec.log(f"{p}/reward", rr.Scalars(float(reward[b])))

    def log_episode_ends(self, step: int, mask: np.ndarray, episode_info: dict) -> None:
        """Envs in ``mask`` [B] bool just ended their first episode; ``episode_info`` holds
        success/length/dist [B] (valid where mask)."""
        rec = self.rec
        rec.set_time("step", sequence=int(step))
        mask = to_numpy(mask).astype(bool)
        success = to_numpy(episode_info["success"]).astype(bool)
        length = to_numpy(episode_info["length"])
        dist = to_numpy(episode_info["dist"]) if "dist" in episode_info else None
        for b in np.flatnonzero(mask):
            if self._ended[b]:
                continue
            self._ended[b] = True
            self._successes.append(bool(success[b]))
            if b < self.drawn:
                p = f"env_{b}"
                rec.log(f"{p}/episode/success", rr.Scalars(float(success[b])))
                rec.log(f"{p}/episode/length", rr.Scalars(float(length[b])))
                if dist is not None:
                    rec.log(f"{p}/episode/dist", rr.Scalars(float(dist[b])))
                # no Clear: the env's last state stays on screen (frozen) once its episode ended
        rec.log("all/success_rate", rr.Scalars(float(np.mean(self._successes))))

    def close(self, ok: bool = True) -> None:
        """Flush and close the file; it replaces ``path`` only if ``ok`` (else it is removed);
        a write that fails (a full disk) removes it too and raises OSError."""
        try:
            self.rec.flush()
            if hasattr(self.rec, "disconnect"):
                self.rec.disconnect()
            if ok:
                os.replace(self._partial, self.path)
        except (OSError, RuntimeError) as exc:
            self._remove_partial()
            if ok:
                raise OSError(f"cannot write the recording {self.path}: {exc}") from None
        finally:
            if not ok:
                self._remove_partial()

    def _remove_partial(self) -> None:
        if os.path.exists(self._partial):
            os.unlink(self._partial)
