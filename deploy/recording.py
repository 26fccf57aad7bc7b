"""Rerun recordings of rollouts (``--record FILE.rrd``, ``swarm replay FILE.npz``), rendered
from the trajectory record (deploy/trajectory.py) by ``write_rrd``: the rollout is recorded
once, as state; this module only draws it. Never imports torch.

Entity paths, per drawn env b, timeline "step":
    env_b/arena        the arena's box (static; logged again when scale="density" grows it)
    env_b/landmarks    Points2D [L]
    env_b/targets      Points2D [M]    where the task wants the agents
    env_b/assignment   LineStrips2D    agent -> its target in the optimal assignment
    env_b/agents       Points2D [M]    coloured by id, labelled with the id and action
    env_b/trails       LineStrips2D    the last few positions of each agent
    env_b/comm         LineStrips2D    the communication graph of the step (undirected i-j)
    env_b/comm_range   LineStrips2D    under RC, the communication radius round each agent
    env_b/attention    LineStrips2D    last-round attention i <- j, alpha = weight (when recorded)
    env_b/reward       Scalars         team reward of the step that led to this state
    env_b/matched_dist_mean  Scalars   mean matched distance d*_i
    env_b/episode/{success,length,dist}  Scalars at the step the env's first episode ended
    all/reward_mean, all/success_rate    Scalars over all B envs
An env is drawn until its first episode ends; its last state then stays on screen.
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


def write_rrd(traj, path: str, app_id: str = "taichi_swarm") -> None:
    """Render the trajectory record ``traj`` (deploy.trajectory.Trajectory) as a Rerun
    recording at ``path``, written beside it and moved there when complete (a failure never
    leaves a truncated recording, nor replaces a good one); OSError with one line on failure."""
    from taichi_swarm.tasks import TASK_SPECS

    h = traj.header
    task, M, D = h["task"], int(h["agents"]), traj.drawn
    spec = TASK_SPECS[task]
    rec = rr.RecordingStream(app_id)
    rec.set_log_time_enabled(False)  # no wall clock: the same rollout gives the same data
    partial = os.path.join(os.path.dirname(os.path.abspath(path)), f".tmp-{os.path.basename(path)}")
    try:
        rec.save(partial, default_blueprint=layout(D))
        _log(rec, traj, task, M, D, spec)
        rec.flush()
        if hasattr(rec, "disconnect"):
            rec.disconnect()
        os.replace(partial, path)
    except BaseException as exc:  # any failure, a record that does not draw included: no .tmp-* left
        if os.path.exists(partial):
            os.unlink(partial)
        if isinstance(exc, (OSError, RuntimeError)):  # Rerun's own error (a path it cannot create, a full disk)
            raise OSError(f"cannot write the recording {path}: {exc}") from None
        raise


def _log(rec, traj, task: str, M: int, D: int, spec) -> None:
    a = traj.arrays
    colors = PALETTE[np.arange(M) % len(PALETTE)]  # [M, 3]
    swarm = M > MAX_TRAILS  # a swarm reads better as points: no trails, labels or circles
    radius = traj.comm_radius  # drawn as a circle round each agent (RC)
    arena = None
    for b in range(D):
        rec.log(f"env_{b}", rr.TextDocument(f"{task}, M={M}, env {b}"), static=True)
    ends = {}  # step -> the envs whose first episode ended there, in env order
    for b in np.flatnonzero(a["end_step"] >= 0):
        ends.setdefault(int(a["end_step"][b]), []).append(int(b))
    successes: list[bool] = []
    for t in range(traj.num_steps):
        step = int(a["step"][t])
        rec.set_time("step", sequence=step)
        reward = a["reward"][t].astype(np.float64)  # [B]
        rec.log("all/reward_mean", rr.Scalars(float(reward.mean())))
        half = float(a["arena"][t])  # scale="density" grows the arena
        if half != arena:
            arena = half
            for b in range(D):
                box = rr.Boxes2D(centers=[0.0, 0.0], half_sizes=[half] * 2, colors=[(60, 60, 60)])
                rec.log(f"env_{b}/arena", box, static=True)
        live, adj, att = traj.live(t), traj.adj(t), traj.attention(t)
        pos, targets, landmarks = a["pos"][t], a["targets"][t], a["landmarks"][t]
        for b in np.flatnonzero(live):
            p = f"env_{b}"
            if not swarm:
                lo = max(0, t - TRAIL + 1)
                strips = a["pos"][lo : t + 1, b].transpose(1, 0, 2)  # [M, S, 2]: the last TRAIL positions
                rec.log(f"{p}/trails", rr.LineStrips2D(list(strips), colors=colors, radii=0.003))
            if "assignment" in a:
                j = a["assignment"][t, b]
                on = j >= 0  # assignment="nearest": -1 where an agent holds no target
                lines = np.stack([pos[b][on], targets[b][j[on]]], axis=1)  # agent -> its target
                rec.log(f"{p}/assignment", rr.LineStrips2D(lines, colors=(40, 40, 40, 120), radii=0.002))
            if "matched_dist" in a:
                rec.log(f"{p}/matched_dist_mean", rr.Scalars(float(a["matched_dist"][t, b].mean())))
            if radius is not None and not swarm:  # RC: each agent's communication range
                circles = [_circle(q, radius) for q in pos[b]]
                rec.log(f"{p}/comm_range", rr.LineStrips2D(circles, colors=(150, 150, 220, 60), radii=0.002))
            rec.log(f"{p}/landmarks", rr.Points2D(landmarks[b], radii=spec.landmark_radius, colors=LANDMARK_COLOR))
            rec.log(f"{p}/targets", rr.Points2D(targets[b], radii=0.015, colors=TARGET_COLOR))
            labels = None if swarm else [f"{i}:{int(x)}" for i, x in enumerate(a["actions"][t, b])]
            agents = rr.Points2D(pos[b], radii=spec.agent_radius, colors=colors, labels=labels, class_ids=np.arange(M))
            rec.log(f"{p}/agents", agents)
            rec.log(f"{p}/comm", rr.LineStrips2D(_edges(adj[b], pos[b]), colors=EDGE_COLOR, radii=0.004))
            if att is not None:
                i, j = np.nonzero(att[b] > 1e-3 * (1 - np.eye(M)))
                keep = i != j
                i, j = i[keep], j[keep]
                alpha = np.clip(att[b][i, j] * 255, 0, 255).astype(np.uint8)
                rgba = np.concatenate([colors[i], alpha[:, None]], axis=1)
                lines = np.stack([pos[b][j], pos[b][i]], axis=1)
                rec.log(f"{p}/attention", rr.LineStrips2D(lines, colors=rgba, radii=0.008))
            rec.log(f"{p}/reward", rr.Scalars(float(reward[b])))
        # the episodes that ended with this step are logged at the step after it
        if step + 1 in ends:
            _log_ends(rec, traj, step + 1, ends.pop(step + 1), successes)
    for end in sorted(ends):  # (ends after the last logged state)
        _log_ends(rec, traj, end, ends[end], successes)


def _log_ends(rec, traj, step: int, envs: list[int], successes: list[bool]) -> None:
    """The scalars of the first episodes that ended at ``step``, and where the agents stood at
    the end (the record's end_pos, where it has one); that state stays on screen (no Clear)."""
    a = traj.arrays
    rec.set_time("step", sequence=step)
    for b in envs:
        successes.append(bool(a["success"][b]))
        if b < traj.drawn:
            p = f"env_{b}"
            if "end_pos" in a and not np.isnan(a["end_pos"][b, 0, 0]):
                rec.log(f"{p}/agents", rr.Points2D.from_fields(positions=a["end_pos"][b]))
            rec.log(f"{p}/episode/success", rr.Scalars(float(a["success"][b])))
            rec.log(f"{p}/episode/length", rr.Scalars(float(a["length"][b])))
            if not np.isnan(a["dist"][b]):
                rec.log(f"{p}/episode/dist", rr.Scalars(float(a["dist"][b])))
    rec.log("all/success_rate", rr.Scalars(float(np.mean(successes))))
