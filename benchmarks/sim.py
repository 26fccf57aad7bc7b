"""Simulator throughput, every implementation side by side in one process.

    python benchmarks/sim.py [options]        # --help: the options

Implementations (coverage / simple_spread, random discrete actions pre-generated):
  taichi      taichi_swarm full step, array="torch", torch int64 actions
  taichi-np   the same env with array="numpy" and numpy actions
  vmas        VMAS ``simple_spread`` (its own 9 discrete actions per agent; no
              episode end, so never resets), a list of per-agent action tensors
  numpy       benchmarks/numpy_step.py's NumpyCoverage, the full step including the exact assignment
              (scipy, a Python loop over the B environments)
  numpy-phys  the same without the assignment (physics, graph, observations, resets)
Each cell: every implementation is built and warmed up (Taichi compiles its kernels on
the first call), then REPEATS rounds in which each implementation in turn runs one chunk
of ~``seconds / REPEATS``, timed with ``time.perf_counter``. Taking turns means a slow
spell of a shared machine hits every implementation alike. The median chunk is reported;
the taichi / vmas ratio is the median of the per-round ratios. agent-steps/s =
B * M * steps / seconds of that chunk; ms/step is one step of the whole batch.
"""

from __future__ import annotations

import io
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

# run from the checkout: its root ahead of benchmarks/ (whose deploy.py would hide the deploy package)
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")  # as `swarm` does: the output is the benchmark's

import numpy as np

from swarm_cli.options import Comm, at_least, fail, parse, positive

IMPLS = ("taichi", "taichi-np", "vmas", "numpy", "numpy-phys")
ACTION_SETS = 8  # distinct pre-generated action batches, cycled
WARMUP_STEPS = 3
REPEATS = 5  # timed chunks per cell; the median chunk is reported
MAX_FIRST_STEP_S = 30.0  # a cell whose first step (compile included) takes longer is skipped, with the reason
COMM_RADIUS = 1.0
# Targets: at B >= TARGET_BIG_B taichi >= 10x VMAS and >= 5 M agent-steps/s; at B = 32 <= 0.3 ms/step.
TARGET_BIG_B, TARGET_VS_VMAS, TARGET_RATE = 1024, 10.0, 5e6
TARGET_SMALL_B, TARGET_SMALL_MS = 32, 0.3
QUICK_SECONDS = 0.25
PROG = "benchmarks/sim.py"

Step = Callable[[int], object]  # step(k): one step of the whole batch with action set k


@dataclass(kw_only=True)
class BenchSimOptions:
    """Agent-steps/s of the taichi_swarm coverage step vs VMAS simple_spread vs plain NumPy,
    measured side by side in one process; prints a table and the target checks."""

    batch_sizes: tuple[int, ...] = (32, 1024, 8192)
    """numbers of environments"""
    agents: tuple[int, ...] = (3, 10)
    """team sizes"""
    vmas: bool = True
    """time VMAS too (--no-vmas: leave it out, shown as skipped)"""
    numpy: bool = True
    """time the NumPy baselines too (--no-numpy: leave them out, shown as skipped)"""
    torch_threads: int = 1
    """torch.set_num_threads during the run (1: see docs/BENCHMARKS.md)"""
    comm: Comm = "rc"
    """communication graph of taichi and numpy: rc = from distances every step, uc = all"""
    seconds: float = 1.5
    """timed seconds per cell"""
    steps: int | None = None
    """a fixed number of timed steps per cell instead (in 5 chunks)"""
    quick: bool = False
    """0.25 s per cell instead of --seconds"""
    json: str | None = None
    """also write the rows and checks to this JSON file"""
    serial_sweep: bool = False
    """instead: time the Taichi step with a serial vs parallel env loop over small B"""

    def __post_init__(self):
        for b in self.batch_sizes:
            at_least(b, 1, "batch-sizes")
        for m in self.agents:
            at_least(m, 1, "agents")
        at_least(self.torch_threads, 1, "torch-threads")
        positive(self.seconds, "seconds")
        at_least(self.steps, 1, "steps")


