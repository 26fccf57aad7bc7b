import os

import pytest

# One Taichi runtime for the whole session, on the CPU, with the offline cache
# shared across runs (kernels compile once per machine, not per test).
os.environ.setdefault("TAICHI_SWARM_CACHE", os.path.join(os.path.dirname(__file__), "..", ".taichi_cache"))
# Kernel variants compile about 5x faster without Taichi's IR optimisation passes (runtime.py), and
# compiling is most of this suite's time on a fresh machine. The tests compare kernels run under
# one setting with each other, or with references within a tolerance; the subprocesses they start
# inherit it.
os.environ.setdefault("TAICHI_SWARM_FAST_COMPILE", "1")


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


# The fast lane (`pytest -m "not slow"`) is the paper-scale product: the dense simulator, PPO,
# checkpoints, export and the in-process executor, the CLI's parsing, the docs and the zoo's index.
# What compiles the large-team kernel variants (neighbour and landmark lists, the radio auction),
# starts agent processes, Ray workers or end-to-end CLI training runs, is slow: each such kernel
# variant costs about 30 s to compile on a fresh machine.
SLOW_MODULES = {
    "test_neighbours.py", "test_density.py", "test_assignment_nearest.py", "test_assignment_large.py",
    "test_radio_auction.py", "test_train_lists.py", "test_model_lists.py", "test_landmark_order.py",
    "test_lists.py", "test_edges.py", "test_network.py", "test_net_lifecycle.py", "test_fine_actions_training.py",
    "test_agent_reward_training.py", "test_agent_reward.py", "test_video.py", "test_radio_agents.py",
}  # fmt: skip
SLOW_TESTS = {"test_readme_python_example_runs", "test_a_large_team_policy_evaluates_in_its_own_setting_as_loaded"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in SLOW_MODULES or item.originalname in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
