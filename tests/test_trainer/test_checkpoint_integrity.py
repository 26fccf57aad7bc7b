"""The whole checkpoint is signed and checked: a flipped byte in any record of a
checkpoint.pt or policy.pt is refused, every restored piece is checked before use, a
file without a digest is refused unless trusted, and no NaN weight is ever written."""

import hashlib
import os
import struct
import zipfile

import pytest
import torch

from trainer import checkpoint
from trainer.checkpoint import save_checkpoint
from trainer.config import PPOConfig, TrainConfig
from trainer.model import ModelConfig, SwarmPolicy
from trainer.ppo import NonFiniteTraining, ppo_update
from trainer.train import build_state, train


def tiny(tmp_path, **kw):
    base = dict(
        task="coverage",
        agents=2,
        updates=1,
        eval_every=1,
        eval_episodes=2,
        checkpoint_every=1,
        run_dir=str(tmp_path / "run"),
        progress=False,
        transfer_offsets=(),
        model=ModelConfig(hidden=16, rounds=1),
        ppo=PPOConfig(num_envs=4, num_steps=8, epochs=1, minibatches=2),
        compile=False,
    )
    return TrainConfig.of(**(base | kw))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    cfg = tiny(tmp_path_factory.mktemp("integrity"))
    train(cfg)
    return cfg.run_dir


def record_spans(path: str) -> list[tuple[str, int, int]]:
    """(name, first byte, size) of the data of every record of a torch zip file."""
    spans = []
    with open(path, "rb") as f, zipfile.ZipFile(path) as z:
        for info in z.infolist():
            f.seek(info.header_offset)
            header = f.read(30)
            name_len, extra_len = struct.unpack("<HH", header[26:30])
            spans.append((info.filename, info.header_offset + 30 + name_len + extra_len, info.compress_size))
    return spans


