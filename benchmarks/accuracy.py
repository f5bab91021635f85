"""Accuracy benchmark in the shape of the paper's noise table, written as Markdown.

Usage: python -m benchmarks.accuracy [--queries 4] [--paper-queries 2] [--out benchmarks/accuracy.md]

Scenes: the embedded demo room and (when ../shared/data/scenes is present) donut.ply. Queries are rendered at
known poses and degraded like photos (gain, gamma, blur, noise, an occluder); coarse poses follow the noise
protocols (the paper's qA,tB and exact SE(3) magnitudes). Each protocol is refined with every heuristic under
the default config (cs as search only, search + polish, gradient only and the default: gradient first, the search
only when its pose is refused; the other heuristics search only: the polish is cs's), and with the emulated official
scheme (paper neighbourhood, fixed step, 399 expansions,
L1) on a subset. Errors: camera-centre distance and rotation angle, medians over queries.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import ROOT
from hgsloc_plugin.cli.demo.queries import degrade, query_poses
from hgsloc_plugin.cli.demo.scene import make_room_scene
from hgsloc_plugin.evaluation.noise import apply_protocol

HEURISTICS = ("sad", "psnr", "ssim", "affine")  # no polish: its derivatives are those of cs
CS_MODES = {"search only": hp.RefineConfig(routes="lattice"), "search + polish": hp.RefineConfig.preset("search"),
            "gradient only": hp.RefineConfig.preset("gradient"), "gradient first (default)": hp.RefineConfig()}


def donut_case(n, seed=0):
    path = ROOT.parent / "shared" / "data" / "scenes" / "donut.ply"
    if not path.exists():
        return None
    scene = hp.GaussianScene.from_ply(path)
    rng = np.random.default_rng(seed)
    gts = []
    for _ in range(n):
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 0.9)
        r = rng.uniform(0.3, 0.38)
        eye = r * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        gts.append(hp.Pose.look_at(eye, [0.0, 0.0, 0.03] + rng.normal(scale=0.01, size=3)))
    return ("donut.ply", scene, hp.Camera.from_fov(320, 240, 50.0), gts,
            ("q3,t3", "1cm,2deg"), "cm/deg (scene units x 100)")


def room_case(n, seed=0):
    return ("demo room", make_room_scene(), hp.Camera.from_fov(320, 240, 65.0), query_poses(n, seed=seed + 1),
            ("q3,t2", "1cm,0.5deg", "3cm,1deg", "5cm,2deg", "10cm,3deg"), "cm/deg")


def median_err(poses, gts):
    e = np.array([p.errors_to(g) for p, g in zip(poses, gts)])
    return np.median(e[:, 0]) * 100, np.median(e[:, 1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--queries", type=int, default=4)
    ap.add_argument("--paper-queries", type=int, default=2)
    ap.add_argument("--donut-queries", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "accuracy.md"))
    a = ap.parse_args()
    hp.init()
    lines = ["| scene | noise | config | heuristic | noise error t / R | refined t / R | improvement t / R | "
             "renders/q | derivative passes/q | s/q |", "|" + "---|" * 10]
    t_start = time.time()
    for case in (room_case(a.queries), donut_case(a.donut_queries) if a.donut_queries else None):
        if case is None and not a.donut_queries:
            continue  # --donut-queries 0: the room only
        if case is None:
            lines.append("| donut.ply | skipped: ../shared/data/scenes/donut.ply not found |" + " |" * 8)
            continue
        label, scene, cam, gts, protocols, units = case
        rng_q = np.random.default_rng(1000)
        imgs = [degrade(im, rng_q) for im in hp.render(scene, cam, gts)]
        for spec in protocols:
            rng = np.random.default_rng(7)
            coarse = [apply_protocol(g, spec, rng) for g in gts]
            t0, r0 = median_err(coarse, gts)
            runs = [(mode, "cs", cfg, len(gts)) for mode, cfg in CS_MODES.items()]
            runs += [("default", h, hp.RefineConfig(metric=h), len(gts)) for h in HEURISTICS]
            if spec in protocols[:2]:
                runs.append(("paper emulation", "sad", hp.RefineConfig.preset(
                    "paper", paper_step_q=2e-4, paper_step_t=2e-3 if label == "demo room" else 2e-4),
                    a.paper_queries))
            for cfg_name, h, cfg, n in runs:
                ref = hp.HGSLocPlugin(scene, cfg)
                res = [ref.refine(im, cam, c) for im, c in zip(imgs[:n], coarse[:n])]
                t1, r1 = median_err([r.pose for r in res], gts[:n])
                tb, rb = median_err(coarse[:n], gts[:n])
                lines.append(
                    f"| {label} | {spec} | {cfg_name} | {h} | {tb:.2f} / {rb:.2f} | {t1:.2f} / {r1:.3f} | "
                    f"{100 * (1 - t1 / tb):.0f} % / {100 * (1 - r1 / rb):.0f} % | "
                    f"{np.median([r.renders for r in res]):.0f} | "
                    f"{np.median([r.derivative_passes for r in res]):.0f} | "
                    f"{np.median([r.seconds for r in res]):.2f} |")
                print(lines[-1], flush=True)
    from benchmarks.harness import regenerate_line, write_keeping_notes

    text = ("# Accuracy benchmark\n\n" + regenerate_line(__file__) + "\n\n"
            f"Queries: {a.queries} on the room, {a.donut_queries} on the donut (paper emulation: "
            f"{a.paper_queries}), photo-degraded renderings at "
            f"320x240, scoring at 200 px (polish at 320 px); backend {hp.current_arch()}; medians over queries; "
            "translation in "
            "scene units x 100 (cm for the room), rotation in degrees. "
            f"Total time {time.time() - t_start:.0f} s.\n\n" + "\n".join(lines) + "\n")
    write_keeping_notes(Path(a.out), text.rstrip("\n").split("\n"))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
