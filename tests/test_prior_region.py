"""A per-query trust region and expected prior error from the localizer's own confidence: the ACE/GLACE inlier
tables against the real 7-Scenes files, the per-call region and prior error of ``refine`` (a prior of known error
is fused with the refined pose), and pose files whose inlier counts set both."""

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
from hgsloc_plugin.evaluation.viz import save_png
from hgsloc_plugin.refine.plan import median_depth
from hgsloc_plugin.run.pipeline import refine_pose_file

from .conftest import FakeScorer, room_query

POSES = Path(__file__).resolve().parents[2] / "shared" / "data" / "poses" / "7scenes"


@pytest.mark.slow
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
        assert inlier_region(bad) is None and inlier_prior_error(bad) is None and inlier_trust(bad) == hp.QueryPrior()
    err, err_deg = inlier_prior_error(3700.0)
    assert 2.0 * err == pytest.approx(MEDIAN_CM[6] / 100) and err_deg == MEDIAN_DEG[6]
    assert inlier_trust(3700.0) == hp.QueryPrior(max_shift_depth=shift, max_rotation_deg=rot, prior_error_depth=err,
                                                 prior_error_deg=err_deg)


@pytest.fixture(scope="module")
def room():
    cam = hp.Camera.from_focal(128, 96, 90.0)
    scene, gt, img, prior = room_query(cam, pose_seed=11, noise_deg=1.0, noise_shift=0.03, noise_seed=1)
    return scene, cam, gt, img, prior


@pytest.mark.slow
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


def _reference_fusion(pose, cov, prior, err_t, err_deg):
    """The Gaussian product written out independently: the prior's offset from ``pose`` by the Rodrigues inverse
    (not the quaternion route), and the posterior mean as a whitened least-squares problem: minimise
    ``|L^-1 x|^2 + sum_i (x_i - xp_i)^2 / s_i^2`` with ``L L^T = cov`` and s the prior's per-axis spread."""
    from hgsloc_plugin.refine.uncertainty import PRIOR_SPREAD

    dR = prior.R @ pose.R.T
    ang = math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))
    w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) * ang / (2 * math.sin(ang))
    xp = np.r_[w, prior.tvec - dR @ pose.tvec]
    rows = [np.linalg.inv(np.linalg.cholesky(cov))]
    rhs = [np.zeros(6)]
    for sl, err in ((slice(0, 3), None if err_deg is None else math.radians(err_deg)), (slice(3, 6), err_t)):
        if err is not None:
            sel = np.eye(6)[sl] / (PRIOR_SPREAD * err)
            rows.append(sel)
            rhs.append(sel @ xp)
    x = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return pose.perturbed_in_camera(x[:3], x[3:])


def _close(a, b, tol=1e-7):
    t, r = a.errors_to(b)
    return t < tol and r < 1e-5