@pytest.mark.parametrize("name", ["checkpoint.pt", "policy.pt"])
def test_a_flipped_byte_in_every_record_is_refused(run_dir, tmp_path, name):
    source = os.path.join(run_dir, name)
    data = open(source, "rb").read()
    spans = [s for s in record_spans(source) if s[2] > 0]
    names = {n.split("/", 1)[1] for n, _, _ in spans}
    assert {"data.pkl", "version", "byteorder"} <= names and any(n.startswith("data/") for n in names)
    for record, start, size in spans:
        for at in {start, start + size // 2, start + size - 1}:
            flipped = bytearray(data)
            flipped[at] ^= 0xFF
            bad = tmp_path / "bad.pt"
            bad.write_bytes(bytes(flipped))
            with pytest.raises(checkpoint.CheckpointError):
                checkpoint.load(str(bad))
                pytest.fail(f"a flipped byte at {at} in record {record} of {name} was accepted")
    checkpoint.load(source)  # the file itself is fine


def test_every_entry_is_under_the_digest(run_dir, tmp_path):
    """A change to any entry, written by torch (valid CRCs) with the old digest, is refused:
    weights, Adam's moments, environment buffers, reward scalers, RNG state, counters, config."""
    payload = checkpoint.load(run_dir)
    assert checkpoint.payload_digest(payload) == payload["sha256"]
    edits = {
        "model": lambda p: p["model"]["comm_update.bias"].add_(1e-3),
        "optimizer": lambda p: p["optimizer"]["state"][0]["exp_avg"].add_(1e-3),
        "env_states": lambda p: p["env_states"][0]["buffers"]["f32"].add_(1e-3),
        "reward_scalers": lambda p: p["reward_scalers"][0]["ret"].add_(1.0),
        "torch_rng": lambda p: p["torch_rng"].__setitem__(100, p["torch_rng"][100] ^ 1),
        "counters": lambda p: p["counters"].__setitem__("env_steps", p["counters"]["env_steps"] + 1),
        "train_config": lambda p: p["train_config"]["ppo"].__setitem__("lr", 1e-3),
        "evals": lambda p: p["evals"][0].__setitem__("success_rate", 1.0),
    }
    for key, edit in edits.items():
        changed = checkpoint.load(run_dir)
        edit(changed)
        torch.save(changed, str(tmp_path / "edited.pt"))
        with pytest.raises(checkpoint.CheckpointError, match="sha256"):
            checkpoint.load(str(tmp_path / "edited.pt"))
            pytest.fail(f"an edit of {key} was accepted")


def resigned(run_dir, tmp_path, edit) -> str:
    """A copy of the run whose checkpoint, edited, carries a valid digest (as a buggy writer
    would leave it): only the checks of what is restored can refuse it."""
    import shutil

    copy = str(tmp_path / "copy")
    shutil.copytree(run_dir, copy)
    payload = checkpoint.load(os.path.join(copy, "checkpoint.pt"))
    edit(payload)
    checkpoint.save(os.path.join(copy, "checkpoint.pt"), payload)
    return copy


def moment(payload: dict, index: int, name: str) -> torch.Tensor:
    return payload["optimizer"]["state"][index][name].view(-1)


def digest_of(path: str) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.mark.parametrize(
    "what, edit, message",
    [
        ("exp_avg NaN", lambda p: moment(p, 0, "exp_avg").__setitem__(0, float("nan")), "NaN"),
        ("exp_avg_sq < 0", lambda p: moment(p, 1, "exp_avg_sq").__setitem__(0, -1.0), "negative"),
        ("moment shape", lambda p: p["optimizer"]["state"][0].__setitem__("exp_avg", torch.zeros(3)), "shape"),
        ("env NaN", lambda p: p["env_states"][0]["buffers"]["f32"].__setitem__(-1, float("nan")), "NaN"),
        ("env header", lambda p: p["env_states"][0]["buffers"]["i32"].__setitem__(0, 10**6), "header"),
        ("env missing", lambda p: p["env_states"][0]["buffers"].pop("u8"), "lacks buffer u8"),
        ("env count", lambda p: p["env_states"].append(p["env_states"][0]), "one state per team size"),
        ("scaler NaN", lambda p: p["reward_scalers"][0]["rms"]["var"].fill_(float("nan")), "NaN"),
        ("scaler envs", lambda p: p["reward_scalers"][0].__setitem__("ret", torch.zeros(7).double()), "ret"),
        ("rng", lambda p: p.__setitem__("torch_rng", torch.zeros(4, dtype=torch.uint8)), "torch_rng"),
        ("counters", lambda p: p["counters"].__setitem__("update", -1), "counters.update"),
        ("counters 10^12", lambda p: p["counters"].update(update=10**12, env_steps=10**12 * 32), "counters.update"),
        ("env_steps", lambda p: p["counters"].__setitem__("env_steps", p["counters"]["env_steps"] + 1), "env_steps"),
        ("float update", lambda p: p["counters"].__setitem__("update", 1.0), "counters.update"),
        ("hidden float", lambda p: p["model_config"].__setitem__("hidden", 16.0), "hidden"),
        ("int64 weights", lambda p: p.__setitem__("model", {k: v.long() for k, v in p["model"].items()}), "float32"),
    ],
    ids=lambda x: x if isinstance(x, str) else "",
)
def test_restored_pieces_are_checked_before_use(run_dir, tmp_path, what, edit, message):
    copy = resigned(run_dir, tmp_path, edit)
    before = {n: digest_of(os.path.join(copy, n)) for n in ("checkpoint.pt", "policy.pt")}
    with pytest.raises(checkpoint.CheckpointError, match=message):
        train(resume=copy, updates=3)
    assert {n: digest_of(os.path.join(copy, n)) for n in before} == before  # nothing written


def test_a_refused_resume_leaves_no_lock_file_behind(run_dir, tmp_path):
    from swarm_cli.main import main as swarm

    copy = resigned(run_dir, tmp_path, lambda p: p["counters"].__setitem__("update", 10**12))
    lock = os.path.join(copy, ".lock")
    if os.path.exists(lock):
        os.remove(lock)
    before = sorted(os.listdir(copy))
    assert swarm(["train", "--resume", copy, "--updates", "3"]) == 2
    assert sorted(os.listdir(copy)) == before and not os.path.exists(lock)
    with open(lock, "w") as f:  # a lock file that was there stays: another process may be about to take it
        f.write("{}")
    with pytest.raises(checkpoint.CheckpointError, match="counters.update"):
        train(resume=copy, updates=3)
    assert os.path.exists(lock)


def test_nan_in_adam_moments_never_reaches_the_written_weights(run_dir, tmp_path):
    """The CLI refuses the resume in one line; and were the moments loaded, the step guard
    puts the weights back and stops before anything is written."""
    from swarm_cli.main import main as swarm

    def poison(p):
        p["optimizer"]["state"][0]["exp_avg"].view(-1)[0] = float("nan")

    copy = resigned(run_dir, tmp_path, poison)
    before = digest_of(os.path.join(copy, "policy.pt"))
    assert swarm(["train", "--resume", copy, "--updates", "3"]) == 2
    assert digest_of(os.path.join(copy, "policy.pt")) == before
    # past the load checks: the optimiser's own state poisoned in memory
    cfg = tiny(tmp_path, run_dir=str(tmp_path / "guard"))
    state = build_state(cfg, checkpoint.load(run_dir), "cpu")
    for entry in state.optimizer.state.values():
        entry["exp_avg"].fill_(float("nan"))
    from trainer.ppo import collect_rollout, make_loss_fn

    g = state.groups[0]
    r = collect_rollout(state.policy, g.env, g.obs, g.buf, g.scaler, cfg.ppo, "cpu")
    loss_fn = make_loss_fn(state.policy, cfg.ppo)
    with pytest.raises(NonFiniteTraining, match="Adam"):
        ppo_update(state.policy, state.optimizer, [(g.buf, r.advantages, r.returns)], cfg.ppo, loss_fn)
    from trainer.rundir import RunDir

    guard = RunDir(str(tmp_path / "guard-out"))
    os.makedirs(guard.path)
    with pytest.raises(NonFiniteTraining, match="not written"):
        save_checkpoint(guard, state, cfg)
    assert not os.listdir(guard.path)


def test_nan_moments_past_the_load_checks_stop_the_run_before_a_write(run_dir, tmp_path, monkeypatch):
    """The second line: were the moments' check missing, the step guard stops the resumed run
    and neither checkpoint.pt nor policy.pt is rewritten."""

    def poison(p):
        for entry in p["optimizer"]["state"].values():
            entry["exp_avg"].fill_(float("nan"))

    copy = resigned(run_dir, tmp_path, poison)
    before = {n: digest_of(os.path.join(copy, n)) for n in ("checkpoint.pt", "policy.pt")}
    monkeypatch.setattr(checkpoint, "check_optimizer_state", lambda *args: None)
    with pytest.raises(NonFiniteTraining):
        train(resume=copy, updates=3)
    assert {n: digest_of(os.path.join(copy, n)) for n in before} == before


def test_a_file_without_a_digest_is_refused_unless_trusted(run_dir, tmp_path):
    payload = checkpoint.load(os.path.join(run_dir, "policy.pt"))
    legacy = {k: v for k, v in payload.items() if k not in ("sha256", "model_sha256")} | {"version": 1}
    unsigned = tmp_path / "unsigned.pt"
    torch.save(legacy, str(unsigned))
    with pytest.raises(checkpoint.UnsignedCheckpoint, match="--trust-unsigned"):
        checkpoint.load(str(unsigned))
    with pytest.raises(checkpoint.UnsignedCheckpoint):
        checkpoint.load_policy(str(unsigned))
    assert checkpoint.load(str(unsigned), trust_unsigned=True)["counters"] == payload["counters"]
    sha = checkpoint.file_sha256(str(unsigned))
    checkpoint.load_policy(str(unsigned), expected_sha256=sha)  # a zoo entry's sha256 signs it
    with pytest.raises(checkpoint.CheckpointError, match="index entry"):
        checkpoint.load(str(unsigned), expected_sha256="0" * 64)
    with pytest.raises(checkpoint.CheckpointError, match="index entry"):  # even when trusted
        checkpoint.load(str(unsigned), expected_sha256="0" * 64, trust_unsigned=True)
    # a version 2 file must carry its digest: deleting it is not a way round
    stripped = {k: v for k, v in payload.items() if k != "sha256"}
    torch.save(stripped, str(tmp_path / "stripped.pt"))
    with pytest.raises(checkpoint.CheckpointError, match="lacks its sha256"):
        checkpoint.load(str(tmp_path / "stripped.pt"), trust_unsigned=True)


def test_version_1_files_unsigned_refused_legacy_signed_loaded(run_dir, tmp_path):
    """The two layouts written before version 2: no digest at all (refused unless trusted),
    and a digest over the weights only ("model_sha256", still checked)."""
    payload = checkpoint.load(os.path.join(run_dir, "policy.pt"))
    v1 = {k: v for k, v in payload.items() if k not in ("sha256", "model_sha256")} | {"version": 1}
    unsigned, legacy, tampered = (str(tmp_path / f"{n}.pt") for n in ("unsigned", "legacy", "tampered"))
    torch.save(v1, unsigned)
    torch.save(v1 | {"model_sha256": checkpoint.weights_digest(v1["model"])}, legacy)
    with pytest.raises(checkpoint.UnsignedCheckpoint, match="carries no sha256"):
        checkpoint.load_policy(unsigned)
    policy, loaded = checkpoint.load_policy(unsigned, trust_unsigned=True)
    assert loaded["version"] == 1 and isinstance(policy, SwarmPolicy)
    _, loaded = checkpoint.load_policy(legacy)
    assert loaded["version"] == 1 and "model_sha256" not in loaded  # checked, then migrated away
    name = next(iter(v1["model"]))
    changed = dict(v1["model"], **{name: v1["model"][name] + 1})
    torch.save(v1 | {"model": changed, "model_sha256": checkpoint.weights_digest(v1["model"])}, tampered)
    with pytest.raises(checkpoint.CheckpointError):
        checkpoint.load_policy(tampered, trust_unsigned=True)


def test_crafted_network_sizes_and_special_files_are_refused(run_dir, tmp_path):
    payload = checkpoint.load(os.path.join(run_dir, "policy.pt"))
    for key, value, message in (("rounds", 10**9, "rounds"), ("hidden", 10**6, "hidden")):
        crafted = dict(payload, model_config=dict(payload["model_config"], **{key: value}))
        checkpoint.save(str(tmp_path / "crafted.pt"), crafted)
        with pytest.raises(checkpoint.CheckpointError, match=message):
            checkpoint.load_policy(str(tmp_path / "crafted.pt"))
    fifo = tmp_path / "fifo.pt"
    os.mkfifo(fifo)
    with pytest.raises(checkpoint.CheckpointError, match="not a regular file"):  # (open() would block)
        checkpoint.load(str(fifo))


def test_init_from_an_unsigned_file_needs_trust_unsigned(run_dir, tmp_path):
    payload = checkpoint.load(os.path.join(run_dir, "policy.pt"))
    unsigned = str(tmp_path / "unsigned.pt")
    torch.save({k: v for k, v in payload.items() if k not in ("sha256", "model_sha256")} | {"version": 1}, unsigned)
    with pytest.raises(checkpoint.UnsignedCheckpoint, match="--trust-unsigned"):
        train(tiny(tmp_path, run_dir=str(tmp_path / "a"), init_from=unsigned))
    assert not (tmp_path / "a").exists()
    summary = train(tiny(tmp_path, run_dir=str(tmp_path / "b"), init_from=unsigned, trust_unsigned=True))
    assert summary["update"] == 1


def as_version_2(payload: dict) -> dict:
    """A version 3 payload in the layout version 2 wrote: beside the whole-payload sha256,
    the weights' "model_sha256" and the first normaliser again as "reward_scaler"."""
    v2 = {k: v for k, v in payload.items() if k != "sha256"} | {"version": 2}
    v2["model_sha256"] = checkpoint.weights_digest(v2["model"])
    if "reward_scalers" in v2:
        v2["reward_scaler"] = v2["reward_scalers"][0]
    v2["sha256"] = checkpoint.payload_digest(v2)
    return v2


def test_a_version_2_checkpoint_resumes_as_its_version_3_twin(run_dir, tmp_path):
    """The one migration: a run checkpointed by version 2 resumes exactly as the same run
    checkpointed by version 3 (the resumed weights are equal to the bit)."""
    import shutil

    payload = checkpoint.load(os.path.join(run_dir, "checkpoint.pt"))
    assert payload["version"] == checkpoint.VERSION and "model_sha256" not in payload
    assert "reward_scaler" not in payload
    old, new = str(tmp_path / "v2"), str(tmp_path / "v3")
    shutil.copytree(run_dir, old)
    shutil.copytree(run_dir, new)
    torch.save(as_version_2(payload), os.path.join(old, "checkpoint.pt"))
    migrated = checkpoint.load(os.path.join(old, "checkpoint.pt"))
    assert migrated["version"] == 2 and set(migrated) == set(payload)
    train(resume=old, updates=2)
    train(resume=new, updates=2)
    a, b = (checkpoint.load(os.path.join(d, "checkpoint.pt")) for d in (old, new))
    assert a["version"] == b["version"] == checkpoint.VERSION  # rewritten by this version
    for name, tensor in b["model"].items():
        assert torch.equal(a["model"][name], tensor), name
