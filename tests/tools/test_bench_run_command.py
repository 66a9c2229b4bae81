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