@pytest.mark.slow
def test_a_prior_of_known_error_is_fused_with_the_refined_pose(room):
    """The prior's expected error given (per call, from the config or depth-relative alike): the accepted refined
    pose is fused with the prior, as an independent Gaussian product computes it; a prior far more precise than
    the refinement holds the pose near it, a vague one leaves the refinement as it is; a prior so precise that the
    fusion is no better in cost is kept ("prior more precise"); one part given pulls only that part."""
    from hgsloc_plugin.refine.uncertainty import PRIOR_SPREAD, fused_covariance

    scene, cam, gt, img, prior = room
    free = hp.HGSLocPlugin(scene).refine(img, cam, prior)
    assert free.accepted and not free.fused and 0 < free.sigma_t < 1 and 0 < free.sigma_r_deg < 1
    assert math.isnan(free.prior_error) and free.pose.errors_to(gt)[0] < 0.5 * prior.errors_to(gt)[0]
    st, sr = free.sigma_t, free.sigma_r_deg
    fused = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error=st / 10, prior_error_deg=sr / 10)
    assert fused.accepted and fused.fused and fused.rejected is None and fused.search_pose == free.pose
    assert _close(fused.pose, _reference_fusion(free.pose, free.rule_covariance, prior, st / 10, sr / 10))
    # moved off the refined pose (towards the prior along the directions the image constrains least; along the
    # well-constrained ones the refinement stays), and more certain than either alone
    assert fused.pose.errors_to(free.pose)[1] > 0.1 * free.pose.errors_to(prior)[1]
    assert fused.sigma_t < min(st, PRIOR_SPREAD * st / 10 * math.sqrt(3))
    assert fused.sigma_r_deg < min(sr, PRIOR_SPREAD * sr / 10 * math.sqrt(3))
    # the returned covariance is the fusion's spread when the refined pose's error has the returned covariance
    # (``fused_covariance``); the rule's is the posterior it weighed by
    np.testing.assert_allclose(fused.covariance, fused_covariance(free.covariance, free.rule_covariance, st / 10,
                                                                  sr / 10), rtol=1e-6)
    assert fused.cost_final < fused.cost_initial and fused.confidence > 0
    rec = json.loads(json.dumps(fused.to_dict()))
    assert rec["prior_error"] == st / 10 and rec["prior_error_deg"] == sr / 10 and rec["fused"] is True
    assert rec["qvec"] == fused.pose.qvec.tolist() and rec["search_qvec"] == free.pose.qvec.tolist()
    # the same from the config, and with the centre's error as a fraction of the median depth
    by_config = hp.HGSLocPlugin(scene, hp.RefineConfig(prior_error=st / 10, prior_error_deg=sr / 10))
    assert by_config.refine(img, cam, prior).pose == fused.pose
    depth = median_depth(scene, cam, prior)
    rel = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error_depth=st / 10 / depth, prior_error_deg=sr / 10)
    assert rel.prior_error == pytest.approx(st / 10) and _close(rel.pose, fused.pose)
    # a vague prior (the per-call value wins over the config): the refinement as it is, to well under its sigma
    vague = by_config.refine(img, cam, prior, prior_error=1e4 * st, prior_error_deg=1e4 * sr)
    assert vague.fused and vague.pose.errors_to(free.pose)[0] < 1e-3 * st
    # a prior far more precise than anything the image can add: the fusion is the prior, no lower cost, kept
    kept = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error=1e-9 * st, prior_error_deg=1e-9 * sr)
    assert not kept.accepted and kept.rejected == "prior more precise" and kept.pose == prior and not kept.fused
    assert kept.confidence == 0.0 and math.isnan(kept.sigma_t) and kept.covariance is None
    assert kept.search_pose == free.pose  # what was refused, for the record
    # one part given: only that part pulls
    rot_only = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error_deg=sr / 10)
    assert _close(rot_only.pose, _reference_fusion(free.pose, free.rule_covariance, prior, None, sr / 10))
    assert rot_only.pose.errors_to(prior)[1] < 0.5 * free.pose.errors_to(prior)[1]
    t_only = hp.HGSLocPlugin(scene).refine(img, cam, prior, prior_error=st / 10)
    assert _close(t_only.pose, _reference_fusion(free.pose, free.rule_covariance, prior, st / 10, None))
    assert not _close(t_only.pose, rot_only.pose, 1e-4 * st)
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
    # each refined pose is fused with its prior's expected error, and the totals count them
    totals = json.loads((tmp_path / "a.txt.json").read_text())["totals"]
    assert all(v["fused"] == v["accepted"] for v in q.values())
    assert totals["fused"] == totals["accepted"] >= 1
    off = run("b.txt", inlier_region=False)
    off_totals = json.loads((tmp_path / "b.txt.json").read_text())["totals"]
    assert off_totals["fused"] == 0 and off_totals["accepted"] >= 1
    assert off["q0.png"]["max_shift"] == off["q1.png"]["max_shift"] > q["q0.png"]["max_shift"]
    assert math.isnan(off["q0.png"]["prior_error"])  # unknown: null in the JSON report
    assert json.loads((tmp_path / "b.txt.json").read_text())["queries"]["q0.png"]["prior_error"] is None
    explicit = run("c.txt", config=hp.RefineConfig(max_shift=0.2, prior_error_deg=3.0))
    assert explicit["q0.png"]["max_shift"] == 0.2 and explicit["q0.png"]["prior_error_deg"] == 3.0
    assert explicit["q0.png"]["max_rotation_deg"] == pytest.approx(inlier_region(3700.0)[1])
    assert explicit["q0.png"]["prior_error"] == pytest.approx(inlier_prior_error(3700.0)[0] * depth)


