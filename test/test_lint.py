"""ruff over the whole tree is part of the test suite (config: ruff.toml)."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_reports_no_problems():
    ruff = Path(sys.executable).parent / "ruff"
    result = subprocess.run([str(ruff), "check", "--no-cache", str(REPO)], capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stdout + result.stderr
