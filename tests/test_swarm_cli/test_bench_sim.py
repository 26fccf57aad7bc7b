"""The benchmarks (benchmarks/, run from the checkout): the simulator's in a tiny configuration,
the NumPy baseline equal to the Taichi step, their options refused in one line, the GPU scripts."""

import json
import os

import numpy as np
import pytest

import taichi_swarm
from benchmarks import numpy_step
from benchmarks import sim as bench_sim

MEASURED = ("taichi", "taichi-np", "numpy", "numpy-phys")


def test_tiny_run_gives_sane_rows_and_json(tmp_path, capsys):
    out = tmp_path / "sim.json"
    rows = bench_sim.run(batch_sizes=(4,), team_sizes=(3,), steps=5, include_vmas=False, out_json=str(out))
    assert [r["impl"] for r in rows] == list(bench_sim.IMPLS)
    for r in rows:
        assert set(r) == {
            "impl",
            "B",
            "M",
            "steps",
            "seconds",
            "ms_per_step",
            "agent_steps_per_s",
            "ms_per_step_best",
            "ms_per_step_worst",
            "chunk_ms",
            "vs_vmas",
            "skipped",
        }
        assert (r["B"], r["M"]) == (4, 3)
    for r in (r for r in rows if r["impl"] in MEASURED):
        assert r["skipped"] is None and r["steps"] == 5 and r["seconds"] > 0
        assert 0 < r["ms_per_step_best"] <= r["ms_per_step"] <= r["ms_per_step_worst"]
        assert r["agent_steps_per_s"] == pytest.approx(4 * 3 * 1e3 / r["ms_per_step"])
        assert len(r["chunk_ms"]) == bench_sim.REPEATS and r["vs_vmas"] is None
    vmas = next(r for r in rows if r["impl"] == "vmas")
    assert "--no-vmas" in vmas["skipped"] and vmas["agent_steps_per_s"] is None
    printed = capsys.readouterr().out
    assert "Target checks:" in printed and "skipped vmas: disabled (--no-vmas)" in printed
    saved = json.loads(out.read_text())
    assert saved["rows"] == rows and saved["meta"]["torch_threads"] == 1
    assert list(tmp_path.iterdir()) == [out]  # the temporary file was renamed


def test_target_checks_say_na_when_vmas_is_skipped():
    rows = [
        {"impl": "taichi", "B": 1024, "M": 3, "agent_steps_per_s": 6e6, "ms_per_step": 0.5, "skipped": None},
        {"impl": "vmas", "B": 1024, "M": 3, "agent_steps_per_s": None, "ms_per_step": None, "skipped": "why"},
    ]
    status = {c["check"]: c["status"] for c in bench_sim.target_checks(rows)}
    assert status == {"taichi >= 10x vmas": "N/A", "taichi >= 5M agent-steps/s": "PASS"}


def test_ratio_to_vmas_is_paired_round_by_round():
    # taichi's slow round coincides with vmas's slow round: the paired ratio stays 10x,
    # while the ratio of the two medians would say 5x
    taichi = {"chunk_ms": [1.0, 1.0, 2.0, 1.0, 2.0]}
    vmas = {"chunk_ms": [10.0, 10.0, 20.0, 5.0, 20.0]}
    assert bench_sim.paired_ratio(taichi, vmas) == pytest.approx(10.0)
    rows = [
        {
            "impl": "taichi",
            "B": 8192,
            "M": 3,
            "agent_steps_per_s": 9e6,
            "ms_per_step": 2.7,
            "vs_vmas": 10.0,
            "skipped": None,
        },
        {"impl": "vmas", "B": 8192, "M": 3, "agent_steps_per_s": 1e6, "ms_per_step": 24.6, "skipped": None},
    ]
    checks = {c["check"]: c for c in bench_sim.target_checks(rows)}
    assert checks["taichi >= 10x vmas"]["status"] == "PASS"
    assert checks["taichi >= 10x vmas"]["detail"].startswith("10.00x")


def bench(module, argv: list[str]) -> int:
    """A benchmark's main(argv): its exit status, a refused option's SystemExit(2) included."""
    try:
        return module.main(argv)
    except SystemExit as exc:
        return exc.code


