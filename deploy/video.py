"""Offline videos of rollouts: GIF, MP4 or PNG frames, drawn with matplotlib (no display,
no GPU). ``FrameRecorder`` has the recorder interface of ``deploy.recording``
(``log_step`` / ``log_episode_ends`` / ``close``), so ``swarm eval`` and ``swarm
execute`` fill it from the same rollout loop; ``close()`` renders the file.

One panel per recorded environment in a grid (never overlaid): the arena, landmarks
(grey), the current targets (black crosses) with the optimal assignment as thin
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


class FrameRecorder:
    """Collects the first ``num_drawn`` environments' states step by step; ``close()``
    renders them to ``path`` (.gif, .mp4, or a directory for PNG frames)."""

    def __init__(
        self, path: str, task: str, num_envs: int, num_agents: int, num_drawn: int = 4, comm_radius=None, fps=10
    ):
        check_video_path(path)
        self.path, self.task, self.fps = path, task, fps
        self.num_agents = int(num_agents)
        self.drawn = max(1, min(int(num_drawn), int(num_envs)))
        self.comm_radius = comm_radius
        self.frames: list[dict] = []
        self._ended = np.zeros(int(num_envs), bool)
        self._outcome: dict[int, str] = {}

    def log_step(self, step: int, env, actions=None, attention=None) -> None:
        from deploy.recording import comm_graph, to_numpy  # deploy.recording imports rerun: only when recording

        D = self.drawn
        state = env.get_state()
        assignment = to_numpy(env.assignment)[:D] if hasattr(env, "assignment") else None
        self.frames.append(
            {
                "step": int(step),
                "pos": to_numpy(state["pos"])[:D].copy(),
                "landmarks": to_numpy(state["landmarks"])[:D].copy(),
                "targets": to_numpy(env.targets)[:D].copy(),
                "adj": comm_graph(env.obs, D),
                "arena": float(getattr(env, "arena", 1.0)),  # half side (scale="density" grows it)
                "assignment": None if assignment is None else assignment.copy(),
                "live": ~self._ended[:D].copy(),
            }
        )

    def log_episode_ends(self, step: int, mask, episode_info: dict) -> None:
        from deploy.recording import to_numpy

        mask = to_numpy(mask).astype(bool)
        success = to_numpy(episode_info["success"]).astype(bool)
        length = to_numpy(episode_info["length"])
        for b in np.flatnonzero(mask):
            if not self._ended[b] and b < self.drawn:
                self._outcome[int(b)] = f"{'success' if success[b] else 'failed'} at step {int(length[b])}"
            self._ended[b] = True

    def close(self, ok: bool = True) -> None:
        """Render the video, if ``ok`` (a failed run renders nothing: its error is the news)."""
        if not ok:
            return
        if self.frames:  # one more frame with every finished env marked, so panels show outcomes
            last = dict(self.frames[-1])
            last["live"] = ~self._ended[: self.drawn].copy()
            self.frames.append(last)
        render(self.frames, self.path, self.task, self.num_agents, self._outcome, self.comm_radius, self.fps)


def check_video_path(path: str) -> None:
    """Fail before any work if ``path`` cannot be written or has an unknown kind."""
    is_dir_target = not os.path.splitext(path)[1]
    if not is_dir_target and not path.lower().endswith(VIDEO_SUFFIXES):
        raise ValueError(f"{path}: a video must end in .gif or .mp4 (or name a directory for PNG frames)")
    ensure_writable(os.path.join(path, "frame_0000.png") if is_dir_target else path, "video")
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


def render(frames: list[dict], path: str, task: str, num_agents: int, outcome=None, comm_radius=None, fps=10):
    """Draw ``frames`` (as FrameRecorder collects them) into ``path``; returns ``path``."""
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
    D = frames[0]["pos"].shape[0]
    # marker and line scale: the paper's sizes up to 20 agents, then smaller as the arena fills
    w = min(1.0, math.sqrt(MAX_TRAILS / max(num_agents, 1)))
    cols = math.ceil(math.sqrt(D))
    rows = math.ceil(D / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * rows), squeeze=False)
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
            adj = f["adj"][b]
            # one LineCollection per kind of line: a swarm has thousands of edges and trails
            i, j = np.nonzero(np.triu(adj | adj.T, k=1))
            ax.add_collection(LineCollection(np.stack([pos[i], pos[j]], 1), colors=[(0.55, 0.6, 0.9)], lw=0.7 * w,
                                             alpha=0.6, zorder=1))  # fmt: skip
            if comm_radius is not None and num_agents <= MAX_RADIUS_CIRCLES:
                for p in pos:
                    ax.add_patch(plt.Circle(p, comm_radius, fill=False, lw=0.4, ec=(0.55, 0.6, 0.9), alpha=0.4))
            ax.scatter(*f["landmarks"][b].T, s=60 * w**2, color="0.55", zorder=2)
            ax.scatter(*f["targets"][b].T, s=25 * w**2, marker="x", color="k", lw=w, zorder=3)
            if f["assignment"] is not None:
                links = np.stack([pos, f["targets"][b][f["assignment"][b]]], 1)
                ax.add_collection(LineCollection(links, colors="0.3", lw=0.4 * w, linestyles=":", zorder=2))
            if num_agents <= MAX_TRAILS:  # a swarm reads better as points
                lo = max(0, last_live[b] - TRAIL)
                trail = np.stack([frames[t]["pos"][b] for t in range(lo, last_live[b] + 1)], 1)  # [M, S, 2]
                ax.add_collection(LineCollection(trail, colors=colors, lw=1, alpha=0.5, zorder=3))
            ax.scatter(*pos.T, s=55 * w**2, color=colors, edgecolors="k", linewidths=0.4 * w, zorder=4)
            title = f"env {b}  step {f['step']}"
            if not frames[k]["live"][b] and b in outcome:
                title = f"env {b}: {outcome[b]}"
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
                fig.savefig(os.path.join(path, f"frame_{k:04d}.png"), dpi=80)
        else:
            anim = animation.FuncAnimation(fig, update, frames=len(frames), blit=False)
            if path.lower().endswith(".gif"):
                writer = animation.PillowWriter(fps=fps)
            else:
                matplotlib.rcParams["animation.ffmpeg_path"] = ffmpeg_path()
                writer = animation.FFMpegWriter(fps=fps)
            name, suffix = os.path.splitext(os.path.basename(path))
            tmp = os.path.join(os.path.dirname(os.path.abspath(path)), f".tmp-{name}{suffix}")
            anim.save(tmp, writer=writer, dpi=80)
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
    """The recorders ``args.record`` (Rerun) and ``args.video`` ask for (``args``: any object
    with ``record``, ``video`` and ``record_envs``, e.g. swarm_cli.options.OutputOptions), or
    None; the video path is checked before any episode runs."""
    if args.record_envs < 1:
        raise ValueError(f"--record-envs must be >= 1, got {args.record_envs}")
    if not (args.record or args.video):
        return None
    from deploy.recording import RolloutRecorder

    radius = comm_radius if comm == "rc" else None
    rrd = video = None
    if args.video:
        video = FrameRecorder(args.video, task, episodes, agents, args.record_envs, radius)
    if args.record:
        rrd = RolloutRecorder(args.record, task, episodes, agents, max_envs_drawn=args.record_envs, comm_radius=radius)
    recorders = Recorders(rrd, video)
    recorders.outputs = [(k, out) for k, out in (("recording", args.record), ("video", args.video)) if out]
    recorders.drawn, recorders.episodes = min(args.record_envs, episodes), episodes
    return recorders


class Recorders:
    """Several recorders fed by one rollout loop (e.g. a Rerun file and a GIF)."""

    def __init__(self, *recorders):
        self.recorders = [r for r in recorders if r is not None]
        self.outputs: list[tuple[str, str]] = []  # (kind, path) to report after close
        self.drawn = self.episodes = 0

    def report(self) -> None:
        """Say what was written and how many environments it draws."""
        for kind, out in self.outputs:
            print(f"{kind}: {out} ({self.drawn} of {self.episodes} environments drawn; --record-envs to change)")

    def log_step(self, *args, **kwargs) -> None:
        for r in self.recorders:
            r.log_step(*args, **kwargs)

    def log_episode_ends(self, *args, **kwargs) -> None:
        for r in self.recorders:
            r.log_episode_ends(*args, **kwargs)

    def close(self, ok: bool = True) -> None:
        """``ok``: the rollout ended normally (else nothing is written, nothing replaced)."""
        for r in self.recorders:
            r.close(ok)


def frames_from_recording(path: str) -> tuple[list[dict], str, int, dict]:
    """Rebuild FrameRecorder's frames from a Rerun recording written by ``--record``
    (agents, landmarks, targets and communication edges of every drawn environment).
    Returns (frames, task, M, outcomes)."""
    import re

    from rerun.chunk import RrdReader

    data: dict[tuple[int, str], dict[int, object]] = {}  # (env, kind) -> step -> value
    task = "swarm"
    try:
        chunks = list(RrdReader(path).stream())
    except Exception as exc:  # noqa: BLE001 - the reader raises RuntimeError and others on a bad file
        raise ValueError(f"cannot read {path} as a Rerun recording ({exc})") from None
    for chunk in chunks:
        m = re.fullmatch(r"/env_(\d+)(?:/(.+))?", chunk.entity_path)
        if not m:
            continue
        b, kind = int(m.group(1)), m.group(2) or ""
        rb = chunk.to_record_batch()
        names = rb.schema.names
        if kind == "" and "TextDocument:text" in names:
            text = rb.column("TextDocument:text").to_pylist()[0]
            task = str(text[0] if isinstance(text, list) else text).split(",")[0]
            continue
        if "step" not in names:
            continue
        column = {
            "agents": "Points2D:positions",
            "landmarks": "Points2D:positions",
            "targets": "Points2D:positions",
            "comm": "LineStrips2D:strips",
            "episode/success": "Scalars:scalars",
            "episode/length": "Scalars:scalars",
        }.get(kind)
        if column is None or column not in names:
            continue
        for step, value in zip(rb.column("step").to_pylist(), rb.column(column).to_pylist(), strict=True):
            if value is not None:
                data.setdefault((b, kind), {})[int(step)] = value
    envs = sorted({b for b, kind in data if kind == "agents"})
    if not envs:
        raise ValueError(f"{path} holds no drawn environments (was it written by --record?)")
    steps = sorted({s for b in envs for s in data[(b, "agents")]})
    M = len(next(iter(data[(envs[0], "agents")].values())))
    outcomes = {}
    for i, b in enumerate(envs):
        if (b, "episode/success") in data:
            (end, success), *_ = data[(b, "episode/success")].items()
            length = int(next(iter(data.get((b, "episode/length"), {end: [end]}).values()))[0])
            outcomes[i] = f"{'success' if success[0] > 0.5 else 'failed'} at step {length}"
    frames, last = [], {}
    for step in steps:
        pos, lmk, tgt, adj, live = [], [], [], [], []
        for b in envs:
            here = step in data[(b, "agents")]
            if here:
                p = np.asarray(data[(b, "agents")][step], np.float32)
                a = np.eye(M, dtype=bool)
                for seg in data.get((b, "comm"), {}).get(step, []) or []:
                    ij = [int(np.argmin(np.abs(p - np.asarray(pt, np.float32)).sum(-1))) for pt in seg]
                    a[ij[0], ij[1]] = a[ij[1], ij[0]] = True
                last[(b, "agents")], last[(b, "adj")] = p, a
                for kind in ("landmarks", "targets"):  # logged every step; keep the last if absent
                    value = data.get((b, kind), {}).get(step, last.get((b, kind), np.zeros((0, 2))))
                    last[(b, kind)] = np.asarray(value, np.float32)
            pos.append(last[(b, "agents")])
            adj.append(last[(b, "adj")])
            lmk.append(last[(b, "landmarks")])
            tgt.append(last[(b, "targets")])
            live.append(here)
        frames.append(
            {
                "step": step,
                "pos": np.stack(pos),
                "landmarks": np.stack(lmk) if len({x.shape for x in lmk}) == 1 else np.stack([lmk[0]] * len(lmk)),
                "targets": np.stack(tgt),
                "adj": np.stack(adj),
                "assignment": None,
                "live": np.array(live),
            }
        )
    frames.append({**frames[-1], "live": np.zeros(len(envs), bool)})
    return frames, task, M, outcomes
