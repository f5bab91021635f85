"""Refinement accuracy and cost: default config vs an emulation of the official scheme, one table.

Usage: python benchmarks/refine.py [--queries 6] [--paper-queries 2] [--lego]
Queries are rendered from the demo room at known poses (degraded like photos unless --clean), coarse poses are
ground truth + exact SE(3) noise; errors are camera-centre distance and rotation angle. With --lego it also
refines the 15 held-out *real* images of ../shared/data/lego.
"""

from __future__ import annotations

import argparse
import json
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

NOISE = ((0.01, 0.5), (0.03, 1.0), (0.10, 3.0))


def run(refiner, cam, gts, imgs, d, deg, seed=0):
    rng = np.random.default_rng(seed)
    e0, e1, renders, secs = [], [], [], []
    for g, im in zip(gts, imgs):
        c = se3_noise(g, deg, d, rng)
        r = refiner.refine(im, cam, c)
        e0.append(c.errors_to(g))
        e1.append(r.pose.errors_to(g))
        renders.append(r.renders)
        secs.append(r.seconds)
    e0, e1 = np.array(e0), np.array(e1)
    return dict(t0=np.median(e0[:, 0]) * 100, r0=np.median(e0[:, 1]), t1=np.median(e1[:, 0]) * 100,
                r1=np.median(e1[:, 1]), renders=float(np.median(renders)), sec=float(np.median(secs)))


def row(label, noise, m):
    red_t = 100 * (1 - m["t1"] / m["t0"])
    red_r = 100 * (1 - m["r1"] / m["r0"])
    return (f"| {label} | {noise} | {m['t0']:.2f} / {m['r0']:.2f} | {m['t1']:.2f} / {m['r1']:.3f} | "
            f"{red_t:.0f} % / {red_r:.0f} % | {m['renders']:.0f} | {m['sec']:.2f} |")


def lego(config):
    from PIL import Image

    d = ROOT.parent / "shared" / "data" / "lego"
    if not d.exists():
        return f"(lego skipped: {d} not found)"
    cj = json.loads((d / "camera.json").read_text())
    cam = hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    scene = hp.GaussianScene.from_ply(d / "lego.ply")
    refiner = hp.HGSLocPlugin(scene, config.replace(background=(1.0, 1.0, 1.0), score_max_side=100))
    gts, imgs = [], []
    for line in (d / "gt.txt").read_text().splitlines():
        t = line.split()
        gts.append(hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]]))
        rgba = np.asarray(Image.open(d / "queries" / t[0]).convert("RGBA"), np.float32) / 255
        imgs.append(rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]))  # composite on white
    out = []
    for dd, deg in ((0.05, 1.0), (0.2, 3.0)):
        out.append(row("default (lego, real images)", f"{dd:g} u, {deg:g} deg", run(refiner, cam, gts, imgs, dd, deg)))
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--queries", type=int, default=6)
    ap.add_argument("--paper-queries", type=int, default=2)
    ap.add_argument("--clean", action="store_true", help="queries are plain renderings (no photo degradation)")
    ap.add_argument("--lego", action="store_true")
    a = ap.parse_args()
    hp.init()
    scene = make_room_scene()
    cam = hp.Camera.from_fov(320, 240, 65.0)
    gts = query_poses(a.queries, seed=1)
    imgs = make_queries(scene, cam, gts, realistic=not a.clean)
    default = hp.RefineConfig()
    paper = hp.RefineConfig.preset("paper", paper_step_q=2e-4, paper_step_t=2e-3, score_max_side=160)
    print(f"demo room: {scene.num_gaussians} Gaussians; queries {cam.width}x{cam.height} "
          f"({'clean' if a.clean else 'photo-degraded'}), scoring at {default.score_max_side} px; backend "
          f"{hp.current_arch()}")
    print("| config | noise | before t (cm) / R (deg) | after | reduction t / R | renders/query | s/query |")
    print("|---|---|---|---|---|---|---|")
    t0 = time.time()
    for d, deg in NOISE:
        print(row("default (lattice, levels)", f"{d * 100:g} cm, {deg:g} deg",
                  run(hp.HGSLocPlugin(scene, default), cam, gts, imgs, d, deg)), flush=True)
    for d, deg in NOISE[:2]:
        print(row("paper emulation (14 raw moves, fixed step, 399 exp.)", f"{d * 100:g} cm, {deg:g} deg",
                  run(hp.HGSLocPlugin(scene, paper), cam, gts[: a.paper_queries], imgs[: a.paper_queries], d, deg)),
              flush=True)
    if a.lego:
        print(lego(default))
    print(f"(total {time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
