"""Writing files so that nothing is lost: every write goes to a temp file beside the
target, is fsynced, then renamed over it (atomic on POSIX); outputs are checked
writable before the work that fills them. Used by every package (no torch here)."""

from __future__ import annotations

import json
import os
import tempfile


def atomic_write_bytes(path: str, write) -> None:
    """Call ``write(fileobj)`` on a temp file beside ``path``, fsync, then rename over it."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_json(path: str, obj) -> None:
    atomic_write_bytes(path, lambda f: f.write((json.dumps(obj, indent=2) + "\n").encode()))


def ensure_writable(path: str, what: str = "output") -> None:
    """Fail before any work if ``path`` cannot be written (its directory missing and not
    creatable, or read-only); names the path and the cause."""
    directory = os.path.dirname(os.path.abspath(path))
    probe = directory
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if os.path.isdir(path):
        raise ValueError(f"{what} {path} is a directory")
    if not os.path.isdir(probe) or not os.access(probe, os.W_OK):
        raise ValueError(f"cannot write {what} {path}: {probe} is not a writable directory")
    try:  # os.access says yes to root everywhere (/proc too): a file made and removed says for sure
        fd, tmp = tempfile.mkstemp(prefix=".tmp-probe-", dir=probe)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise ValueError(f"cannot write {what} {path}: {exc.strerror or exc} in {probe}") from None


def clean_leftovers(directory: str) -> list[str]:
    """Remove temp files a killed write left in ``directory`` (call under the run lock)."""
    removed = []
    if os.path.isdir(directory):
        for name in os.listdir(directory):
            if name.startswith(".tmp-"):
                os.unlink(os.path.join(directory, name))
                removed.append(name)
    return removed
