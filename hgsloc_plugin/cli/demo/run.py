"""``hgsloc demo``: the whole chain on the embedded room, through the same code paths as a user's files."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ...adapters.dialects import read_poses
from ...adapters.intrinsics import from_focal
from ...adapters.posefile import format_pose_tokens
from ...core.camera import Camera
from ...core.fileio import atomic_write_bytes, write_json
from ...core.scene import GaussianScene
from ...evaluation.evaluate import evaluate
from ...evaluation.noise import apply_protocol
from ...evaluation.viz import comparison_figure, plot_costs, plot_errors, save_png
from ...refine import RefineConfig
from ...refine.plan import median_depth
from .queries import make_queries, query_poses
from .scene import make_room_scene

logger = logging.getLogger("hgsloc_plugin")
DEFAULT_NOISE = ("1cm,0.5deg", "3cm,1deg", "10cm,3deg")
QUERY_CAMERA = Camera.from_fov(320, 240, 65.0)


def _write_pose_file(path: Path, poses: dict) -> None:
    lines = [" ".join([n] + format_pose_tokens(p)) for n, p in poses.items()]
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


def run_demo(out: Path, queries: int = 6, noise=DEFAULT_NOISE, preset: str = "default", seed: int = 0,
             progress: bool = True) -> dict:
    """Build the room, render queries, perturb, refine through the HLoc-dialect adapter, evaluate, plot.

    Returns the summary dict (also written to ``out/summary.json``; per noise level, ``seconds_per_query`` is the
    refinement's wall time over its queries, which a lockstep batch refines together); prints nothing.
    """
    from ...run.pipeline import refine_pose_file

    out = Path(out)
    (out / "images" / "seq-01").mkdir(parents=True, exist_ok=True)
    scene_path = make_room_scene(seed).to_ply(out / "room.ply")
    scene = GaussianScene.from_ply(scene_path)  # exercise the loader
    cam = QUERY_CAMERA
    gts = query_poses(queries, seed=seed + 1)
    imgs = make_queries(scene, cam, gts, seed=seed)
    names = [f"seq-01/frame-{k:06d}.color.png" for k in range(queries)]
    for n, im in zip(names, imgs):
        save_png(im, out / "images" / n)
    gt = dict(zip(names, gts))
    _write_pose_file(out / "gt.txt", gt)
    config = RefineConfig.preset(preset)
    rows = []
    for spec in noise:
        tag = spec.replace(",", "_").replace(".", "p")
        rng = np.random.default_rng(seed + 7)
        coarse = {n: apply_protocol(g, spec, rng, median_depth(scene, cam, g)) for n, g in gt.items()}
        coarse_path = out / f"coarse_{tag}.txt"
        _write_pose_file(coarse_path, coarse)
        refined_path = out / f"refined_{tag}.txt"
        start = time.perf_counter()
        rep = refine_pose_file(scene, coarse_path, out / "images", from_focal(cam.fx), refined_path, config=config,
                               progress=progress, gt_variant="synthetic", settings={"noise": spec}, restart=True)
        elapsed = time.perf_counter() - start  # the whole file: queries refined together overlap in time
        ev0 = evaluate(read_poses(coarse_path), gt)
        ev1 = evaluate(read_poses(refined_path), gt)
        q = rep["queries"]
        rows.append({
            "noise": spec, "before": {k: ev0[k] for k in ("median_translation_cm", "median_rotation_deg", "recall")},
            "after": {k: ev1[k] for k in ("median_translation_cm", "median_rotation_deg", "recall")},
            "renders_per_query": float(np.mean([v["renders"] for v in q.values()])),
            "seconds_per_query": elapsed / max(len(q), 1),
            "accepted": sum(v["accepted"] for v in q.values()),
        })
        t0 = [ev0["errors"][n][0] for n in names]
        t1 = [ev1["errors"][n][0] for n in names]
        r0 = [ev0["errors"][n][1] for n in names]
        r1 = [ev1["errors"][n][1] for n in names]
        plot_errors(t0, t1, r0, r1, out / "figures" / f"errors_{tag}.png")
        plot_costs(list(q.values()), out / "figures" / f"cost_{tag}.png", names=list(q))
        n0 = names[0]
        comparison_figure(scene, cam, imgs[0], coarse[n0], read_poses(refined_path)[n0],
                          out / "figures" / f"compare_{tag}_{n0.replace('/', '_')}", background=config.background)
    summary = {"queries": queries, "preset": preset, "scene_gaussians": scene.num_gaussians, "rows": rows}
    write_json(out / "summary.json", summary)
    return summary


def format_table(summary: dict) -> str:
    """The demo's table as Markdown."""
    head = ("| noise | t before (cm) | t after (cm) | R before (deg) | R after (deg) | recall 5/2/1 before (%) "
            "| recall 5/2/1 after (%) | renders/query | s/query |")
    lines = [head, "|" + "---|" * 9]
    for r in summary["rows"]:
        def rec(d):
            return "/".join(f"{100 * d['recall'][k]:.0f}" for k in ("5cm5deg", "2cm2deg", "1cm1deg"))

        lines.append(f"| {r['noise']} | {r['before']['median_translation_cm']:.2f} | "
                     f"{r['after']['median_translation_cm']:.2f} | {r['before']['median_rotation_deg']:.3f} | "
                     f"{r['after']['median_rotation_deg']:.3f} | {rec(r['before'])} | {rec(r['after'])} | "
                     f"{r['renders_per_query']:.0f} | {r['seconds_per_query']:.2f} |")
    return "\n".join(lines)
