"""Derivative pass: its time with and without the pixel masks, in units of one plain render, in one run.

Usage: python benchmarks/derivative_pass.py [--cases snow_sharp snow lego room room_x20] [--repeats 15]
                                           [--out FILE]

Per case (the maps and first query of ``benchmarks/throughput.py``; the densified room through its working set)
and per scoring size the default refinement uses: one plain render of one pose (ms), one derivative pass
(``Renderer.pose_gradient``: the cs cost, gradient and JtJ) with the pixel masks (``RasterConfig.grad_masks``
"on", the CPU's default) and without them ("off", the reference), each the median of ``--repeats`` calls made in
turn on poses about one pixel around the true one; the pass in render-times (over the plain render at the same
size) and the speed-up; and whether both passes give the same numbers bit for bit.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from real_photos import write_keeping_notes  # noqa: E402
from throughput import load  # noqa: E402

import hgsloc_plugin as hp  # noqa: E402
from hgsloc_plugin.image import resize_image  # noqa: E402
from hgsloc_plugin.noise import se3_noise  # noqa: E402
from hgsloc_plugin.refine.plan import make_plan  # noqa: E402

HEADER = ("| case | Gaussians rendered | size | render (ms) | pass, masks (ms) | pass, no masks (ms) | "
          "pass in render-times: masks / none | speed-up | same numbers |\n|---|---|---|---|---|---|---|---|---|")


def renderer_for(scene, bg, raster: hp.RasterConfig, plan_args):
    """The renderer a refinement of ``plan_args``' query uses (the working set covering its prior on large maps)
    with the rasterizer settings ``raster``; and the plan."""
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg), raster=raster)
    plan = make_plan(refiner.config, scene, *plan_args, hp.QueryPrior())
    r = refiner._working_set(plan)
    return (r.covering([plan.coarse_pose]) if hasattr(r, "covering") else r), plan


def compared_rows(case: str, repeats: int, rasters: tuple[hp.RasterConfig, hp.RasterConfig], size_row) -> list[str]:
    """``size_row(case, a, b, camera, image, poses, background)`` per scoring size of ``case``'s first query, ``a``
    and ``b`` its renderers with the two ``rasters``; ``poses``: ``repeats`` about one pixel around the true one."""
    loaded = load(case)
    if loaded is None:
        print(f"skipping {case}: data not found", file=sys.stderr)
        return []
    cam, scene, qs, bg = loaded
    _, truth, image, _ = qs[0]
    a, plan = renderer_for(scene, bg, rasters[0], (cam, truth))
    b, _ = renderer_for(scene, bg, rasters[1], (cam, truth))
    rng = np.random.default_rng(3)
    f = 0.5 * (plan.cam_final.fx + plan.cam_final.fy)
    poses = [se3_noise(truth, np.degrees(1.0 / f), plan.depth / f, rng) for _ in range(repeats)]
    return [size_row(case, a, b, c, image, poses, bg)
            for c in dict.fromkeys([plan.cam_coarse, plan.cam_final, plan.cam_polish])]


def rows(case: str, repeats: int) -> list[str]:
    return compared_rows(case, repeats, (hp.RasterConfig(grad_masks="on"), hp.RasterConfig(grad_masks="off")),
                         size_row)


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


def size_row(case: str, with_masks, without, cam: hp.Camera, image: np.ndarray, poses: list, bg) -> str:
    """One Markdown row: the render and both passes at ``cam``'s size, timed in turn on each of ``poses``."""
    img = resize_image(image, cam.width, cam.height)
    qa, qb = with_masks.upload_window_query(img), without.upload_window_query(img)
    same = all(np.array_equal(a, b) for a, b in zip(with_masks.pose_gradient(cam, poses[:3], qa, bg),
                                                    without.pose_gradient(cam, poses[:3], qb, bg)))
    calls = {"render": lambda p: with_masks.render_full(cam, [p], bg),
             "masks": lambda p: with_masks.pose_gradient(cam, [p], qa, bg),
             "none": lambda p: without.pose_gradient(cam, [p], qb, bg)}
    ms = median_ms(calls, poses)
    row = (f"| {case} | {with_masks.n:,} | {cam.width}x{cam.height} | {ms['render']:.1f} | {ms['masks']:.1f} | "
           f"{ms['none']:.1f} | {ms['masks'] / ms['render']:.2f} / {ms['none'] / ms['render']:.2f} | "
           f"{ms['none'] / ms['masks']:.2f}x | {'yes' if same else 'NO'} |")
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
                                          f"Regenerate: `python benchmarks/{script} --out "
                                          f"benchmarks/{Path(script).stem}.md`.", "", header, *body])


def main() -> None:
    table_main(__doc__, "derivative_pass.py", "Derivative pass", HEADER, rows, 15)


if __name__ == "__main__":
    main()
