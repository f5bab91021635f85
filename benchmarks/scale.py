"""Scale-out throughput on the demo room: in-process vs Ray with 1 and 2 workers, in one run.

Usage: python benchmarks/scale.py [--queries 8] [--config fast]
Prints queries per second for each mode and the Ray path's overhead per query against the in-process path
(same queries, same config, results checked equal).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import hgsloc_plugin as hp  # noqa: E402
from hgsloc_plugin.demo.queries import make_queries, query_poses  # noqa: E402
from hgsloc_plugin.demo.scene import make_room_scene  # noqa: E402
from hgsloc_plugin.noise import se3_noise  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--queries", type=int, default=8)
    ap.add_argument("--config", default="fast")
    a = ap.parse_args()
    import ray

    hp.init("cpu")
    scene = make_room_scene()
    cam = hp.Camera.from_fov(320, 240, 65.0)
    gts = query_poses(a.queries, seed=3)
    imgs = make_queries(scene, cam, gts)
    rng = np.random.default_rng(0)
    items = [(imgs[k], cam, se3_noise(g, 1.0, 0.03, rng), f"q{k}") for k, g in enumerate(gts)]
    cfg = hp.RefineConfig.preset(a.config)
    refiner = hp.HGSLocPlugin(scene, cfg)
    refiner.refine(imgs[0], cam, items[0][2])  # warm-up
    t0 = time.perf_counter()
    ref = refiner.refine_many(items, progress=False)
    t_in = time.perf_counter() - t0
    print(f"{a.queries} queries, preset {a.config}, {scene.num_gaussians} Gaussians, {2} CPU cores")
    print("| mode | queries/s | s/query | overhead/query vs in-process |")
    print("|---|---|---|---|")
    print(f"| in-process (2 Taichi threads) | {a.queries / t_in:.2f} | {t_in / a.queries:.2f} | - |")
    for workers in (1, 2):
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        t0 = time.perf_counter()
        got = refiner.refine_many(items, progress=False, workers=workers)
        dt = time.perf_counter() - t0
        ray.shutdown()
        same = all(x.pose == y.pose for x, y in zip(ref, got))
        print(f"| Ray, {workers} worker(s) x 1 thread | {a.queries / dt:.2f} | {dt / a.queries:.2f} | "
              f"{(dt - t_in) / a.queries:+.2f} s (results equal: {same}) |")


if __name__ == "__main__":
    main()