def test_cli_runs_and_rejects_bad_arguments(capsys):
    from benchmarks import deploy, train

    assert bench_sim.main(["--batch-sizes", "4", "--agents", "2", "--steps", "2", "--no-vmas"]) == 0
    assert "taichi" in capsys.readouterr().out
    refusals = [
        (bench_sim, ["--batch-sizes", "0"], "--batch-sizes must be >= 1"),
        (bench_sim, ["--agents", "x"], "--agents"),
        (bench_sim, ["--seconds", "-1"], "--seconds must be a positive finite number"),
        (bench_sim, ["--batch-sizes"], "needs at least one value"),  # not "every size"
        (train, ["--threads"], "needs at least one value"),
        (train, ["--minibatches", "0"], "--minibatches must be >= 1"),
        (train, ["--device", "foo"], "device must be cpu, cuda or auto"),  # a ValueError of the benchmark
        (deploy, ["--repeats", "0"], "--repeats must be >= 1"),
        (deploy, ["--checkpoint", "no/such.pt"], "does not exist"),
    ]
    for option in ("--agents", "--updates", "--threads", "--num-envs"):  # nan, inf, negative never run
        refusals += [(train, ["--presets", "paper", option, v], option) for v in ("nan", "-inf", "-1", "0", "abc")]
    for module, argv, says in refusals:
        assert bench(module, argv) == 2, argv
        err = capsys.readouterr().err
        assert says in " ".join(err.split()) and "error" in err and "Traceback" not in err, (argv, err)
    from swarm_cli.main import dispatch  # the lazy import of `swarm`'s subcommands

    assert dispatch("swarm", {"x": ("trainer.no_such_module:main", "")}, ["x"]) == 2
    assert "cannot import trainer.no_such_module" in capsys.readouterr().err


@pytest.mark.parametrize("M", [1, 3, 10])
def test_numpy_step_equals_taichi_step(M):
    """Physics, observations, graph and reward of the NumPy baseline equal the Taichi env's."""
    B, radius = 32, 1.0
    rng = np.random.default_rng(M)
    env = taichi_swarm.make("coverage", B, M, comm="rc", comm_radius=radius, seed=0, array="numpy")
    env.reset()
    # crowded agents (many contacts, graph neither empty nor full), landmarks anywhere
    pos = rng.uniform(-0.6, 0.6, (B, M, 2)).astype(np.float32)
    vel = rng.uniform(-2, 2, (B, M, 2)).astype(np.float32)
    lmk = rng.uniform(-1, 1, (B, M, 2)).astype(np.float32)
    env.set_state(pos=pos, vel=vel, landmarks=lmk, step=np.zeros(B, dtype=np.int32))
    actions = rng.integers(0, 5, (B, M))
    env.step(actions)
    new, live = env.get_state(), ~env.done  # finished envs have restarted: compare the others
    assert live.sum() > B // 2

    pos2, vel2 = numpy_step.physics(pos, vel, actions)
    np.testing.assert_allclose(pos2[live], new["pos"][live], atol=1e-5)
    np.testing.assert_allclose(vel2[live], new["vel"][live], atol=1e-5)
    obs_self, entities = numpy_step.observe(pos2, vel2, lmk)
    np.testing.assert_allclose(obs_self[live], env.obs["self"][live], atol=1e-5)
    np.testing.assert_allclose(entities[live], env.obs["entities"][live], atol=1e-5)
    adj = numpy_step.comm_graph(pos2, radius)
    assert (adj[live] == env.obs["adj"][live]).all()
    assert adj.sum() < B * M * M or M == 1
    d = numpy_step.matched_distances(pos2, lmk)
    np.testing.assert_allclose(d[live], env.matched_dist[live], atol=1e-5)
    np.testing.assert_allclose(np.clip(-d.mean(axis=1), -15, 15)[live], env.reward[live], atol=1e-5)


def test_numpy_env_resets_at_the_time_limit():
    env = numpy_step.NumpyCoverage(8, 3, comm_radius=None, seed=0)
    actions = np.zeros((8, 3), dtype=np.int64)
    for t in range(1, numpy_step.MAX_STEPS + 1):
        (obs_self, entities, adj), reward, done = env.step(actions)
        assert obs_self.shape == (8, 3, 4) and entities.shape == (8, 3, 3, 2) and adj.all()
        assert reward.shape == (8,) and (reward <= 0).all()
        if not done.any():
            assert (env.t == t).all()
    assert done.all() and (env.t == 0).all() and (env.vel == 0).all()


