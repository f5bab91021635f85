"""Ray scale-out: same results as one process, in order, with the same raster config; a killed worker loses no
query; resume."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

ray = pytest.importorskip("ray", reason='Ray not installed (pip install "hgsloc-plugin[ray]")')
pytestmark = pytest.mark.slow  # worker processes start Ray and Taichi: seconds each

import hgsloc_plugin as hp  # noqa: E402
from hgsloc_plugin.cli.demo.queries import query_poses  # noqa: E402
from hgsloc_plugin.cli.demo.scene import make_room_scene  # noqa: E402
from hgsloc_plugin.evaluation.noise import se3_noise  # noqa: E402
from hgsloc_plugin.run.batch import Query  # noqa: E402
from hgsloc_plugin.run.distributed import ray_results, worker_resources  # noqa: E402

CFG = hp.RefineConfig.preset("fast", max_expansions=8)


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def case():
    scene = make_room_scene(density=0.3)
    cam = hp.Camera.from_focal(96, 72, 70.0)
    gts = query_poses(5, seed=21)
    imgs = hp.render(scene, cam, gts)
    rng = np.random.default_rng(2)
    tasks = [Query(k, f"q{k}", imgs[k], cam, se3_noise(g, 1.0, 0.03, rng)) for k, g in enumerate(gts)]
    return scene, tasks


def _items(tasks):
    return [(t.image, t.camera, t.coarse_pose, t.name) for t in tasks]


@pytest.mark.parametrize("gpus", [1, 2, 3, 4, 2.5])
def test_workers_share_the_gpus_and_all_fit(gpus):
    """Every worker goes on a GPU when the cluster has one (before: two workers on one GPU both ran on the CPU),
    as many per GPU as the pool needs, and the shares of one GPU's workers never add up to more than it (Ray
    keeps four decimals: 7 shares of 1/7 rounded to 0.1429 would leave the seventh worker waiting forever)."""
    whole = int(gpus)
    for workers in range(1, 18):
        res, arch = worker_resources(gpus, workers, threads=2, arch="auto")
        assert arch == "cuda" and res["num_cpus"] == 2
        share = res["num_gpus"]
        assert 0 < share <= 1
        per_gpu = round(share * 1e4) // 1  # in Ray's units of 1e-4 GPU
        fits = whole * (10_000 // per_gpu)  # workers that can be placed at once
        assert fits >= workers, (gpus, workers, share)
        assert share == 1.0 if workers <= whole else share < 1.0
        assert share >= 1.0 / (-(-workers // whole)) - 1e-4  # no smaller than the pool needs


def test_no_gpu_or_the_cpu_asked_for_means_cpu_workers():
    assert worker_resources(0, 3, arch="auto") == ({"num_cpus": 1, "num_gpus": 0}, "cpu")
    assert worker_resources(0.5, 3, arch="auto")[1] == "cpu"  # a GPU already shared out is not a GPU to start CUDA on
    assert worker_resources(2, 3, arch="cpu") == ({"num_cpus": 1, "num_gpus": 0}, "cpu")  # HGSLOC_ARCH=cpu
    assert worker_resources(2, 3, arch="CUDA")[1] == "cuda"
    with pytest.raises(RuntimeError, match="0 GPUs"):
        worker_resources(0, 3, arch="cuda")
    with pytest.raises(ValueError, match="workers"):
        worker_resources(1, 0, arch="auto")
    with pytest.raises(ValueError, match="arch"):
        worker_resources(1, 2, arch="gpu")


def test_worker_backend_follows_hgsloc_arch(monkeypatch):
    """Without ``arch``, the caller's ``HGSLOC_ARCH`` decides, as for ``backend.init``."""
    monkeypatch.setenv("HGSLOC_ARCH", "cpu")
    assert worker_resources(1, 2)[1] == "cpu"
    monkeypatch.setenv("HGSLOC_ARCH", "auto")
    assert worker_resources(1, 2)[1] == "cuda"


def test_two_workers_equal_single_process_in_order(local_ray, case):
    """Also the workers' own default batch size (``batch_size`` None goes to the workers)."""
    scene, tasks = case
    refiner = hp.HGSLocPlugin(scene, CFG)
    ref = refiner.refine_many(_items(tasks), progress=False)
    got = refiner.refine_many(_items(tasks), progress=False, workers=2)
    assert [r.name for r in got] == [t.name for t in tasks]
    for a, b in zip(ref, got):
        assert a.pose == b.pose and a.cost_final == b.cost_final and a.renders == b.renders


