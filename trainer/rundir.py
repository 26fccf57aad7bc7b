"""The run directory: the one owner of every file a training run keeps, and of the run's
lifecycle around PPO (the lock, metrics, checkpoints, resume, signals).

    RUN_DIR/.lock          held (flock) by the process training there; the kernel drops it
                           when that process exits, however it exits
    RUN_DIR/config.json    the run's TrainConfig, rewritten at every start and resume
    RUN_DIR/metrics.jsonl  one JSON line per update (eval_* keys on evaluation updates);
                           a resume first drops the lines after its checkpoint
    RUN_DIR/checkpoint.pt  everything to resume bit-identically, written atomically every
                           checkpoint_every updates, at the end and on Ctrl-C / SIGTERM
    RUN_DIR/policy.pt      the same weights without optimiser state (~1 MB: commit it,
                           `swarm eval` / `export` it)
    RUN_DIR/summary.json   written last, atomically: the run is done
    RUN_DIR/curves.png     metrics.jsonl drawn at the end (trainer.plot)
    RUN_DIR/tensorboard/   with --tensorboard, metrics.jsonl's scalars as events

A kill at any moment leaves a directory that resumes: writes go to a temporary file that
is renamed into place, a torn last metrics line is dropped, and a policy.pt one update
behind its checkpoint.pt is rewritten from it.

Light at import, the standard library only (reproduce's status, the CLI and a lock-holding
helper process read the names and the lock here, without torch or Taichi); the functions
that write files or checkpoints import what they need when called.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import socket
import threading
import time

# ----------------------------------------------------------------------------- file names

LOCK = ".lock"
CONFIG = "config.json"
METRICS = "metrics.jsonl"
CHECKPOINT = "checkpoint.pt"
POLICY = "policy.pt"
SUMMARY = "summary.json"
CURVES = "curves.png"
TENSORBOARD = "tensorboard"
# what trainer.curriculum keeps in a stage's run directory
FRESH_EVAL = "fresh-eval.json"  # the stage's final policy on fresh episodes
POLISH_OF = "polish-of.json"  # in a polish run: the stage (and its last update) it polished
STARTED_FROM = "started-from.json"  # in a stage after the first: the run (and its last update) it started from

# what a checkpoint needs beyond a policy file's keys to resume a run
RESUME_KEYS = ("counters", "optimizer", "reward_scalers", "torch_rng", "cuda_rng", "env_states")

# ----------------------------------------------------------------------------- the lock

PROBE_RETRIES = 25  # acquire's retries, 10 ms apart, before it refuses


class RunDirLocked(ValueError):
    """Another live process holds the run directory."""


class RunDirLock:
    """One process per directory: an advisory lock (``flock``) on ``directory/name``. The
    same lock under another name guards other per-directory work (``swarm reproduce``
    holds ``CELL_DIR/.cell.lock`` while it brings a cell to its result). A stale lock left
    by a killed process is simply taken over; the file's content (pid, host, start time)
    only names the holder in the error."""

    def __init__(
        self,
        run_dir: str,
        name: str = LOCK,
        holder: str = "another training process",
        advice: str = "wait for it to finish or pick another --run-dir",
    ):
        self.path = os.path.join(run_dir, name)
        self.holder, self.advice = holder, advice  # what a refused caller is told
        self.fd: int | None = None
        self.created = False  # this acquire made the lock file (a failed run removes it: __exit__)

    def acquire(self) -> RunDirLock:
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        try:  # O_EXCL first, to know whether the file is this process's own
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            created = True
        except FileExistsError:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            created = False
        try:
            for attempt in range(PROBE_RETRIES + 1):
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if attempt < PROBE_RETRIES:  # (an is_held probe holds it for microseconds)
                        time.sleep(0.01)
            else:
                try:
                    holder = json.loads(os.read(fd, 4096) or b"{}")
                except ValueError:
                    holder = {}
                who = f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since {holder.get('since', '?')}"
                raise RunDirLocked(
                    f"{os.path.dirname(self.path)} is in use by {self.holder} ({who}); {self.advice}"
                ) from None
            info = json.dumps(
                {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
            ).encode()
            os.pwrite(fd, info, 0)  # written, then cut to length: a reader never sees it empty
            os.ftruncate(fd, len(info))
        except BaseException:
            os.close(fd)  # (closing drops the lock if it was taken: a failed acquire holds nothing)
            raise
        self.fd, self.created = fd, created
        return self

    def release(self) -> None:
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> RunDirLock:
        return self.acquire()

    def __exit__(self, exc_type, *exc) -> None:
        # work that failed (a refused --resume DIR) leaves no lock file it made behind. (A second
        # process that opened the file in these milliseconds would go on under the unlinked one:
        # only a third could then meet it, as with the run directory a failed new run removes.)
        if exc_type is not None and self.created and self.fd is not None:
            try:
                os.unlink(self.path)
            except OSError:
                pass
        self.release()


def is_held(directory: str, name: str = LOCK) -> bool:
    """Whether a live process holds ``directory/name`` now (False where the file cannot be
    read: no lock there). Ask from another process than the holder: on NFS, where flock is
    emulated with POSIX locks, a probe by the holder itself would release its lock."""
    try:
        fd = os.open(os.path.join(directory, name), os.O_RDONLY)
    except OSError:  # missing, a path through a file, another user's file
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:  # a file system without locks: nobody can hold one there
        return False
    finally:
        os.close(fd)  # (closing drops the probe's own shared lock)
    return False


# ----------------------------------------------------------------------------- the files


class RunDir:
    """The files of one run directory."""

    def __init__(self, path: str):
        self.path = path
        self.config = os.path.join(path, CONFIG)
        self.metrics = os.path.join(path, METRICS)
        self.checkpoint = os.path.join(path, CHECKPOINT)
        self.policy = os.path.join(path, POLICY)
        self.summary = os.path.join(path, SUMMARY)

    def lock(self) -> RunDirLock:
        return RunDirLock(self.path)

    def log(self, record: dict) -> None:
        with open(self.metrics, "a") as f:
            f.write(json.dumps(record) + "\n")

    def truncate_metrics(self, last_update: int) -> None:
        """Drop metric lines written after the checkpoint we resume from."""
        if not os.path.exists(self.metrics):
            return
        with open(self.metrics) as f:
            lines = [line for line in f if line.strip()]
        keep = []
        for number, line in enumerate(lines, 1):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                if number == len(lines):  # the last line, torn by a kill or a full disk mid-write
                    break
                raise ValueError(f"{self.metrics}: line {number} is not JSON; fix or remove it to resume") from None
            if record["update"] <= last_update:
                keep.append(line if line.endswith("\n") else line + "\n")
        from taichi_swarm.files import atomic_write_bytes

        atomic_write_bytes(self.metrics, lambda f: f.write("".join(keep).encode()))

    def write_config(self, config: dict) -> None:
        """config.json: the run's config, as ``trainer.config.to_dict`` writes it."""
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(self.config, config)

    def budget(self) -> int:
        """The update budget config.json holds."""
        with open(self.config) as f:
            return json.load(f)["updates"]

    def read_summary(self) -> dict | None:
        """summary.json, or None where the run has not finished."""
        if not os.path.exists(self.summary):
            return None
        with open(self.summary) as f:
            return json.load(f)

    def write_summary(self, summary: dict) -> None:
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(self.summary, summary)