def test_gpu_check_script_arguments():
    import subprocess

    script = os.path.join(os.path.dirname(__file__), "..", "..", "tools", "gpu_check.sh")
    r = subprocess.run([script, "--dry-run", "--agents", "3 5", "--updates", "2"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = [x for x in r.stdout.splitlines() if x.startswith("+ ")]
    assert any("tests/test_taichi_swarm/test_cuda.py" in x for x in lines)
    bench = [x for x in lines if "benchmarks/train.py" in x]
    assert len(bench) == 2 and "--agents 3" in bench[0] and "--agents 5" in bench[1] and "--device cuda" in bench[0]
    assert not any("swarm_cli train" in x for x in lines)  # no training unless asked
    assert any("benchmarks/swarm.py --arch cuda" in x for x in lines)  # large teams on CUDA
    # the layouts it names are benchmarks/swarm.py's (the dry run drops their quotes: read the script)
    import shlex

    from benchmarks import swarm as bench_swarm

    text = open(script).read().replace("\\\n", " ")
    call = next(x for x in text.splitlines() if "benchmarks/swarm.py --arch cuda" in x)
    layouts = shlex.split(call.split("--layouts", 1)[1])
    names = [name for name, _ in bench_swarm.LAYOUTS]
    assert "lists KL=16 free wide" in layouts and set(layouts) <= set(names), layouts
    r = subprocess.run(
        [script, "--dry-run", "--python", "python3", "--train-seconds", "60", "--precisions", "bf16"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    lines = [x for x in r.stdout.splitlines() if x.startswith("+ ")]
    bench = [x for x in lines if "benchmarks/train.py" in x]
    assert len(bench) == 2 and all("--precisions bf16" in x for x in bench)
    assert any(x.startswith("+ timeout --preserve-status -k 60 -s INT 60 python3 -m swarm_cli train") for x in lines)
    bad_args = (["--agents", "0"], ["--bogus"], ["--updates", "x"], ["--precisions", "fp16"], ["--precisions", " "])
    for bad in (*bad_args, ["--train-seconds", "x"]):
        r = subprocess.run([script, "--dry-run", *bad], capture_output=True, text=True)
        assert r.returncode == 2 and r.stderr, bad


def test_bench_train_measures_a_preset_with_overrides():
    """One timed update on the CPU with --num-envs and --minibatches overriding the preset."""
    from benchmarks.train import measure

    row = measure("fast", "coverage", 3, 1, 1, num_envs=8, compile=False, minibatches=2)
    assert row["minibatches"] == 2 and row["agent_samples_per_update"] == 8 * 32 * 3
    assert row["env_steps_per_s"] > 0 and 0 < row["share_update"] < 1


def test_gpu_campaign_script_arguments(tmp_path):
    """tools/gpu_campaign.sh: the jobs it lists are swarm commands that parse here, on the CPU."""
    import shlex
    import subprocess

    from swarm_cli.train import config_from_argv
    from trainer.config import CurriculumConfig, TrainConfig

    script = os.path.join(os.path.dirname(__file__), "..", "..", "tools", "gpu_campaign.sh")
    r = subprocess.run([script, "--list"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    jobs = dict(line.split(": swarm ", 1) for line in r.stdout.splitlines())
    assert len(jobs) == 13 and {"table1-cov6-uc", "curr-cov-rc", "curr-cov-uc-noemp"} <= set(jobs)
    for name, command in jobs.items():
        argv = shlex.split(command)
        config_type = TrainConfig if argv[0] == "train" else CurriculumConfig
        cfg = config_from_argv(argv[1:], f"swarm {argv[0]}", config_type)
        assert cfg.preset == "gpu" and cfg.device == "cuda" and cfg.arch == "cuda", name
        assert cfg.ppo.num_envs == 4096 and cfg.ppo.minibatches == 16, name
        if cfg.init_from.startswith("results/"):  # a policy the tree holds, not a zoo name
            assert os.path.exists(os.path.join(os.path.dirname(script), "..", cfg.init_from)), name
        want_mode = "concat" if name.endswith("-concat") else "padded" if name.endswith("-noemp") else "emp"
        assert cfg.model.entity_mode == want_mode, name
    r = subprocess.run([script, "--dry-run", "--device", "cpu", "curr-form-uc"], capture_output=True, text=True)
    lines = [x for x in r.stdout.splitlines() if x.startswith("+ ")]
    assert r.returncode == 0 and len(lines) == 1 and "curriculum --task formation --comm uc" in lines[0]
    assert "--device cpu --arch cpu" in lines[0] and lines[0].startswith(
        "+ timeout --preserve-status -k 60 -s INT 240 "
    )
    r = subprocess.run([script, "--dry-run", "--work", "w", "curr-cov-rc"], capture_output=True, text=True, cwd="/")
    assert r.returncode == 0 and "--run-dir /w/curr-cov-rc" in r.stdout and "--work /w again resumes" in r.stdout
    work = tmp_path / "work"  # a train job whose run has a checkpoint continues it; a curriculum reruns its command
    (work / "table1-cov3-rc").mkdir(parents=True)
    (work / "table1-cov3-rc" / "checkpoint.pt").write_bytes(b"")
    r = subprocess.run(
        [script, "--dry-run", "--work", str(work), "table1-cov3-rc", "table1-cov6-uc"], capture_output=True, text=True
    )
    lines = [x for x in r.stdout.splitlines() if x.startswith("+ ")]
    assert r.returncode == 0 and f"train --resume {work}/table1-cov3-rc --no-progress --device cuda" in lines[0]
    assert "train --task coverage --agents 6 --comm uc" in lines[1] and f"--run-dir {work}/table1-cov6-uc" in lines[1]
    r = subprocess.run([script, "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.rstrip().endswith("swarm eval RUN/policy.pt --episodes 500 --seed 777")
    r = subprocess.run([script, "--dry-run"], capture_output=True, text=True)
    assert r.returncode == 0 and sum(x.startswith("+ ") for x in r.stdout.splitlines()) == 6  # the default jobs
    bad_args = (
        ["bogus-job"],
        ["--seconds", "0"],
        ["--device", "tpu"],
        ["--frobnicate"],
        list(jobs),
        ["curr-cov-rc"] * 2,
    )
    for bad in bad_args:
        r = subprocess.run([script, "--dry-run", *bad], capture_output=True, text=True)
        assert r.returncode == 2 and r.stderr, bad
