"""One process per run directory: an advisory lock (``flock``) on ``RUN_DIR/.lock``.

The same lock under another file name guards other per-directory work (``swarm
reproduce`` holds ``CELL_DIR/.cell.lock`` while it brings a cell to its result), and
``is_held`` asks, without waiting or creating anything, whether a live process holds one.

The kernel drops the lock when its holder exits, however it exits (kill -9 included),
so a stale lock left by a killed run is simply taken over by the next one; the file's
content (pid, host, start time) only serves to name the holder in the error.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time


PROBE_RETRIES = 4  # acquire's retries, 50 ms apart, before it refuses


class RunDirLocked(ValueError):
    """Another live process holds the run directory."""


class RunDirLock:
    def __init__(
        self,
        run_dir: str,
        name: str = ".lock",
        holder: str = "another training process",
        advice: str = "wait for it to finish or pick another --run-dir",
    ):
        self.path = os.path.join(run_dir, name)
        self.holder, self.advice = holder, advice  # what a refused caller is told
        self.fd: int | None = None

    def acquire(self) -> RunDirLock:
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        for attempt in range(PROBE_RETRIES + 1):
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if attempt < PROBE_RETRIES:  # (an is_held probe holds it for microseconds)
                    time.sleep(0.05)
        else:
            try:
                holder = json.loads(os.read(fd, 4096) or b"{}")
            except ValueError:
                holder = {}
            os.close(fd)
            who = f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since {holder.get('since', '?')}"
            raise RunDirLocked(
                f"{os.path.dirname(self.path)} is in use by {self.holder} ({who}); {self.advice}"
            ) from None
        os.ftruncate(fd, 0)
        info = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.pwrite(fd, json.dumps(info).encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> RunDirLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def is_held(directory: str, name: str = ".lock") -> bool:
    """Whether a live process (this one included) holds ``directory/name`` now."""
    try:
        fd = os.open(os.path.join(directory, name), os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # (closing drops the probe's own shared lock)
    return False
