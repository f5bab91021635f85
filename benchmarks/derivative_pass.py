"""Derivative pass: its time in its two blend layouts, in units of one plain render, in one run.

Usage: python -m benchmarks.derivative_pass [--cases snow_sharp snow lego room room_x20] [--repeats 41]
                                           [--out FILE]

Per case (the maps and first query of ``benchmarks/throughput.py``; the densified room through its working set)
and per scoring size the default refinement uses: one plain render of one pose (ms; in the backend's default
layout), one derivative pass (``Renderer.pose_gradient``: the cs cost, gradient and JtJ) with the tile-parallel
derivative blend (``RasterConfig.blend`` "splat", the CPU's default), the per-pixel one with pixel masks
(``grad_masks`` "on", the CPU's layout before it) and without them ("off", CUDA's default), each the median of
``--repeats`` calls made in turn on poses about one pixel around the true one; the passes in render-times (over
the plain render at the same size); and how far the tile layout's derivatives are from the per-pixel one's
(largest difference over the largest derivative; colour and alpha must agree within 1e-5, float32 rounding, but
for at most 1 in 10,000 values: ``tests/test_pose_grad.py::assert_same_to_rounding``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import load, write_keeping_notes
from hgsloc_plugin.core.image import resize_image
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine.plan import make_plan

HEADER = ("| case | Gaussians rendered | size | render (ms) | pass (ms): tiles / pixels + masks / pixels | "
          "pass in render-times: tiles / pixels + masks / pixels | tiles vs pixels + masks | derivatives apart |"
          "\n|---|---|---|---|---|---|---|---|")
LAYOUTS = {"tiles": hp.RasterConfig(blend="splat"), "pixels + masks": hp.RasterConfig(blend="pixel", grad_masks="on"),
           "pixels": hp.RasterConfig(blend="pixel", grad_masks="off")}


def renderer_for(scene, bg, raster: hp.RasterConfig, plan_args):
    """The renderer a refinement of ``plan_args``' query uses (the working set covering its prior on large maps)
    with the rasterizer settings ``raster``; and the plan."""
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg), raster=raster)
    plan = make_plan(refiner.config, scene, *plan_args, hp.QueryPrior())
    r = refiner.renderer_for(plan)
    return (r.covering([plan.coarse_pose]) if hasattr(r, "covering") else r), plan


def compared_rows(case: str, repeats: int, rasters: tuple[hp.RasterConfig, ...], size_row) -> list[str]:
    """``size_row(case, renderers, camera, image, poses, background)`` per scoring size of ``case``'s first query,
    ``renderers`` its renderers with the ``rasters``; ``poses``: ``repeats`` about one pixel around the true one."""
    loaded = load(case)
    if loaded is None:
        print(f"skipping {case}: data not found", file=sys.stderr)
        return []
    cam, scene, qs, bg = loaded
    _, truth, image, _ = qs[0]
    renderers = [renderer_for(scene, bg, raster, (cam, truth)) for raster in rasters]
    plan = renderers[0][1]
    rng = np.random.default_rng(3)
    f = 0.5 * (plan.cam_final.fx + plan.cam_final.fy)
    poses = [se3_noise(truth, np.degrees(1.0 / f), plan.depth / f, rng) for _ in range(repeats)]
    return [size_row(case, [r for r, _ in renderers], c, image, poses, bg)
            for c in dict.fromkeys([plan.cam_coarse, plan.cam_final, plan.cam_polish])]


def rows(case: str, repeats: int) -> list[str]:
    return compared_rows(case, repeats, tuple(LAYOUTS.values()), size_row)


def median_ms(calls: dict, poses: list) -> dict:
    """Per key of ``calls`` (each a function of one pose), its median time in ms over ``poses``, the calls made
    in turn on each pose (so that a slow stretch of a shared machine falls on all of them)."""
    times: dict = {k: [] for k in calls}
    for p in poses:
        for k, fn in calls.items():
            t0 = time.perf_counter()
            fn(p)
            times[k].append(time.perf_counter() - t0)
    return {k: 1000 * float(np.median(v)) for k, v in times.items()}


def size_row(case: str, renderers, cam: hp.Camera, image: np.ndarray, poses: list, bg) -> str:
    """One Markdown row: the render and the pass in each layout (``renderers``, in ``LAYOUTS``' order) at ``cam``'s
    size, timed in turn on each of ``poses``."""
    img = resize_image(image, cam.width, cam.height)
    rs = dict(zip(LAYOUTS, renderers))
    q = {k: r.upload_window_query(img) for k, r in rs.items()}
    (rgb, alpha, d), (rgb2, alpha2, d2) = (rs[k].render_derivatives(cam, poses[:3], bg) for k in ("tiles", "pixels"))
    for x, y in ((rgb, rgb2), (alpha, alpha2)):  # to rounding, but where an alpha is alpha_min to the last bit
        off = np.abs(x - y)
        if not (off.max() <= 2 * hp.RasterConfig().alpha_min and (off > 1e-5).mean() <= 1e-4):
            raise SystemExit(f"{case} {cam.width}x{cam.height}: the two layouts render different images")
    apart = float(np.abs(d - d2).max() / np.abs(d2).max())
    calls = {k: (lambda p, r=r, k=k: r.pose_gradient(cam, [p], q[k], bg)) for k, r in rs.items()}
    unit = rs["tiles" if hp.init() == "cpu" else "pixels"]  # the render in the backend's default layout
    ms = median_ms({"render": lambda p: unit.render_full(cam, [p], bg), **calls}, poses)
    passes = " / ".join(f"{ms[k]:.1f}" for k in LAYOUTS)
    times = " / ".join(f"{ms[k] / ms['render']:.2f}" for k in LAYOUTS)
    row = (f"| {case} | {renderers[0].n:,} | {cam.width}x{cam.height} | {ms['render']:.1f} | {passes} | {times} | "
           f"{ms['pixels + masks'] / ms['tiles']:.2f}x | {apart:.1e} |")
    print(row, flush=True)
    return row


def table_main(doc: str, script: str, title: str, header: str, rows, repeats: int) -> None:
    """The command line of a per-case, per-size timing table: ``--cases``, ``--repeats``, ``--out``; prints
    ``header`` and ``rows(case, repeats)``'s rows, and writes them under ``title`` to ``--out`` (notes kept)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["snow_sharp", "snow", "lego", "room", "room_x20"])
    ap.add_argument("--repeats", type=int, default=repeats)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    hp.init()
    print(header, flush=True)
    body = [r for case in a.cases for r in rows(case, a.repeats)]
    if a.out:
        write_keeping_notes(Path(a.out), [f"# {title} (`benchmarks/{script}`)", "",
                                          f"Regenerate: `python -m benchmarks.{Path(script).stem} --out "
                                          f"benchmarks/{Path(script).stem}.md`.", "", header, *body])


def main() -> None:
    table_main(__doc__, "derivative_pass.py", "Derivative pass", HEADER, rows, 41)


if __name__ == "__main__":
    main()
