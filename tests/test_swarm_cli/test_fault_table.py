"""tools/fault_table.py: a policy under each fault cell through the executor, one file per
policy that a second run reuses cell by cell, and the table docs/DEPLOY.md shows from them."""

import importlib.util
import json
import os

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
spec = importlib.util.spec_from_file_location("fault_table", os.path.join(ROOT, "tools", "fault_table.py"))
fault_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(fault_table)


def test_measure_reuses_its_cells_and_renders(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(fault_table, "OUT", str(tmp_path))
    assert fault_table.main(["coverage-uc-m3", "--episodes", "6"]) == 0
    data = json.loads((tmp_path / "coverage-uc-m3.json").read_text())
    assert list(data["cells"]) == list(fault_table.CELLS) and data["episodes"] == 6
    assert all(0 <= c["success_rate"] <= 1 for c in data["cells"].values())
    import deploy.executor

    def no_run(*args, **kwargs):
        raise AssertionError("a cell in the file was run again")

    monkeypatch.setattr(deploy.executor, "run_episodes", no_run)
    assert fault_table.main(["coverage-uc-m3", "--episodes", "6"]) == 0
    table = capsys.readouterr().out
    assert "| policy | none | drop 0.3 | bursty 0.3 (len 4) | delay 1 |" in table
    assert "| `coverage-uc-m3` | " in table


def test_hold_is_its_own_row_and_file(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(fault_table, "OUT", str(tmp_path))
    assert fault_table.main(["coverage-uc-m3", "--episodes", "4", "--hold", "2"]) == 0
    data = json.loads((tmp_path / "coverage-uc-m3-hold-2.json").read_text())
    assert data["hold"] == 2 and list(data["cells"]) == list(fault_table.CELLS)
    assert "| `coverage-uc-m3` hold 2 | " in capsys.readouterr().out


def test_the_committed_fault_table_renders(capsys):
    assert fault_table.main(["--render"]) == 0
    out = capsys.readouterr().out
    assert "| `coverage-rc-m5` | 94.6 | 86.0 (-8.6) | 83.4 (-11.2) | 90.0 (-4.6) |" in out
    with open(os.path.join(ROOT, "docs", "DEPLOY.md")) as f:
        assert out.strip() in f.read(), "docs/DEPLOY.md's fault table is not tools/fault_table.py --render's"
