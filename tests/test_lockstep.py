"""Many queries per launch: stacked query statistics in the cost and derivative kernels, and lockstep batches
(``hgsloc_plugin/run/lockstep.py``) returning the poses of one query at a time, on real photos first."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.core.image import resize_image
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.kernels.config import CUDA_LAYOUT
from hgsloc_plugin.render import get_renderer
from hgsloc_plugin.run.batch import as_queries
from hgsloc_plugin.run.lockstep import Lockstep, refine_queries

from .conftest import random_scene, room_query
from .test_trust import SNOW, snow_case


@pytest.fixture(scope="module")
def room():
    """(scene, camera, query image, prior) of a small synthetic room."""
    cam = hp.Camera.from_focal(96, 72, 70.0)
    scene, _, img, prior = room_query(cam, pose_seed=5, noise_deg=1.0, noise_shift=0.03, noise_seed=2)
    return scene, cam, img, prior


def _stack_case():
    """A scene, a camera, three query images and two poses per query."""
    scene = random_scene(n=300, seed=4)
    cam = hp.Camera(48, 40, 50.0, 50.0, 24.0, 20.0)
    rng = np.random.default_rng(3)
    base = [se3_noise(hp.Pose.identity(), 2.0, 0.05, rng) for _ in range(3)]
    images = hp.render(scene, cam, base)
    poses = [[se3_noise(b, 1.0, 0.02, rng) for _ in range(2)] for b in base]
    return scene, cam, images, poses


def test_stacked_queries_score_each_pose_as_its_own_launch():
    """One launch over three queries' poses (query statistics stacked, a slot per pose) gives every pose the
    cost, gradient and Gauss-Newton matrix of a launch of its own query, bit for bit; the slots matter (a pose
    scored against another query's slot differs)."""
    scene, cam, images, poses = _stack_case()
    r = get_renderer(scene)
    stats = [r.upload_window_query(im) for im in images]
    stacked = r.stack_window_queries(stats)
    assert tuple(stacked.shape[:3]) == (3, cam.height, cam.width)
    flat = [p for ps in poses for p in ps]
    index = np.repeat(np.arange(3), 2)
    got = r.window_cost(cam, flat, stacked, query_index=index)
    want = np.concatenate([r.window_cost(cam, ps, q) for ps, q in zip(poses, stats)])
    np.testing.assert_array_equal(got, want)
    c, g, h = r.pose_gradient(cam, flat, stacked, query_index=index)
    parts = [r.pose_gradient(cam, ps, q) for ps, q in zip(poses, stats)]
    np.testing.assert_array_equal(c, np.concatenate([p[0] for p in parts]))
    np.testing.assert_array_equal(g, np.concatenate([p[1] for p in parts]))
    np.testing.assert_array_equal(h, np.concatenate([p[2] for p in parts]))
    wrong = r.window_cost(cam, flat, stacked, query_index=index[::-1].copy())
    assert not np.array_equal(wrong, got)
    with pytest.raises(ValueError, match="query_index"):
        r.window_cost(cam, flat, stacked, query_index=index[:3])


def test_query_slots_copy_each_query_once_and_recycle_the_least_recent():
    """A lockstep's query slots (one device array per image size): each query's statistics are copied into a slot
    once and stay there while used; when the slots are full the least recently used query not in the group gives
    way; a launch against the slots scores every pose as a launch of its own query does, bit for bit."""
    from hgsloc_plugin.run.lockstep import QuerySlots

    scene, cam, images, poses = _stack_case()
    r = get_renderer(scene)
    rng = np.random.default_rng(5)
    images = list(images) + [np.clip(im + rng.normal(scale=0.05, size=im.shape), 0, 1).astype(np.float32)
                             for im in images]
    stats = [r.upload_window_query(im) for im in images]  # six queries
    slots = QuerySlots(4, tuple(stats[0].shape[1:]))
    copies = []
    original = r.stack_window_queries
    r.stack_window_queries = lambda qs, out=None, slots=None: copies.append(len(qs)) or original(qs, out, slots)
    try:
        array, first = slots.place(r, stats[:3])
        again, second = slots.place(r, [stats[2], stats[0]])
        assert again is array and len(copies) == 3  # no new array, no new copy
        assert second == {id(stats[2]): first[id(stats[2])], id(stats[0]): first[id(stats[0])]}
        _, third = slots.place(r, stats[3:5])  # one free slot, then the least recent (query 1) gives way
        assert len(copies) == 5 and third[id(stats[4])] == first[id(stats[1])]
        _, fourth = slots.place(r, [stats[5], stats[4]])  # query 2 is now the least recent
        assert fourth[id(stats[5])] == first[id(stats[2])] and fourth[id(stats[4])] == third[id(stats[4])]
    finally:
        del r.stack_window_queries
    for q, k in [(stats[0], first[id(stats[0])]), (stats[3], third[id(stats[3])]), (stats[5], fourth[id(stats[5])])]:
        np.testing.assert_array_equal(array.to_numpy()[k], q.to_numpy()[0])
    index = np.array([fourth[id(stats[5])], third[id(stats[3])]], np.int32)
    got = r.window_cost(cam, poses[0], array, query_index=index)
    want = np.concatenate([r.window_cost(cam, poses[0][:1], stats[5]), r.window_cost(cam, poses[0][1:], stats[3])])
    np.testing.assert_array_equal(got, want)


def test_poses_of_other_intrinsics_render_as_their_own_launches():
    """A call with a camera per pose (intrinsics differ, one image size) gives every pose the image, cost,
    gradient and Gauss-Newton matrix of a call with its own camera, bit for bit; the cameras matter (swapped,
    they differ); mixed sizes, a wrong count or query statistics of another size are refused."""
    scene, cam, images, poses = _stack_case()
    r = get_renderer(scene)
    other = hp.Camera(48, 40, 56.0, 53.0, 23.0, 21.5)
    q = r.upload_window_query(images[0])
    flat = poses[0] + poses[1]
    cams = [cam, cam, other, other]
    got = r.window_cost(cams, flat, q)
    want = np.concatenate([r.window_cost(cam, poses[0], q), r.window_cost(other, poses[1], q)])
    np.testing.assert_array_equal(got, want)
    parts = [r.pose_gradient(cam, poses[0], q), r.pose_gradient(other, poses[1], q)]
    for x, y in zip(r.pose_gradient(cams, flat, q), zip(*parts)):
        np.testing.assert_array_equal(x, np.concatenate(y))
    for x, y in zip(r.render_full(cams, flat), zip(r.render_full(cam, poses[0]), r.render_full(other, poses[1]))):
        np.testing.assert_array_equal(x, np.concatenate(y))
    assert not np.array_equal(r.window_cost(cams[::-1], flat, q), got)
    with pytest.raises(ValueError, match="one image size"):
        r.window_cost([cam, hp.Camera(40, 40, 50.0, 50.0, 20.0, 20.0)], poses[0], q)
    with pytest.raises(ValueError, match="one per pose"):
        r.window_cost([cam], poses[0], q)
    small = r.upload_window_query(images[0][:20, :24])
    for call in (r.window_cost, r.pose_gradient):  # query statistics of another size than the cameras'
        with pytest.raises(ValueError, match="query statistics"):
            call(cams, flat, small)


def test_stacking_rejects_mixed_sizes():
    scene, cam, images, _ = _stack_case()
    r = get_renderer(scene)
    small = resize_image(images[1], 24, 20)
    with pytest.raises(ValueError, match="one size"):
        r.stack_window_queries([r.upload_window_query(images[0]), r.upload_window_query(small)])


def _record(res) -> dict:
    d = res.to_dict()
    d.pop("seconds")
    for p in d["polish"]:
        p.pop("seconds", None)
    return d


def _snow_items(cam: hp.Camera, queries: list) -> list:
    """(image, camera, prior, name) per snow photo of ``snow_case``'s ``queries``: priors 2 % of the depth / 1 deg off
    (the gradient route), the second 12 % / 6 deg (the search)."""
    rng = np.random.default_rng(21)
    items = []
    for k, (name, gt, img, depth) in enumerate(queries):
        far = k == 1
        items.append((img, cam, se3_noise(gt, 6.0 if far else 1.0, (0.12 if far else 0.02) * depth, rng), name))
    return items


@pytest.mark.slow
@pytest.mark.skipif(not (SNOW / "snow_sharp.ply").exists(), reason="../shared/data/snow not present")
def test_real_photos_batched_equal_one_at_a_time():
    """Snow photos on the sharp map, queries that take different routes and finish at different steps (2 % / 1
    deg priors: the gradient route; 12 % / 6 deg: the search) and one bad image: in lockstep batches of 3 (so a
    finished query makes room for the next) every result equals the one-at-a-time result field for field, in input
    order, the bad image fails alone, and launches serve several queries' calls at once."""
    scene, cam, queries = snow_case("snow_sharp.ply")
    items = _snow_items(cam, queries[:4])
    items.insert(2, (np.zeros((5, 5, 3)), cam, items[0][2], "bad"))
    refiner = hp.HGSLocPlugin(scene)
    one = refiner.refine_many(items, progress=False, batch_size=1)
    gate = Lockstep(3)
    pairs = list(refine_queries(refiner, as_queries(items), gate=gate))
    batched = [res for _, res in sorted(pairs, key=lambda qr: qr[0].index)]
    assert [r.name for r in batched] == [it[3] for it in items]
    assert batched[2].error and "bad" == batched[2].name and not any(r.error for k, r in enumerate(batched) if k != 2)
    assert one[1].route != one[0].route  # the far prior went on to the search: the batch's queries diverged
    for a, b in zip(one, batched):
        assert _record(a) == _record(b), a.name
    assert gate.launches < gate.requests  # calls of several queries shared launches
    default = refiner.refine_many(items[:2], progress=False)  # the backend's default batch size
    assert [_record(r) for r in default] == [_record(r) for r in one[:2]]


@pytest.mark.slow
@pytest.mark.skipif(not (SNOW / "snow_sharp.ply").exists(), reason="../shared/data/snow not present")
def test_real_photos_in_the_cuda_layout_match_the_cpu_layout():
    """CUDA's renderer layout (what "auto" picks there: per-pixel blends, the Taichi radix sort, no pixel masks,
    tile lists by ellipse), run on this backend in lockstep batches as CUDA runs them, refines snow photos on the
    sharp map to the poses the CPU's layout gives one at a time within issue 33's 0.001 % of the depth: the same
    routes (the gradient from 2 % / 1 deg, the search from 12 % / 6 deg) and acceptance. What a GPU adds is its
    compiler's rounding."""
    cuda_layout = hp.RasterConfig(**CUDA_LAYOUT)
    scene, cam, queries = snow_case("snow_sharp.ply")
    items = _snow_items(cam, queries[:3])
    cpu = hp.HGSLocPlugin(scene).refine_many(items, progress=False, batch_size=1)
    cuda = hp.HGSLocPlugin(scene, raster=cuda_layout).refine_many(items, progress=False, batch_size=3)
    assert [r.route for r in cpu] == ["gradient", "search", "gradient"]
    for (name, _, _, depth), a, b in zip(queries, cpu, cuda):
        assert b.name == name and a.accepted and b.accepted and a.route == b.route, name
        dt, dr = a.pose.errors_to(b.pose)
        assert dt < 1e-5 * depth and dr < 5e-4, (name, dt / depth, dr)


def test_stopped_batch_releases_its_workers(room):
    """A caller that stops reading a batch (an error in its callback) leaves no worker thread waiting."""
    scene, cam, img, gt = room
    refiner = hp.HGSLocPlugin(scene)
    before = threading.active_count()
    queries = as_queries([(img, cam, gt, f"q{k}") for k in range(4)])
    it = refine_queries(refiner, queries, batch_size=2)
    next(it)
    it.close()
    for t in threading.enumerate():
        if t.name == "hgsloc-lockstep":
            t.join(timeout=30)
    assert threading.active_count() == before


@pytest.mark.parametrize("bad", [0, -2, 1.5, True])
def test_batch_size_must_be_a_positive_integer(room, bad):
    scene, cam, img, gt = room
    with pytest.raises(ValueError, match="batch_size"):
        hp.HGSLocPlugin(scene).refine_many([(img, cam, gt)], progress=False, batch_size=bad)


def test_cli_rejects_a_zero_batch_size(tmp_path: Path):
    p = subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli", "refine", "--scene", "x.ply", "--poses", "p.txt",
                        "--images", ".", "--out", str(tmp_path / "o.txt"), "--batch-size", "0"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "--batch-size" in p.stderr and p.stdout == ""


def test_a_gate_runs_batch_after_batch(room):
    """One :class:`Lockstep` serves a second batch after the first ended (its counts add up), with the poses of
    one query at a time."""
    scene, cam, img, prior = room
    refiner = hp.HGSLocPlugin(scene)
    queries = as_queries([(img, cam, prior, "a"), (img, cam, prior, "b")])
    gate = Lockstep(2)
    first = [r for _, r in refine_queries(refiner, queries, gate=gate)]
    calls = gate.requests
    second = [r for _, r in refine_queries(refiner, queries, gate=gate)]
    alone = refiner.refine(img, cam, prior)
    assert gate.requests == 2 * calls > 0
    assert all(np.array_equal(r.pose.as_array(), alone.pose.as_array()) for r in first + second)


def test_working_sets_share_launches_through_their_union():
    """On a map rendered from per-query working sets, the calls of several queries (each on its own subset of
    the map) share launches rendered from the union of their subsets (``union_limit`` 2), and every result equals
    the one-at-a-time result field for field; with ``union_limit`` 1 (the CPU's default) no two working sets share a
    launch, with the same poses."""
    cam = hp.Camera.from_focal(96, 72, 70.0)
    items = []
    for k in range(3):
        scene, _, img, prior = room_query(cam, pose_seed=5 + k, noise_deg=1.0, noise_shift=0.03, noise_seed=2 + k)
        items.append((img, cam, prior, f"q{k}"))
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("fast", working_set_min=0))
    one = refiner.refine_many(items, progress=False, batch_size=1)
    assert all(r.working_set < 0.6 * len(scene) for r in one) and len({r.working_set for r in one}) == 3
    gate = Lockstep(3, union_limit=2.0)
    pairs = list(refine_queries(refiner, as_queries(items), gate=gate))
    batched = [res for _, res in sorted(pairs, key=lambda qr: qr[0].index)]
    for a, b in zip(one, batched):  # as text: the records hold NaN (no prior error given)
        assert json.dumps(_record(a), sort_keys=True) == json.dumps(_record(b), sort_keys=True), a.name
    assert gate.union_launches > 0 and gate.launches < gate.requests
    whole = Lockstep(3, union_limit=math.inf)  # CUDA's default: any union, the whole map when it holds nearly all
    pairs = list(refine_queries(refiner, as_queries(items), gate=whole))
    assert [r.pose for _, r in sorted(pairs, key=lambda qr: qr[0].index)] == [r.pose for r in one]
    assert whole.launches <= gate.launches
    alone = Lockstep(3, union_limit=1.0)
    pairs = list(refine_queries(refiner, as_queries(items), gate=alone))
    assert alone.union_launches == 0 and alone.launches == alone.requests
    assert [r.pose for _, r in sorted(pairs, key=lambda qr: qr[0].index)] == [r.pose for r in one]
    with pytest.raises(ValueError, match="union_limit"):
        Lockstep(3, union_limit=0.5)
    from hgsloc_plugin.core import backend

    assert Lockstep(3).union_limit == backend.DEFAULT_UNION_LIMIT[backend.current_arch()]


