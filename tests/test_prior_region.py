"""A per-query trust region and expected prior error from the localizer's own confidence: the ACE/GLACE inlier
tables against the real 7-Scenes files, the per-call region and prior error of ``refine`` (a prior more precise
than the refined pose is kept), and pose files whose inlier counts set both."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.adapters.confidence import (
    INLIER_EDGES,
    MEDIAN_CM,
    MEDIAN_DEG,
    Q99_CM,
    Q99_DEG,
    REGION_MARGIN,
    inlier_prior_error,
    inlier_region,
    inlier_trust,
)
from hgsloc_plugin.pipeline import refine_pose_file
from hgsloc_plugin.refine.refiner import median_depth
from hgsloc_plugin.viz import save_png

from .conftest import room_query

POSES = Path(__file__).resolve().parents[2] / "shared" / "data" / "poses" / "7scenes"


@pytest.mark.skipif(not POSES.exists(), reason="../shared/data/poses/7scenes not present")
def test_inlier_tables_are_the_percentiles_of_real_ace_and_glace_errors():
    """Recompute the tables from the real files: per inlier bin, the shipped 99th percentiles and medians match
    the errors of ACE + GLACE against the SfM pGT (to 2 % and to their 0.01 rounding), and the bins hold
    thousands of poses each above 1,000 inliers."""
    err = []
    for scene in sorted(POSES.iterdir()):
        gt = {n.replace("/", "-"): p for n, p in read_poses(scene / "pgt_sfm_test.txt").items()}
        for method in ("ace", "glace"):
            pf = read_poses(scene / f"{method}.txt")
            assert pf.dialect == "ace"
            for name in pf:
                t, r = pf[name].errors_to(gt[name.replace("/", "-")])
                err.append((100 * t, r, float(pf.record(name).tokens[10])))
    err = np.array(err)
    assert len(err) == 34000
    bins = np.searchsorted(INLIER_EDGES, err[:, 2], side="right") - 1
    for i in range(len(INLIER_EDGES)):
        e = err[bins == i]
        assert len(e) > (800 if i == 0 else 1500)
        assert np.quantile(e[:, 0], 0.99) == pytest.approx(Q99_CM[i], rel=0.02)
        assert np.quantile(e[:, 1], 0.99) == pytest.approx(Q99_DEG[i], rel=0.02)
        assert np.median(e[:, 0]) == pytest.approx(MEDIAN_CM[i], abs=0.006)  # the table: to 0.01
        assert np.median(e[:, 1]) == pytest.approx(MEDIAN_DEG[i], abs=0.006)
    # fewer inliers, larger errors: neither the region nor the expected error shrinks as the count falls
    for table in (Q99_CM, Q99_DEG, MEDIAN_CM, MEDIAN_DEG):
        assert all(a >= b - 0.02 for a, b in zip(table, table[1:]))


def test_inlier_region_is_depth_relative_and_refuses_unusable_counts():
    shift, rot = inlier_region(3700.0)  # a fraction of the median depth: at 2 m, the table's cm
    assert 2.0 * shift == pytest.approx(REGION_MARGIN * Q99_CM[6] / 100)
    assert rot == pytest.approx(REGION_MARGIN * Q99_DEG[6])
    assert inlier_region(500.0)[0] > 10 * shift
    for bad in (math.nan, -1.0, math.inf):
        assert inlier_region(bad) is None and inlier_prior_error(bad) is None and inlier_trust(bad) == {}
    err, err_deg = inlier_prior_error(3700.0)
    assert 2.0 * err == pytest.approx(MEDIAN_CM[6] / 100) and err_deg == MEDIAN_DEG[6]
    assert inlier_trust(3700.0) == {"max_shift_depth": shift, "max_rotation_deg": rot, "prior_error_depth": err,
                                    "prior_error_deg": err_deg}


@pytest.fixture(scope="module")
def room():
    cam = hp.Camera.from_focal(128, 96, 90.0)
    scene, gt, img, prior = room_query(cam, pose_seed=11, noise_deg=1.0, noise_shift=0.03, noise_seed=1)
    return scene, cam, gt, img, prior


def test_per_call_region_equals_the_configured_one_and_overrides_it(room):
    scene, cam, gt, img, prior = room
    by_config = hp.HGSLocPlugin(scene, hp.RefineConfig(max_shift=0.05, max_rotation_deg=1.5)).refine(img, cam, prior)
    per_call = hp.HGSLocPlugin(scene, hp.RefineConfig(max_shift=9.0, max_rotation_deg=30.0)).refine(
        img, cam, prior, max_shift=0.05, max_rotation_deg=1.5)
    assert per_call.pose == by_config.pose and per_call.search_pose == by_config.search_pose
    assert (per_call.max_shift, per_call.max_rotation_deg) == (0.05, 1.5)
    assert json.loads(json.dumps(per_call.to_dict()))["max_shift"] == 0.05
    # a depth-relative shift bound is scaled by the query's median depth; an absolute one wins over it
    depth = median_depth(scene, cam, prior)
    rel = hp.HGSLocPlugin(scene).refine(img, cam, prior, max_shift_depth=0.05 / depth, max_rotation_deg=1.5)
    assert rel.max_shift == pytest.approx(0.05) and rel.pose == by_config.pose
    both = hp.HGSLocPlugin(scene).refine(img, cam, prior, max_shift=0.05, max_shift_depth=1.0, max_rotation_deg=1.5)
    assert both.max_shift == 0.05 and both.pose == by_config.pose
    # a region too small for the prior's error: the search stops at its edge and the prior is kept
    tight = hp.HGSLocPlugin(scene).refine(img, cam, prior, max_shift=0.003, max_rotation_deg=0.1)
    assert not tight.accepted and tight.pose == prior
    assert tight.search_pose.errors_to(prior)[0] <= 0.003 + 1e-9
    with pytest.raises(ValueError, match="max_shift"):
        hp.HGSLocPlugin(scene).refine(img, cam, prior, max_shift=-1.0)


def test_a_prior_more_precise_than_the_refined_pose_is_kept(room):
    """The prior's expected error against the refined pose's own uncertainty: below it in translation and in
    rotation, the prior is returned ("prior more precise"); below in one only, the refined pose is; per call,
    from the config and depth-relative alike; unknown (default), no change."""
    scene, cam, gt, img, prior = room
    free = hp.HGSLocPlugin(scene).refine(img, cam, prior)
    assert free.accepted and 0 < free.sigma_t < 1 and 0 < free.sigma_r_deg < 1
    assert math.isnan(free.prior_error) and free.pose.errors_to(gt)[0] < 0.5 * prior.errors_to(gt)[0]
    st, sr = free.sigma_t, free.sigma_r_deg
    kept = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error=st / 2, prior_error_deg=sr / 2)
    assert not kept.accepted and kept.rejected == "prior more precise" and kept.pose == prior
    assert kept.confidence == 0.0 and math.isnan(kept.sigma_t) and kept.covariance is None
    assert kept.search_pose is not None and kept.search_pose != prior  # what was refused, for the record
    rec = json.loads(json.dumps(kept.to_dict()))
    assert rec["prior_error"] == st / 2 and rec["prior_error_deg"] == sr / 2 and rec["rejected"] == kept.rejected
    # the same from the config, and with the centre's error as a fraction of the median depth
    by_config = hp.HGSLocPlugin(scene, hp.RefineConfig(prior_error=st / 2, prior_error_deg=sr / 2))
    assert by_config.refine(img, cam, prior).pose == prior
    depth = median_depth(scene, cam, prior)
    rel = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error_depth=st / 2 / depth, prior_error_deg=sr / 2)
    assert rel.prior_error == pytest.approx(st / 2) and rel.rejected == "prior more precise"
    # a prior less precise in either part: the refined pose is returned (the per-call value wins over the config)
    for t_err, r_err in ((st / 2, 2 * sr), (2 * st, sr / 2)):
        r = by_config.refine(img, cam, prior, prior_error=t_err, prior_error_deg=r_err)
        assert r.accepted and r.pose == free.pose, (t_err, r_err, r.rejected)
    # one part given: only that one is compared
    assert hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error_deg=sr / 2).pose == prior
    assert hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error=2 * st).pose == free.pose
    with pytest.raises(ValueError, match="prior_error"):
        hp.RefineConfig(prior_error=0.0)
    with pytest.raises(ValueError, match="prior_error_deg"):
        hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error_deg=math.nan)


def test_ace_file_inlier_counts_set_each_query_region(tmp_path, room):
    """An ACE-dialect file: each query's region and expected error are the inlier tables' at its median depth;
    explicit values in the config win; ``inlier_region=False`` keeps the defaults."""
    scene, cam, gt, img, prior = room
    save_png(img, tmp_path / "q0.png")
    save_png(img, tmp_path / "q1.png")
    lines = [" ".join([n] + [repr(float(v)) for v in prior.as_array()] + ["1.0", "0.03", inl])
             for n, inl in (("q0.png", "3700"), ("q1.png", "800"))]
    (tmp_path / "ace.txt").write_text("\n".join(lines) + "\n")
    depth = median_depth(scene, cam, prior)

    def run(out, **kw):
        rep = refine_pose_file(scene, tmp_path / "ace.txt", tmp_path, lambda n, w, h: cam, tmp_path / out,
                               progress=False, **kw)
        return rep["queries"]

    q = run("a.txt")
    for name, inl in (("q0.png", 3700.0), ("q1.png", 800.0)):
        shift, rot = inlier_region(inl)
        assert q[name]["max_shift"] == pytest.approx(shift * depth)
        assert q[name]["max_rotation_deg"] == pytest.approx(rot)
        err, err_deg = inlier_prior_error(inl)
        assert q[name]["prior_error"] == pytest.approx(err * depth)
        assert q[name]["prior_error_deg"] == pytest.approx(err_deg)
    assert q["q0.png"]["max_shift"] < q["q1.png"]["max_shift"] / 10
    off = run("b.txt", inlier_region=False)
    assert off["q0.png"]["max_shift"] == off["q1.png"]["max_shift"] > q["q0.png"]["max_shift"]
    assert math.isnan(off["q0.png"]["prior_error"])  # unknown: null in the JSON report
    assert json.loads((tmp_path / "b.txt.json").read_text())["queries"]["q0.png"]["prior_error"] is None
    explicit = run("c.txt", config=hp.RefineConfig(max_shift=0.2, prior_error_deg=3.0))
    assert explicit["q0.png"]["max_shift"] == 0.2 and explicit["q0.png"]["prior_error_deg"] == 3.0
    assert explicit["q0.png"]["max_rotation_deg"] == pytest.approx(inlier_region(3700.0)[1])
    assert explicit["q0.png"]["prior_error"] == pytest.approx(inlier_prior_error(3700.0)[0] * depth)
