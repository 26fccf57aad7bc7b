"""A radio policy's team as agent processes: each agent runs its own side of the auction
(deploy/radio.py) from what it senses and the tables its teammates send it (TABLE packets).
Pinned here: the numpy agents hold the simulator's tables and observe its landmark rows bit for
bit, through an auto-reset; as processes over Zenoh the team acts as `swarm execute` does, action
for action, at M = 5 and M = 20; the manifest carries the auction's rules."""

from __future__ import annotations

import copy
import os
import secrets

import numpy as np
import pytest
import torch

pytest.importorskip("zenoh")

import taichi_swarm  # noqa: E402
from deploy.executor import Executor, ExportedModel, make_env, resolve_settings  # noqa: E402
from deploy.export import export  # noqa: E402
from deploy.net.transport import Endpoint, open_session  # noqa: E402
from deploy.net.world import AgentProcesses, NetSettings, World  # noqa: E402
from deploy.radio import AgentAuction, sense  # noqa: E402
from taichi_swarm.metrics import run_first_episodes  # noqa: E402
from trainer import checkpoint  # noqa: E402
from trainer.model import ModelConfig, SwarmPolicy  # noqa: E402

# the simulator's setting: tests/test_taichi_swarm/test_radio_auction.py's (one compiled variant)
SWARM = {
    "neighbours": 6, "landmark_neighbours": 8, "sense_radius": 2.0, "landmark_occupancy": True,
    "landmark_order": "radio", "auction_rounds": 4, "scale": "density", "assignment": "free",
}  # fmt: skip


def test_agents_hold_the_simulators_tables_and_observe_its_landmarks():
    """Every agent's numpy auction, fed what the world's sensors report and the tables of the
    teammates on its list, gives the kernel's landmark and landmark rows bit for bit, for 60 steps
    of random actions (coverage's episodes end at 50: the tables start afresh)."""
    M, B = 20, 2
    env = taichi_swarm.make("coverage", B, M, comm="rc", comm_radius=1.0, seed=7, array="numpy", **SWARM)
    obs = env.reset()
    rules = {
        "rounds": 4, "table": 8, "sense_radius": 2.0, "success_threshold": env.params["success_threshold"],
        "increment": 0.5, "hold_slack": 2.0, "stay_out": 2.0,
    }  # fmt: skip
    agents = [AgentAuction(i, B, rules) for i in range(M)]
    rng = np.random.default_rng(1)
    fresh_steps, held = 0, []
    for step in range(61):
        if step:
            obs = env.step(rng.integers(0, 5, size=(B, M)))[0]
        state = env.get_state()
        fresh_steps += int(step > 0 and (state["step"] == 0).all())
        for b in range(B):
            sensing = sense(state["pos"][b], state["landmarks"][b], 2.0, 16)
            for i, a in enumerate(agents):
                a.rebuild(b, state["step"][b] == 0, sensing[i])
            for _ in range(env.auction_rounds):
                for a in agents:
                    a.bid(b)
                sent = [copy.deepcopy(a.table(b)) for a in agents]  # what each sends this round
                for i, a in enumerate(agents):
                    heard = obs["nbr"][b, i][obs["nbr_mask"][b, i]]
                    a.merge(b, [sent[j] for j in heard])
            won = np.array([a.won[b] for a in agents])
            np.testing.assert_array_equal(won, np.asarray(env._view("radio_won"))[b], err_msg=f"step {step}")
            held.append((won >= 0).mean())
            for i, a in enumerate(agents):
                n = int(obs["entity_mask"][b, i].sum())
                np.testing.assert_array_equal(a.landmarks(b, sensing[i]), obs["entities"][b, i, :n])
    assert fresh_steps == 1
    assert np.mean(held) > 0.5  # the auction does something under motion


@pytest.fixture(scope="module")
def radio_export(tmp_path_factory):
    """A random-init radio policy for coverage (relative edges, occupancy input, K = 2), exported."""
    d = tmp_path_factory.mktemp("radio")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        cfg = ModelConfig(hidden=32, rounds=2, self_position="none", edge_position="relative", landmark_occupancy=True)
        policy = SwarmPolicy(cfg).eval()
        payload = {
            "model_config": policy.config.to_dict(),
            "model": policy.state_dict(),
            "task": {"task": "coverage", "agents": 20, "comm": "rc", "comm_radius": 1.0},
            "swarm": SWARM,
        }
        checkpoint.save(str(d / "ckpt.pt"), payload)
        export(str(d / "ckpt.pt"), str(d / "onnx"))
    finally:
        torch.set_num_threads(threads)
    return str(d / "onnx")


def test_the_manifest_carries_the_auctions_rules(radio_export):
    rules = ExportedModel(radio_export).manifest["contract"]["radio"]
    assert rules["rounds"] == 4 and rules["table"] == 8 and rules["sense_radius"] == 2.0
    assert (rules["increment"], rules["hold_slack"], rules["stay_out"]) == (
        taichi_swarm.radio.ROUND_EPS, taichi_swarm.radio.HOLD_SLACK, taichi_swarm.radio.OUT,
    )  # fmt: skip