def test_queries_of_other_intrinsics_share_launches():
    """Queries whose cameras differ in focal length and principal point (one image size: per-query intrinsics,
    as HLoc's query lists give) share launches, each pose rendered with its own query's camera, and every result
    equals the one-at-a-time result field for field."""
    cams = [hp.Camera(96, 72, f, f, cx, cy) for f, cx, cy in ((70.0, 48.0, 36.0), (76.0, 47.0, 37.5),
                                                                (64.0, 49.5, 35.0))]
    items = []
    for k, cam in enumerate(cams):
        scene, _, img, prior = room_query(cam, pose_seed=5, noise_deg=1.0, noise_shift=0.03, noise_seed=2 + k)
        items.append((img, cam, prior, f"q{k}"))
    refiner = hp.HGSLocPlugin(scene)
    one = refiner.refine_many(items, progress=False, batch_size=1)
    gate = Lockstep(3)
    pairs = list(refine_queries(refiner, as_queries(items), gate=gate))
    batched = [res for _, res in sorted(pairs, key=lambda qr: qr[0].index)]
    for a, b in zip(one, batched):  # as text: the records hold NaN (no prior error given)
        assert json.dumps(_record(a), sort_keys=True) == json.dumps(_record(b), sort_keys=True), a.name
    assert gate.launches < gate.requests