def test_workers_use_the_callers_raster_config(local_ray, case):
    scene, tasks = case
    raster = hp.RasterConfig(alpha_max=0.9, eps2d=0.6, radius_mode="inria")
    refiner = hp.HGSLocPlugin(scene, CFG, raster=raster)
    ref = refiner.refine_many(_items(tasks[:3]), progress=False)
    got = refiner.refine_many(_items(tasks[:3]), progress=False, workers=2)
    default = hp.HGSLocPlugin(scene, CFG).refine_many(_items(tasks[:3]), progress=False)
    assert [r.cost_initial for r in got] == [r.cost_initial for r in ref]
    assert [r.pose for r in got] == [r.pose for r in ref]
    assert [r.cost_initial for r in default] != [r.cost_initial for r in ref]  # the config does change renders


def test_workers_get_each_querys_region_and_prior_error(local_ray, case):
    """Per-query fields (``Refiner.refine``'s keywords, from dicts) travel to the workers: the same results as in
    process, each recording its own region and expected error; a misspelt key is refused, not dropped."""
    scene, tasks = case
    refiner = hp.HGSLocPlugin(scene, CFG)
    per_query = [{"max_shift": 0.004, "max_rotation_deg": 0.2}, {"prior_error": 0.02, "prior_error_deg": 0.5}, {}]
    items = [dict(image=t.image, camera=t.camera, coarse_pose=t.coarse_pose, name=t.name, **extra)
             for t, extra in zip(tasks, per_query)]
    ref = refiner.refine_many(items, progress=False)
    got = refiner.refine_many(items, progress=False, workers=2)
    assert [r.pose for r in got] == [r.pose for r in ref]
    assert (got[0].max_shift, got[0].max_rotation_deg) == (0.004, 0.2) and got[2].max_shift != 0.004
    assert (got[1].prior_error, got[1].prior_error_deg) == (0.02, 0.5) and math.isnan(got[0].prior_error)
    with pytest.raises(ValueError, match="max_shif_depth"):
        refiner.refine_many([dict(items[2], max_shif_depth=0.1)], progress=False)


def test_killed_worker_still_yields_every_query_once(local_ray, case):
    scene, tasks = case
    killed = []

    def kill_first(actor):
        if not killed:
            killed.append(actor)
            ray.kill(actor)

    got = list(ray_results(scene, CFG, hp.RasterConfig(), tasks, workers=2, chunk_size=1,
                           _after_chunk=kill_first))
    assert killed
    assert sorted(q.index for q, _ in got) == list(range(len(tasks)))
    assert all(r.error is None for _, r in got)


def test_pipeline_with_workers_and_resume(local_ray, case, tmp_path):
    from hgsloc_plugin.adapters.intrinsics import from_focal
    from hgsloc_plugin.evaluation.viz import save_png
    from hgsloc_plugin.run.pipeline import refine_pose_file

    scene, tasks = case
    (tmp_path / "img").mkdir()
    lines = []
    for t in tasks:
        save_png(t.image, tmp_path / "img" / f"{t.name}.png")
        lines.append(" ".join([f"{t.name}.png"] + [repr(float(v)) for v in t.coarse_pose.as_array()]))
    (tmp_path / "in.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out.txt"
    refine_pose_file(scene, tmp_path / "in.txt", tmp_path / "img", from_focal(70.0), out, config=CFG, limit=2,
                     progress=False, workers=2)
    rep = refine_pose_file(scene, tmp_path / "in.txt", tmp_path / "img", from_focal(70.0), out, config=CFG,
                           progress=False, workers=2)
    assert len(rep["queries"]) == 5
    names = [ln.split()[0] for ln in out.read_text().splitlines()]
    assert names == [f"q{k}.png" for k in range(5)]
    single = tmp_path / "single.txt"
    refine_pose_file(scene, tmp_path / "in.txt", tmp_path / "img", from_focal(70.0), single, config=CFG,
                     progress=False)
    assert single.read_text() == out.read_text()
    assert json.loads((tmp_path / "out.txt.json").read_text())["totals"]["queries"] == 5
