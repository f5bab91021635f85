"""Every benchmark script answers ``--help`` (imports resolve, the parser builds): a smoke test of each, run in
its own process as its regenerate command runs it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

#: the scripts (``machine.py`` is the others' helper module, no script)
BENCHMARKS = sorted(p for p in (Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py")
                    if '__name__ == "__main__"' in p.read_text())


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_each_benchmark_answers_help(script):
    p = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "usage:" in p.stdout, p.stderr[-2000:]
