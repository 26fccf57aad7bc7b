"""``swarm bench deploy``: per-agent decision latency, onnxruntime vs torch eager.

One agent's decision at batch 1: encode (own state, L landmark offsets) + K
communication rounds over n messages heard (its own included) + heads, i.e.
exactly what each ``deploy.executor.Agent`` does per step (``calls_per_step``
onnxruntime calls: encode, K - 1 rounds, fused last round + heads). torch runs
the same pieces of ``SwarmPolicy`` eagerly (``set_num_threads(1)``,
``no_grad``). Both get the same inputs; medians over many repetitions.
Target: <= 0.3 ms per agent-step with onnxruntime; the speedup over torch eager is printed as measured.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time

import numpy as np

from swarm_cli.options import BenchDeployOptions, fail, parse

TARGET_MS = 0.3


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
) -> dict:
    """Time one agent-step both ways; returns the numbers and the verdicts."""
    import logging

    import onnxruntime
    import torch

    from deploy.executor import Agent, ExportedModel
    from deploy.export import export
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

    agent = Agent(0, model, threads=1)

    def onnx_step():
        agent.encode(self_obs, entities)
        for _ in range(K - 1):
            agent.round(heard)
        return agent.decide(heard)[0]

    t_obs, t_ent = torch.from_numpy(self_obs), torch.from_numpy(entities)
    t_keys, t_values = torch.from_numpy(heard[:, 0].copy()), torch.from_numpy(heard[:, 1].copy())

    @torch.no_grad()
    def torch_step():
        h = policy.encode(t_obs, t_ent)  # [H]
        for _ in range(K):
            key, value = policy.message(h)
            keys = torch.cat([key[None], t_keys])  # [n + 1, H], own first
            values = torch.cat([value[None], t_values])
            h, _ = policy.update(h[None], keys, values, None)
            h = h[0]
        return policy.heads(h)[0]

    np.testing.assert_allclose(onnx_step(), torch_step().numpy(), atol=1e-4)  # same computation
    onnx_ms, torch_ms = _interleaved_median_ms([onnx_step, torch_step], repeats, warmup)
    speedup = torch_ms / onnx_ms
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
        "versions": {
            "torch": torch.__version__,
            "onnxruntime": onnxruntime.__version__,
            "python": platform.python_version(),
        },
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
    }


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
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """``swarm bench deploy``; returns 0 (the verdicts are printed, not the exit code); a
    refused option raises SystemExit(2)."""
    args = parse(BenchDeployOptions, argv, "swarm bench deploy")
    if args.checkpoint is not None and not os.path.exists(args.checkpoint):
        return fail("swarm bench deploy", f"checkpoint {args.checkpoint} does not exist")
    from trainer.checkpoint import CheckpointError

    try:
        if args.json:
            from taichi_swarm.files import ensure_writable

            ensure_writable(args.json, "--json")  # before the benchmark, not after it
        result = run(args.checkpoint, args.agents, args.landmarks, args.repeats, warmup=max(10, args.repeats // 10))
    except (CheckpointError, ValueError) as exc:
        return fail("swarm bench deploy", exc)
    print(format_result(result))
    if args.json:
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
