"""tools.bench.run_command: what the benches log of the commands they run, and how a failure ends them."""
import sys

import pytest

from tools.bench import run_command


def test_run_command_logs_and_returns_the_exit_code():
    lines = []
    code = run_command([sys.executable, "-c", "print('a'); print('b'); raise SystemExit(3)"], lines.append)
    assert code == 3
    assert lines[0].startswith("$ ") and "  b" in lines and lines[-1].startswith("  exit 3 after ")


def test_run_command_with_check_stops_on_failure_with_the_output_tail():
    lines = []
    assert run_command([sys.executable, "-c", "pass"], lines.append, check=True) == 0
    assert lines[-1].startswith("  done in ")
    with pytest.raises(SystemExit, match=r"(?s)exit 2.*boom"):
        run_command([sys.executable, "-c", "import sys; print('boom'); sys.exit(2)"], lines.append, check=True)


def test_write_json_keeps_a_backup_and_skips_without_a_path(tmp_path):
    import json

    import numpy as np

    from tools.bench import write_json

    write_json(None, {"a": 1})
    write_json("", {"a": 1})
    assert list(tmp_path.iterdir()) == []
    out = tmp_path / "figures.json"
    out.write_text("old")
    write_json(str(out), {"psnr": np.float32(25.5), "rows": [1, 2]})
    assert json.loads(out.read_text()) == {"psnr": 25.5, "rows": [1, 2]}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["figures.json", "figures.json.bak"]
    assert (tmp_path / "figures.json.bak").read_text() == "old"
