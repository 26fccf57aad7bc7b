"""Learning curves of a run directory (metrics.jsonl -> curves.png)."""

from __future__ import annotations

import json
import os

from taichi_swarm.files import ensure_writable, read_input_text
from trainer.rundir import CURVES, METRICS


def read_metrics(run_dir: str) -> list[dict]:
    path = os.path.join(run_dir, METRICS)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{run_dir} has no {METRICS} (is it a run directory?)")
    text = read_input_text(path, "metrics file")
    try:
        rows = [json.loads(line) for line in text.splitlines() if line.strip()]
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON lines ({exc})") from None
    for number, row in enumerate(rows, 1):
        missing = [k for k in ("update", "env_steps", "reward") if not isinstance(row, dict) or k not in row]
        if missing:
            raise ValueError(f"{path}: line {number} lacks {missing}: not a training run's metrics")
    return rows


def plot_run(run_dir: str, out: str | None = None) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = out or os.path.join(run_dir, CURVES)
    ensure_writable(out, "--out")  # before the work (a FIFO there would be replaced by the PNG)
    rows = read_metrics(run_dir)
    steps = [r["env_steps"] / 1e6 for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].plot(steps, [r["reward"] for r in rows])
    axes[0].set(title="mean team reward per step", xlabel="env steps (M)")
    ev = [r for r in rows if r.get("eval_success_rate") is not None]
    axes[1].plot([r["env_steps"] / 1e6 for r in ev], [100 * r["eval_success_rate"] for r in ev], "o-", label="eval")
    tr = [r for r in rows if r.get("train_success") is not None]
    axes[1].plot(
        [r["env_steps"] / 1e6 for r in tr], [100 * r["train_success"] for r in tr], alpha=0.5, label="train (sampling)"
    )
    sizes = sorted({int(k) for r in ev for k in (r.get("eval_transfer") or {})})
    for size in sizes:
        pts = [
            (r["env_steps"] / 1e6, 100 * r["eval_transfer"][str(size)])
            for r in ev
            if str(size) in (r.get("eval_transfer") or {})
        ]
        axes[1].plot(*zip(*pts, strict=True), "x--", alpha=0.7, label=f"eval at M={size} (zero-shot)")
    axes[1].set(title="success S%", xlabel="env steps (M)", ylim=(-2, 102))
    axes[1].legend()
    axes[2].plot([r["env_steps"] / 1e6 for r in ev], [r["eval_mean_length"] for r in ev], "o-")
    axes[2].set(title="eval episode length T", xlabel="env steps (M)")
    fig.suptitle(os.path.basename(os.path.normpath(run_dir)))
    return _save(fig, out)


def _save(fig, out: str) -> str:
    """Write ``fig`` to ``out`` atomically (temp file, then rename) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    tmp = out + ".tmp.png"
    try:
        fig.savefig(tmp, dpi=90)
        os.replace(tmp, out)
    except BaseException:  # a failed write leaves nothing behind
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    finally:
        plt.close(fig)
    return out


def plot_zero_shot(json_paths: list[str], out: str, labels: list[str] | None = None) -> str:
    """S% against team size from ``swarm zero-shot --json`` files, one line each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ensure_writable(out, "--out")
    texts = [read_input_text(path, "--zero-shot file") for path in json_paths]  # every one before drawing
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    for k, path in enumerate(json_paths):
        try:
            data = json.loads(texts[k])
        except json.JSONDecodeError:
            data = None
        rows = data.get("results") if isinstance(data, dict) else None
        fields = ("agents", "success_rate")
        if (
            not isinstance(rows, list)
            or not rows
            or not all(isinstance(r, dict) and all(k in r for k in fields) for r in rows)
        ):
            raise ValueError(f"{path} is not a `swarm zero-shot --json` file (results with agents and success_rate)")
        sizes = [r["agents"] for r in rows]
        rates = [100 * r["success_rate"] for r in rows]
        trained = data.get("trained_agents")
        label = labels[k] if labels and k < len(labels) else os.path.splitext(os.path.basename(path))[0]
        line = ax.plot(sizes, rates, "o-", label=label)[0]
        if trained in sizes:
            ax.plot([trained], [rates[sizes.index(trained)]], "*", ms=14, color=line.get_color())
    ax.set(xlabel="team size M (star: the size trained on)", ylabel="success S%", ylim=(-2, 102))
    ax.set_title("zero-shot transfer (no fine-tuning)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, out)
