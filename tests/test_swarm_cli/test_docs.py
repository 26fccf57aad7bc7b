"""The docs describe the product as it is: every command they show names a real subcommand,
options its --help lists, files that exist and zoo entries that exist; the generated pages
(CLI reference, results tables, zoo cards) match a fresh render; no history in code or docs."""

import os
import re
import shlex
import subprocess
import sys

import pytest

from swarm_cli.main import COMMANDS

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
README = open(os.path.join(ROOT, "README.md")).read()
DOCS = ["README.md", "models/README.md"] + sorted(
    os.path.join("docs", f)
    for f in os.listdir(os.path.join(ROOT, "docs"))
    if f.endswith(".md") and f not in ("CLI.md", "HISTORY.md")
)


def _zoo_names() -> set[str]:
    from trainer.zoo import load_index

    return {e.name for e in load_index()}


def _blocks(text: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", text, flags=re.S)


def command_lines(prefix: str) -> list[tuple[str, list[str]]]:
    """(doc, argv) of every line starting with ``prefix`` in a bash block of a doc, and of every
    inline `swarm ...` / `python tools/...` span (commands chained with && are split)."""
    lines = []
    for doc in DOCS:
        text = open(os.path.join(ROOT, doc)).read()
        candidates = [line for block in _blocks(text) for line in block.splitlines()]
        candidates += re.findall(r"`((?:swarm|python tools/)[^`]*)`", text)
        for line in candidates:
            for part in line.split("&&"):
                part = part.split("  #")[0].strip()
                if part.startswith(prefix) and "|" not in part and "..." not in part:
                    lines.append((doc, shlex.split(part)))
    return lines


def _id(item) -> str:
    doc, argv = item
    return f"{doc}: {' '.join(argv[:4])}"


def _help(argv: list[str]) -> str:
    out = subprocess.run([sys.executable, "-m", "swarm_cli", *argv, "--help"], capture_output=True, text=True, cwd=ROOT)
    return out.stdout + out.stderr


def test_readme_starts_with_setup_and_test_commands():
    first = _blocks(README)[0]
    commands = [x for x in first.splitlines() if x and not x.startswith("#")]
    assert "pip install torch==2.13.0" in commands[0] and "swarm train" in commands[0]
    assert "swarm eval coverage-uc-m10" in commands[0]  # a pretrained zoo policy first
    assert commands[1].endswith("python -m pytest")
    assert commands[1] in open(os.path.join(ROOT, ".ci", "run")).read()


SWARM_LINES = command_lines("swarm ")


@pytest.mark.parametrize("item", SWARM_LINES, ids=_id)
def test_doc_swarm_command(item):
    doc, argv = item
    assert argv[1] in COMMANDS, f"{doc}: unknown subcommand {argv[1]}"
    names = _zoo_names()
    for token in argv[2:]:
        if token.startswith(("results/", "models/", "docs/")) and argv[1] != "reproduce":
            assert os.path.exists(os.path.join(ROOT, token)) or "--gif" in argv or "--out" in argv, token
        if re.fullmatch(r"(coverage|formation|line)-(uc|rc)-m\d+(-\w+)?", token):
            assert token in names, f"{doc}: {token} is not a zoo entry"
    sub = argv[1:3] if argv[1] == "bench" and len(argv) > 2 else argv[1:2]
    options = {t.split("=")[0] for t in argv[2:] if t.startswith("--")}
    if options:
        text = _help(sub)
        for option in options:
            assert option in text, f"{doc}: swarm {' '.join(sub)} --help does not list {option}"


@pytest.mark.parametrize("item", command_lines("python tools/"), ids=_id)
def test_doc_tool_command(item):
    doc, argv = item
    script = os.path.join(ROOT, argv[1])
    assert os.path.exists(script), f"{doc}: {argv[1]} does not exist"
    out = subprocess.run([sys.executable, script, "--help"], capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0 and "No module named" in out.stderr:
        pytest.skip(f"{argv[1]} needs an optional extra: {out.stderr.strip().splitlines()[-1]}")
    assert out.returncode == 0, out.stderr
    for option in {t.split("=")[0] for t in argv[2:] if t.startswith("--")}:
        assert option in out.stdout, f"{doc}: {argv[1]} --help does not list {option}"


def test_doc_links_land():
    """Every relative link of a doc names a file of the repository."""
    for doc in DOCS + [os.path.join("models", "cards", f) for f in os.listdir(os.path.join(ROOT, "models", "cards"))]:
        text = open(os.path.join(ROOT, doc)).read()
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
            if "://" in target:
                continue
            path = os.path.normpath(os.path.join(ROOT, os.path.dirname(doc), target))
            assert os.path.exists(path), f"{doc} links {target}, which does not exist"


def test_readme_headline_table_matches_the_zoo():
    from trainer.zoo import get

    rows = re.findall(r"^\| [^|]+ \| `([\w-]+)` \| ([\d.]+) \| (\d+) \|$", README, flags=re.M)
    assert len(rows) >= 8
    for name, ours, paper in rows:
        e = get(name)
        at = e.agents
        if "zero-shot at M = " in README.split(f"`{name}`")[0].splitlines()[-1]:
            at = int(re.search(r"zero-shot at M = (\d+)", README.split(f"`{name}`")[0].splitlines()[-1]).group(1))
            assert f"{100 * e.zero_shot[at]:.1f}" == ours, name
            continue
        assert f"{100 * e.success:.1f}" == ours, name
        assert e.paper_success is not None and round(100 * e.paper_success) == int(paper), name


HISTORY = re.compile(r"\bsessions? \d+|\bsession-\d+", re.I)


def test_no_history_in_code_specs_or_docs():
    """Code, help texts, specs and docs say what the software does now; the story lives in git
    (docs/HISTORY.md is the one page that may say "session")."""
    files = subprocess.run(["git", "ls-files"], capture_output=True, text=True, cwd=ROOT).stdout.split()
    offenders = []
    for f in files:
        if f.startswith("results/") or f == "docs/HISTORY.md" or not f.endswith((".py", ".md", ".toml", ".sh", ".txt")):
            continue
        path = os.path.join(ROOT, f)
        if not os.path.exists(path) or os.path.abspath(path) == os.path.abspath(__file__):
            continue
        text = open(path, errors="replace").read()
        for m in HISTORY.finditer(text):
            offenders.append(f"{f}: ...{text[max(0, m.start() - 30) : m.end() + 10]!r}")
        if f.endswith(".md") and "../shared" in text:
            offenders.append(f"{f}: cites ../shared, which a clone does not have")
    assert not offenders, "\n".join(offenders[:20])


def _tool(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, os.path.join(ROOT, "tools", name), *args], capture_output=True, text=True, cwd=ROOT
    )


def test_results_page_is_generated_from_the_committed_results():
    r = _tool("render_results.py", "--check")
    assert r.returncode == 0, r.stdout + r.stderr


def test_zoo_index_and_cards_are_current():
    r = _tool("make_zoo.py", "--check")
    assert r.returncode == 0, r.stdout + r.stderr
    from swarm_cli.models import rendered_files
    from trainer.zoo import load_index

    for path, text in rendered_files(load_index()).items():
        assert os.path.exists(path) and open(path).read() == text, f"{path} is stale: swarm models --render"


@pytest.mark.slow
def test_cli_reference_is_generated_from_help():
    r = _tool("cli_reference.py", "--check")
    assert r.returncode == 0, r.stdout + r.stderr


def test_readme_python_example_runs():
    """The README's "use a pretrained policy" lines run as written and print a success rate."""
    blocks = re.findall(r"```python\n(.*?)```", README, flags=re.S)
    assert blocks
    out = subprocess.run([sys.executable, "-c", blocks[0]], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr
    assert 0.0 <= float(out.stdout.strip().splitlines()[-1]) <= 1.0