class Skip(Exception):
    """A cell that is not measured; the message says why and is printed in the table."""


def _taichi(B: int, M: int, comm: str, array: str) -> Step:
    import taichi_swarm

    env = taichi_swarm.make("coverage", B, M, comm=comm, comm_radius=COMM_RADIUS, seed=0, array=array)
    env.reset()
    if array == "torch":
        import torch

        gen = torch.Generator().manual_seed(0)
        acts = [torch.randint(0, 5, (B, M), generator=gen) for _ in range(ACTION_SETS)]  # int64 [B, M]
    else:
        rng = np.random.default_rng(0)
        acts = [rng.integers(0, 5, (B, M)) for _ in range(ACTION_SETS)]  # int64 [B, M]
    return lambda k: env.step(acts[k % ACTION_SETS])


def _vmas(B: int, M: int) -> Step:
    try:
        import torch
        import vmas
    except ImportError as exc:
        raise Skip(f"vmas not importable ({exc}); pip install vmas") from exc
    env = vmas.make_env(
        scenario="simple_spread",
        num_envs=B,
        device="cpu",
        continuous_actions=False,
        n_agents=M,
        seed=0,
    )
    env.reset()
    n = env.action_space[0].n  # 9 in vmas 1.5.2: {-, 0, +} per axis
    gen = torch.Generator().manual_seed(0)
    # per action set: a list of M tensors int64 [B, 1]
    acts = [[torch.randint(0, n, (B, 1), generator=gen) for _ in range(M)] for _ in range(ACTION_SETS)]
    return lambda k: env.step(acts[k % ACTION_SETS])


def _numpy(B: int, M: int, comm: str, assign: bool) -> Step:
    from benchmarks.numpy_step import NumpyCoverage

    env = NumpyCoverage(B, M, comm_radius=COMM_RADIUS if comm == "rc" else None, assign=assign, seed=0)
    rng = np.random.default_rng(0)
    acts = [rng.integers(0, 5, (B, M)) for _ in range(ACTION_SETS)]  # int64 [B, M]
    return lambda k: env.step(acts[k % ACTION_SETS])


def _make(impl: str, B: int, M: int, comm: str) -> Step:
    if impl in ("taichi", "taichi-np"):
        return _taichi(B, M, comm, "torch" if impl == "taichi" else "numpy")
    if impl == "vmas":
        return _vmas(B, M)
    return _numpy(B, M, comm, assign=impl == "numpy")


def warm_up(step: Step) -> None:
    """The first step (Taichi compiles its kernels there), then WARMUP_STEPS - 1 more."""
    t0 = time.perf_counter()
    step(0)
    first = time.perf_counter() - t0
    if first > MAX_FIRST_STEP_S:
        raise Skip(f"first step took {first:.1f} s > {MAX_FIRST_STEP_S:.0f} s cap")
    for k in range(1, WARMUP_STEPS):
        step(k)


def time_chunk(step: Step, k: int, seconds: float, steps: int | None) -> tuple[int, float]:
    """Run ``step`` for ~``seconds`` (or exactly ``steps`` steps, at least one) from action set
    ``k``; returns (steps run, elapsed seconds)."""
    n, start = 0, time.perf_counter()
    while True:
        step(k + n)
        n += 1
        elapsed = time.perf_counter() - start
        if (n >= max(1, steps)) if steps else elapsed >= seconds:
            return n, elapsed


def summarise(chunks: list[tuple[int, float]], agents: int) -> dict:
    """The median chunk (robust to a busy machine), the best and the worst."""
    per_step = [elapsed / n for n, elapsed in chunks]
    median = statistics.median(per_step)
    return {
        "steps": sum(n for n, _ in chunks),  # timed steps (warm-up not counted)
        "seconds": sum(elapsed for _, elapsed in chunks),
        "ms_per_step": 1e3 * median,
        "agent_steps_per_s": agents / median,
        "ms_per_step_best": 1e3 * min(per_step),
        "ms_per_step_worst": 1e3 * max(per_step),
    }


