"""A per-query trust region from the localizer's own confidence: the ACE/GLACE inlier table against the real
7-Scenes files, the per-call region of ``refine``, and pose files whose inlier counts set it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.adapters.confidence import INLIER_EDGES, Q99_CM, Q99_DEG, REGION_MARGIN, inlier_region
from hgsloc_plugin.demo.queries import query_poses
from hgsloc_plugin.demo.scene import make_room_scene
from hgsloc_plugin.noise import se3_noise
from hgsloc_plugin.pipeline import refine_pose_file
from hgsloc_plugin.refine.refiner import median_depth
from hgsloc_plugin.viz import save_png

POSES = Path(__file__).resolve().parents[2] / "shared" / "data" / "poses" / "7scenes"


@pytest.mark.skipif(not POSES.exists(), reason="../shared/data/poses/7scenes not present")
def test_inlier_table_is_the_99th_percentile_of_real_ace_and_glace_errors():
    """Recompute the table from the real files: per inlier bin, the shipped 99th percentiles match the errors of
    ACE + GLACE against the SfM pGT (to 2 %), and the bins hold thousands of poses each above 1,000 inliers."""
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
    # fewer inliers, larger errors: the region never shrinks as the count falls
    assert all(a >= b - 0.02 for a, b in zip(Q99_CM, Q99_CM[1:]))
    assert all(a >= b - 0.02 for a, b in zip(Q99_DEG, Q99_DEG[1:]))


def test_inlier_region_is_depth_relative_and_refuses_unusable_counts():
    shift, rot = inlier_region(3700.0)  # a fraction of the median depth: at 2 m, the table's cm
    assert 2.0 * shift == pytest.approx(REGION_MARGIN * Q99_CM[6] / 100)
    assert rot == pytest.approx(REGION_MARGIN * Q99_DEG[6])
    assert inlier_region(500.0)[0] > 10 * shift
    for bad in (math.nan, -1.0, math.inf):
        assert inlier_region(bad) is None


@pytest.fixture(scope="module")
def room():
    scene = make_room_scene(density=0.35)
    cam = hp.Camera.from_focal(128, 96, 90.0)
    gt = query_poses(1, seed=11)[0]
    img = hp.render(scene, cam, gt)
    prior = se3_noise(gt, 1.0, 0.03, np.random.default_rng(1))
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


def test_ace_file_inlier_counts_set_each_query_region(tmp_path, room):
    """An ACE-dialect file: each query's region is the inlier table's at its median depth; an explicit region in
    the config wins; ``inlier_region=False`` keeps the default."""
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
    assert q["q0.png"]["max_shift"] < q["q1.png"]["max_shift"] / 10
    off = run("b.txt", inlier_region=False)
    assert off["q0.png"]["max_shift"] == off["q1.png"]["max_shift"] > q["q0.png"]["max_shift"]
    explicit = run("c.txt", config=hp.RefineConfig(max_shift=0.2))
    assert explicit["q0.png"]["max_shift"] == 0.2
    assert explicit["q0.png"]["max_rotation_deg"] == pytest.approx(inlier_region(3700.0)[1])
