import os

import pytest

# One Taichi runtime for the whole session, on the CPU, with the offline cache
# shared across runs (kernels compile once per machine, not per test).
os.environ.setdefault("TAICHI_SWARM_CACHE", os.path.join(os.path.dirname(__file__), "..", ".taichi_cache"))


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    import taichi_swarm

    # TAICHI_SWARM_TEST_ARCH=cuda runs the whole suite on a GPU (tests/test_taichi_swarm/test_cuda.py checks it)
    taichi_swarm.init(os.environ.get("TAICHI_SWARM_TEST_ARCH", "cpu"))
    yield
