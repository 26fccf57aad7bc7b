"""The paper's evaluation metrics (s.5), shared by ``swarm eval`` (torch) and
``swarm execute`` (onnxruntime, no torch): one episode per environment,
S% = share of successful episodes, T = mean episode length (the time limit
for failures), DIST = mean landmark-to-closest-agent distance at the end
(the tasks that report it: coverage)."""

from __future__ import annotations

import numpy as np

from .tasks import TASK_SPECS


def _np(x) -> np.ndarray:
    return np.asarray(x.cpu()) if hasattr(x, "cpu") else np.asarray(x)


class FirstEpisodes:
    """Collects the statistics of the first episode of each of B environments."""

    def __init__(self, num_envs: int):
        self.finished = np.zeros(num_envs, bool)
        self.success = np.zeros(num_envs, bool)
        self.length = np.zeros(num_envs, np.int64)
        self.dist = np.zeros(num_envs, np.float64)
        self.covered = None  # [B]: fraction of landmarks covered at the end, where the simulator reports it

    def all_done(self) -> bool:
        return bool(self.finished.all())

    def add(self, done, episode_info: dict) -> np.ndarray:
        """Record the episodes that just ended for the first time; returns that mask [B]."""
        done = _np(done).astype(bool)
        new = done & ~self.finished
        if new.any():
            self.success[new] = _np(episode_info["success"])[new]
            self.length[new] = _np(episode_info["length"])[new]
            self.dist[new] = _np(episode_info["dist"])[new]
            if "covered" in episode_info:
                if self.covered is None:
                    self.covered = np.zeros(len(self.finished), np.float64)
                self.covered[new] = _np(episode_info["covered"])[new]
        self.finished |= done
        return new

    def summary(self, task: str) -> dict:
        out = {
            "success_rate": float(self.success.mean()),
            "mean_length": float(self.length.mean()),
            "dist": float(self.dist.mean()) if TASK_SPECS[task].reports_dist else None,
            "per_episode": {
                "success": self.success.tolist(),
                "length": self.length.tolist(),
                "dist": self.dist.tolist(),
            },
        }
        if self.covered is not None:  # beside S%: at M = 1000 a single miss fails S%
            out["covered"] = float(self.covered.mean())
            out["per_episode"]["covered"] = self.covered.tolist()
        return out


def run_first_episodes(env, decide, recorder=None, on_done=None) -> FirstEpisodes:
    """The evaluation loop of ``swarm eval`` (torch) and ``swarm execute`` (onnxruntime):
    from ``env.reset()``, step every environment with ``decide(obs) -> (actions,
    attention or None)`` until each has finished its first episode; ``on_done(done)``
    sees every step's done mask [B] (numpy bool); ``recorder`` (deploy/recording.py)
    logs the steps and episode ends. Returns the tally of those first episodes."""
    obs = env.reset()
    tally = FirstEpisodes(env.num_envs)
    step = 0
    while not tally.all_done():
        actions, attention = decide(obs)
        if recorder is not None:
            recorder.log_step(step, env, actions, attention=attention)
        obs, _, done, info = env.step(actions)
        step += 1
        done = _np(done).astype(bool)
        if on_done is not None and done.any():
            on_done(done)
        new = tally.add(done, info["episode"])
        if recorder is not None and new.any():
            # where the agents stood at the end: the env has already restarted them
            recorder.log_episode_ends(step, new, info["episode"], _np(info["terminal_obs"]["self"])[..., 2:4])
    return tally


def result_header(task: str, agents: int, comm: str, comm_radius: float, episodes: int, seed: int) -> dict:
    """The setting every evaluation result row starts with."""
    return {
        "task": task,
        "agents": agents,
        "comm": comm,
        "comm_radius": comm_radius,
        "episodes": episodes,
        "seed": seed,
    }


def format_results(rows: list[dict], extra: tuple[str, ...] = ()) -> str:
    """Result rows as an aligned table: task, comm, M, episodes, [extra columns], S%, T, DIST;
    an extra column "covered" (3 decimals: at M = 1000 a miss is 0.001) or
    "messages_per_agent_step" (the radio's, as "msgs")."""
    label = {"messages_per_agent_step": "msgs"}
    fmt = {"covered": ".3f", "messages_per_agent_step": ".1f"}
    width = {c: max(5, len(label.get(c, c))) for c in extra}
    head = f"{'task':<10} {'comm':<4} {'M':>4} {'episodes':>8}" + "".join(
        f" {label.get(c, c):>{width[c]}}" for c in extra
    )
    head += f" {'S%':>6} {'T':>6} {'DIST':>7}"
    lines = [head, "-" * len(head)]
    for r in rows:
        d = "-" if r["dist"] is None else f"{r['dist']:.3f}"
        cells = "".join(
            f" {r[c]:>{width[c]}{fmt.get(c, '.2f')}}" if isinstance(r[c], float) else f" {r[c]:>{width[c]}}"
            for c in extra
        )
        lines.append(
            f"{r['task']:<10} {r['comm']:<4} {r['agents']:>4} {r['episodes']:>8}{cells} "
            f"{100 * r['success_rate']:>6.1f} {r['mean_length']:>6.2f} {d:>7}"
        )
    return "\n".join(lines)