@pytest.mark.parametrize("agents", [5, 20])
def test_the_radio_team_as_processes_acts_as_execute(radio_export, agents):
    """M agent processes on 127.0.0.1 running the auction by TABLE packets, then the network by
    MSG: every action of every step equals the in-process executor's (whose simulator runs the
    auction in its kernels); nothing missed or late."""
    model = ExportedModel(radio_export)
    s = resolve_settings(model, "coverage", agents, episodes=2, seed=5)
    executor = Executor(model, s.episodes, s.agents, seed=s.seed)
    reference = []

    def decide(obs):
        graph = {k: obs[k] for k in ("nbr", "nbr_mask", "entity_mask")}
        actions = executor.decide(obs["self"], obs["entities"], **graph)[1]
        reference.append(actions)
        return actions, None

    summary = run_first_episodes(make_env(model, s), decide).summary(s.task)
    port = 20000 + secrets.randbelow(20000)
    ns = f"radio{secrets.token_hex(4)}"
    endpoint = Endpoint(open_session("router", [f"tcp/127.0.0.1:{port}"], []), ns)
    net = NetSettings(period=0.0, round_deadline=10.0, action_deadline=120.0, start_timeout=120.0)
    world = World(model, s, net, endpoint, quiet=True)
    procs = AgentProcesses(radio_export, agents, f"tcp/127.0.0.1:{port}", ns, net.round_deadline)
    try:
        for i in range(agents):
            procs.start(i)
        world.watch = procs.check
        assert world.wait_for_agents(range(agents)) == set(range(agents))
        row = world.run_episodes()
        rss, pss = procs.memory_mb("status", "VmHWM:"), procs.memory_mb("smaps_rollup", "Pss:")
    finally:
        world.stop_agents()
        procs.stop(timeout=15)
        endpoint.close()
    if os.path.exists("/proc/self/smaps_rollup"):  # (Linux): each agent's peak RSS, and its share of pages now
        assert set(rss) == set(pss) == set(range(agents))
        assert all(0 < pss[i] <= rss[i] for i in range(agents))  # shared pages split: never more than RSS
    assert row["missing_actions"] == 0
    assert all(r["missed"] == 0 and r["late"] == 0 for r in row["agents_report"])
    assert len(world.history) == len(reference)
    for t, (got, want) in enumerate(zip(world.history, reference, strict=True)):
        np.testing.assert_array_equal(got, want, err_msg=f"step {t}")
    assert row["success_rate"] == summary["success_rate"]
    # each agent heard a table and a message per teammate on its list, per round
    assert all(r["msgs_heard"] > 0 for r in row["agents_report"])


class _Endpoint:
    ns = "swarm"
    sent = sent_bytes = 0

    def subscribe(self, *parts):
        pass

    def publish(self, data, *parts):
        pass

    def matched(self, *parts):
        return True

    def get(self, timeout):
        return None


def test_tables_are_messages_like_any_other(radio_export):
    """A TABLE goes through the agent's faults like a MSG (all lost at drop 1), one from an agent
    it does not hear this step is not read, and a malformed one is counted, never acted on."""
    from deploy.net import protocol as P
    from deploy.net.agent import NetAgent
    from deploy.net.faults import FaultSpec
    from deploy.radio import Table

    table = [Table(np.array([1, 4], np.int32), np.zeros(2, np.int32), np.ones(2, np.float32), np.array([2, -1]))]
    for drop, sender, kept in ((0.0, 2, True), (1.0, 2, False), (0.0, 3, False)):
        agent = NetAgent(ExportedModel(radio_export), 0, _Endpoint(), faults=FaultSpec(drop=drop), quiet=True)
        agent.run, agent.step, agent.round, agent.B, agent.M = 5, 3, 0, 1, 4
        agent._need = {3: [{1, 2}]}  # this step it hears agents 1 and 2
        agent._on_packet(f"swarm/table/{sender}", P.table_packet(5, 3, 0, sender, table), 0.0)
        got = agent.box.get((3, 0), {}).get(0, {})
        assert (sender in got) == kept, (drop, sender)
        if kept:
            np.testing.assert_array_equal(got[sender].lid, [1, 4])
    assert agent.faults.injected_losses == 0 and agent.stats["late"] == 0  # (agent 3's: not read at all)
    unsorted = Table(np.array([4, 1], np.int32), np.zeros(2, np.int32), np.ones(2, np.float32), np.array([2, -1]))
    bad = P.table_packet(5, 3, 0, 2, [unsorted])
    agent._on_packet("swarm/table/2", bad, 0.0)
    assert agent.stats["malformed"] == 1


@pytest.mark.parametrize("command", ["agent", "world"])
def test_a_radio_export_without_its_rules_is_refused_in_one_line(radio_export, tmp_path, capsys, command):
    import json
    import shutil

    from deploy.manifest import seal
    from swarm_cli.net import agent_main, world_main

    old = str(tmp_path / "old")
    shutil.copytree(radio_export, old)
    manifest = json.load(open(f"{old}/manifest.json"))
    del manifest["contract"]["radio"]
    manifest.pop("manifest_sha256")
    json.dump(seal(manifest), open(f"{old}/manifest.json", "w"))
    code = agent_main([old, "--id", "0"]) if command == "agent" else world_main(["--export", old, "--episodes", "1"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "exported without its auction's rules" in lines[0], lines
