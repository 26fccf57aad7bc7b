"""A file that is signed but says the wrong thing: a re-signed checkpoint whose model config has
the wrong types, whose weights are not float32 or whose counters disagree is refused in one
line naming the field; and load_policy's own arguments are checked (expected_sha256 wins over a
zoo entry's, trust_unsigned must be a bool, a path of None or a missing device is one error)."""

import pytest
import torch

from trainer import checkpoint, zoo
from trainer.model import ModelConfig, SwarmPolicy


@pytest.fixture(scope="module")
def payload():
    torch.manual_seed(0)
    policy = SwarmPolicy(ModelConfig(hidden=8, rounds=1))
    return {
        "model_config": policy.config.to_dict(),
        "model": policy.state_dict(),
        "task": {"task": "coverage", "agents": 3, "comm": "uc", "comm_radius": 1.0},
        "counters": {"update": 2, "env_steps": 64, "wall_time": 1.0, "skipped_minibatches": 0},
    }


def signed(tmp_path, payload, **changes) -> str:
    """``payload`` with ``changes``, saved with a valid digest (as a buggy writer would)."""
    path = str(tmp_path / "policy.pt")
    checkpoint.save(path, {**payload, **changes})
    return path


def test_the_fixture_itself_loads(tmp_path, payload):
    policy, _ = checkpoint.load_policy(signed(tmp_path, payload))
    assert policy.config.hidden == 8


@pytest.mark.parametrize(
    "field, value",
    [
        ("hidden", 128.0),
        ("hidden", True),
        ("num_actions", 5.0),
        ("rounds", 3.0),
        ("rounds", False),
        ("num_landmarks", "2"),
        ("entity_mode", 1),
        ("landmark_occupancy", 0),
    ],
)
def test_a_model_config_field_of_the_wrong_type_is_refused(tmp_path, payload, field, value):
    path = signed(tmp_path, payload, model_config={**payload["model_config"], field: value})
    with pytest.raises(checkpoint.CheckpointError, match=field) as info:
        checkpoint.load_policy(path)
    assert not isinstance(info.value, TypeError) and "\n" not in str(info.value)
    with pytest.raises(ValueError, match=field):  # the dataclass itself, not only the loader
        ModelConfig(**{field: value})


def test_a_model_config_that_is_not_a_dict_is_refused(tmp_path, payload):
    with pytest.raises(checkpoint.CheckpointError, match="model_config"):
        checkpoint.load_policy(signed(tmp_path, payload, model_config=[1, 2]))


@pytest.mark.parametrize("dtype", [torch.int64, torch.float64, torch.float16])
def test_weights_that_are_not_float32_are_refused_not_cast(tmp_path, payload, dtype):
    name = "comm_update.weight"
    weights = {**payload["model"], name: payload["model"][name].to(dtype)}
    with pytest.raises(checkpoint.CheckpointError, match="float32") as info:
        checkpoint.load_policy(signed(tmp_path, payload, model=weights))
    assert name in str(info.value) and str(dtype) in str(info.value)


@pytest.mark.parametrize(
    "counters, field",
    [
        ({"update": 10**12, "env_steps": 10**12 * 32}, "counters.update"),
        ({"update": 5, "env_steps": 4}, "counters.update"),
        ({"update": 2, "env_steps": 65}, "counters.env_steps"),
        ({"update": 2.0, "env_steps": 64}, "counters.update"),
        ({"update": True, "env_steps": 64}, "counters.update"),
    ],
)
def test_counters_must_agree_with_each_other_and_the_steps_per_update(counters, field):
    base = {"update": 2, "env_steps": 64, "wall_time": 1.0, "skipped_minibatches": 0}
    assert checkpoint.check_counters("c", base, steps_per_update=32) is base
    with pytest.raises(checkpoint.CheckpointError, match=field):
        checkpoint.check_counters("c", {**base, **counters}, steps_per_update=32)


def test_expected_sha256_wins_over_a_zoo_entry(tmp_path):
    name = zoo.load_index()[0].name
    entry = zoo.get(name)
    actual = zoo.file_sha256(entry.path)
    checkpoint.load_policy(name, expected_sha256=actual.upper())  # the right digest: loaded (any case)
    with pytest.raises(checkpoint.CheckpointError, match="sha256"):
        checkpoint.load_policy(name, expected_sha256="0" * 64)
    with pytest.raises(checkpoint.CheckpointError, match="sha256"):
        checkpoint.load(name, expected_sha256="0" * 64)


def test_trust_unsigned_must_be_a_bool(tmp_path, payload):
    unsigned = str(tmp_path / "unsigned.pt")
    torch.save({"format": checkpoint.FORMAT, "version": 1, **payload}, unsigned)
    for value in ("no", "yes", 1, None):
        with pytest.raises(checkpoint.CheckpointError, match="trust_unsigned"):
            checkpoint.load_policy(unsigned, trust_unsigned=value)
    with pytest.raises(checkpoint.UnsignedCheckpoint):
        checkpoint.load_policy(unsigned, trust_unsigned=False)
    checkpoint.load_policy(unsigned, trust_unsigned=True)


@pytest.mark.parametrize("path", [None, 3, b"policy.pt", ""])
def test_a_path_that_is_not_a_path_is_one_error(path):
    with pytest.raises(checkpoint.CheckpointError, match="path"):
        checkpoint.load_policy(path)
    with pytest.raises(TypeError, match="path"):  # (also a TypeError, which it is)
        checkpoint.load(path)


def test_expected_sha256_must_be_a_digest(tmp_path, payload):
    with pytest.raises(checkpoint.CheckpointError, match="expected_sha256"):
        checkpoint.load_policy(signed(tmp_path, payload), expected_sha256="abc")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_a_device_this_machine_lacks_is_one_line(tmp_path, payload):
    path = signed(tmp_path, payload)
    for device in ("cuda", "cuda:0"):
        with pytest.raises(checkpoint.CheckpointError, match="device") as info:
            checkpoint.load_policy(path, device=device)
        assert "\n" not in str(info.value)
    with pytest.raises(checkpoint.CheckpointError, match="device"):
        checkpoint.load_policy(path, device="tpu-ish")


def test_files_written_while_goal_pass_was_a_field_still_load(tmp_path, payload):
    old = signed(tmp_path, payload, model_config={**payload["model_config"], "goal_pass": False})
    assert checkpoint.load_policy(old)[0].config == ModelConfig(**payload["model_config"])
    goal = signed(tmp_path, payload, model_config={**payload["model_config"], "goal_pass": True})
    with pytest.raises(checkpoint.CheckpointError, match="goal_pass"):
        checkpoint.load_policy(goal)
