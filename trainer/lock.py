"""One process per run directory: an advisory lock (``flock``) on ``RUN_DIR/.lock``.

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


class RunDirLocked(ValueError):
    """Another live process holds the run directory."""


class RunDirLock:
    def __init__(self, run_dir: str):
        self.path = os.path.join(run_dir, ".lock")
        self.fd: int | None = None

    def acquire(self) -> RunDirLock:
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = json.loads(os.read(fd, 4096) or b"{}")
            except ValueError:
                holder = {}
            os.close(fd)
            who = f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since {holder.get('since', '?')}"
            raise RunDirLocked(
                f"{os.path.dirname(self.path)} is in use by another training process ({who}); "
                "wait for it to finish or pick another --run-dir"
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
