"""The benchmarks as a suite: every script answers ``--help`` when run as its regenerate command runs it
(``python -m benchmarks.<name>``: imports resolve, the parser builds), none edits ``sys.path`` or replaces a
package function, every page is its regenerate command, its tables and a short dated findings list (which a
regeneration keeps), and the harness's stage and launch clocks (the refiner's ``on_stage`` hook,
``kernels.launch.timed_launches``) report what a refinement does."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the scripts (``harness.py`` and ``machine.py`` are the others' helper modules, no scripts)
BENCHMARKS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if '__name__ == "__main__"' in p.read_text())


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_each_benchmark_answers_help(script):
    p = subprocess.run([sys.executable, "-m", f"benchmarks.{script.stem}", "--help"], capture_output=True, text=True,
                       timeout=300, cwd=ROOT)
    assert p.returncode == 0 and "usage:" in p.stdout, p.stderr[-2000:]


def test_no_benchmark_edits_the_path_or_replaces_package_functions():
    """No ``sys.path`` edit, no ``setattr`` and no assignment to a private name of another object."""
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        text = path.read_text()
        assert "sys.path" not in text and "setattr(" not in text, path.name
        assert not re.search(r"^\s*[\w.]+\.(_\w+)\s*=", text, re.M), path.name  # e.g. renderer._sort = ...
        assert not re.search(r"^\s*(?!self\.)\w+\.\w+(, \w+\.\w+)+ = ", text, re.M), path.name  # mod.a, mod.b = ...


#: pages that are no benchmark's output: the decision log, and the reasons behind the tuning constants
NOT_PAGES = {"DECISIONS.md", "defaults.md"}
PAGES = sorted(p for p in (ROOT / "benchmarks").glob("*.md") if p.name not in NOT_PAGES)
DATE = re.compile(r"\b20\d\d-\d\d-\d\d")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_each_page_is_its_command_tables_and_dated_findings(page):
    """A title, then ``Regenerate: `python -m benchmarks.<script> ...``` naming a script that exists, a table, and a
    last section ``## Findings`` of at most 60 lines whose bullets each carry a date; 200 lines at most in all."""
    lines = page.read_text().splitlines()
    assert lines[0].startswith("# ") and len(lines) <= 200, (page.name, len(lines))
    regen = next((ln for ln in lines[1:5] if ln.startswith("Regenerate: `")), None)
    assert regen is not None, f"{page.name}: no Regenerate line under the title"
    script = re.search(r"python -m benchmarks\.(\w+)", regen)
    assert script and (ROOT / "benchmarks" / f"{script.group(1)}.py").exists(), regen
    assert any(ln.startswith("|---") for ln in lines), f"{page.name}: no table"
    heads = [i for i, ln in enumerate(lines) if ln.startswith("## ")]
    assert heads and lines[heads[-1]] == "## Findings", f"{page.name}: the last section is not ## Findings"
    findings = lines[heads[-1] + 1:]
    assert len(findings) <= 60, (page.name, len(findings))
    bullets = [ln for ln in findings if ln.startswith("- ")]
    assert bullets, f"{page.name}: no findings"
    undated = [b[:60] for b in bullets if not DATE.search(b) and not b.startswith("- **")]
    assert len(undated) <= len(bullets) // 2, (page.name, undated)
    assert DATE.search("\n".join(findings)), f"{page.name}: no dated finding"


def test_a_regeneration_keeps_the_findings(tmp_path):
    from benchmarks.harness import write_keeping_notes

    page = tmp_path / "x.md"
    page.write_text("# X\n\nold table\n\n## Findings\n\n- **2026-12-06**: kept\n")
    write_keeping_notes(page, ["# X", "", "new table"])
    assert page.read_text() == "# X\n\nnew table\n\n## Findings\n\n- **2026-12-06**: kept\n"


def test_the_stage_and_launch_clocks_report_a_refinement(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))
    import hgsloc_plugin as hp
    from benchmarks.harness import stage_clock
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.evaluation.noise import se3_noise
    from hgsloc_plugin.kernels.launch import timed_launches

    scene, cam = make_room_scene(), hp.Camera(96, 72, 84.0, 84.0, 48.0, 36.0)
    gt = query_poses(1, seed=2)[0]
    img, prior = hp.render(scene, cam, gt), se3_noise(gt, 1.0, 0.03, np.random.default_rng(5))
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("search"))
    plain = refiner.refine(img, cam, prior)
    with stage_clock(refiner) as spent, timed_launches() as launches:
        with timed_launches() as inner:  # nested: the inner clock's launches are not the outer one's
            hp.render(scene, cam, gt)
        timed = refiner.refine(img, cam, prior)
    assert refiner.on_stage is None  # restored
    assert np.array_equal(timed.pose.as_array(), plain.pose.as_array())  # the hooks change nothing
    assert "rule" in spent and any(k.startswith("search ") for k in spent)
    assert any(k.startswith("polish ") for k in spent)
    assert all(v > 0 for v in spent.values())
    assert inner.count >= 3 and "project" in inner.by_kernel  # projection, sort, blend, read-back
    assert launches.count > 20 and launches.seconds > 0  # batched: fewer launches than renders
    assert abs(sum(launches.by_kernel.values()) - launches.seconds) < 1e-9
