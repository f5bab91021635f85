"""The trials benchmark (``python -m benchmarks.trials``): its statistics, and a smoke run in a subprocess."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import shared_path

ROOT = Path(__file__).resolve().parents[1]


def _trials():
    return importlib.import_module("benchmarks.trials")  # the repository root is on the tests' path


def test_upper_bound_is_clopper_pearson():
    t = _trials()
    # no event in n trials: 1 - 0.05^(1/n) exactly (the "rule of three" ~ 3/n)
    for n in (6, 20, 3000):
        assert t.upper_bound(0, n) == pytest.approx(1 - 0.05 ** (1 / n), rel=1e-6)
    assert t.upper_bound(0, 3000) < 0.001  # the goal: 0 events in 3,000 trials bound the rate at 0.1 %
    # one event in 20: the bound p solves P(X <= 1) = 0.05, i.e. (1-p)^20 + 20 p (1-p)^19 = 0.05
    p = t.upper_bound(1, 20)
    assert (1 - p) ** 20 + 20 * p * (1 - p) ** 19 == pytest.approx(0.05, abs=1e-6)
    assert t.upper_bound(5, 5) == 1.0 and t.upper_bound(0, 0) == 1.0


def _row(t0, r0, t1, r1, accepted=True, sigma=(1.0, 1.0), confidence=0.5, **kw):
    return {"t0": t0, "r0": r0, "t1": t1, "r1": r1, "accepted": accepted, "moved": accepted,
            "sigma_t": sigma[0], "sigma_r": sigma[1], "renders": 10, "seconds": 0.1, "confidence": confidence, **kw}


def test_summarise_counts_worse_clearly_worse_and_calibration():
    t = _trials()
    rows = [_row(2.0, 1.0, 0.5, 0.2),                 # better
            _row(2.0, 1.0, 2.1, 0.2),                 # worse by 0.1 cm-eq: worse, not clearly
            _row(2.0, 1.0, 3.5, 0.2),                 # clearly worse (> 1 cm-eq further)
            _row(2.0, 1.0, 0.5, 1.6),                 # clearly worse in rotation (> 0.5 deg further)
            _row(2.0, 1.0, 2.0, 1.0, accepted=False)]  # prior kept: neither
    s = t.summarise(rows)
    assert (s["n"], s["accepted"], s["worse"], s["clearly"]) == (5, 4, 3, 2)
    assert s["recall0"][1] == 1.0 and s["recall1"][0] == pytest.approx(0.2)  # 2cm2deg before; 1cm1deg after
    # calibration over the 4 accepted with sigma 1: centre errors 0.5, 2.1, 3.5, 0.5 -> 2/4 within 1, 2/4 within 2,
    # 3/4 within 3
    assert s["within"][0] == [0.5, 0.5, 0.75]
    assert s["clearly_ub"] > 2 / 5 and math.isfinite(s["worse_ub"])


def test_confidence_auc_and_trial_by_trial_comparison():
    t = _trials()
    assert t.auc([0.9, 0.8], [0.1, 0.2]) == 1.0 and t.auc([0.1], [0.9]) == 0.0
    assert t.auc([0.5, 0.9], [0.5]) == 0.75 and math.isnan(t.auc([], [0.3]))
    # right answers (within 2 cm-eq and 1 deg) ranked above the one wrong answer but one: AUC 0.5
    rows = [_row(3, 1, 0.5, 0.2, confidence=0.9), _row(3, 1, 0.5, 0.2, confidence=0.3),
            _row(3, 1, 4.0, 0.2, confidence=0.5), _row(3, 1, 4.0, 0.2, accepted=False, confidence=0.0)]
    assert t.summarise(rows)["auc"] == 0.5
    key = dict(scene="room", localizer="ace", route="gradient")
    before = [_row(3, 1, 0.5, 0.2, view=k, error=k, **key) for k in range(4)]
    after = [dict(r, renders=r["renders"] + 5 * (r["view"] == 0)) for r in before] + [
        _row(3, 1, 0.5, 0.2, view=9, error=9, **key)]  # a trial only one run holds is left out
    lines = t.compare(before, after, ["room"])
    assert lines[2].startswith("| room | 4 | 100/100 | 100/100 | 0 | 0 | 10 | 11 | 10.0 | 11.2 |"), lines[2]


def test_plan_trials_is_seeded_and_cycles_fixed_views():
    t = _trials()
    a = t.plan_trials(["room", "snow"], ["ace", "dfnet"], 4, {"ace": 17000, "dfnet": 17000},
                      {"room": None, "snow": 6})
    b = t.plan_trials(["room", "snow"], ["ace", "dfnet"], 4, {"ace": 17000, "dfnet": 17000},
                      {"room": None, "snow": 6})
    assert a == b and len(a) == 16
    room = [x.view for x in a if x.scene == "room"]
    assert len(set(room)) == 8 and max(room) < t.SYNTHETIC_VIEWS  # random views, shared out among localizers
    assert [x.view for x in a if x.scene == "snow"] == [0, 1, 2, 3, 0, 1, 2, 3]
    assert len({x.error for x in a}) > 8  # errors drawn, not repeated
    # a cell's trials are the first ones of a larger run's, whatever other cells run
    big = t.plan_trials(["snow"], ["dfnet"], 10, {"dfnet": 17000}, {"snow": 6})
    assert [(x.view, x.error) for x in big[:4]] == [(x.view, x.error) for x in a if x.scene == "snow"][4:]


@pytest.mark.slow
def test_trials_smoke_run(tmp_path):
    shared_path("poses", "7scenes")
    raw, out = tmp_path / "raw.jsonl", tmp_path / "trials.md"
    proc = subprocess.run([sys.executable, "-m", "benchmarks.trials", "--per-cell", "1", "--scenes", "room",
                           "--localizers", "ace", "marepo", "--jobs", "1", "--raw", str(raw), "--out", str(out)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [json.loads(line) for line in raw.read_text().splitlines()]
    assert [r["localizer"] for r in rows] == ["ace", "marepo"]
    assert rows[0]["inliers"] is not None and rows[1]["inliers"] is None  # ACE's draws carry their counts
    text = out.read_text()
    assert "| ace | room | 1 |" in text and "| **all** | **all** | 2 |" in text


def test_from_raw_scales_sigma_in_the_calibration_columns(tmp_path):
    """``--from-raw FILE --sigma-scale F`` tabulates a kept run with every sigma times F: errors 0.5, 1.5, 2.5 at
    sigma 1 lie one, two and three within 1, 2 and 3 sigma; at three times sigma, all three within 1."""
    raw = tmp_path / "raw.jsonl"
    rows = [_row(3.0, 1.0, e, 0.1, index=i, scene="room", view=i, localizer="ace") for i, e in
            enumerate((0.5, 1.5, 2.5))]
    raw.write_text("".join(json.dumps(r) + "\n" for r in rows))

    def within(scale):
        proc = subprocess.run([sys.executable, "-m", "benchmarks.trials", "--from-raw", str(raw), "--sigma-scale",
                               str(scale)], capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert proc.returncode == 0, proc.stderr[-2000:]
        line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("| ace | room |"))
        return line.split("|")[11].strip()

    assert within(1.0) == "33/67/100" and within(3.0) == "100/100/100"
