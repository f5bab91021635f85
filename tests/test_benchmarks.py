"""The benchmarks as a suite: every script answers ``--help`` when run as its regenerate command runs it
(``python -m benchmarks.<name>``: imports resolve, the parser builds), none edits ``sys.path`` or replaces a
package function, and the harness's stage and launch clocks (the refiner's ``on_stage`` hook,
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
