"""The per-query working set (kernels/cull.py): conservative, so renders from it equal the whole map's."""

from __future__ import annotations

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.cli.demo.queries import degrade, query_poses
from hgsloc_plugin.cli.demo.scene import densify, make_room_scene
from hgsloc_plugin.core.image import resize_image
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine.scorer import Scorer
from hgsloc_plugin.render import get_renderer
from hgsloc_plugin.render.buffers import Pool

from .conftest import random_scene, shared_path


def region_poses(centre: hp.Pose, max_shift: float, max_rotation: float, n: int, seed: int) -> list[hp.Pose]:
    """n poses on the region's edge (shift exactly max_shift and rotation exactly max_rotation, random directions), plus
    n inside it."""
    rng = np.random.default_rng(seed)
    edge = [se3_noise(centre, max_rotation, max_shift, rng) for _ in range(n)]
    inside = [se3_noise(centre, rng.uniform(0, max_rotation), rng.uniform(0, max_shift), rng) for _ in range(n)]
    return edge + inside


def check_equal(scene, cams, centre, max_shift, max_rotation, n=6, seed=0, background=(0.0, 0.0, 0.0)):
    """Assert: every Gaussian the projection keeps for a region pose is in the working set, and images and
    window costs from the working set are bit-identical to the whole map's. Returns the kept fraction."""
    full = get_renderer(scene)
    sub = full.working_set(cams, centre, max_shift, max_rotation)
    kept = sub.source_index
    poses = region_poses(centre, max_shift, max_rotation, n, seed)
    for cam in cams:
        seen = full.source_index[full.visible(cam, poses).any(axis=0)]
        missing = np.setdiff1d(seen, kept)
        assert missing.size == 0, f"{missing.size} visible Gaussians dropped, e.g. {missing[:5]}"
        a = full.render_full(cam, poses, background)
        b = sub.render_full(cam, poses, background)
        for x, y, what in zip(a, b, ("rgb", "alpha", "depth")):
            assert np.array_equal(x, y), f"{what} differs at {cam.width}x{cam.height}"
    cam = cams[0]
    query = np.asarray(a[0][0])
    s_full, s_sub = (Scorer(r, "cs", background, 0.0) for r in (full, sub))
    for s in (s_full, s_sub):
        s.set_query(cam, query)
    assert np.array_equal(s_full(poses), s_sub(poses))
    return kept.size / scene.num_gaussians


def test_room_densified_edge_poses_bit_identical():
    scene = densify(make_room_scene(), 2)
    cam = hp.Camera.from_fov(320, 240, 65.0).with_max_side(200)
    for k, T in enumerate(query_poses(2, seed=1)):
        frac = check_equal(scene, [cam, cam.with_max_side(100)], T, 0.10, 3.0, seed=k)
        # the test must be able to fail: a 10 cm / 3 deg region in a room sees well under half of it
        assert frac < 0.6, frac


@pytest.mark.parametrize("name", ["donut.ply", "small_sh3.ply"])
def test_real_scenes_edge_poses_bit_identical(name):
    scene = hp.GaussianScene.from_ply(shared_path("scenes", name))
    lo, hi = scene.bounds()
    centre, size = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    cam = hp.Camera.from_fov(160, 120, 50.0)
    rng = np.random.default_rng(3)
    for k in range(2):  # close views that see part of the object
        d = rng.normal(size=3)
        eye = centre + 0.35 * size * d / np.linalg.norm(d)
        T = hp.Pose.look_at(eye, centre + rng.normal(scale=0.1 * size, size=3))
        check_equal(scene, [cam, cam.with_max_side(80)], T, 0.05 * size, 5.0, seed=k)


def test_snow_real_photo_poses_bit_identical():
    import json

    d = shared_path("snow")
    cj = json.loads((d / "camera.json").read_text())
    cam = hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"]).with_max_side(200)
    scene = hp.GaussianScene.from_ply(d / "snow.ply")
    t = (d / "gt.txt").read_text().split()
    T = hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]])
    frac = check_equal(scene, [cam, cam.with_max_side(100)], T, 0.2, 4.0)
    assert frac < 1.0