def measure(step: Step, agents: int, seconds: float, steps: int | None = None) -> dict:
    """One implementation alone: warm up, then REPEATS chunks of ``seconds / REPEATS``
    (or ``steps // REPEATS`` steps) each; see ``summarise``."""
    warm_up(step)
    chunk_steps = max(1, steps // REPEATS) if steps else None
    chunks = [time_chunk(step, WARMUP_STEPS + r, seconds / REPEATS, chunk_steps) for r in range(REPEATS)]
    return summarise(chunks, agents)


def measure_interleaved(
    steps_by_impl: dict[str, Step], agents: int, seconds: float, steps: int | None = None
) -> dict[str, dict]:
    """Every implementation of one cell, timed in alternation.

    REPEATS rounds; in each, every implementation runs one chunk (the order reversed
    every other round), so a slow spell of a shared machine hits all of them alike.
    Each result is ``summarise``d, plus ``chunk_ms``: its per-step time in every round,
    so that ratios can be taken round by round (``paired_ratio``). Call ``warm_up`` first.
    """
    chunk_steps = max(1, steps // REPEATS) if steps else None
    chunks: dict[str, list[tuple[int, float]]] = {impl: [] for impl in steps_by_impl}
    order = list(steps_by_impl)
    for r in range(REPEATS):
        for impl in order if r % 2 == 0 else order[::-1]:
            chunks[impl].append(time_chunk(steps_by_impl[impl], WARMUP_STEPS + r, seconds / REPEATS, chunk_steps))
    out = {}
    for impl, cs in chunks.items():
        out[impl] = summarise(cs, agents)
        out[impl]["chunk_ms"] = [1e3 * elapsed / n for n, elapsed in cs]
    return out


def paired_ratio(fast: dict, slow: dict) -> float:
    """Median over rounds of (slow's ms/step / fast's ms/step) in the same round."""
    return statistics.median(s / f for f, s in zip(fast["chunk_ms"], slow["chunk_ms"], strict=True))


def _set_torch_threads(n: int) -> int | None:
    """Set torch's intra-op threads; returns the previous value (None without torch)."""
    try:
        import torch
    except ImportError:
        return None
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    return previous


def run(
    batch_sizes: tuple[int, ...] = (32, 1024, 8192),
    team_sizes: tuple[int, ...] = (3, 10),
    steps: int | None = None,
    seconds: float = 1.5,
    include_vmas: bool = True,
    include_numpy: bool = True,
    out_json: str | None = None,
    torch_threads: int = 1,
    comm: str = "rc",
    verbose: bool = True,
) -> list[dict]:
    """Measure every (implementation, B, M) cell; print the table and target checks; return the rows.

    Each row: impl, B, M, steps and seconds (all timed chunks), ms_per_step and
    agent_steps_per_s (median chunk), ms_per_step_best/worst, skipped (None or the
    reason; then the numbers are None). ``steps`` fixes the timed steps per cell,
    otherwise each cell runs for ~``seconds``. ``comm``: "rc" computes the graph from
    distances every step (taichi and numpy), "uc" is all-to-all.
    """
    disabled = {"vmas": None if include_vmas else "disabled (--no-vmas)"}
    for impl in ("numpy", "numpy-phys"):
        disabled[impl] = None if include_numpy else "disabled (--no-numpy)"
    previous = _set_torch_threads(torch_threads)
    rows = []
    try:
        for B in batch_sizes:
            for M in team_sizes:
                rows += _measure_cell(B, M, comm, seconds, steps, disabled, verbose)
    finally:
        if previous is not None:
            _set_torch_threads(previous)
    checks = target_checks(rows)
    meta = machine_info(torch_threads, comm, seconds, steps)
    if verbose:
        print(format_report(rows, checks, meta))
    if out_json:
        write_json(out_json, {"meta": meta, "rows": rows, "checks": checks})
    return rows


def _measure_cell(B, M, comm, seconds, steps, disabled, verbose) -> list[dict]:
    """One (B, M): build every implementation, time them interleaved, one row each."""
    rows, live = {}, {}
    for impl in IMPLS:
        rows[impl] = {
            "impl": impl,
            "B": B,
            "M": M,
            "steps": None,
            "seconds": None,
            "ms_per_step": None,
            "agent_steps_per_s": None,
            "ms_per_step_best": None,
            "ms_per_step_worst": None,
            "chunk_ms": None,
            "vs_vmas": None,
            "skipped": disabled.get(impl),
        }
        if rows[impl]["skipped"] is None:
            try:
                live[impl] = _make(impl, B, M, comm)
                warm_up(live[impl])  # a too-slow first step skips this impl only
            except Skip as exc:
                rows[impl]["skipped"] = str(exc)
                live.pop(impl, None)
    for impl, result in measure_interleaved(live, B * M, seconds, steps).items():
        rows[impl].update(result)
    if "vmas" in live:
        for impl in ("taichi", "taichi-np"):
            if impl in live:
                rows[impl]["vs_vmas"] = paired_ratio(rows[impl], rows["vmas"])
    if verbose:
        for row in rows.values():
            print(_progress(row), file=sys.stderr, flush=True)
    return list(rows.values())


def _progress(row: dict) -> str:
    where = f"  {row['impl']:<10} B={row['B']:<5} M={row['M']:<3}"
    if row["skipped"]:
        return f"{where} skipped: {row['skipped']}"
    return (
        f"{where} {_rate(row['agent_steps_per_s'])} agent-steps/s, {row['ms_per_step']:.3f} ms/step "
        f"(chunks {row['ms_per_step_best']:.3f}..{row['ms_per_step_worst']:.3f}; {row['steps']} steps, "
        f"{row['seconds']:.2f} s)"
    )


def _rate(x: float | None) -> str:
    if x is None:
        return "skipped"
    return f"{x / 1e6:.2f}M" if x >= 1e6 else f"{x / 1e3:.1f}k"


def _ratio(a: float | None, b: float | None) -> str:
    return "-" if a is None or b is None else f"{a / b:.1f}x"


def _cells(rows: list[dict]) -> dict[tuple[int, int], dict[str, dict]]:
    """(B, M) -> impl -> row, in measurement order."""
    cells: dict[tuple[int, int], dict[str, dict]] = {}
    for r in rows:
        cells.setdefault((r["B"], r["M"]), {})[r["impl"]] = r
    return cells


def target_checks(rows: list[dict]) -> list[dict]:
    """PASS / FAIL / N/A per target and (B, M): dicts with check, B, M, status, detail."""
    out = []
    for (B, M), c in _cells(rows).items():
        t, v = c["taichi"]["agent_steps_per_s"], c.get("vmas", {}).get("agent_steps_per_s")
        ms = c["taichi"]["ms_per_step"]
        if B >= TARGET_BIG_B:
            if t is None or v is None:
                why = c["taichi"]["skipped"] if t is None else c.get("vmas", {}).get("skipped", "not run")
                out.append(_check(f"taichi >= {TARGET_VS_VMAS:.0f}x vmas", B, M, None, f"not measured: {why}"))
            else:
                ratio = _vs_vmas(c)
                out.append(
                    _check(
                        f"taichi >= {TARGET_VS_VMAS:.0f}x vmas",
                        B,
                        M,
                        ratio >= TARGET_VS_VMAS,
                        f"{ratio:.2f}x (median of per-round ratios; medians: taichi {_rate(t)} / vmas {_rate(v)} "
                        f"= {t / v:.2f}x)",
                    )
                )
            out.append(
                _check(
                    f"taichi >= {TARGET_RATE / 1e6:.0f}M agent-steps/s",
                    B,
                    M,
                    None if t is None else t >= TARGET_RATE,
                    f"taichi {_rate(t)}",
                )
            )
        if B == TARGET_SMALL_B:
            ok = None if ms is None else ms <= TARGET_SMALL_MS
            out.append(
                _check(
                    f"taichi <= {TARGET_SMALL_MS} ms/step",
                    B,
                    M,
                    ok,
                    "not measured" if ms is None else f"taichi {ms:.3f} ms/step",
                )
            )
    return out


def _vs_vmas(cell: dict[str, dict]) -> float | None:
    """taichi / vmas: paired round by round when measured interleaved, else of the medians."""
    t, v = cell["taichi"]["agent_steps_per_s"], cell.get("vmas", {}).get("agent_steps_per_s")
    if t is None or v is None:
        return None
    return cell["taichi"].get("vs_vmas") or t / v


def _check(name: str, B: int, M: int, ok: bool | None, detail: str) -> dict:
    status = "N/A" if ok is None else "PASS" if ok else "FAIL"
    return {"check": name, "B": B, "M": M, "status": status, "detail": detail}


def format_report(rows: list[dict], checks: list[dict], meta: dict) -> str:
    """The printed table (agent-steps/s, M = million) and the target checks."""
    head = (
        f"{'B':>6} {'M':>3} | {'taichi':>8} {'ms/step':>8} | {'taichi-np':>9} | {'vmas':>8} {'ms/step':>8} | "
        f"{'numpy':>8} {'numpy-phys':>10} | {'t/vmas':>7} {'t/numpy':>7} {'t/np-phys':>9}"
    )
    lines = [
        f"Simulator benchmark: coverage (VMAS: simple_spread), comm={meta['comm']}, {meta['cpu_count']} CPU cores, "
        f"torch threads={meta['torch_threads']}, taichi threads={meta['taichi_threads']}",
        f"agent-steps/s (M = million, k = thousand); ms/step = one step of the whole batch of B envs; "
        f"median of {REPEATS} timed chunks per cell, the implementations taking turns chunk by chunk; "
        "t/vmas = median of the per-round ratios",
        head,
        "-" * len(head),
    ]
    skipped: dict[str, list[str]] = {}
    for (B, M), c in _cells(rows).items():
        rate = {impl: r["agent_steps_per_s"] for impl, r in c.items()}
        ms = {impl: r["ms_per_step"] for impl, r in c.items()}
        for impl, r in c.items():
            if r["skipped"]:
                skipped.setdefault(f"{impl}: {r['skipped']}", []).append(f"B={B} M={M}")
        t = rate["taichi"]
        lines.append(
            f"{B:>6} {M:>3} | {_rate(t):>8} {_ms(ms['taichi']):>8} | {_rate(rate['taichi-np']):>9} | "
            f"{_rate(rate['vmas']):>8} {_ms(ms['vmas']):>8} | "
            f"{_rate(rate['numpy']):>8} {_rate(rate['numpy-phys']):>10} | "
            f"{_x(_vs_vmas(c)):>7} {_ratio(t, rate['numpy']):>7} {_ratio(t, rate['numpy-phys']):>9}"
        )
    for reason, where in skipped.items():
        lines.append(f"skipped {reason} ({', '.join(where)})")
    lines += ["", "Target checks:"]
    lines += [f"  [{c['status']:>4}] B={c['B']:<5} M={c['M']:<3} {c['check']}: {c['detail']}" for c in checks]
    return "\n".join(lines)


def _x(ratio: float | None) -> str:
    return "-" if ratio is None else f"{ratio:.1f}x"


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def machine_info(torch_threads: int, comm: str, seconds: float, steps: int | None) -> dict:
    """What the numbers depend on: machine, library versions and benchmark settings."""
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    for name in ("taichi", "torch", "scipy", "vmas"):
        try:
            mod = __import__(name)
            v = getattr(mod, "__version__", "?")
            versions[name] = ".".join(map(str, v)) if isinstance(v, tuple) else str(v)
        except ImportError:
            versions[name] = "not installed"
    cpu = platform.processor() or "?"
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "versions": versions,
        "torch_threads": torch_threads,
        "taichi_threads": os.environ.get("TAICHI_SWARM_THREADS") or "all cores",
        "comm": comm,
        "seconds_per_cell": seconds,
        "steps_per_cell": steps,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def write_json(path: str, payload: dict) -> None:
    """Write atomically (taichi_swarm.files: the temp file removed on any failure, a FIFO
    or device at ``path`` refused rather than replaced)."""
    from taichi_swarm.files import atomic_write_bytes

    def write(f):
        text = io.TextIOWrapper(f, encoding="utf-8")
        json.dump(payload, text, indent=2)
        text.write("\n")
        text.flush()
        text.detach()  # (f stays open for atomic_write_bytes' fsync)

    atomic_write_bytes(path, write)


def serial_sweep(
    team_sizes: tuple[int, ...] = (3, 10),
    batch_sizes: tuple[int, ...] = (16, 64, 128, 256, 512, 1024),
    seconds: float = 0.5,
    comm: str = "rc",
) -> list[dict]:
    """Taichi step with the env loop serial vs parallel, and which one ``SwarmEnv`` picks (env.py)."""
    import torch

    import taichi_swarm

    print("serial vs parallel Taichi step ('env picks': the loop SwarmEnv chooses for this B, M)")
    print(f"{'B':>6} {'M':>3} | {'serial ms':>9} {'parallel ms':>11} | {'faster':>8} {'env picks':>9}")
    out = []
    for M in team_sizes:
        for B in batch_sizes:
            env = taichi_swarm.make("coverage", B, M, comm=comm, comm_radius=COMM_RADIUS, seed=0)
            env.reset()
            picked = env._parallel  # the switch SwarmEnv.__init__ sets from B and M
            acts = torch.randint(0, 5, (B, M), generator=torch.Generator().manual_seed(0))
            ms = {}
            for parallel in (False, True):
                env._parallel = parallel
                ms[parallel] = measure(lambda k, e=env, a=acts: e.step(a), B * M, seconds)["ms_per_step"]
            faster = "parallel" if ms[True] < ms[False] else "serial"
            print(
                f"{B:>6} {M:>3} | {ms[False]:>9.3f} {ms[True]:>11.3f} | {faster:>8} "
                f"{'parallel' if picked else 'serial':>9}"
            )
            out.append({"B": B, "M": M, "serial_ms": ms[False], "parallel_ms": ms[True], "env_parallel": picked})
    return out


def main(argv: list[str] | None = None) -> int:
    """Parse, run, print; returns the exit status (a refused option raises SystemExit(2))."""
    args = parse(BenchSimOptions, sys.argv[1:] if argv is None else argv, PROG)
    if args.json is not None:  # ('' too: refused, not skipped)
        from taichi_swarm.files import ensure_writable

        try:
            ensure_writable(args.json, "--json")  # before the benchmark, not after it
        except ValueError as exc:
            return fail(PROG, exc)
    seconds = QUICK_SECONDS if args.quick else args.seconds
    if args.serial_sweep:
        serial_sweep(tuple(args.agents), seconds=seconds, comm=args.comm)
        return 0
    run(
        batch_sizes=tuple(args.batch_sizes),
        team_sizes=tuple(args.agents),
        steps=args.steps,
        seconds=seconds,
        include_vmas=args.vmas,
        include_numpy=args.numpy,
        out_json=args.json,
        torch_threads=args.torch_threads,
        comm=args.comm,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
