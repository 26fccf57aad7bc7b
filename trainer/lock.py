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

PROBE_RETRIES = 25  # acquire's retries, 10 ms apart, before it refuses


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
