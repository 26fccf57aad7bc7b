"""Writing files so that nothing is lost: every write goes to a temp file beside the
target, is fsynced, then renamed over it (atomic on POSIX); outputs are checked
writable before the work that fills them (``ensure_writable``). Reading what a user
names: a regular file of bounded size only (``check_input``, ``read_input``), so a FIFO
cannot block a command and /dev/zero cannot fill the memory. Used by every package
(no torch here)."""

from __future__ import annotations

import json
import os
import stat
import tempfile

MIB = 1 << 20
# The largest file each kind of input can be. A manifest, spec or results JSON is a few KB;
# 64 MiB leaves room without letting one fill the memory.
MAX_TEXT_BYTES = 64 * MIB
# protobuf refuses a message over 2 GiB, so no ONNX file beyond it is loadable
MAX_ONNX_BYTES = 2048 * MIB
# trainer.model.MAX_HIDDEN's 0.7 GB of weights, with Adam's two moments beside them
MAX_CHECKPOINT_BYTES = 4096 * MIB


class InputFileError(ValueError):
    """A file given as input is missing, not a regular file, or larger than its kind can be."""


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
    ):  # fmt: skip
        if test(mode):
            return name
    return "not a regular file"


def _check_stat(st: os.stat_result, path: str, what: str, max_bytes: int | None) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise InputFileError(f"{what} {path} is not a regular file ({_kind(st.st_mode)})")
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputFileError(f"{what} {path} is {st.st_size} bytes, over the limit of {max_bytes}")


def check_input(path: str, what: str, max_bytes: int | None = MAX_TEXT_BYTES) -> int:
    """Refuse ``path`` (symlinks followed) unless it is a regular file of at most ``max_bytes``
    (None: any size, for a file streamed rather than held); returns its size. For readers that
    open the path themselves (torch.load, zipfile); ``read_input`` where the bytes are read
    here. ``what`` names the option or the file's role."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputFileError(f"{what} {path} does not exist") from None
    except OSError as exc:
        raise InputFileError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    _check_stat(st, path, what, max_bytes)
    return st.st_size


def read_input(path: str, what: str, max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of ``path``, a regular file of at most ``max_bytes`` (else InputFileError,
    naming ``what``). Checked before the open, and again on the open file: O_NONBLOCK so that
    a FIFO swapped in between cannot block the open, fstat so that it is refused then."""
    check_input(path, what, max_bytes)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise InputFileError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    try:
        _check_stat(os.fstat(fd), path, what, max_bytes)
        chunks, total = [], 0
        while True:  # at most max_bytes + 1: a file that grew since its fstat is refused, not read on
            chunk = os.read(fd, min(MIB, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:
                raise InputFileError(f"{what} {path} grew past the limit of {max_bytes} bytes while read")
        return b"".join(chunks)
    except OSError as exc:
        raise InputFileError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def read_input_text(path: str, what: str, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """``read_input`` decoded as UTF-8 (InputFileError if it is not)."""
    try:
        return read_input(path, what, max_bytes).decode()
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{what} {path} is not UTF-8 text (byte {exc.start})") from None


def atomic_write_bytes(path: str, write) -> None:
    """Call ``write(fileobj)`` on a temp file beside ``path``, fsync, then rename over it."""
    directory = os.path.dirname(os.path.abspath(path))
    _refuse_special_target(path, "output")  # the rename would replace a FIFO or device with a file
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        _refuse_special_target(path, "output")  # (made one while the work ran)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _refuse_special_target(path: str, what: str) -> None:
    """ValueError if ``path`` (symlinks followed) exists and is not a regular file."""
    if not path:
        raise ValueError(f"{what}: an empty path names no file")
    try:
        st = os.stat(path)
    except OSError:  # missing, or a dangling symlink (the rename replaces the link): writable
        return
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{what} {path} is {_kind(st.st_mode)}: it takes a regular file")


def atomic_write_json(path: str, obj) -> None:
    atomic_write_bytes(path, lambda f: f.write((json.dumps(obj, indent=2) + "\n").encode()))


def ensure_writable(path: str, what: str = "output", *, make_dirs: bool = False) -> None:
    """Fail before any work if ``path`` cannot be written: an empty path, a directory, a FIFO
    or a device there (the atomic rename would replace it with a file), its directory missing
    (``make_dirs``: not creatable), or read-only; names ``what`` (the option), the path and
    the cause."""
    _refuse_special_target(path, what)
    directory = os.path.dirname(os.path.abspath(path))
    probe = directory
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if probe != directory and not make_dirs and os.path.isdir(probe):  # (a file there: refused below)
        raise ValueError(f"cannot write {what} {path}: directory {directory} does not exist")
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
