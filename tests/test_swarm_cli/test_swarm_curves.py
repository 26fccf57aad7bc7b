"""tools/swarm_curves.py: the zero-shot files become the table docs/SWARM.md shows and a
plot; a file that is not a zero-shot result is refused in one line."""

import importlib.util
import json
import os

import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
spec = importlib.util.spec_from_file_location("swarm_curves", os.path.join(ROOT, "tools", "swarm_curves.py"))
swarm_curves = importlib.util.module_from_spec(spec)
spec.loader.exec_module(swarm_curves)


def zero_shot(path, name, rows):
    results = [dict(agents=m, success_rate=s, covered=c) for m, s, c in rows]
    path.write_text(json.dumps({"checkpoint": name, "results": results}))
    return str(path)


def test_table_and_plot(tmp_path, capsys):
    a = zero_shot(tmp_path / "a.json", "a", [(100, 0.0, 0.22), (10, 0.9, 0.98)])
    b = zero_shot(tmp_path / "b.json", "b", [(10, 0.5, None)])
    out = tmp_path / "c.png"
    assert swarm_curves.main([a, b, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| policy | | M = 10 | M = 100 |" in text
    assert "| `a` | S% | 90.0 | 0.0 |" in text and "| `a` | covered | 0.980 | 0.220 |" in text
    assert "| `b` | covered | - | - |" in text  # a size not run and a metric not reported
    assert out.stat().st_size > 1000 and not list(tmp_path.glob("*.tmp.png"))


def test_the_committed_curves_read(capsys):
    assert swarm_curves.main(["--no-plot"]) == 0
    assert "`coverage-rc-m10`" in capsys.readouterr().out


def test_a_file_that_is_not_a_zero_shot_result_is_refused(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"results": [{"agents": 3}]}))
    with pytest.raises(SystemExit, match="is not a `swarm zero-shot --json` file"):
        swarm_curves.main([str(bad), "--no-plot"])


def test_max_matching_rows_are_labelled(tmp_path, capsys):
    path = tmp_path / "n.json"
    rows = [dict(agents=100, success_rate=0.0, covered=0.6, assignment="nearest")]
    path.write_text(json.dumps({"checkpoint": "p", "results": rows}))
    assert swarm_curves.main([str(path), "--no-plot"]) == 0
    assert "| `p (max matching)` | covered | 0.600 |" in capsys.readouterr().out


def test_the_swarm_doc_table_is_generated_from_the_committed_results(capsys):
    assert swarm_curves.main(["--no-plot"]) == 0
    table = capsys.readouterr().out.strip()
    assert table in open(os.path.join(ROOT, "docs", "SWARM.md")).read(), "run python tools/swarm_curves.py"


def test_a_policy_run_on_other_landmark_lists_is_labelled(tmp_path, capsys):
    """The same policy on its own lists and on wider ones are two rows that read apart."""
    rows = [dict(agents=100, success_rate=0.2, covered=0.97, landmark_neighbours=24)]
    other = tmp_path / "kl24.json"
    other.write_text(json.dumps({"checkpoint": "p", "trained_swarm": {"landmark_neighbours": 12}, "results": rows}))
    own = tmp_path / "own.json"
    rows = [dict(agents=100, success_rate=0.13, covered=0.96, landmark_neighbours=12)]
    own.write_text(json.dumps({"checkpoint": "p", "trained_swarm": {"landmark_neighbours": 12}, "results": rows}))
    assert swarm_curves.main([str(other), str(own), "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert "| `p (KL = 24)` | S% | 20.0 |" in text and "| `p` | S% | 13.0 |" in text
