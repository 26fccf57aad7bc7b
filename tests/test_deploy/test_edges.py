"""Relative-edge exports (edge_position "relative"): the round pieces take the senders' offsets,
the executor computes them from the observations and equals the torch policy, dense and on
neighbour lists, under drops and delay too; the manifest says which, and the networked agents
refuse such an export."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch
from test_export_execute import _assert_parity, _uc
from test_export_execute import _states as dense_states
from test_lists import _states as list_states
from test_lists import _torch

from deploy.executor import Executor, ExportedModel
from deploy.export import export
from deploy.manifest import MANIFEST, ManifestError, edge_position, seal
from trainer import checkpoint
from trainer.model import ModelConfig, SwarmPolicy


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _export(d, **config) -> tuple[SwarmPolicy, ExportedModel]:
    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=32, rounds=2, **config)).eval()
    if policy.config.edge_position == "relative":  # E_k, E_v start at zero: a test of them needs them non-zero
        for lin in (policy.edge_key, policy.edge_value):
            torch.nn.init.normal_(lin.weight, 0.0, 0.5)
    path = str(d / "ckpt.pt")
    task = {"task": "coverage", "agents": 3, "comm": "rc", "comm_radius": 0.8}
    checkpoint.save(path, {"model_config": policy.config.to_dict(), "model": policy.state_dict(), "task": task})
    export(path, str(d / "onnx"))
    return policy, ExportedModel(str(d / "onnx"))


@pytest.fixture(scope="module")
def relative(tmp_path_factory):
    """self_position "none": the encoder sees (vx, vy, 0, 0), the offsets still the true positions."""
    return _export(tmp_path_factory.mktemp("relative"), edge_position="relative", self_position="none")


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    return _export(tmp_path_factory.mktemp("plain"))


def _graph_inputs(model: ExportedModel, name: str) -> list[str]:
    return [i.name for i in onnx.load_from_string(model.models[name]).graph.input]


@pytest.mark.parametrize("M", [1, 5])
def test_relative_export_matches_torch_dense(relative, M):
    policy, model = relative
    assert model.edge_position == "relative" and _graph_inputs(model, "round") == ["h", "heard", "offsets"]
    executor = Executor(model, 2, M)
    for obs in dense_states("coverage", M, radius=0.8):
        _assert_parity(policy, executor, obs)  # rc
        _assert_parity(policy, executor, _uc(obs))  # uc (M = 1: n = 0, offsets [0, 2])


@pytest.mark.parametrize("M,K", [(12, 2)])
def test_relative_export_matches_torch_on_lists(relative, M, K):
    """K < M - 1: the lists are cut to the K nearest, the offsets those of the listed."""
    policy, model = relative
    executor = Executor(model, 2, M)
    for obs in list_states(M, K):
        want, want_att = _torch(policy, obs)
        got, _, att = executor.decide(obs["self"], obs["entities"], nbr=obs["nbr"], nbr_mask=obs["nbr_mask"])
        np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
        np.testing.assert_allclose(att, want_att, atol=1e-5)


def test_offsets_go_with_the_messages_delivered(relative):
    """Under drops and a one-step delay a receiver gets p_j - p_i of exactly the senders whose
    messages reached it, measured at the step it uses them (receive time)."""
    _, model = relative
    M = 5
    executor = Executor(model, 2, M, drop=0.4, delay=1, seed=3)
    delivered, calls = [], []
    exchange = executor.bus.exchange

    def spy_exchange(r, messages, adj):
        arrived, edges = exchange(r, messages, adj)
        delivered.append(edges.copy())
        return arrived, edges

    executor.bus.exchange = spy_exchange
    for name in ("round", "decide"):
        piece = getattr(executor.pieces, name)

        def spy(h, heard, offsets, piece=piece):
            calls.append((heard, offsets))
            return piece(h, heard, offsets)

        setattr(executor.pieces, name, spy)
    for obs in dense_states("coverage", M, n_states=3, radius=0.8):
        delivered.clear(), calls.clear()
        executor.decide(obs["self"], obs["entities"], obs["adj"])
        pos = obs["self"][..., 2:4]
        it = iter(calls)
        for edges in delivered:  # per round, agent by agent
            for b, i in np.ndindex(2, M):
                heard, offsets = next(it)
                senders = np.flatnonzero(edges[b, i])
                assert len(heard) == len(offsets) == len(senders)
                np.testing.assert_array_equal(offsets, pos[b, senders] - pos[b, i])
    assert 0 < executor.bus.delivered < executor.bus.sent


def test_a_plain_export_takes_no_offsets(plain, tmp_path):
    """No edges: the round pieces take h and heard only; a manifest older than edge_position reads as "none"."""
    _, model = plain
    assert model.manifest["edge_position"] == "none" == model.edge_position
    for name in ("round", "round_heads"):
        assert model.manifest["files"][name]["inputs"] == _graph_inputs(model, name) == ["h", "heard"]
    old = {k: v for k, v in model.manifest.items() if k not in ("edge_position", "manifest_sha256")}
    old["model_config"] = {k: v for k, v in old["model_config"].items() if k != "edge_position"}
    assert edge_position(seal(old)) == "none"
    d = tmp_path / "old"
    d.mkdir()
    for name, entry in model.manifest["files"].items():
        (d / entry["file"]).write_bytes(model.models[name])
    (d / MANIFEST).write_text(json.dumps(seal(old)))
    assert ExportedModel(str(d)).edge_position == "none"


def _set_edge(m: dict, top, config=None) -> dict:
    m = {k: v for k, v in m.items() if k != "manifest_sha256"}
    return {**m, "edge_position": top, "model_config": {**m["model_config"], "edge_position": config or top}}


@pytest.mark.parametrize(
    ("which", "top", "config", "words"),
    [
        ("relative", "none", "relative", "edge_position 'none' differs from model_config.edge_position 'relative'"),
        ("relative", "none", None, "edge_position 'none', but files.round takes offsets"),
        ("plain", "relative", None, "edge_position 'relative', but files.round does not take offsets"),
        ("plain", "absolute", None, "field 'edge_position'"),
    ],
)
def test_an_inconsistent_edge_position_is_refused_in_one_line(relative, plain, which, top, config, words):
    model = (relative if which == "relative" else plain)[1]
    with pytest.raises(ManifestError) as exc:
        seal(_set_edge(model.manifest, top, config))  # sealed again: the check, not the seal, refuses it
    assert words in str(exc.value) and "\n" not in str(exc.value)


def test_networked_agents_measure_the_offsets_of_those_they_hear(relative):
    """Relative edges over the wire: each OBS carries the offsets of the agents heard (a range
    sensor's reading), so M = 3 processes act as the in-process executor does, action for action."""
    pytest.importorskip("zenoh")
    import secrets

    from deploy.executor import make_env, resolve_settings
    from deploy.net.transport import Endpoint, open_session
    from deploy.net.world import AgentProcesses, NetSettings, World
    from taichi_swarm.metrics import run_first_episodes

    _, model = relative
    s = resolve_settings(model, "coverage", 3, "rc", 0.8, episodes=3, seed=11)
    executor, reference = Executor(model, s.episodes, s.agents, seed=s.seed), []

    def decide(obs):
        reference.append(executor.decide(obs["self"], obs["entities"], obs["adj"])[1])
        return reference[-1], None

    run_first_episodes(make_env(model, s), decide)
    port, ns = 20000 + secrets.randbelow(20000), f"edges{secrets.token_hex(4)}"
    endpoint = Endpoint(open_session("router", [f"tcp/127.0.0.1:{port}"], []), ns)
    net = NetSettings(period=0.0, round_deadline=5.0, action_deadline=30.0, start_timeout=60.0)
    world = World(model, s, net, endpoint, quiet=True)
    procs = AgentProcesses(model.directory, 3, f"tcp/127.0.0.1:{port}", ns, net.round_deadline)
    try:
        for i in range(3):
            procs.start(i)
        world.watch = procs.check
        assert world.wait_for_agents(range(3)) == {0, 1, 2}
        row = world.run_episodes()
    finally:
        world.stop_agents()
        procs.stop(timeout=15)
        endpoint.close()
    assert row["missing_actions"] == 0 and len(world.history) == len(reference)
    for t, (got, want) in enumerate(zip(world.history, reference, strict=True)):
        np.testing.assert_array_equal(got, want, err_msg=f"step {t}")