def test_large_gaussians_near_and_beside_the_camera():
    """Big, close Gaussians whose centres lie outside the view (or behind it) but whose boxes reach the image."""
    scene = random_scene(n=3000, sh_degree=1, seed=5, spread=2.5, centre=(0.0, 0.0, 0.5))
    big = hp.GaussianScene.from_arrays(scene.means, scene.quats, scene.scales * 4.0, scene.opacities, sh=scene.sh)
    cam = hp.Camera.from_fov(96, 64, 70.0)
    check_equal(big, [cam], hp.Pose.identity(), 0.3, 8.0, n=8)


def test_refine_with_and_without_working_set_identical():
    scene = make_room_scene()
    cam = hp.Camera.from_fov(160, 120, 65.0)
    gt = query_poses(1, seed=4)[0]
    img = degrade(hp.render(scene, cam, gt), np.random.default_rng(0))
    prior = se3_noise(gt, 1.0, 0.03, np.random.default_rng(1))
    cfg = hp.RefineConfig.preset("fast", working_set_min=0)
    a = hp.HGSLocPlugin(scene, cfg).refine(img, cam, prior)
    b = hp.HGSLocPlugin(scene, cfg.replace(working_set=False)).refine(img, cam, prior)
    assert a.working_set < 0.8 * scene.num_gaussians and b.working_set == scene.num_gaussians
    assert a.working_set_selections >= 1 and b.working_set_selections == 0
    assert a.pose == b.pose and a.search_pose == b.search_pose
    assert a.cost_initial == b.cost_initial and a.search_cost == b.search_cost and a.renders == b.renders
    # below working_set_min the whole map is used
    assert hp.HGSLocPlugin(scene, hp.RefineConfig.preset("fast")).refine(img, cam, prior).working_set == len(scene)


def test_following_working_set_equals_whole_map_and_reselects():
    """WorkingSet: batches that wander beyond its region are re-selected (and a batch too spread for one region
    is rendered from the whole map); every cost, image and pose derivative equals the whole map's bit for bit."""
    from hgsloc_plugin.render.working_set import WorkingSet, mean_pose

    scene = densify(make_room_scene(), 2)
    full = get_renderer(scene)
    cam = hp.Camera.from_fov(320, 240, 65.0).with_max_side(160)
    T0 = query_poses(1, seed=2)[0]
    rng = np.random.default_rng(0)
    ws = WorkingSet(full, [cam], 0.02, 1.0)
    walk = [T0]
    for _ in range(4):  # each step leaves the previous region (4 cm, 2 deg)
        walk.append(se3_noise(walk[-1], 2.0, 0.04, rng))
    batches = [[se3_noise(T, 0.4, 0.004, rng) for _ in range(3)] + [T] for T in walk]
    batches.append([walk[0], walk[-1]])  # too far apart for one region: whole map
    query = full.render_full(cam, [T0])[0][0]
    qstats = full.upload_window_query(query)
    target = full.upload_image(query)
    for batch in batches:
        np.testing.assert_array_equal(ws.window_cost(cam, batch, qstats), full.window_cost(cam, batch, qstats))
        np.testing.assert_array_equal(ws.cost_stats(cam, batch, target), full.cost_stats(cam, batch, target))
        for x, y in zip(ws.render_full(cam, batch), full.render_full(cam, batch)):
            np.testing.assert_array_equal(x, y)
    for x, y in zip(ws.pose_gradient(cam, walk[-1:], qstats), full.pose_gradient(cam, walk[-1:], qstats)):
        np.testing.assert_array_equal(x, y)
    assert ws.selections == len(walk), ws.selections
    assert ws.fallback_poses == 3 * 2  # the spread batch, in three calls
    assert 0 < ws.largest < 0.6 * full.n
    m = mean_pose(batches[0])
    assert max(np.linalg.norm(m.centre() - p.centre()) for p in batches[0]) < 0.01
    with pytest.raises(ValueError, match="radii"):
        WorkingSet(full, [cam], 0.0, 1.0)


def test_per_camera_working_set_selects_once_per_camera_and_equals_the_whole_map():
    """WorkingSet(per_camera=True): one selection per image size, for that size alone (no larger than the
    selection for both), reused while the poses stay in its region; images equal the whole map's bit for bit."""
    from hgsloc_plugin.render.working_set import WorkingSet

    scene = densify(make_room_scene(), 2)
    full = get_renderer(scene)
    big = hp.Camera.from_fov(320, 240, 65.0)
    small = big.with_max_side(100)
    T = query_poses(1, seed=2)[0]
    both = WorkingSet(full, [big, small], 0.02, 1.0)
    ws = WorkingSet(full, [big, small], 0.02, 1.0, per_camera=True)
    for cam in (big, small, big, small):
        for x, y in zip(ws.render_full(cam, [T]), full.render_full(cam, [T])):
            np.testing.assert_array_equal(x, y)
    both.render_full(big, [T])
    assert ws.selections == 2 and both.selections == 1
    assert ws.largest <= both.largest


