"""Coarse level of detail (hgsloc_plugin/render/lod.py): the merge rule, its fidelity, its use by the coarse levels."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.cli.demo.queries import degrade, query_poses
from hgsloc_plugin.cli.demo.scene import densify, make_room_scene
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.render import get_renderer
from hgsloc_plugin.render.lod import coarse_lod, merge_cells, psnr


def _arrays(means, var, opac, sh=None):
    n = len(means)
    cov = np.zeros((n, 6), np.float32)
    cov[:, 0] = cov[:, 3] = cov[:, 5] = var
    sh = np.zeros((n, 1, 3), np.float32) if sh is None else sh
    return {"means": np.asarray(means, np.float32), "cov3d": cov, "opacities": np.asarray(opac, np.float32),
            "sh": sh, "smax": np.full(n, math.sqrt(var), np.float32)}


def test_coincident_members_composite_like_their_stack():
    """k tiny Gaussians at one point merge into one with their mean, covariance, weighted colour and the opacity
    of their stack, 1 - prod(1 - o_i); a lone tiny Gaussian and a large one are kept as they are."""
    f, depth, tau = 100.0, 2.0, 1.0  # one pixel = 2 cm; members 1 mm
    pts = [[0.1001, 0.2001, 2.0]] * 3 + [[1.0, 1.0, 2.0], [0.5, 0.5, 2.0]]
    var = np.array([1e-6, 1e-6, 1e-6, 1e-6, 0.01], np.float32)
    sh = np.zeros((5, 1, 3), np.float32)
    sh[:3, 0, 0] = [0.1, 0.2, 0.6]
    a = _arrays(pts, 0.0, [0.5, 0.6, 0.7, 0.9, 0.8], sh)
    a["cov3d"][:, [0, 3, 5]] = var[:, None]
    a["smax"] = np.sqrt(var)
    out, src = merge_cells(a, np.full(5, depth), f, tau)
    assert len(out["means"]) == 3
    np.testing.assert_array_equal(src, [-1, 3, 4])  # merged one at its first member's place (index 0)
    np.testing.assert_allclose(out["means"][0], pts[0], rtol=1e-6)
    np.testing.assert_allclose(out["cov3d"][0, [0, 3, 5]], 1e-6, rtol=1e-4)
    assert out["opacities"][0] == pytest.approx(1 - 0.5 * 0.4 * 0.3, rel=1e-6)
    w = np.array([0.5, 0.6, 0.7])  # equal footprints: weights are the opacities
    assert out["sh"][0, 0, 0] == pytest.approx(float(w @ [0.1, 0.2, 0.6] / w.sum()), rel=1e-5)
    for k, i in ((1, 3), (2, 4)):
        for key in out:
            np.testing.assert_array_equal(out[key][k], a[key][i])


def test_spread_members_conserve_footprint():
    """Members spread over a cell (no overlap) give a wider Gaussian whose opacity x footprint is about theirs."""
    f, tau = 100.0, 4.0  # one pixel = 1 cm at depth 1; cells up to 4 px
    rng = np.random.default_rng(0)
    pts = np.array([0.0156, 0.0156, 1.0]) + rng.uniform(-0.015, 0.015, size=(16, 3)) * [1, 1, 0]  # one 3.1 cm cell
    a = _arrays(pts, 1e-8, np.full(16, 0.3))
    out, src = merge_cells(a, np.ones(16), f, tau)
    assert len(out["means"]) == 1 and src[0] == -1
    unit = 1.0 / f
    a_m = out["cov3d"][0, [0, 3, 5]].sum() / 3 / unit ** 2 + 0.3
    a_i = 3e-8 / 3 / unit ** 2 + 0.3
    assert a_m > 1.5 * a_i  # wider than a member
    mass = 1 - (1 - 0.3 * a_i / a_m) ** 16
    assert out["opacities"][0] == pytest.approx(mass, rel=1e-5)
    assert out["opacities"][0] < 1 - 0.7 ** 16  # less than a full stack: they do not overlap


def test_coarse_lod_fidelity_and_exactness_without_merges():
    """On the 4x densified room at 100 px: merging at 2 px keeps under 80 % of the Gaussians (measured 70 %) and
    renders above 30 dB PSNR of the exact map at poses of the region (measured 35); 3 px keeps fewer; at 0.01 px
    nothing merges and the images equal the working set's."""
    scene = densify(make_room_scene(), 4)
    full = get_renderer(scene)
    cam = hp.Camera.from_fov(320, 240, 65.0).with_max_side(100)
    T = query_poses(1, seed=5)[0]
    max_shift, max_rotation = 0.2, 5.0
    poses = [T] + [se3_noise(T, max_rotation * 0.5, max_shift * 0.5, np.random.default_rng(s)) for s in range(3)]
    ws = full.working_set([cam], T, max_shift, max_rotation)
    exact = ws.render_full(cam, poses)[0]
    lod2 = coarse_lod(full, cam, T, max_shift, max_rotation, 2.0)
    assert lod2.n < 0.8 * ws.n
    p2 = [psnr(a, b) for a, b in zip(lod2.render_full(cam, poses)[0], exact)]
    assert min(p2) > 30.0, p2
    assert coarse_lod(full, cam, T, max_shift, max_rotation, 3.0).n < lod2.n
    none = coarse_lod(full, cam, T, max_shift, max_rotation, 0.01)
    assert none.n == ws.n and np.all(none.source_index == ws.source_index)
    np.testing.assert_array_equal(none.render_full(cam, poses)[0], exact)
    with pytest.raises(ValueError, match="tau_px"):
        coarse_lod(full, cam, T, max_shift, max_rotation, 0.0)


def test_refine_with_coarse_lod_scores_fine_levels_on_the_exact_map():
    scene = make_room_scene()
    cam = hp.Camera.from_fov(160, 120, 65.0)
    gt = query_poses(1, seed=4)[0]
    img = degrade(hp.render(scene, cam, gt), np.random.default_rng(0))
    prior = se3_noise(gt, 1.0, 0.03, np.random.default_rng(1))
    cfg = hp.RefineConfig.preset("fast", working_set_min=0, coarse_lod_pixels=2.0)
    r = hp.HGSLocPlugin(scene, cfg).refine(img, cam, prior)
    r0 = hp.HGSLocPlugin(scene, cfg.replace(coarse_lod_pixels=None)).refine(img, cam, prior)
    assert r.cost_initial == r0.cost_initial  # scored before the levels, on the exact map
    # the judged cost is the exact map's at the returned search pose
    from hgsloc_plugin.core.image import resize_image
    from hgsloc_plugin.refine.plan import make_plan

    plan = make_plan(cfg, scene, cam, prior, hp.QueryPrior())
    from hgsloc_plugin.refine.scorer import Scorer

    s = Scorer(get_renderer(scene), "cs", (0.0, 0.0, 0.0), 0.0)
    s.set_query(plan.cam_polish, resize_image(img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img,
                                              plan.cam_polish.width, plan.cam_polish.height))
    assert float(s([r.search_pose])[0]) == pytest.approx(r.search_cost, abs=1e-9)
    assert r.accepted and r.pose.errors_to(gt)[0] < 0.3 * prior.errors_to(gt)[0]
    with pytest.raises(ValueError, match="coarse_lod_pixels"):
        hp.Tuning(coarse_lod_pixels=-1.0)
