"""hloc's PnP inlier counts (``<results>_logs.pkl``): read without running foreign code, turned into each query's
trust region and expected error, in ``refine_pose_file``, the hloc step and ``hgsloc refine``."""

from __future__ import annotations

import json
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.adapters.confidence import (
    HLOC_FEW_INLIERS,
    HLOC_MEDIAN_CM,
    HLOC_MEDIAN_DEG,
    HLOC_Q99_CM,
    HLOC_Q99_DEG,
    hloc_trust,
    inlier_trust,
)
from hgsloc_plugin.adapters.hloc import inlier_log_path, read_inlier_log
from hgsloc_plugin.evaluation.viz import save_png
from hgsloc_plugin.refine.plan import median_depth
from hgsloc_plugin.run.pipeline import refine_pose_file

from .conftest import room_query

POSES = Path(__file__).resolve().parents[2] / "shared" / "data" / "poses" / "7scenes"
RAN = []


class Rigid3d:
    """Stands in for a pycolmap object in the log: unpickling it must not run its code."""

    def __setstate__(self, state):
        RAN.append(state)


def _write_log(results: Path, counts: dict) -> None:
    loc = {}
    for name, n in counts.items():
        pose = Rigid3d()
        loc[name] = {"PnP_ret": {"num_inliers": np.int64(n), "inliers": np.ones(4, bool), "cam_from_world": pose},
                     "db": [np.int32(1)]} if n is not None else {"PnP_ret": None}
    logs = {"features": results.parent / "feats.h5", "matches": results.parent / "m.h5", "retrieval": None,
            "loc": loc}
    with open(inlier_log_path(results), "wb") as f:
        pickle.dump(logs, f)


def test_read_inlier_log_reads_counts_and_never_runs_a_logged_class(tmp_path):
    results = tmp_path / "results.txt"
    assert read_inlier_log(results) is None  # no log: None, no error
    _write_log(results, {"a.png": 812, "b.png": 12, "c.png": None})
    RAN.clear()
    counts = read_inlier_log(results)
    assert counts == {"a.png": 812.0, "b.png": 12.0}  # c.png: hloc failed, no count
    assert RAN == []  # the stand-in's __setstate__ did not run: it was read as an inert placeholder
    inlier_log_path(results).write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="results.txt_logs.pkl"):
        read_inlier_log(results)
    with open(inlier_log_path(results), "wb") as f:
        pickle.dump({"loc": [1, 2]}, f)
    with pytest.raises(ValueError, match="not a readable hloc log"):
        read_inlier_log(results)


def test_hloc_trust_is_hlocs_own_error_above_few_inliers_and_the_widest_bin_below():
    many, few = hloc_trust(500.0), hloc_trust(HLOC_FEW_INLIERS - 1.0)
    assert many.prior_error_depth == pytest.approx(HLOC_MEDIAN_CM / 100 / 2.0)
    assert many.prior_error_deg == HLOC_MEDIAN_DEG
    assert many.max_shift_depth == pytest.approx(1.5 * HLOC_Q99_CM / 100 / 2.0)
    assert few == inlier_trust(0.0) and few.max_shift_depth > 3 * many.max_shift_depth
    assert hloc_trust(float("nan")) == hp.QueryPrior() and hloc_trust(-1.0) == hp.QueryPrior()


@pytest.mark.slow
@pytest.mark.skipif(not POSES.exists(), reason="../shared/data/poses/7scenes not present")
def test_hloc_constants_are_its_real_7scenes_errors():
    err = []
    for scene in sorted(POSES.iterdir()):
        gt = read_poses(scene / "pgt_sfm_test.txt")
        for name, p in read_poses(scene / "hloc.txt").items():
            t, r = p.errors_to(gt[name])
            err.append((100 * t, r))
    err = np.array(err)
    assert len(err) == 17000
    assert np.median(err[:, 0]) == pytest.approx(HLOC_MEDIAN_CM, abs=0.006)
    assert np.median(err[:, 1]) == pytest.approx(HLOC_MEDIAN_DEG, abs=0.006)
    assert np.quantile(err[:, 0], 0.99) == pytest.approx(HLOC_Q99_CM, rel=0.02)
    assert np.quantile(err[:, 1], 0.99) == pytest.approx(HLOC_Q99_DEG, rel=0.02)


@pytest.fixture(scope="module")
def room():
    cam = hp.Camera.from_fov(96, 72, 60.0)
    return room_query(cam, pose_seed=3, noise_deg=0.3, noise_shift=0.01, noise_seed=5) + (cam,)


def _hloc_file(tmp_path, room):
    scene, gt, img, prior, cam = room
    for n in ("q0.png", "q1.png", "q2.png"):
        save_png(img, tmp_path / n)
    results = tmp_path / "results.txt"
    results.write_text("".join(" ".join([n] + [repr(float(v)) for v in prior.as_array()]) + "\n"
                               for n in ("q0.png", "q1.png", "q2.png")))
    return scene, cam, prior, results


@pytest.mark.slow
def test_hloc_results_with_a_log_set_each_querys_region_and_without_one_warn_once(tmp_path, room, caplog):
    scene, cam, prior, results = _hloc_file(tmp_path, room)
    _write_log(results, {"q0.png": 900, "q1.png": 10, "q2.png": None})
    depth = median_depth(scene, cam, prior)
    rep = refine_pose_file(scene, results, tmp_path, lambda n, w, h: cam, tmp_path / "a.txt", progress=False)
    q = rep["queries"]
    assert q["q0.png"]["prior_error"] == pytest.approx(hloc_trust(900).prior_error_depth * depth)
    assert q["q1.png"]["max_shift"] == pytest.approx(hloc_trust(10).max_shift_depth * depth)
    assert q["q2.png"]["prior_error"] != q["q2.png"]["prior_error"]  # no count: unknown (nan)
    off = refine_pose_file(scene, results, tmp_path, lambda n, w, h: cam, tmp_path / "b.txt", progress=False,
                           inlier_region=False)["queries"]
    assert off["q0.png"]["prior_error"] != off["q0.png"]["prior_error"]
    # the hloc step without a log: one warning, the refinement goes on
    from hgsloc_plugin import hloc_step

    inlier_log_path(results).unlink()
    qlist = tmp_path / "queries.txt"
    qlist.write_text("".join(f"{n} PINHOLE {cam.width} {cam.height} {cam.fx} {cam.fy} {cam.cx} {cam.cy}\n"
                             for n in ("q0.png", "q1.png", "q2.png")))
    with caplog.at_level(logging.WARNING, logger="hgsloc_plugin"):
        hloc_step.main(scene, qlist, results, tmp_path, tmp_path / "c.txt", limit=1)
    warned = [r for r in caplog.records if "_logs.pkl" in r.getMessage()]
    assert len(warned) == 1 and "not found" in warned[0].getMessage()
    c = json.loads((tmp_path / "c.txt.json").read_text())["queries"]
    assert c["q0.png"]["prior_error"] is None
