"""The heuristic pose search: convergence, keep-best, lattice bookkeeping, determinism, API errors."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.cli.demo.queries import query_poses
from hgsloc_plugin.cli.demo.scene import make_room_scene
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine.search import LatticeSpace, PaperSpace, best_first

from .conftest import shared_path


def test_distinct_minima_takes_the_lowest_poses_apart_by_more_than_the_separation():
    """``routes.distinct_minima``: the wide search's hypotheses, lowest cost first, each more than the separation
    (image motion at the final size) from every one taken before; a pose within it of a lower one is passed over
    however low its own cost."""
    from hgsloc_plugin.refine.plan import make_plan
    from hgsloc_plugin.refine.routes import distinct_minima

    scene = make_room_scene(density=0.35)
    cam = hp.Camera(200, 150, 180.0, 180.0, 100.0, 75.0)
    base = query_poses(1, seed=1)[0]
    plan = make_plan(hp.RefineConfig(), scene, cam, base, hp.QueryPrior())
    step = plan.depth / 180.0  # one pixel of image motion: a camera shift of depth / f

    def shifted(px):
        return hp.Pose(base.qvec, base.tvec + np.array([px * step, 0.0, 0.0]))

    scored = [(shifted(0), 1.0), (shifted(10), 1.05), (shifted(40), 1.2), (shifted(-40), 1.3), (shifted(45), 1.1),
              (shifted(90), 1.4), (shifted(200), 2.0)]
    got = distinct_minima(scored, plan, 3, 32.0)
    px = [round(plan.pixels_apart(base, p)) for p in got]
    assert px == [0, 45, 40] and plan.pixels_apart(got[2], shifted(-40)) == 0  # 10 px and 40 px too close
    assert [round(plan.pixels_apart(base, p)) for p in distinct_minima(scored, plan, 5, 32.0)] == [0, 45, 40, 90, 200]
    assert len(distinct_minima(scored, plan, 1, 32.0)) == 1 and distinct_minima([], plan, 3, 32.0) == []


def _dfnet_trial(scene: str, view: int, error: int):
    """One of ``benchmarks/trials.py``'s trials: the scene's views, view ``view``'s true pose and photo-degraded
    reference render, the prior made of DFNet's 7-Scenes error ``error`` scaled to the view's depth, and cm-eq
    per scene unit."""
    from benchmarks.trials import REFERENCE_DEPTH, Views, localizer_errors

    shared_path("poses", "7scenes")
    views = Views(scene)
    gt, img, depth = views.view(view)
    err = localizer_errors("dfnet")[0][error]
    return views, gt, img, hp.Pose(err.qvec, err.tvec * depth / REFERENCE_DEPTH) @ gt, 100.0 * REFERENCE_DEPTH / depth


@pytest.mark.slow
def test_wide_search_polishes_distinct_lattice_minima(monkeypatch):
    """A real DFNet 7-Scenes error (29 cm-eq / 4.4 deg, the trials' donut trial 1356: view 176, error 16364) on a
    photo-degraded reference render of the donut: the gradient route and the search are refused and the wide
    search's best lattice pose lies in another minimum. Since 2026-12-07 it polishes that pose and the next two
    distinct low ones (``routes.WIDE_HYPOTHESES``), and one of those reaches the truth at the lowest cost: accepted
    within 0.1 cm-eq / 0.1 deg. From the best lattice pose alone the prior is kept."""
    from hgsloc_plugin.refine import routes

    shared_path("scenes", "donut.ply")
    donut, gt, img, prior, cm = _dfnet_trial("donut", 176, 16364)
    assert prior.errors_to(gt)[0] * cm > 25.0
    refiner = hp.HGSLocPlugin(donut.scene)
    r = refiner.refine(img, donut.cam, prior)
    t, a = r.pose.errors_to(gt)
    assert r.accepted and r.route == "wide search" and t * cm < 0.1 and a < 0.1, (r.route, r.rejected, t * cm, a)
    monkeypatch.setattr(routes, "WIDE_HYPOTHESES", 1)
    one = refiner.refine(img, donut.cam, prior)
    assert one.route == "wide search" and not one.accepted and one.renders < r.renders


@pytest.mark.slow
def test_agreeing_wide_hypotheses_stand_in_for_the_alignment_test(monkeypatch):
    """A real DFNet 7-Scenes error (62 cm-eq / 15 deg, the trials' room trial 362: view 182, error 15721) on a
    photo-degraded reference render of the room: the wide search reaches the truth, but its minimum's one-pixel rise
    is under ``MIN_ALIGNMENT`` of its cost (weak alignment). Its three hypotheses, started over 32 px apart, end
    within ``WIDE_AGREEMENT_PX`` of each other: since 2026-12-07 that agreement stands in for the alignment test
    and the pose is accepted within 0.1 cm-eq / 0.1 deg. Without it (no agreement possible) the prior is kept."""
    from hgsloc_plugin.refine import routes

    room, gt, img, prior, cm = _dfnet_trial("room", 182, 15721)
    refiner = hp.HGSLocPlugin(room.scene)
    judged = []
    refiner.on_judged = lambda cand, verdict, plan: judged.append((cand.route, verdict.rejected, cand.agreeing))
    r = refiner.refine(img, room.cam, prior)
    t, a = r.pose.errors_to(gt)
    assert prior.errors_to(gt)[0] * cm > 50.0
    assert judged[-2:] == [("wide search", "weak alignment", 2), ("wide search", None, 2)], judged
    assert r.accepted and r.route == "wide search" and t * cm < 0.1 and a < 0.1, (t * cm, a)
    monkeypatch.setattr(routes, "WIDE_AGREEMENT_PX", -1.0)
    judged.clear()
    kept = refiner.refine(img, room.cam, prior)
    assert not kept.accepted and kept.rejected == "weak alignment" and judged[-1][:2] == ("wide search",
                                                                                         "weak alignment")


@pytest.fixture(scope="module")
def room():
    return make_room_scene(density=0.5)


CAM = hp.Camera.from_fov(160, 120, 65.0)


def _pose_cost(target: hp.Pose):
    """Analytic stand-in for an image cost: weighted pose distance to ``target``."""

    def score(poses):
        out = []
        for p in poses:
            dt, dr = p.errors_to(target)
            out.append(100 * dt + math.radians(dr) * 50)
        return np.array(out)

    return score


def test_lattice_search_converges_and_never_rescores():
    truth = hp.Pose.look_at([0.1, 0.2, 1.4], [2.0, 1.0, 1.2])
    start = se3_noise(truth, 2.0, 0.05, np.random.default_rng(3))
    seen = []
    score = _pose_cost(truth)

    def recording(poses):
        seen.extend(p.as_array().tobytes() for p in poses)
        return score(poses)

    pose, cost = start, float(score([start])[0])
    for px in (4, 2, 1, 0.5, 0.25):
        seen.clear()
        space = LatticeSpace(pose, px / 125, px * 2.5 / 125, pivot_depth=0.0)
        res = best_first(space, cost, recording, lambda p: True, budget=60, patience=3, weight=1.0, depth_cost=0.0)
        assert res.best_cost <= cost
        pose, cost = space.pose(res.best_key), res.best_cost
        assert len(seen) == len(set(seen)), "a pose was scored twice within a level"
    dt, dr = pose.errors_to(truth)
    assert dt < 0.005 and dr < 0.2, (dt, dr)


def test_lattice_keys_are_unique_within_a_level():
    truth = hp.Pose.identity()
    start = se3_noise(truth, 1.0, 0.02, np.random.default_rng(0))
    keys = []
    space = LatticeSpace(start, 0.01, 0.01, 2.0)
    orig_pose = space.pose

    def spy(key):
        keys.append(key)
        return orig_pose(key)

    space.pose = spy
    best_first(space, 1e9, _pose_cost(truth), lambda p: True, budget=40, patience=0, weight=1.0, depth_cost=1.0)
    assert len(keys) > 40, "the search built too few nodes to test anything"
    assert len(keys) == len(set(keys)), "a lattice key was built twice"
    assert all(isinstance(k, tuple) and all(isinstance(v, int) for v in k) for k in keys)


def test_paper_neighbourhood_gives_proper_rotations():
    base = hp.Pose([0.9, 0.1, -0.3, 0.2], [0.1, 0.2, 0.3])
    space = PaperSpace(base, 1e-2, 1e-2)
    keys = space.neighbours((0,) * 7)
    assert len(keys) == 14
    for k in keys + [(3, -2, 5, 1, 0, 0, 0)]:
        R = space.pose(k).R
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        assert np.linalg.norm(space.pose(k).qvec) == pytest.approx(1.0, abs=1e-12)


def test_trust_region_is_respected():
    truth = hp.Pose.identity()
    far = se3_noise(truth, 0.0, 0.5, np.random.default_rng(1))  # the optimum is 50 cm away
    space = LatticeSpace(far, 0.0, 0.05)
    centre = far.centre()
    res = best_first(space, 1e9, _pose_cost(truth), lambda p: np.linalg.norm(p.centre() - centre) <= 0.1,
                     budget=100, patience=0, weight=1.0, depth_cost=0.0)
    assert np.linalg.norm(space.pose(res.best_key).centre() - centre) <= 0.1 + 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("metric", ["sad", "affine"])
def test_refine_reduces_error_on_rendered_queries(room, metric):
    gts = query_poses(3, seed=4)
    imgs = hp.render(room, CAM, gts)
    refiner = hp.HGSLocPlugin(room, hp.RefineConfig.preset("default", metric=metric, patience=2))
    rng = np.random.default_rng(0)
    before, after = [], []
    for gt, im in zip(gts, imgs):
        coarse = se3_noise(gt, 1.5, 0.04, rng)
        r = refiner.refine(im, CAM, coarse)
        assert r.accepted and r.cost_final < r.cost_initial
        assert r.renders > 0 and r.expansions > 0 and len(r.levels) == len(refiner.config.step_pixels)
        before.append(coarse.errors_to(gt))
        after.append(r.pose.errors_to(gt))
    b, a = np.median(before, 0), np.median(after, 0)
    assert a[0] < b[0] / 3 and a[1] < b[1] / 3, f"before {b}, after {a}"


def test_keep_best_on_noise_query(room):
    gt = query_poses(1, seed=9)[0]
    noise = np.random.default_rng(0).uniform(size=(120, 160, 3)).astype(np.float32)
    refiner = hp.HGSLocPlugin(room, hp.RefineConfig.preset("fast", metric="sad"))
    r = refiner.refine(noise, CAM, gt)
    assert r.cost_final <= r.cost_initial
    if not r.accepted:
        assert r.pose == gt


def test_refine_is_deterministic(room):
    gt = query_poses(1, seed=2)[0]
    img = hp.render(room, CAM, gt)
    coarse = se3_noise(gt, 1.0, 0.03, np.random.default_rng(5))
    cfg = hp.RefineConfig.preset("fast")
    a = hp.HGSLocPlugin(room, cfg).refine(img, CAM, coarse)
    b = hp.HGSLocPlugin(room, cfg).refine(img, CAM, coarse)
    assert a.pose == b.pose and a.renders == b.renders and a.cost_final == b.cost_final


def test_image_inputs_and_size_errors(room, tmp_path):
    import torch
    from PIL import Image

    gt = query_poses(1, seed=3)[0]
    img = hp.render(room, CAM, gt)
    cfg = hp.RefineConfig.preset("fast", max_expansions=2)
    ref = hp.HGSLocPlugin(room, cfg)
    u8 = (img * 255).round().astype(np.uint8)
    path = tmp_path / "q.png"
    Image.fromarray(u8).save(path)
    r1 = ref.refine(u8, CAM, gt)
    r2 = ref.refine(path, CAM, gt)
    r3 = ref.refine(torch.from_numpy(u8.astype(np.float32) / 255).permute(2, 0, 1), CAM, gt)
    assert r1.pose == r2.pose == r3.pose
    with pytest.raises(ValueError, match="160x120"):
        ref.refine(np.zeros((100, 100, 3), np.float32), CAM, gt)
    resized = hp.HGSLocPlugin(room, cfg.replace(resize_query=True)).refine(np.zeros((60, 80, 3), np.float32), CAM, gt)
    assert resized.renders > 0


def test_scorer_never_renders_a_pose_twice(room):
    from hgsloc_plugin.refine.scorer import Scorer
    from hgsloc_plugin.render import get_renderer

    gt = query_poses(1, seed=3)[0]
    img = hp.render(room, CAM, gt)
    sc = Scorer(get_renderer(room), "sad", (0, 0, 0), 0.0)
    sc.set_query(CAM, img)
    p2 = gt.perturbed_in_camera([0, 0.01, 0], [0, 0, 0])
    a = sc([gt, p2, gt])
    b = sc([p2, gt])
    assert sc.renders == 2 and a[0] == a[2] == b[1] and a[1] == b[0]
    assert a[0] < a[1]


def test_query_statistics_are_made_once_per_size_and_image(room):
    """The polish's stages and the rule share the query's window statistics per size; a new image gets its own."""
    from hgsloc_plugin.render.renderer import Renderer

    gt = query_poses(1, seed=3)[0]
    img = hp.render(room, CAM, gt)
    prior = se3_noise(gt, 1.0, 0.02, np.random.default_rng(0))
    ref = hp.HGSLocPlugin(room)
    made = []

    def counted(image):
        made.append(image.shape[:2])
        return Renderer.upload_window_query(image)

    ref.renderer.upload_window_query = counted  # the whole map: under working_set_min
    res = ref.refine(img, CAM, prior)
    sizes = {(s.height, s.width) for s in res.polish}
    assert res.route == "gradient" and len(sizes) >= 2
    assert sorted(made) == sorted(sizes)  # each stage's size once, the rule's (the last stage's) not again

    from hgsloc_plugin.refine.scorer import Scorer
    sc = Scorer(ref.renderer, "cs", (0, 0, 0), 0.0)
    other = hp.render(room, CAM, prior)
    sc.set_query(CAM, img)
    a = sc([prior])
    sc.set_query(CAM, other)
    b = sc([prior])
    sc.set_query(CAM, img)
    assert b[0] < a[0] and sc([prior])[0] == a[0]  # other is prior's own image: a perfect match


def test_refine_many_records_failures(room):
    gt = query_poses(1, seed=1)[0]
    img = hp.render(room, CAM, gt)
    ref = hp.HGSLocPlugin(room, hp.RefineConfig.preset("fast", max_expansions=3))
    out = ref.refine_many([(img, CAM, gt, "good"), (np.zeros((5, 5, 3)), CAM, gt, "bad"), (img, CAM, gt, "again")],
                          progress=False)
    assert [r.name for r in out] == ["good", "bad", "again"]
    assert out[1].error and "ValueError" in out[1].error and out[1].pose == gt
    assert out[0].error is None and out[2].error is None


def test_config_presets_and_validation():
    assert hp.RefineConfig.preset("paper").tuning.neighbourhood == "paper"
    assert (hp.RefineConfig.preset("fast").tuning.max_expansions
            < hp.RefineConfig.preset("accurate").tuning.max_expansions)
    from hgsloc_plugin.refine.plan import make_plan

    # with the gradient route first the polish size sets a query's cost: fast polishes smaller than the default
    # on the real photos' 198 px too (the old fast did not), accurate larger on 640 px queries
    room = make_room_scene()
    for width, height in ((198, 148), (640, 480)):
        cam = hp.Camera.from_focal(width, height, 0.8 * width)
        plans = {name: make_plan(hp.RefineConfig.preset(name), room, cam, query_poses(1, seed=1)[0], hp.QueryPrior())
                 for name in ("fast", "default", "accurate")}
        side = {name: max(p.cam_polish.width, p.cam_polish.height) for name, p in plans.items()}
        assert side["fast"] <= 120 < side["default"] <= side["accurate"], side
        assert (side["accurate"] > side["default"]) == (width == 640), side
    with pytest.raises(ValueError):
        hp.RefineConfig(metric="nope")
    with pytest.raises(ValueError):
        hp.RefineConfig.preset("nope")
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        hp.RefineConfig().metric = "sad"  # frozen


def test_config_holds_what_a_user_sets_and_routes_choose_the_routes():
    """RefineConfig has at most 12 fields (the inner ones in Tuning); ``routes`` alone picks the routes; overrides
    of a preset reach Tuning's fields by name; an old route flag is an error that names its replacement."""
    import dataclasses

    assert len(dataclasses.fields(hp.RefineConfig)) <= 12
    choice = {name: hp.RefineConfig.preset(name).route_choice() for name in ("default", "search", "gradient", "paper")}
    assert choice["default"] == (True, "search", True, True)
    assert choice["search"] == (False, "search", True, True)
    assert choice["gradient"] == (False, "gradient", True, False)
    assert choice["paper"] == (False, "search", False, False)
    # the cost rule accepts every descent: no gradient route first; a non-cs metric has no polish, so no wide search
    assert not hp.RefineConfig(acceptance="cost").route_choice().gradient_first
    assert hp.RefineConfig(metric="sad").route_choice() == (False, "search", False, False)
    assert hp.RefineConfig.preset("default", wide_step_pixels=()).route_choice().wide is False
    cfg = hp.RefineConfig.preset("search", max_expansions=60, max_shift=0.2)
    assert (cfg.tuning.max_expansions, cfg.max_shift, cfg.routes) == (60, 0.2, "search")
    assert cfg.tuning.patience == hp.Tuning().patience  # the other tuning fields keep the preset's
    with pytest.raises(TypeError, match="routes='lattice'"):
        hp.RefineConfig.preset("default", polish=False)
    with pytest.raises(ValueError, match="routes must be one of"):
        hp.RefineConfig(routes="polish")


@pytest.mark.parametrize("metric", ["cs", "sad", "psnr", "ssim", "ncc", "affine"])
def test_every_heuristic_ranks_the_true_pose_first(room, metric):
    from hgsloc_plugin.cli.demo.queries import degrade
    from hgsloc_plugin.refine.scorer import Scorer
    from hgsloc_plugin.render import get_renderer

    gt = query_poses(1, seed=6)[0]
    img = hp.render(room, CAM, gt)
    if metric in ("ncc", "affine", "ssim", "cs"):  # exposure-robust or structural: survive a photo-like change
        img = degrade(img, np.random.default_rng(0), occluder=False)
    sc = Scorer(get_renderer(room), metric, (0, 0, 0), 0.0)
    sc.set_query(CAM, img)
    others = [gt.perturbed_in_camera([0, 0.02, 0], [0, 0, 0]), gt.perturbed_in_camera([0, 0, 0], [0.05, 0, 0]),
              gt.perturbed_in_camera([0.01, 0, 0.01], [0, 0.02, 0.03])]
    c = sc([gt] + others)
    assert np.argmin(c) == 0, c


def test_exposure_change_flattens_sad_but_not_affine(room):
    """Under a strong gain/offset change SAD barely separates the true pose from a wrong one; affine does."""
    from hgsloc_plugin.refine.scorer import Scorer
    from hgsloc_plugin.render import get_renderer

    gt = query_poses(1, seed=6)[0]
    img = np.clip(hp.render(room, CAM, gt) * 0.6 + 0.3, 0, 1)  # strong gain/offset change
    near = gt.perturbed_in_camera([0, 0.004, 0], [0, 0, 0])
    out = {}
    for m in ("sad", "affine"):
        sc = Scorer(get_renderer(room), m, (0, 0, 0), 0.0)
        sc.set_query(CAM, img)
        out[m] = sc([gt, near])
    margin = {m: (c[1] - c[0]) / max(c[0], 1e-9) for m, c in out.items()}
    assert abs(margin["sad"]) < 0.01, margin  # the exposure residual swamps the pose signal
    assert margin["affine"] > 1.0, margin


def test_masked_cost_ignores_uncovered_pixels():
    from .conftest import random_scene

    scene = random_scene(n=60, sh_degree=0, seed=4)
    cam = hp.Camera(48, 36, 40.0, 40.0, 24.0, 18.0)
    T = hp.Pose.identity()
    rgb, alpha, _ = hp.render_full(scene, cam, T)
    target = rgb.copy()
    target[alpha < 0.5] = 1.0  # change only pixels the scene does not cover
    assert hp.render_cost(scene, cam, T, target, mask_alpha=0.5) == pytest.approx(0.0, abs=1e-6)
    assert hp.render_cost(scene, cam, T, target) > 1.0


def test_backend_arch_validation(monkeypatch):
    from hgsloc_plugin.core import backend

    with pytest.raises(ValueError, match="arch"):
        backend.init("tpu")
    monkeypatch.setenv("HGSLOC_ARCH", "bogus")
    with pytest.raises(ValueError, match="HGSLOC_ARCH"):
        backend.init()
    monkeypatch.setenv("HGSLOC_ARCH", "cpu")
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv("HGSLOC_CPU_THREADS", bad)
        with pytest.raises(ValueError, match="HGSLOC_CPU_THREADS"):
            backend.init()


def test_cpu_threads_from_the_environment():
    """``HGSLOC_CPU_THREADS`` caps Taichi's CPU threads in a new process (an explicit ``cpu_threads`` wins)."""
    code = ("import hgsloc_plugin as hp, taichi as ti; hp.init('cpu'{}); "
            "print(ti.lang.impl.current_cfg().cpu_max_num_threads)")
    for n, explicit, want in (("1", "", "1"), ("3", "", "3"), ("1", ", cpu_threads=2", "2")):
        env = dict(os.environ, HGSLOC_CPU_THREADS=n, HGSLOC_ARCH="cpu")
        out = subprocess.run([sys.executable, "-c", code.format(explicit)], env=env, capture_output=True, text=True,
                             check=True)
        assert out.stdout.split()[-1] == want


@pytest.mark.slow
def test_wide_search_reaches_a_far_prior_only_after_a_refused_search():
    """``Tuning.wide_step_pixels`` (default (16, 8)): a 30 cm / 8 deg prior the usual search refuses (beyond
    its 32 px trust region) is refined to the truth by the wide search (its lattice levels at ``wide_max_side``,
    then the polish from that size up); a query the gradient route (and the search checking its far travel) already
    answers pays nothing."""
    from hgsloc_plugin.cli.demo.queries import degrade, query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.evaluation.noise import se3_noise

    scene, cam = make_room_scene(), QUERY_CAMERA
    gts = query_poses(2, seed=1)
    imgs = [degrade(im, np.random.default_rng(1000 + k)) for k, im in enumerate(hp.render(scene, cam, gts))]
    rng = np.random.default_rng(308)
    priors = [se3_noise(g, 8.0, 0.3, rng) for g in gts]
    plain, wide = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("default", wide_step_pixels=())), hp.HGSLocPlugin(scene)
    a, b = plain.refine(imgs[1], cam, priors[1]), wide.refine(imgs[1], cam, priors[1])
    assert not a.accepted and a.route == "search"
    assert b.accepted and b.route == "wide search" and b.pose.errors_to(gts[1])[0] < 0.01
    assert b.max_shift > 3 * a.max_shift  # the wide levels' own trust region
    assert [(lv.width, lv.height) for lv in b.levels[-2:]] == [(32, 24), (32, 24)]  # 200x150 scoring size
    assert (b.polish[-4].width, b.polish[-1].width) == (32, 320)  # wide, pyramid, final and polish sizes
    a, b = plain.refine(imgs[0], cam, priors[0]), wide.refine(imgs[0], cam, priors[0])
    assert a.accepted and a.route == b.route and a.renders == b.renders
    assert np.array_equal(a.pose.as_array(), b.pose.as_array())
    with pytest.raises(ValueError, match="wide_step_pixels"):
        hp.Tuning(wide_step_pixels=(16.0, -8.0))
    with pytest.raises(ValueError, match="wide_max_side"):
        hp.Tuning(wide_max_side=8)
    with pytest.raises(ValueError, match="same_minimum_pixels"):
        hp.Tuning(same_minimum_pixels=-1.0)


@pytest.mark.slow
def test_no_wide_search_when_both_routes_end_in_one_minimum():
    """A 15 cm / 3 deg prior on the sparse room (the digest's room query 3) with a noisy photo (noise of 0.15, so
    the minimum's one-pixel rise is under 0.1 % of its cost): the gradient route and the usual search are both
    refused for "weak alignment" in one minimum (their poses within ``same_minimum_pixels``). Their agreement
    stands in for the alignment test (since 2026-12-05): the search's pose is judged without it and accepted,
    1.8 cm / 0.39 deg off, with the honest uncertainty of a photo that noisy (sigma over 10 cm, confidence near 0);
    no wide search runs. Without the agreement (``same_minimum_pixels=0``) the wide search runs, at about 1.6 times
    the renders, and ends in the same minimum (refused for weak alignment until 2026-12-07; now accepted on its own
    hypotheses' agreement). With the query's own small trust region there is nothing wider to search."""
    scene = make_room_scene(density=0.35)
    cam = hp.Camera(160, 120, 140.0, 140.0, 80.0, 60.0)
    rng = np.random.default_rng(7)
    gts = query_poses(4, seed=3)
    priors = [se3_noise(g, 1.0 + 2.0 * (k == 3), 0.03 + 0.12 * (k == 3), rng) for k, g in enumerate(gts)]
    img = hp.render(scene, cam, gts[3])
    img = np.clip(img + np.random.default_rng(1).normal(0.0, 0.15, img.shape), 0.0, 1.0).astype(np.float32)
    skip = hp.HGSLocPlugin(scene).refine(img, cam, priors[3])
    run = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("default", same_minimum_pixels=0.0)).refine(img, cam, priors[3])
    assert skip.route == "search" and skip.gradient_rejected == "weak alignment" and skip.accepted
    t, a = skip.pose.errors_to(gts[3])
    # the rule's covariance is wide on this noisy image (low confidence); the returned sigma covers the error
    rule_t = math.sqrt(np.trace(skip.rule_covariance[3:, 3:]))
    assert t < 0.03 and a < 0.5 and rule_t > 0.1 and skip.confidence < 0.01, (t, a, rule_t)
    assert t < 2 * skip.sigma_t, (t, skip.sigma_t)
    assert run.route == "wide search" and run.accepted and run.pose.errors_to(gts[3])[0] < 0.03
    assert skip.renders < 0.8 * run.renders
    # a query's own trust region, no larger than the wide search's would be, leaves it no room: not run either
    no_skip = hp.RefineConfig.preset("default", same_minimum_pixels=0.0)
    tight = hp.HGSLocPlugin(scene, no_skip).refine(img, cam, priors[3], max_shift=0.05,
                                            max_rotation_deg=1.0)
    assert tight.route == "search" and not tight.accepted and tight.max_shift == 0.05


