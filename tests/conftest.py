import os

import pytest

# One Taichi runtime for the whole session, on the CPU, with the offline cache
# shared across runs (kernels compile once per machine, not per test).
os.environ.setdefault("TAICHI_SWARM_CACHE", os.path.join(os.path.dirname(__file__), "..", ".taichi_cache"))


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    import taichi_swarm

    # TAICHI_SWARM_TEST_ARCH=cuda runs the whole suite on a GPU (tests/test_taichi_swarm/test_cuda.py checks it)
    try:
        taichi_swarm.init(os.environ.get("TAICHI_SWARM_TEST_ARCH", "cpu"))
    except ValueError as exc:  # no CUDA on this machine: a GPU run skips instead of failing
        pytest.skip(str(exc))
    yield


@pytest.fixture(scope="session")
def tiny_policy_file(tmp_path_factory) -> str:
    """A signed checkpoint of a random-init policy (hidden 8, one round; seed 0) for coverage,
    M = 2, uc: for tests of commands that take a policy file, not of what it learned. Shared by
    the files a worker runs: read it, never write it."""
    import torch

    from trainer.checkpoint import save
    from trainer.model import ModelConfig, SwarmPolicy

    torch.manual_seed(0)
    net = SwarmPolicy(ModelConfig(hidden=8, rounds=1))
    path = str(tmp_path_factory.mktemp("tiny-policy") / "p.pt")
    task = {"task": "coverage", "agents": 2, "comm": "uc", "comm_radius": 1.0}
    save(path, {"model_config": net.config.to_dict(), "model": net.state_dict(), "task": task})
    return path


@pytest.fixture
def lock_held_elsewhere():
    """``with lock_held_elsewhere(directory, name) as pid``: another process holds
    trainer.rundir's lock ``directory/name`` until the block ends, then dies like kill -9
    (the kernel drops the lock)."""
    import contextlib
    import subprocess
    import sys
    import textwrap

    @contextlib.contextmanager
    def hold(directory: str, name: str = ".lock"):
        holder = subprocess.Popen(
            [
                sys.executable,
                "-c",
                textwrap.dedent(f"""
                import time
                from trainer.rundir import RunDirLock
                RunDirLock({directory!r}, {name!r}).acquire()
                print("locked", flush=True)
                time.sleep(120)
                """),
            ],
            stdout=subprocess.PIPE,
            text=True,
            cwd=os.path.join(os.path.dirname(__file__), ".."),
        )
        try:
            assert holder.stdout.readline().strip() == "locked"
            yield holder.pid
        finally:
            holder.kill()
            holder.wait()

    return hold