# ----------------------------------------------------------------------------- metrics sinks


class TensorBoardLog:
    """metrics.jsonl's scalars as TensorBoard events (RUN_DIR/tensorboard), step = update."""

    def __init__(self, run_dir: str):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            raise ValueError('--tensorboard needs the tensorboard package: pip install -e ".[tensorboard]"') from None
        self.writer = SummaryWriter(os.path.join(run_dir, TENSORBOARD))

    def log(self, record: dict) -> None:
        step = record["update"]
        for key, value in record.items():
            if isinstance(value, dict):
                for sub, v in value.items():
                    self.writer.add_scalar(f"{key}/M{sub}", v, step)
            elif isinstance(value, (int, float)) and key != "update":
                self.writer.add_scalar(key, value, step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


# ----------------------------------------------------------------------------- signals


class StopAtUpdateEnd:
    """While inside: Ctrl-C (SIGINT) or SIGTERM during an update lets the update, its
    evaluation and its checkpoint finish, then takes the signal's own path (its previous
    handler, else a KeyboardInterrupt), so a stopped run resumes from a whole update. A
    second signal takes that path at once. Signals the process ignores stay ignored; off
    the main thread (where no signal arrives) it does nothing.

    The previous handler is kept so that `swarm`'s own SIGTERM handler (swarm_cli.main,
    which gives every command Ctrl-C's path and the exit code 143) still runs."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.pending: int | None = None
        self.previous: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                if signal.getsignal(s) is not signal.SIG_IGN:
                    self.previous[s] = signal.signal(s, self._note)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    def _restore(self) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
        self.previous = {}

    def _note(self, signum, frame) -> None:
        if self.pending is not None:
            self.take(signum)
        self.pending = signum

    def check(self) -> None:
        """At an update's end: stop now if a signal came."""
        if self.pending is not None:
            self.take(self.pending)

    def take(self, signum: int) -> None:
        handler = self.previous.get(signum)
        self._restore()
        if callable(handler):
            handler(signum, None)  # e.g. Python's SIGINT handler, `swarm`'s SIGTERM one: raise KeyboardInterrupt
        raise KeyboardInterrupt(f"stopped by {signal.Signals(signum).name}")