@pytest.mark.slow
def test_routes_agreeing_at_their_trust_regions_edge_are_judged_in_the_wide_region():
    """A real DFNet 7-Scenes error (38.6 cm-eq / 10.5 deg, the trials' room trial 388: view 8, error 15765) on a
    photo-degraded reference render of the room: the gradient route and the usual search both reach the truth and
    are refused at their trust region's edge only, at one pose. Since 2026-12-06 that pose is judged in the wide
    search's larger region, where it passes: accepted within 0.1 cm-eq / 0.1 deg, no wide search run. Without
    the agreement (``same_minimum_pixels=0``) the wide search, from the prior, ends elsewhere and is refused."""
    room, gt, img, prior, cm = _dfnet_trial("room", 8, 15765)
    assert prior.errors_to(gt)[0] * cm > 30.0
    r = hp.HGSLocPlugin(room.scene).refine(img, room.cam, prior)
    t, a = r.pose.errors_to(gt)
    assert r.accepted and r.route == "search" and r.gradient_rejected == "trust-region edge", (r.route, r.rejected)
    assert t * cm < 0.1 and a < 0.1, (t * cm, a)
    old = hp.HGSLocPlugin(room.scene, hp.RefineConfig.preset("default", same_minimum_pixels=0.0)).refine(
        img, room.cam, prior)
    assert old.route == "wide search" and not old.accepted and old.pose.errors_to(gt)[0] * cm > 30.0
    assert r.renders < old.renders  # the wide search not run (373 against 552 renders)