def test_fusion_in_closed_form_and_an_unbounded_refinement_keeps_the_prior():
    """Diagonal case by hand: the prior 1 rad-equivalent off along one rotation axis and 1 unit along one shift
    axis, the refinement's variance there a, the prior's s^2 = (PRIOR_SPREAD * error)^2: the fused offset is
    xp * a / (a + s^2) per axis and the posterior variance a s^2 / (a + s^2). A refinement with an unbounded
    covariance (singular Hessian) leaves the prior of known error, "prior more precise"; a bounded one is fused,
    the fusion scored in the rule's one batch with the coarse pose and the candidate."""
    from types import SimpleNamespace

    from hgsloc_plugin.refine.polish import PolishStats
    from hgsloc_plugin.refine.routes import Candidate
    from hgsloc_plugin.refine.trust import PRIOR_MORE_PRECISE, judge
    from hgsloc_plugin.refine.uncertainty import PRIOR_SPREAD, fuse_with_prior

    pose = hp.Pose.identity()
    prior = pose.perturbed_in_camera([0.0, 0.02, 0.0], [0.0, 0.0, 0.05])
    a = np.array([1e-4, 4e-4, 9e-4, 1e-3, 4e-3, 2.5e-3])
    err_t, err_deg = 0.04, 0.8
    fused, post = fuse_with_prior(pose, np.diag(a), prior, err_t, err_deg)
    s2 = np.r_[[(PRIOR_SPREAD * math.radians(err_deg)) ** 2] * 3, [(PRIOR_SPREAD * err_t) ** 2] * 3]
    expect = np.r_[0.0, 0.02, 0.0, 0.0, 0.0, 0.05] * a / (a + s2)
    assert _close(fused, pose.perturbed_in_camera(expect[:3], expect[3:]), 1e-12)
    np.testing.assert_allclose(np.diag(post), a * s2 / (a + s2), rtol=1e-9)
    np.testing.assert_allclose(post - np.diag(np.diag(post)), 0.0, atol=1e-15)
    plan = SimpleNamespace(coarse_pose=prior, prior_error=err_t, prior_error_deg=err_deg, depth=1.0)
    batches = []

    def judged(jtj):  # the coarse pose costs 1, anything else 0.5
        scorer = FakeScorer(lambda poses: [1.0 if p is prior else 0.5 for p in poses], jtj)
        scorer.batches = batches
        stats = PolishStats(8, 8, 1.0, 0.5, 1, 1, 0, 0.1, "converged", jtj)
        cand = Candidate("gradient", pose, math.nan, math.nan, prior, polish=[stats])
        return judge(cand, plan, scorer, None, rule="cost", lattice=False, structural=True, pivot=True), cand

    verdict, cand = judged(np.zeros((6, 6)))  # singular: no fusion, the prior is kept
    assert verdict.rejected == PRIOR_MORE_PRECISE and verdict.pose is prior and not verdict.fused
    assert (cand.cost_initial, cand.cost) == (1.0, 0.5) and len(batches[-1]) == 2
    verdict, _ = judged(np.diag(1.0 / a))  # a bounded covariance
    assert verdict.accepted and verdict.fused and len(batches[-1]) == 3  # coarse, candidate, fusion: one batch
    assert verdict.pose is batches[-1][2] and verdict.cost == 0.5