def test_working_sets_share_workspaces_and_ignore_stale_columns():
    """Working sets of one map share the map's workspaces (no allocation per query); a smaller set rendered
    after a larger one ignores the larger one's leftover per-Gaussian columns (the sort takes N as an argument:
    reading the buffer's width, it would bin the stale entries)."""
    scene = densify(make_room_scene(), 2)
    full = get_renderer(scene)
    cam = hp.Camera.from_fov(320, 240, 65.0).with_max_side(120)
    T = query_poses(1, seed=3)[0]
    big = full.working_set([cam], T, 0.3, 10.0)
    small = full.working_set([cam], T, 0.01, 0.5)
    assert small.n < big.n < full.n
    poses = [T, se3_noise(T, 0.3, 0.005, np.random.default_rng(1))]
    big.render_full(cam, poses)
    ws = big.workspace(cam, 2)
    got = small.render_full(cam, poses)
    assert small.workspace(cam, 2) is ws and small.pool is full.pool
    fresh = full.subset(np.flatnonzero(np.isin(full.source_index, small.source_index)).astype(np.int32))
    fresh.pool = Pool()  # its own, exactly sized workspaces
    for x, y, z in zip(got, fresh.render_full(cam, poses), full.render_full(cam, poses)):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(x, z)


def test_union_of_working_sets_renders_each_region_like_the_whole_map():
    """``Renderer.union``: the union of two working sets (regions around two poses), in resident order,
    renders the poses of either region bit for bit as the whole map does, while holding fewer Gaussians than it;
    a subset of a subset maps to the map's indices; the map itself, or a renderer of another map, is refused or
    returned as asked."""
    scene = densify(make_room_scene(), 2)
    full = get_renderer(scene)
    cam = hp.Camera.from_fov(320, 240, 65.0).with_max_side(96)
    T1, T2 = query_poses(2, seed=3)
    a = full.working_set([cam], T1, 0.02, 1.0)
    b = full.working_set([cam], T2, 0.02, 1.0)
    u = full.union([a, b])
    assert max(a.n, b.n) < u.n < full.n and u.root is full and a.root is full
    both = np.union1d(a.source_index, b.source_index)
    assert np.array_equal(u.source_index, full.source_index[np.isin(full.source_index, both)])  # resident order
    rng = np.random.default_rng(4)
    poses = [se3_noise(T, 0.5, 0.01, rng) for T in (T1, T2)]
    q = full.upload_window_query(hp.render(scene, cam, T1))
    np.testing.assert_array_equal(u.window_cost(cam, poses, q), full.window_cost(cam, poses, q))
    for x, y in zip(u.pose_gradient(cam, poses, q), full.pose_gradient(cam, poses, q)):
        np.testing.assert_array_equal(x, y)
    inner = a.subset(np.arange(0, a.n, 2, dtype=np.int32))
    assert inner.root is full and np.array_equal(inner.source_index, a.source_index[::2])
    assert full.union([a, full]) is full
    with pytest.raises(ValueError, match="subset"):
        full.union([get_renderer(random_scene(n=50))])


def test_subset_rejects_bad_indices():
    r = get_renderer(random_scene(n=50))
    for idx in ([], [3, 2], [0, 50], [-1, 2]):
        with pytest.raises(ValueError, match="increasing"):
            r.subset(np.array(idx, np.int64))


