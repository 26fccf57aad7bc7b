"""The README's commands name real subcommands, options their --help lists, and
files that exist in the repository."""

import os
import re
import shlex
import subprocess
import sys

import pytest

from swarm_cli.main import COMMANDS

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
README = open(os.path.join(ROOT, "README.md")).read()


def swarm_lines() -> list[list[str]]:
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", README, flags=re.S):
        for line in block.splitlines():
            line = line.split("   #")[0].strip()
            if line.startswith("swarm ") and "|" not in line:
                lines.append(shlex.split(line))
    return lines


def test_readme_starts_with_setup_and_test_commands():
    first = re.search(r"```bash\n(.*?)```", README, flags=re.S).group(1)
    commands = [x for x in first.splitlines() if x and not x.startswith("#")]
    assert "pip install torch==2.13.0" in commands[0] and "swarm train" in commands[0]
    assert commands[1].endswith("python -m pytest")
    assert "python -m pytest" in open(os.path.join(ROOT, ".ci", "run")).read()


@pytest.mark.parametrize("argv", swarm_lines(), ids=lambda a: " ".join(a[:3]))
def test_readme_swarm_command(argv):
    assert argv[1] in COMMANDS, f"unknown subcommand {argv[1]}"
    for token in argv[2:]:
        if token.startswith("results/"):
            assert os.path.exists(os.path.join(ROOT, token)), f"{token} does not exist"
    options = {t.split("=")[0] for t in argv[2:] if t.startswith("--")}
    if not options:
        return
    out = subprocess.run(
        [sys.executable, "-m", "swarm_cli", argv[1], "--help"], capture_output=True, text=True, cwd=ROOT
    )
    text = out.stdout + out.stderr
    for option in options:
        assert option in text, f"swarm {argv[1]} --help does not list {option}"


def tool_lines() -> list[list[str]]:
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", README, flags=re.S):
        for line in block.splitlines():
            line = line.split("   #")[0].strip()
            if line.startswith("python tools/"):
                lines.append(shlex.split(line))
    lines += [shlex.split(m) for m in re.findall(r"`(python tools/[^`]+)`", README)]
    return lines


@pytest.mark.parametrize("argv", tool_lines(), ids=lambda a: " ".join(a[:2]))
def test_readme_tool_command(argv):
    script = os.path.join(ROOT, argv[1])
    assert os.path.exists(script), f"{argv[1]} does not exist"
    out = subprocess.run([sys.executable, script, "--help"], capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0 and "No module named" in out.stderr:
        pytest.skip(f"{argv[1]} needs an optional extra: {out.stderr.strip().splitlines()[-1]}")
    assert out.returncode == 0, out.stderr
    for option in {t.split("=")[0] for t in argv[2:] if t.startswith("--")}:
        assert option in out.stdout, f"{argv[1]} --help does not list {option}"


def _anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.lstrip("#").strip().lower())
    return text.replace(" ", "-")


def test_results_contents_list_every_section_and_every_link_lands():
    """docs/RESULTS.md opens with a contents list: each written section is in it (the tables
    `swarm reproduce` generates are left out), and each of its links names a heading."""
    text = open(os.path.join(ROOT, "docs", "RESULTS.md")).read()
    headings = [h for h in re.findall(r"^#{2,3} .+$", text, flags=re.M)]
    anchors = {_anchor(h) for h in headings}
    contents = text.split("## At a glance")[0]
    links = re.findall(r"\]\(#([^)]+)\)", contents)
    assert links and set(links) <= anchors, sorted(set(links) - anchors)
    written = [h for h in headings if not re.match(r"### (Table \d|Beyond the paper:)", h)]
    assert [_anchor(h) for h in written] == links  # all of them, in the document's order
