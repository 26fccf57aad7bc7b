"""Offline videos of rollouts: GIF, MP4 or PNG frames, drawn with matplotlib (no display,
no GPU), rendered from the trajectory record (deploy/trajectory.py): ``frames`` turns a
``Trajectory`` into the frames ``render`` draws. ``open_recorders`` is what ``swarm eval``,
``swarm execute`` and ``swarm world`` call for ``--record`` / ``--video``: one
``TrajectoryRecorder`` fed by the rollout loop, and on ``close()`` every asked-for output
rendered from its one record.

One panel per recorded environment in a grid (never overlaid): the arena, landmarks
(grey), the current targets (crosses: green once an agent is within the task's success
threshold of it, red before; the title counts them) with the optimal assignment as thin
lines, the communication graph (light blue; under RC the radius as a circle round
each agent), and the agents coloured by id with a short trail. An environment's
panel freezes on its last frame once its first episode ends, titled with the outcome.
"""

from __future__ import annotations

import math
import os
import shutil

import numpy as np

from taichi_swarm.files import ensure_writable

VIDEO_SUFFIXES = (".gif", ".mp4")
TRAIL = 6  # steps of trail behind each agent


def frames(traj) -> list[dict]:
    """The frames ``render`` draws, one per recorded step and one more with every finished
    env marked (so the panels show their outcomes)."""
    a = traj.arrays
    out = [
        {
            "step": int(a["step"][t]),
            "pos": a["pos"][t],
            "landmarks": a["landmarks"][t],
            "targets": a["targets"][t],
            "adj": traj.adj(t),
            "arena": float(a["arena"][t]),
            "assignment": a["assignment"][t] if "assignment" in a else None,
            "live": traj.live(t),
        }
        for t in range(traj.num_steps)
    ]
    # the outcome frame: each finished env where its agents stood at the end (the last logged
    # state is the one they acted on in the final step; a record without end_pos shows that)
    last = {**out[-1], "live": a["end_step"][: traj.drawn] < 0}
    if "end_pos" in a:
        ended = ~np.isnan(a["end_pos"][:, 0, 0])
        last["pos"] = np.where(ended[:, None, None], a["end_pos"], last["pos"])
        last["ended_pos"] = ended
    out.append(last)
    return out


def render_trajectory(traj, path: str, fps: int = 10) -> str:
    """``traj`` (a Trajectory) -> the video ``path``."""
    h = traj.header
    return render(frames(traj), path, h["task"], int(h["agents"]), traj.outcomes(), traj.comm_radius, fps)


def check_video_path(path: str) -> None:
    """Fail before any work if ``path`` cannot be written or has an unknown kind."""
    if not path:  # (it would name a folder of frames in the working directory)
        raise ValueError("--video: an empty path names no file")
    is_dir_target = not os.path.splitext(path)[1]
    if not is_dir_target and not path.lower().endswith(VIDEO_SUFFIXES):
        raise ValueError(f"{path}: a video must end in .gif or .mp4 (or name a directory for PNG frames)")
    if is_dir_target:  # a folder of frames, made if missing
        ensure_writable(os.path.join(path, "frame_0000.png"), "--video", make_dirs=True)
    else:
        ensure_writable(path, "--video")
    if path.lower().endswith(".mp4") and ffmpeg_path() is None:
        raise ValueError(
            f'{path}: writing MP4 needs ffmpeg (on PATH, or pip install -e ".[video]" for imageio-ffmpeg); '
            "or write a .gif"
        )


def ffmpeg_path() -> str | None:
    """An ffmpeg binary: on PATH, else the one imageio-ffmpeg ships (the [video] extra)."""
    import shutil

    found = shutil.which("ffmpeg")
    if found:
        return found
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    return imageio_ffmpeg.get_ffmpeg_exe()


MAX_TRAILS = 20  # more agents are drawn as points, without trails, and smaller
MAX_RADIUS_CIRCLES = 50  # RC's radius drawn round each agent up to this many


def _success_threshold(task: str) -> float | None:
    """The task's default success threshold (a target counts as reached within it), or None for
    a task that has none."""
    from taichi_swarm.tasks import TASK_SPECS

    spec = TASK_SPECS.get(task)
    return getattr(spec.params_type(), "success_threshold", None) if spec is not None else None


