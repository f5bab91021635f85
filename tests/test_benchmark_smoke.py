"""A smoke run of each benchmark on its smallest case, in this process (kernels already loaded), as its
regenerate command runs it (``python -m benchmarks.<name> ARGS``): it must finish and print its table.

Those whose smallest case takes a few seconds run with the suite; the rest (5-110 s each on this 2-core machine:
a search from wide priors, every heuristic, both backends' records) run when ``HGSLOC_BENCH_SMOKE=1`` is set, as
``HGSLOC_BENCH_SMOKE=1 python -m pytest tests/test_benchmark_smoke.py``. ``trials`` has its own smoke run
(``test_trials.py``); ``scale`` starts processes and Ray workers, as the Ray tests do.
"""

from __future__ import annotations

import contextlib
import io
import os
import runpy
import sys
from pathlib import Path

import pytest

from .conftest import shared_path

ROOT = Path(__file__).resolve().parents[1]
ALL = os.environ.get("HGSLOC_BENCH_SMOKE") == "1"

#: benchmark -> (its smallest case's arguments, shared data it reads or None, seconds: "fast" or "long")
SMOKE = {
    "derivative_pass": (["--cases", "room", "--repeats", "1"], None, "fast"),
    "map_scale": (["--stages", "--k", "1"], None, "fast"),
    "presets": (["--cases", "room", "--presets", "fast", "--rounds", "1"], None, "fast"),
    "query_time": (["--child", "room", "--seeds", "7"], None, "fast"),
    "rule_model": (["--cases", "room", "--noise", "0"], None, "fast"),
    "sigma": (["--views", "1", "--seeds", "2", "--degradations", "noise"], None, "fast"),
    "startup": (["--child"], None, "fast"),
    "throughput": (["--cases", "room", "--rounds", "1"], None, "long"),
    "tile_lists": (["--cases", "room", "--repeats", "1"], None, "fast"),
    "tile_sort": (["--child", "room", "--repeats", "1"], None, "fast"),
    "accuracy": (["--queries", "1", "--paper-queries", "1", "--donut-queries", "0", "--out", "{tmp}/page.md"], None,
                 "long"),
    "backends": (["--out", "{tmp}/record.json"], None, "long"),
    "basin": (["--cases", "room", "--queries", "1"], None, "long"),
    "curvature": (["--cases", "room"], None, "long"),
    "distortion": (["--seeds", "0"], "snow", "long"),
    "map_floor": (["--datasets", "lego", "--queries", "1", "--draws", "1"], "lego", "long"),
    "real_photos": (["--datasets", "lego", "--heuristics", "cs", "--seeds", "1"], "lego", "long"),
    "refine": (["--cases", "room", "--queries", "1", "--out", "{tmp}/page.md"], None, "long"),
    "render": (["--repeats", "1"], None, "long"),
    "trust": (["--scenes", "room", "--queries", "1", "--draws", "1"], None, "long"),
}


def test_every_benchmark_has_a_smoke_run():
    scripts = {p.stem for p in (ROOT / "benchmarks").glob("*.py") if '__name__ == "__main__"' in p.read_text()}
    assert scripts - set(SMOKE) == {"trials", "scale"}, scripts - set(SMOKE)


@pytest.mark.parametrize("name", sorted(SMOKE), ids=str)
def test_benchmark_smoke_run(name, tmp_path, monkeypatch):
    args, data, length = SMOKE[name]
    if length == "long" and not ALL:
        pytest.skip("5-110 s: run with HGSLOC_BENCH_SMOKE=1")
    if data is not None:
        shared_path(data)
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setattr(sys, "argv", [f"benchmarks/{name}.py", *(a.format(tmp=tmp_path) for a in args)])
    pages = {p: p.read_bytes() for p in (ROOT / "benchmarks").glob("*.md")}
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            runpy.run_module(f"benchmarks.{name}", run_name="__main__")
        except SystemExit as exc:
            assert exc.code in (0, None), f"{name} exited with {exc.code}"
    text = out.getvalue()
    assert {p: p.read_bytes() for p in (ROOT / "benchmarks").glob("*.md")} == pages, "a smoke run wrote a page"
    if name == "backends":  # its record goes to --out
        assert (tmp_path / "record.json").stat().st_size > 0
    else:
        assert "|" in text or text.lstrip().startswith("{"), text[-2000:]  # a table row, or a child's JSON record


def test_map_scale_level_of_detail_rows(tmp_path, monkeypatch):
    """map_scale's query rows, exact and through the hierarchy, on the smallest split map (its children run as
    processes: long)."""
    if not ALL:
        pytest.skip("5-110 s: run with HGSLOC_BENCH_SMOKE=1")
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setenv("HGSLOC_LOD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(sys, "argv", ["benchmarks/map_scale.py", "--k", "1", "--queries", "1", "--paths",
                                      "working set, gradient first", "working set + LOD 1 px, gradient first",
                                      "working set, gradient first, priors nudged 1e-5 of the depth"])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        runpy.run_module("benchmarks.map_scale", run_name="__main__")
    rows = [line for line in out.getvalue().splitlines() if line.startswith("| 48,761 | working set")]
    assert len(rows) == 6, out.getvalue()[-2000:]  # three table rows, three stage rows
    for row in rows[1:3]:  # accepted, and compared with the exact path
        assert "1 / 1" in row and "(max" in row


def _run(monkeypatch, name: str, args: list[str]) -> str:
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setattr(sys, "argv", [f"benchmarks/{name}.py", *args])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        runpy.run_module(f"benchmarks.{name}", run_name="__main__")
    return out.getvalue()


def test_map_scale_cut_sizes(tmp_path, monkeypatch):
    """``map_scale --cuts``: a row per scoring size with the exact and the 1 / 2 / 4 px counts, and the unsplit
    room against itself (infinite PSNR)."""
    monkeypatch.setenv("HGSLOC_LOD_CACHE_DIR", str(tmp_path))
    text = _run(monkeypatch, "map_scale", ["--cuts", "--k", "1", "--queries", "2"])
    rows = [line.split("|")[3:7] for line in text.splitlines() if line.startswith("| 48,761 | ") and "x" in line]
    assert len(rows) == 3, text
    counts = [[int(c.replace(",", "")) for c in row] for row in rows]
    assert all(0 < n <= 48761 for row in counts for n in row)
    assert counts[-1][3] <= counts[-1][0] and counts[0][3] < counts[0][0]  # 4 px merges at the coarsest size
    assert "| 48,761 | inf / inf / inf |" in text


def test_map_floor_regional(monkeypatch):
    """``map_floor --regional``: the whole image and its four halves per query, and the floors of nearby views."""
    if not ALL:
        pytest.skip("5-110 s: run with HGSLOC_BENCH_SMOKE=1")
    shared_path("lego")
    text = _run(monkeypatch, "map_floor", ["--regional", "--datasets", "lego", "--queries", "2"])
    for part in ("whole", "left", "right", "top", "bottom"):
        assert sum(f"| {part} |" in line for line in text.splitlines()) == 2, text
    assert "| the 1 nearest other view |" in text and "| all other views |" in text
