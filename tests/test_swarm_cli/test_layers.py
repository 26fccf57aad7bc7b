"""Layers depend only downwards: taichi_swarm < trainer < deploy < swarm_cli, baselines on
the simulator alone, reproduce (the paper's tables) on trainer and baselines. Checked on
the import statements of every module."""

import ast
import os

import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
PACKAGES = ("taichi_swarm", "trainer", "deploy", "baselines", "reproduce", "swarm_cli")
# what each package may import from this project (itself always)
ALLOWED = {
    "taichi_swarm": set(),
    "trainer": {"taichi_swarm"},
    "deploy": {"taichi_swarm", "trainer"},
    "baselines": {"taichi_swarm"},
    "reproduce": {"taichi_swarm", "trainer", "baselines"},
    "swarm_cli": {"taichi_swarm", "trainer", "deploy", "baselines", "reproduce"},
}


def imported_packages(path: str) -> set[str]:
    tree = ast.parse(open(path).read(), path)
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names & {*PACKAGES, "benchmarks"}  # (benchmarks/ is not installed: no package may import it)


def modules():
    for package in PACKAGES:
        for dirpath, _, files in os.walk(os.path.join(ROOT, package)):
            for name in files:
                if name.endswith(".py"):
                    yield package, os.path.relpath(os.path.join(dirpath, name), ROOT)


@pytest.mark.parametrize(("package", "path"), list(modules()), ids=lambda x: x)
def test_imports_point_downwards(package, path):
    upward = imported_packages(os.path.join(ROOT, path)) - ALLOWED[package] - {package}
    assert not upward, f"{path} imports {sorted(upward)}: {package} may use only {sorted(ALLOWED[package])}"


def test_test_folders_mirror_the_packages():
    """tests/test_<package>/ holds the tests of <package>, one folder per package and no
    test file loose in tests/ (the folder is not named <package> itself, which would
    shadow the package on sys.path)."""
    tests = os.path.join(ROOT, "tests")
    folders = {d for d in os.listdir(tests) if os.path.isdir(os.path.join(tests, d)) and d.startswith("test_")}
    assert folders == {f"test_{p}" for p in PACKAGES}
    loose = [f for f in os.listdir(tests) if f.startswith("test_") and f.endswith(".py")]
    assert not loose, f"test files outside a package folder: {loose}"


def test_the_checker_sees_an_upward_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from swarm_cli.main import main\n    import deploy.export\n")
    assert imported_packages(str(bad)) == {"swarm_cli", "deploy"}


def test_every_command_option_has_help(monkeypatch):
    """Every option of every `swarm` subcommand (argparse or tyro) says what it does."""
    import argparse
    import importlib

    from swarm_cli.main import COMMANDS

    missing = []
    real = argparse.ArgumentParser.add_argument

    def recording(self, *args, **kwargs):
        action = real(self, *args, **kwargs)
        user_facing = self.add_help and args and str(args[0]).startswith("--")
        if user_facing and not kwargs.get("help") and args[0] != "--help":
            missing.append(f"{self.prog}: {args[0]}")
        return action

    monkeypatch.setattr(argparse.ArgumentParser, "add_argument", recording)
    for target, _ in COMMANDS.values():
        module, func = target.split(":")
        try:
            getattr(importlib.import_module(module), func)(["--help"])
        except SystemExit:
            pass
    assert not missing, missing
