"""Renderer speed: Taichi (batched) vs the PyTorch reference of tests/reference, in one run.

Usage: python -m benchmarks.render [--scene ../shared/data/scenes/donut.ply] [--repeats 5]
Prints ms per pose for B=1 and B=14 at 160x120 and 640x480, the reference's ms per pose and the ratio.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import ROOT
from hgsloc_plugin.cli.demo.scene import make_room_scene


def timed(fn, repeats):
    fn()  # warm-up (compile / allocate)
    best = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best.append(time.perf_counter() - t0)
    return float(np.median(best))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default=str(ROOT.parent / "shared" / "data" / "scenes" / "donut.ply"))
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    from tests.reference.render_torch import render_reference

    hp.init()
    if Path(a.scene).exists():
        scene = hp.GaussianScene.from_ply(a.scene)
        eye, target = (0.25, -0.25, 0.25), (0.0, 0.0, 0.03)
        label = Path(a.scene).name
    else:
        print(f"({a.scene} not found: using the demo room)")
        scene = make_room_scene()
        eye, target = (0.0, 0.0, 1.4), (2.0, 1.0, 1.2)
        label = "demo room"
    T = hp.Pose.look_at(eye, target)
    rng = np.random.default_rng(0)
    poses = [T.perturbed_in_camera(rng.normal(scale=0.01, size=3), rng.normal(scale=0.005, size=3))
             for _ in range(14)]
    print(f"scene {label}: {scene.num_gaussians} Gaussians, SH {scene.sh_degree}; backend {hp.current_arch()}")
    print("| size | B | Taichi ms/pose | fused cost ms/pose | torch reference ms/pose | speed-up |")
    print("|---|---|---|---|---|---|")
    for w, h in ((160, 120), (640, 480)):
        cam = hp.Camera.from_fov(w, h, 50.0)
        target_img = hp.render(scene, cam, T)
        ref = timed(lambda cam=cam: render_reference(scene, cam, T), max(1, a.repeats // 2))
        for B in (1, 14):
            ps = poses[:B]
            t_img = timed(lambda cam=cam, ps=ps: hp.render(scene, cam, ps), a.repeats) / B
            t_cost = timed(lambda cam=cam, ps=ps, t=target_img: hp.render_cost(scene, cam, ps, t), a.repeats) / B
            print(f"| {w}x{h} | {B} | {t_img * 1e3:.2f} | {t_cost * 1e3:.2f} | {ref * 1e3:.1f} | "
                  f"{ref / t_cost:.0f}x |")


if __name__ == "__main__":
    main()
