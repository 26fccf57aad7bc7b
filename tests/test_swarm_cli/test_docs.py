"""The docs describe the product as it is: every command they show names a real subcommand,
options its --help lists, files that exist and zoo entries that exist; the generated pages
(CLI reference, results tables, zoo cards) match a fresh render; no history in code or docs.

A documented `swarm` line is checked in this process: each subcommand's --help is rendered
once (swarm_cli.main.main) and its option names parsed into a set, which every line's options
must belong to (no subprocess per line)."""

import contextlib
import functools
import io
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
    os.path.join("docs", f) for f in os.listdir(os.path.join(ROOT, "docs")) if f.endswith(".md") and f != "CLI.md"
)


@functools.cache
def _zoo_names() -> frozenset[str]:
    from trainer.zoo import load_index

    return frozenset(e.name for e in load_index())


def _blocks(text: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", text, flags=re.S)


def command_lines(prefix: str) -> list[tuple[str, list[str]]]:
    """(doc, argv) of every line starting with ``prefix`` in a bash block of a doc, and of every
    inline `swarm ...` / `python tools/...` / `python benchmarks/...` span (commands chained with && are split)."""
    lines = []
    for doc in DOCS:
        text = open(os.path.join(ROOT, doc)).read()
        candidates = [line for block in _blocks(text) for line in block.splitlines()]
        candidates += re.findall(r"`((?:swarm|python tools/|python benchmarks/)[^`]*)`", text)
        for line in candidates:
            for part in line.split("&&"):
                part = part.split("  #")[0].strip()
                if part.startswith(prefix) and "|" not in part and "..." not in part:
                    lines.append((doc, shlex.split(part)))
    return lines


def _id(item) -> str:
    doc, argv = item
    return f"{doc}: {' '.join(argv[:4])}"


# a --help row that names an option: its invocation at the row's start ("--x STR, --y STR  help"),
# inside a tyro box's border (Unicode or ASCII) or argparse's indent; wrapped help text is
# indented further and never matches
_OPTION_ROW = re.compile(r"^[│|]? {1,2}(-{1,2}\w.*?)(?= {2,}|│|$)")


def options_of_help(text: str) -> frozenset[str]:
    """The option names (--x, with aliases and --no-x) a --help text lists."""
    found = set()
    for line in text.splitlines():
        m = _OPTION_ROW.match(line)
        if m:
            found.update(re.findall(r"--\w[\w.-]*", m.group(1)))
    return frozenset(found)


@functools.cache
def swarm_options(sub: tuple[str, ...]) -> frozenset[str]:
    """The options of ``swarm <sub>``, from its --help rendered in this process, once per subcommand."""
    from swarm_cli.main import main

    out = io.StringIO()
    saved = {k: os.environ.get(k) for k in ("COLUMNS", "NO_COLOR")}
    os.environ.update(COLUMNS="80", NO_COLOR="1")  # tyro's boxes one under another (not side by side), no colour
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            code = main([*sub, "--help-all" if sub[0] in ("train", "curriculum") else "--help"])  # every option
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    assert code == 0, f"swarm {' '.join(sub)} --help exited {code}:\n{out.getvalue()[-2000:]}"
    options = options_of_help(out.getvalue())
    assert "--help" in options, f"swarm {' '.join(sub)} --help lists no options:\n{out.getvalue()[:2000]}"
    return options


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
    options = {t.split("=")[0] for t in argv[2:] if t.startswith("--")}
    if options:
        unknown = sorted(options - swarm_options((argv[1],)))
        assert not unknown, f"{doc}: swarm {argv[1]} --help does not list {', '.join(unknown)}"


# the repository's own top-level packages (a folder of the root with Python files; trainer/ is a
# namespace package): a tool that cannot import one of them is broken, not short of an extra
PROJECT_PACKAGES = frozenset(
    name
    for name in os.listdir(ROOT)
    if os.path.isdir(os.path.join(ROOT, name)) and any(f.endswith(".py") for f in os.listdir(os.path.join(ROOT, name)))
)


@functools.cache
def tool_help(script: str) -> subprocess.CompletedProcess:
    """``python tools/X.py --help`` (or benchmarks/X.py), run once per script (its own process: a
    script may import what the suite's process should not)."""
    return subprocess.run([sys.executable, script, "--help"], capture_output=True, text=True, cwd=ROOT)


@pytest.mark.parametrize("item", command_lines("python tools/") + command_lines("python benchmarks/"), ids=_id)
def test_doc_tool_command(item):
    doc, argv = item
    script = os.path.join(ROOT, argv[1])
    assert os.path.exists(script), f"{doc}: {argv[1]} does not exist"
    out = tool_help(script)
    missing = re.search(r"No module named '([\w.]+)'", out.stderr) if out.returncode != 0 else None
    if missing:
        module, package = missing.group(1), missing.group(1).split(".")[0]
        assert package not in PROJECT_PACKAGES, f"{argv[1]}: the project has no module {module}:\n{out.stderr}"
        pytest.skip(f"{argv[1]} needs the optional package {package}")
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
    (no page may say "session")."""
    files = subprocess.run(["git", "ls-files"], capture_output=True, text=True, cwd=ROOT).stdout.split()
    offenders = []
    for f in files:
        if f.startswith("results/") or not f.endswith((".py", ".md", ".toml", ".sh", ".txt")):
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


def _tool_main(name: str, monkeypatch, *args: str) -> tuple[int, str]:
    """``tools/name``'s main(args) in this process (the tool's own code, without an interpreter's
    start and imports): its exit status and what it printed."""
    import importlib.util

    monkeypatch.chdir(ROOT)  # (the tools name files from the root; the cwd comes back afterwards)
    spec = importlib.util.spec_from_file_location(f"_doc_tool_{name[:-3]}", os.path.join(ROOT, "tools", name))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        code = module.main(list(args))
    return code, out.getvalue()


def test_results_page_is_generated_from_the_committed_results(monkeypatch):
    import matplotlib.pyplot as plt

    import trainer.plot

    def no_png(fig, out):  # --check compares the text without its figure links: the figures are
        plt.close(fig)  # laid out but not written (tests/test_reproduce checks the writing)
        return out

    monkeypatch.setattr(trainer.plot, "_save", no_png)
    code, out = _tool_main("render_results.py", monkeypatch, "--check")
    assert code == 0, out


def test_zoo_index_and_cards_are_current(monkeypatch):
    code, out = _tool_main("make_zoo.py", monkeypatch, "--check")
    assert code == 0, out
    from swarm_cli.models import rendered_files
    from trainer.zoo import load_index

    for path, text in rendered_files(load_index()).items():
        assert os.path.exists(path) and open(path).read() == text, f"{path} is stale: swarm models --render"


@pytest.mark.slow
def test_cli_reference_is_generated_from_help():
    r = _tool("cli_reference.py", "--check")
    assert r.returncode == 0, r.stdout + r.stderr


def test_readme_python_example_runs():
    """The README's "use a pretrained policy" lines run as written and print a success rate
    (in this process: the lines import what the suite already has)."""
    blocks = re.findall(r"```python\n(.*?)```", README, flags=re.S)
    assert blocks
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(blocks[0], "README.md", "exec"), {"__name__": "__main__"})
    assert 0.0 <= float(out.getvalue().strip().splitlines()[-1]) <= 1.0