def targets_reached(targets: np.ndarray, pos: np.ndarray, threshold: float) -> np.ndarray:
    """[T] bool: the targets [T, 2] with an agent (pos [M, 2]) nearer than ``threshold``, strictly
    as the success rule (duplicates count: it is an upper bound on the matched count)."""
    if len(pos) == 0:
        return np.zeros(len(targets), bool)
    return np.linalg.norm(targets[:, None] - pos[None], axis=-1).min(1) < threshold


def render(frames: list[dict], path: str, task: str, num_agents: int, outcome=None, comm_radius=None, fps=10):
    """Draw ``frames`` (as ``frames`` makes them from a trajectory record) into ``path``; returns ``path``."""
    if not frames:
        raise ValueError("nothing to render: no steps were recorded")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.animation as animation
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from tqdm import tqdm

    from deploy.recording import ARENA_HALF_SIZE, PALETTE

    outcome = outcome or {}
    threshold = _success_threshold(task)
    D = frames[0]["pos"].shape[0]
    # marker and line scale: the paper's sizes up to 20 agents, then smaller as the arena fills
    w = min(1.0, math.sqrt(MAX_TRAILS / max(num_agents, 1)))
    cols = math.ceil(math.sqrt(D))
    rows = math.ceil(D / cols)
    panel = 3.2 if num_agents <= 100 else 6.4  # inches; a swarm's points need the pixels
    dpi = 80 if num_agents <= 100 else 100
    fig, axes = plt.subplots(rows, cols, figsize=(panel * cols, panel * rows), squeeze=False)
    colors = PALETTE[np.arange(num_agents) % len(PALETTE)] / 255.0
    last_live = [0] * D  # the frame each panel froze on

    def draw(k: int) -> None:
        for b in range(rows * cols):
            ax = axes[b // cols][b % cols]
            ax.clear()
            half = frames[k].get("arena", ARENA_HALF_SIZE)
            lim = half * 1.1
            if b < D:  # MPE has no walls: widen the view when an agent leaves the arena
                lim = max(
                    lim, float(np.abs(frames[last_live[b] if not frames[k]["live"][b] else k]["pos"][b]).max()) + 0.1
                )
            ax.set_xlim(-lim, lim)
            ax.set_ylim(-lim, lim)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            for spine in ax.spines.values():
                spine.set_visible(False)
            if b >= D:
                ax.axis("off")
                continue
            if frames[k]["live"][b]:
                last_live[b] = k
            f = frames[last_live[b]]
            half = f.get("arena", ARENA_HALF_SIZE)
            ax.add_patch(plt.Rectangle((-half, -half), 2 * half, 2 * half, fill=False, lw=0.8, ec="0.4"))
            pos = f["pos"][b]
            if not frames[k]["live"][b] and frames[-1].get("ended_pos", np.zeros(D, bool))[b]:
                pos = frames[-1]["pos"][b]  # a finished env: where its agents stood at the end
            adj = f["adj"][b]
            # one LineCollection per kind of line: a swarm has thousands of edges and trails
            i, j = np.nonzero(np.triu(adj | adj.T, k=1))
            ax.add_collection(LineCollection(np.stack([pos[i], pos[j]], 1), colors=[(0.55, 0.6, 0.9)], lw=0.7 * w,
                                             alpha=0.6, zorder=1))  # fmt: skip
            if comm_radius is not None and num_agents <= MAX_RADIUS_CIRCLES:
                for p in pos:
                    ax.add_patch(plt.Circle(p, comm_radius, fill=False, lw=0.4, ec=(0.55, 0.6, 0.9), alpha=0.4))
            ax.scatter(*f["landmarks"][b].T, s=60 * w**2, color="0.55", zorder=2)
            targets = f["targets"][b]
            # at M = 1000 S% is 0 for one miss: the count is what reads
            reached = None if threshold is None else targets_reached(targets, pos, threshold)
            shade = "k" if reached is None else np.where(reached[:, None], (0.1, 0.6, 0.2), (0.85, 0.15, 0.1))
            ax.scatter(*targets.T, s=max(25 * w**2, 6.0), marker="x", color=shade, lw=max(w, 0.6), zorder=3)
            if f["assignment"] is not None:
                j = f["assignment"][b]
                on = j >= 0  # assignment="nearest": -1 where an agent holds no target
                links = np.stack([pos[on], f["targets"][b][j[on]]], 1)
                ax.add_collection(LineCollection(links, colors="0.3", lw=0.4 * w, linestyles=":", zorder=2))
            if num_agents <= MAX_TRAILS:  # a swarm reads better as points
                lo = max(0, last_live[b] - TRAIL)
                trail = np.stack([frames[t]["pos"][b] for t in range(lo, last_live[b] + 1)], 1)  # [M, S, 2]
                ax.add_collection(LineCollection(trail, colors=colors, lw=1, alpha=0.5, zorder=3))
            ax.scatter(*pos.T, s=max(55 * w**2, 4.0), color=colors, edgecolors="k", linewidths=0.4 * w, zorder=4)
            title = f"env {b}  step {f['step']}"
            if not frames[k]["live"][b] and b in outcome:
                title = f"env {b}: {outcome[b]}"
            if reached is not None:
                title += f", {reached.sum()} of {len(reached)} targets reached"
            ax.set_title(title, fontsize=8)
        fig.suptitle(f"{task}, M = {num_agents}", fontsize=10)

    fig.tight_layout(rect=(0, 0, 1, 0.95))
    bar = tqdm(total=len(frames), desc=f"rendering {os.path.basename(path) or path}", unit="frame", leave=False)

    def update(k):
        draw(k)
        bar.update(1)
        return []

    tmp = None
    made = not os.path.exists(path)
    try:
        if not os.path.splitext(path)[1]:
            os.makedirs(path, exist_ok=True)
            for k in range(len(frames)):
                update(k)
                fig.savefig(os.path.join(path, f"frame_{k:04d}.png"), dpi=dpi)
        else:
            anim = animation.FuncAnimation(fig, update, frames=len(frames), blit=False)
            if path.lower().endswith(".gif"):
                writer = animation.PillowWriter(fps=fps)
            else:
                matplotlib.rcParams["animation.ffmpeg_path"] = ffmpeg_path()
                writer = animation.FFMpegWriter(fps=fps)
            name, suffix = os.path.splitext(os.path.basename(path))
            tmp = os.path.join(os.path.dirname(os.path.abspath(path)), f".tmp-{name}{suffix}")
            anim.save(tmp, writer=writer, dpi=dpi)
            os.replace(tmp, path)
    except BaseException:  # (Ctrl-C, a full disk, no ffmpeg): nothing half-written is left
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if made and os.path.isdir(path):
            shutil.rmtree(path, ignore_errors=True)
        raise
    finally:
        bar.close()
        plt.close(fig)
    return path


def open_recorders(args, task: str, episodes: int, agents: int, comm: str, comm_radius: float):
    """The recorder ``args.record`` and ``args.video`` ask for (``args``: any object with
    ``record``, ``video`` and ``record_envs``, e.g. swarm_cli.options.OutputOptions), or
    None; the video path is checked before any episode runs."""
    if args.record_envs < 1:
        raise ValueError(f"--record-envs must be >= 1, got {args.record_envs}")
    if not (args.record or args.video):
        return None
    from deploy.trajectory import TrajectoryRecorder

    if args.video:
        check_video_path(args.video)
    outputs = [(k, out) for k, out in (("recording", args.record), ("video", args.video)) if out]
    return Recording(TrajectoryRecorder(task, episodes, agents, args.record_envs, comm, comm_radius), outputs)


class Recording:
    """One rollout's recorder (a TrajectoryRecorder) and the files to render from its record:
    ("recording", FILE.npz: the record itself, else a Rerun .rrd), ("video", FILE)."""

    def __init__(self, recorder, outputs: list[tuple[str, str]]):
        self.recorder = recorder
        self.outputs = outputs
        self.drawn, self.episodes = recorder.drawn, recorder.num_envs
        self.log_step, self.log_episode_ends = recorder.log_step, recorder.log_episode_ends

    def report(self) -> None:
        """Say what was written and how many environments it draws."""
        for kind, out in self.outputs:
            print(f"{kind}: {out} ({self.drawn} of {self.episodes} environments drawn; --record-envs to change)")

    def close(self, ok: bool = True) -> None:
        """``ok``: the rollout ended normally (else nothing is written, nothing replaced)."""
        if not ok:
            return
        traj = self.recorder.trajectory()
        for kind, out in self.outputs:
            if kind == "video":
                render_trajectory(traj, out)
            elif out.lower().endswith(".npz"):
                traj.save(out)
            else:
                from deploy.recording import write_rrd

                write_rrd(traj, out)