def test_image_sizes_share_one_set_of_per_gaussian_buffers():
    """Every image size's workspace (and every derivative workspace) uses the pool's one set of per-Gaussian
    buffers, grown in place of the old one when a call needs more poses; costs and derivatives equal those of
    renderers that each allocate their own, whatever the order of sizes and batch sizes."""
    from hgsloc_plugin.render import Renderer

    scene = make_room_scene()
    cams = [hp.Camera.from_fov(320, 240, 65.0).with_max_side(s) for s in (64, 96, 128)]
    gt = query_poses(1, seed=5)[0]
    rng = np.random.default_rng(2)
    poses = [gt] + [se3_noise(gt, 0.02, 0.01, rng) for _ in range(17)]
    img = hp.render(scene, cams[-1], poses[3])
    shared = Renderer(scene)
    plan = [(0, 3), (1, 1), (2, 5), (0, 16), (2, 2), (1, 18), (0, 1)]  # (size, poses): the batch grows twice
    for i, b in plan:
        cam = cams[i]
        q = shared.upload_window_query(resize_image(img, cam.width, cam.height))
        got = shared.window_cost(cam, poses[:b], q)
        c, g, H = shared.pose_gradient(cam, poses[:2], q)
        own = Renderer(scene)  # its own workspaces, exactly this call's
        np.testing.assert_array_equal(got, own.window_cost(cam, poses[:b], q))
        for x, y in zip((c, g, H), own.pose_gradient(cam, poses[:2], q)):
            np.testing.assert_array_equal(x, y)
    pool = shared.pool
    sizes = {(c.width, c.height) for c in cams}
    cfg = shared.config  # one geometry workspace per size and tiling (renders; the derivative pass's lists)
    assert set(pool.workspaces) == {(w, h, t) for w, h in sizes for t in (cfg.tile_size, cfg.grad_tile_size)}
    assert set(pool.derivative_workspaces) == sizes
    assert pool.records.batch >= 18  # one set of per-Gaussian records, grown for the largest batch


def reference_keep(means, smax, opacities, viewmat, planes, fac, max_shift, max_rotation, alpha_min=None):
    """NumPy float64 twin of ``kernels/cull.py::keep_kernel`` (every plane through the angles): keep flags [N]."""
    q = means.astype(np.float64) @ viewmat[:, :3].T + viewmat[:, 3]
    d = np.linalg.norm(q, axis=1)
    s = smax.astype(np.float64)
    ok = np.ones(len(means), bool) if alpha_min is None else opacities >= alpha_min
    for n, f in zip(np.asarray(planes, np.float64), fac):
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.where(d > 0, np.clip(q @ n[:3] / d, -1.0, 1.0), 1.0)
        ang = np.maximum(0.0, np.arccos(c) - max_rotation)
        ok &= ~(d * np.cos(ang) + max_shift < -(f * s + n[3]))
    return ok


@pytest.mark.parametrize("radius_mode", ["gsplat", "inria"])
def test_keep_kernel_matches_the_bound_through_the_angles(radius_mode):
    """The keep kernel, which passes most planes on ``n.q + max_shift`` alone, keeps exactly the Gaussians the
    bound through the angles keeps (float64 NumPy twin), for small and large regions and both radius modes."""
    import taichi as ti

    from hgsloc_plugin.kernels import cull
    from hgsloc_plugin.render.buffers import read_rows
    from hgsloc_plugin.render.prepare import upload

    scene = densify(make_room_scene(), 2)
    full = get_renderer(scene, hp.RasterConfig(radius_mode=radius_mode))
    g = full.gaussians
    means, smax, opac = g.means.to_numpy(), g.smax.to_numpy(), g.opacities.to_numpy()
    cams = [hp.Camera.from_fov(320, 240, 65.0).with_max_side(s) for s in (200, 100)]
    rows, fac = cull.planes(cams, full.config)
    alpha_min = full.config.alpha_min if radius_mode == "gsplat" else None
    kept = []
    for k, T in enumerate(query_poses(3, seed=6)):
        for shift, rot in ((0.005, 0.2), (0.05, 3.0), (0.5, 30.0)):
            keep = ti.ndarray(ti.i32, (full.n,))
            args = [upload(np.asarray(a, np.float64), ti.f64) for a in (T.matrix34(), rows, fac)]
            cull.keep_kernel(full.config)(g.means, g.smax, g.opacities, *args, shift, np.radians(rot), keep)
            got = read_rows(keep, full.n).astype(bool)
            want = reference_keep(means, smax, opac, T.matrix34(), rows, fac, shift, np.radians(rot), alpha_min)
            assert np.array_equal(got, want), f"{np.sum(got != want)} flags differ (pose {k}, {shift}, {rot})"
            kept.append(got.mean())
    assert min(kept) < 0.25 and max(kept) > 0.4, kept  # regions that keep a sixth and half of the room
