"""The one place that calls ``ti.init``.

Taichi keeps one runtime per process, so the first ``make`` (or an explicit
``init``) fixes the architecture; asking for another one later is an error
rather than a silent re-initialisation that would invalidate live buffers.
"""

from __future__ import annotations

import contextlib
import io
import os

import taichi as ti

ARCHES = ("cpu", "cuda", "gpu", "auto")

_state: dict = {"arch": None}


def _default_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "taichi_swarm", "ti_offline_cache")


def init(arch: str = "cpu") -> str:
    """Initialise Taichi once; returns the resolved arch ("cpu" or "cuda").

    ``arch="auto"`` takes CUDA when Taichi finds a GPU and torch can use it,
    otherwise the CPU. Calling again with the same (or "auto") arch is a no-op.
    """
    if arch not in ARCHES:
        raise ValueError(f"arch must be one of {ARCHES}, got {arch!r}")
    want = "cuda" if arch == "gpu" else arch
    current = _state["arch"]
    if current is not None:
        if want not in ("auto", current):
            raise ValueError(
                f"arch={arch!r} requested but Taichi is already initialised on {current!r}; "
                "one process runs one Taichi arch"
            )
        return current
    if want == "auto":
        want = "cuda" if _cuda_usable() else "cpu"
    elif want == "cuda" and not _cuda_usable():  # (Taichi would fall back to the CPU, torch then fail)
        raise ValueError(f"arch={arch!r} but this machine has no CUDA GPU that both torch and Taichi can use")
    cache_dir = os.environ.get("TAICHI_SWARM_CACHE", _default_cache_dir())
    extra = {}
    threads = int(os.environ.get("TAICHI_SWARM_THREADS", "0"))
    if threads > 0:  # default: Taichi uses every core
        extra["cpu_max_num_threads"] = threads
    if os.environ.get("TAICHI_SWARM_FAST_COMPILE") == "1":
        # Taichi's IR optimisation passes off: a kernel variant compiles about 5x faster (43 against
        # 230 s for the radio step on a busy 2-core machine) and steps as fast, but its float32 results
        # are not bit for bit the default's, so the zoo's numbers are measured without it. The test
        # suite sets it (tests/conftest.py): there compiling is most of the time.
        extra["advanced_optimization"] = False
    # ti.init prints its arch unconditionally (a plain print, whatever the log level): a caller's
    # output is the caller's own
    with contextlib.redirect_stdout(io.StringIO()):
        ti.init(
            arch=ti.cuda if want == "cuda" else ti.cpu,
            offline_cache=True,
            offline_cache_file_path=cache_dir,
            default_fp=ti.f32,
            default_ip=ti.i32,
            random_seed=0,
            log_level=ti.WARN,
            **extra,
        )
    _state["arch"] = want
    return want


def _cuda_usable() -> bool:
    """True when torch sees a CUDA device and Taichi was built with CUDA."""
    try:
        import torch  # noqa: PLC0415 - optional: the numpy path runs without torch
    except ImportError:
        return False
    if not torch.cuda.is_available():
        return False
    try:
        return bool(ti._lib.core.with_cuda())
    except Exception:  # noqa: BLE001 - any probe failure means "no CUDA"
        return False


def current_arch() -> str | None:
    """The arch Taichi runs on, or None before ``init``."""
    return _state["arch"]
