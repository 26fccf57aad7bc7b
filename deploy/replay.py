"""``swarm replay FILE``: summarise a trajectory record (.npz) or a Rerun recording (.rrd), or
open it in a Rerun viewer (a trajectory record is drawn into a temporary .rrd first)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys


def rerun_command() -> list[str]:
    """The ``rerun`` binary that ships with rerun-sdk (beside this Python, else on PATH)."""
    beside = os.path.join(os.path.dirname(sys.executable), "rerun")
    if os.path.exists(beside):
        return [beside]
    found = shutil.which("rerun")
    if found:
        return [found]
    return [sys.executable, "-m", "rerun"]


def looks_like_rrd(path: str) -> bool:
    """True if the file starts with Rerun's RRD magic bytes."""
    with open(path, "rb") as f:
        return f.read(3) == b"RRF"


def looks_like_npz(path: str) -> bool:
    """True if the file starts like a zip archive, as .npz files (trajectory records) do."""
    with open(path, "rb") as f:
        return f.read(4) == b"PK\x03\x04"


def format_trajectory(path: str, traj) -> str:
    """A trajectory record in a few lines: setting, steps, and each drawn env's first episode."""
    h, a = traj.header, traj.arrays
    comm = f"rc {h['comm_radius']:g}" if h["comm"] == "rc" else h["comm"]
    lines = [
        f"{path}: trajectory record (schema {h['schema']}), {h['task']}, M={h['agents']}, {comm}, "
        f"{h['drawn']} of {h['envs']} environments drawn, steps {int(a['step'][0])}..{int(a['step'][-1])}"
        + (", with attention" if h["attention"] else "")
    ]
    outcomes = traj.outcomes()
    for b in range(traj.drawn):
        lines.append(f"  env {b}: {outcomes.get(b, 'episode not ended')}")
    ended = a["end_step"] >= 0
    if ended.any():
        lines.append(f"  success rate over the {int(ended.sum())} ended episodes: {a['success'][ended].mean():.2f}")
    return "\n".join(lines)


def summarize(path: str) -> dict:
    """Per entity path: rows, static or not, and the range of the "step" timeline (RrdReader)."""
    from rerun.chunk import RrdReader

    entities: dict[str, dict] = {}
    for chunk in RrdReader(path).stream():
        e = entities.setdefault(chunk.entity_path, {"rows": 0, "static": False, "steps": None})
        e["rows"] += chunk.num_rows
        e["static"] |= chunk.is_static
        if "step" in chunk.timeline_names:
            col = chunk.to_record_batch().column("step").to_pylist()
            lo, hi = min(col), max(col)
            e["steps"] = (lo, hi) if e["steps"] is None else (min(lo, e["steps"][0]), max(hi, e["steps"][1]))
    steps = [e["steps"] for e in entities.values() if e["steps"]]
    return {
        "path": path,
        "bytes": os.path.getsize(path),
        "entities": entities,
        "steps": (min(s[0] for s in steps), max(s[1] for s in steps)) if steps else None,
    }


def format_summary(summary: dict) -> str:
    lines = [
        f"{summary['path']}: {summary['bytes'] / 1e6:.2f} MB, {len(summary['entities'])} entity paths, "
        f"steps {summary['steps'][0]}..{summary['steps'][1]}"
        if summary["steps"]
        else f"{summary['path']}: {summary['bytes'] / 1e6:.2f} MB, {len(summary['entities'])} entity paths"
    ]
    lines.append(f"  {'entity':<28} {'rows':>6}  steps")
    for name in sorted(summary["entities"]):
        e = summary["entities"][name]
        steps = (
            "static" if e["static"] and not e["steps"] else (f"{e['steps'][0]}..{e['steps'][1]}" if e["steps"] else "-")
        )
        lines.append(f"  {name:<28} {e['rows']:>6}  {steps}")
    return "\n".join(lines)


def has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view(path: str, serve_web: bool = False, port: int | None = None) -> int:
    """Run the viewer (blocks until it exits); returns its exit code."""
    cmd = rerun_command() + [path]
    if serve_web:
        cmd += ["--serve-web", "--bind", "127.0.0.1"]
        if port:
            cmd += ["--web-viewer-port", str(port)]
        print(f"serving {path} in the web viewer (the URL is printed below; Ctrl-C stops it)", flush=True)
    # its own process group: the viewer server the launcher starts is stopped with it, however
    # this command is stopped (Ctrl-C, `kill PID`), instead of being left running
    proc = subprocess.Popen(cmd, start_new_session=True)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        stop_group(proc)
        return 0
    except BaseException:
        stop_group(proc)
        raise


def stop_group(proc: subprocess.Popen, grace: float = 5.0) -> None:
    """SIGTERM to ``proc``'s process group, SIGKILL after ``grace`` seconds; waits for it."""
    for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, None)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=wait)
            break
        except subprocess.TimeoutExpired:
            continue
