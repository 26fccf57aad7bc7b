"""Deployment latency: per-agent decision latency, onnxruntime vs torch eager; and the
executor's shared sessions vs one set of sessions per agent.

    python benchmarks/deploy.py [options]     # --help: the options

One agent's decision at batch 1: encode (own state, L landmark offsets) + K
communication rounds over n messages heard (its own included) + heads, i.e.
exactly what ``deploy.executor.Pieces`` runs per agent and step (``calls_per_step``
onnxruntime calls: encode, K - 1 rounds, fused last round + heads). torch runs
the same pieces of ``SwarmPolicy`` eagerly (``set_num_threads(1)``,
``no_grad``). Both get the same inputs; medians over many repetitions.
Target: <= 0.3 ms per agent-step with onnxruntime; the speedup over torch eager is printed as measured.

The executor comparison runs ``Executor.decide`` on B teams of M agents ("uc") twice: as
it is (one session per ONNX piece, shared by all B x M agents) and with every agent
given its own sessions (``_PerAgentSessions``, the reference kept only here). The code
path and the arithmetic are the same, the actions equal; only the sessions differ.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Annotated

# run from the checkout: its root ahead of benchmarks/ (whose deploy.py would hide the deploy package)
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")  # as `swarm` does: the output is the benchmark's

import numpy as np

from swarm_cli.options import Default, at_least, fail, parse

TARGET_MS = 0.3
PROG = "benchmarks/deploy.py"


@dataclass(kw_only=True)
class BenchDeployOptions:
    """Per-agent decision latency (onnxruntime against torch eager) and the executor's shared
    sessions against per-agent sessions."""

    checkpoint: Annotated[str | None, Default("a random-init policy")] = None
    """a checkpoint to time"""
    agents: int = 5
    """team size M: the agent hears M - 1 others"""
    landmarks: Annotated[int | None, Default("M, as in coverage")] = None
    """L"""
    repeats: int = 3000
    """timed agent-steps per backend"""
    envs: int = 20
    """teams B of the executor comparison (B x M agents)"""
    steps: int = 20
    """timed executor decision steps per variant"""
    json: str | None = None
    """also write the result to this JSON file"""

    def __post_init__(self):
        for name in ("agents", "landmarks", "repeats", "envs", "steps"):
            at_least(getattr(self, name), 1, name)


def _interleaved_median_ms(fns, repeats: int, warmup: int, block: int = 100) -> list[float]:
    """Median ms per call of each function, timed in alternating blocks of ``block``
    calls, so that a slow spell of a shared machine hits every backend alike."""
    for fn in fns:
        for _ in range(warmup):
            fn()
    times = [[] for _ in fns]
    for _ in range(max(1, repeats // block)):
        for fn, out in zip(fns, times, strict=True):
            for _ in range(block):
                t0 = time.perf_counter()
                fn()
                out.append(time.perf_counter() - t0)
    return [float(np.median(t) * 1e3) for t in times]


def run(
    checkpoint: str | None = None,
    agents: int = 5,
    landmarks: int | None = None,
    repeats: int = 3000,
    warmup: int = 300,
    seed: int = 0,
    envs: int = 20,
    steps: int = 20,
) -> dict:
    """Time one agent-step both ways; returns the numbers and the verdicts."""
    import logging

    import onnxruntime
    import torch

    from deploy.export import export, round_update
    from deploy.policy import ExportedModel, Pieces
    from trainer import checkpoint as ckpt
    from trainer.model import ModelConfig, SwarmPolicy

    for name in ("torch.onnx", "torch.onnx._internal.exporter._registration"):
        logging.getLogger(name).setLevel(logging.ERROR)
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    with tempfile.TemporaryDirectory() as tmp:
        if checkpoint is None:
            policy = SwarmPolicy(ModelConfig())
            checkpoint = os.path.join(tmp, "random_init.pt")
            ckpt.save(
                checkpoint,
                {
                    "model_config": policy.config.to_dict(),
                    "model": policy.state_dict(),
                    "task": {"task": "coverage", "agents": agents, "comm": "uc", "comm_radius": 1.0},
                },
            )
            source = "random-init SwarmPolicy (H=128, K=3, emp)"
        else:
            source = checkpoint
        export(checkpoint, os.path.join(tmp, "onnx"))
        model = ExportedModel(os.path.join(tmp, "onnx"))
        policy, _ = ckpt.load_policy(checkpoint)
    cfg = policy.config
    L = landmarks or (cfg.num_landmarks if cfg.entity_mode == "concat" else agents)
    H, K, n = cfg.hidden, cfg.rounds, agents - 1  # n neighbours heard (uc), own message added by the agent
    rng = np.random.default_rng(seed)
    self_obs = rng.normal(size=4).astype(np.float32)  # [4]
    entities = rng.normal(size=(L, 2)).astype(np.float32)  # [L, 2]
    heard = rng.normal(size=(n, 2, H)).astype(np.float32)  # [n, 2, H]: key, value of each neighbour
    # relative edges: the senders' offsets p_j - p_i [n, 2], an input of every round
    offsets = rng.normal(size=(n, 2)).astype(np.float32) if cfg.edge_position == "relative" else None

    pieces = Pieces(model, threads=1)

    def onnx_step():
        h, _ = pieces.encode(self_obs, entities)
        for _ in range(K - 1):
            h, _ = pieces.round(h, heard, offsets)
        return pieces.decide(h, heard, offsets)[0]

    t_obs, t_ent, t_heard = torch.from_numpy(self_obs), torch.from_numpy(entities), torch.from_numpy(heard)
    t_offsets = None if offsets is None else torch.from_numpy(offsets)

    @torch.no_grad()
    def torch_step():
        h = policy.encode(t_obs, t_ent)  # [H]
        for _ in range(K):
            h, _ = round_update(policy, h, t_heard, t_offsets)  # the round pieces' torch code, eager
        return policy.heads(h)[0]

    np.testing.assert_allclose(onnx_step(), torch_step().numpy(), atol=1e-4)  # same computation
    onnx_ms, torch_ms = _interleaved_median_ms([onnx_step, torch_step], repeats, warmup)
    speedup = torch_ms / onnx_ms
    executor = executor_ab(model, envs, agents, L, steps, seed)
    return {
        "source": source,
        "agents": agents,
        "neighbours_heard": n,
        "landmarks": L,
        "hidden": H,
        "rounds": K,
        "onnx_calls_per_step": 1 + max(K, 1),
        "repeats": repeats,
        "onnxruntime_ms": onnx_ms,
        "torch_ms": torch_ms,
        "speedup": speedup,
        "pass_latency": onnx_ms <= TARGET_MS,
        "executor": executor,
        "versions": {
            "torch": torch.__version__,
            "onnxruntime": onnxruntime.__version__,
            "python": platform.python_version(),
        },
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
    }


class _PerAgentSessions:
    """The reference: every agent of every team its own ``Pieces`` (own sessions). ``Executor``
    calls its pieces agent by agent, b-major, B x M calls in every phase, so the k-th call of
    a step is agent k mod (B x M)'s and goes to that agent's sessions."""

    def __init__(self, model, agents: int):
        from deploy.policy import Pieces

        self.agents = [Pieces(model) for _ in range(agents)]
        self.k = 0

    def _next(self):
        pieces = self.agents[self.k]
        self.k = (self.k + 1) % len(self.agents)
        return pieces

    def encode(self, *args):
        return self._next().encode(*args)

    def round(self, *args):
        return self._next().round(*args)

    def decide(self, *args):
        return self._next().decide(*args)


def _rss_mb() -> float | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None  # not Linux: memory is left out


def executor_ab(model, envs: int, agents: int, landmarks: int, steps: int, seed: int = 0) -> dict:
    """Setup time, resident memory and ms per decision step of ``Executor`` with shared vs
    per-agent sessions, on the same observations (timed in alternating steps)."""
    from deploy.executor import Executor

    B, M = envs, agents
    rng = np.random.default_rng(seed)
    self_obs = rng.normal(size=(B, M, 4)).astype(np.float32)
    entities = rng.normal(size=(B, M, landmarks, 2)).astype(np.float32)
    adj = np.ones((B, M, M), bool)
    built = {}
    for name in ("shared", "per_agent"):
        rss, t0 = _rss_mb(), time.perf_counter()
        ex = Executor(model, B, M, seed=seed)
        if name == "per_agent":
            ex.pieces = _PerAgentSessions(model, B * M)
        setup = time.perf_counter() - t0
        memory = None if rss is None else _rss_mb() - rss
        built[name] = (ex, setup, memory)
    shared, per_agent = built["shared"][0], built["per_agent"][0]
    a, b = shared.decide(self_obs, entities, adj), per_agent.decide(self_obs, entities, adj)
    np.testing.assert_array_equal(a[1], b[1])  # the same actions: only the sessions differ
    np.testing.assert_allclose(a[0], b[0], atol=1e-6)
    ms = _interleaved_median_ms(
        [lambda: shared.decide(self_obs, entities, adj), lambda: per_agent.decide(self_obs, entities, adj)],
        repeats=steps, warmup=1, block=1,
    )  # fmt: skip
    out = {"envs": B, "agents": M, "steps": steps}
    for (name, (_, setup, memory)), step_ms in zip(built.items(), ms, strict=True):
        out[name] = {"setup_s": setup, "memory_mb": memory, "step_ms": step_ms}
    pieces = 2 + (model.rounds > 1)  # encode, [round,] round_heads or heads
    out["shared"]["sessions"], out["per_agent"]["sessions"] = pieces, B * M * pieces
    return out


def format_result(r: dict) -> str:
    def verdict(ok: bool) -> str:
        return "PASS" if ok else "FAIL"

    return "\n".join(
        [
            f"per-agent decision latency (batch 1, 1 thread): {r['source']}",
            f"  M={r['agents']} (heard {r['neighbours_heard']} + self), L={r['landmarks']}, H={r['hidden']}, "
            f"K={r['rounds']}, {r['onnx_calls_per_step']} onnxruntime calls per step, median of {r['repeats']}",
            f"  {'backend':<26} {'ms/agent-step':>13}",
            f"  {'onnxruntime ' + r['versions']['onnxruntime']:<26} {r['onnxruntime_ms']:>13.4f}",
            f"  {'torch eager ' + r['versions']['torch']:<26} {r['torch_ms']:>13.4f}",
            f"  speedup onnxruntime vs torch: {r['speedup']:.2f}x",
            f"  target <= {TARGET_MS} ms per agent-step: {verdict(r['pass_latency'])} ({r['onnxruntime_ms']:.3f} ms)",
            *_format_executor(r["executor"]),
        ]
    )


def _format_executor(e: dict) -> list[str]:
    shared, ref = e["shared"], e["per_agent"]

    def mb(v):
        return "n/a" if v is None else f"{v:.0f}"

    def ratio(key):
        return f"{ref[key] / shared[key]:.2f}x" if ref[key] is not None and shared[key] else "n/a"

    lines = [
        f'executor ("uc"): B={e["envs"]} teams x M={e["agents"]} = {e["envs"] * e["agents"]} agents, '
        f"median of {e['steps']} decision steps",
        f"  {'sessions':<22} {'count':>7} {'setup s':>9} {'memory MB':>10} {'ms/step':>9}",
    ]
    for name, v in (("shared (executor)", shared), ("per agent (reference)", ref)):
        lines.append(
            f"  {name:<22} {v['sessions']:>7} {v['setup_s']:>9.3f} {mb(v['memory_mb']):>10} {v['step_ms']:>9.2f}"
        )
    lines.append(
        f"  per agent / shared: setup {ratio('setup_s')}, memory {ratio('memory_mb')}, step {ratio('step_ms')}"
    )
    return lines


def main(argv: list[str] | None = None) -> int:
    """Returns 0 (the verdicts are printed, not the exit code); a refused option raises SystemExit(2)."""
    args = parse(BenchDeployOptions, sys.argv[1:] if argv is None else argv, PROG)
    if args.checkpoint is not None and not os.path.exists(args.checkpoint):
        return fail(PROG, f"checkpoint {args.checkpoint} does not exist")
    from trainer.checkpoint import CheckpointError

    try:
        if args.json is not None:  # ('' too: refused, not skipped)
            from taichi_swarm.files import ensure_writable

            ensure_writable(args.json, "--json")  # before the benchmark, not after it
        result = run(
            args.checkpoint, args.agents, args.landmarks, args.repeats, warmup=max(10, args.repeats // 10),
            envs=args.envs, steps=args.steps,
        )  # fmt: skip
    except (CheckpointError, ValueError) as exc:
        return fail(PROG, exc)
    print(format_result(result))
    if args.json:
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
