"""Map-scale benchmark: per-render and per-query cost from 50k to 1M Gaussians, whole map vs working set vs routes.

Usage: python -m benchmarks.map_scale [--k 1 4 10 20] [--queries 9] [--noise 3cm,1deg] [--paths P ...] [--out FILE]
       python -m benchmarks.map_scale --stages [--k 1 20]
       python -m benchmarks.map_scale --footprints [--k 1 20] [--queries 9]
       python -m benchmarks.map_scale --cuts [--k 1 4 10 20] [--queries 9]

The demo room densified k times: ``--maps split`` (the default; ``demo.scene.densify_split``: every Gaussian split
into k children with its moments, queries rendered from the densified map, so the truth is a minimum) or
``--maps jitter`` (``demo.scene.densify``: copies with jittered centres, queries rendered from the undensified
room, so the map is as imperfect at every size and every prior is kept); photo-degraded 320x240 queries and the
same coarse poses for every size. Each (size, path) runs in its own
process so that its peak memory (max RSS) is its own. Paths (``--paths``; default: the first two and the last):
- ``whole map, search``: the lattice search + polish, every render projecting, sorting and blending the whole map
  (``RefineConfig(working_set=False, routes="search")``);
- ``working set, search``: the same search on the Gaussians some pose near the poses scored can see
  (``working_set.WorkingSet``: a region of ``working_set_pixels`` around the first poses scored, selected again
  when the search leaves it; ``kernels/cull.py``); forced at every size here (the default: from
  ``working_set_min``);
- ``working set + coarse LOD, search``: the same, and the coarse (pyramid) levels render a level of detail with
  Gaussians of up to 2 px merged per 2 px cell (``lod.py``, ``Tuning.coarse_lod_pixels=2``; opt-in).
- ``working set, gradient first``: Levenberg-Marquardt from the prior first, the search only when its pose is
  refused (``RefineConfig.routes``); ``working set + coarse LOD, gradient first``: the same with the
  coarse LOD above;
- ``working set, gradient first, priors nudged 1e-5 of the depth``: the exact path from priors moved that far
  (``NUDGED``): its ``vs exact`` is the refinement's own sensitivity to its start, against which a level of
  detail's change reads;
- ``working set + LOD 1 / 2 / 3 / 4 px, gradient first``: every render from a cut of the map's level-of-detail
  hierarchy (``render/hierarchy.py``, ``Tuning.lod_pixels``), built in the process (its seconds and size are a
  column) and compared per query with the exact path (``vs exact``: the median and largest change of the
  translation error, in % of the query's depth);
- ``working set, gradient first, plain renders``: the exact path with every scoring size rendered as 3DGS renders
  at its training size (``Tuning.antialias=False``; the default until 2026-12-07: each size below the query image
  renders as the image reduced to it, ``Camera.downsample``), compared with the default exact path;
  ``working set + LOD 2 px, gradient first, plain renders``: the cut so rendered, compared with the plain path;
- ``the undensified map (the parents), gradient first`` (``--maps split``): the split map's queries refined on the
  room before the split, what a hierarchy merging each parent's children back into it would draw, compared with
  the split map's exact path.

Before the timed queries, each process refines the first query once untimed (kernel compilation or loading
from Taichi's offline cache, once per process; its time is printed as "warm-up").
Columns: ms per render (14 poses per call at the default scoring size, 200x150, from the first query's prior;
the working-set row includes nothing of the selection, which is counted in s / query), working-set size (the
largest selection of a query, median) and selections per query,
renders, derivative passes and seconds per query, accuracy before / after (medians, cm / deg), peak RSS; then
where the timed queries' seconds go, by stage and scoring size (``harness.stage_clock``).

``--cuts``: at the first query's true pose, the Gaussians each scoring size draws, exact and from cuts at 1 / 2 / 4 px;
and the split maps' PSNR against the room at the query poses.

``--stages``: where one render's time goes at each size (the default path's renderer, the first query's prior at the
final scoring size, one pose, median of 15): projection, tile sort, blending (each its kernels' launches,
``kernels.launch.timed_launches``: on the CPU a launch runs its kernel; the rest of a render is host time), with the
Gaussians rendered (the working set), those visible (touching a tile), their tile-list entries, the pixels their
alpha ellipses cover (summed, unclipped, per image pixel: what the blend visits at most); and one working-set
selection around that prior (the default region, whatever the map's size), which a query makes a few times.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.machine import ROOT, module_command

# path -> RefineConfig fields (the first is the reference of the speed-up column)
PATHS = {
    "whole map, search": dict(working_set=False, routes="search"),
    "working set, search": dict(working_set=True, routes="search"),
    "working set + coarse LOD, search": dict(working_set=True, routes="search", coarse_lod_pixels=2.0),
    "working set, gradient first": dict(working_set=True, routes="gradient_first"),
    "working set + coarse LOD, gradient first": dict(working_set=True, routes="gradient_first", coarse_lod_pixels=2.0),
    **{f"working set + LOD {px} px, gradient first": dict(working_set=True, routes="gradient_first",
                                                          lod_pixels=float(px)) for px in (1, 2, 3, 4)},
    "working set, gradient first, plain renders": dict(working_set=True, routes="gradient_first", antialias=False),
    "working set + LOD 2 px, gradient first, plain renders": dict(working_set=True, routes="gradient_first",
                                                                 lod_pixels=2.0, antialias=False),
}
#: the exact path with every prior's centre moved by this fraction of its depth (a seeded direction per query): its
#: ``vs exact`` is how much the refined pose moves for a change of the start far below anything a map could show,
#: the scale the level of detail's change is read against
NUDGED = {"working set, gradient first, priors nudged 1e-5 of the depth": 1e-5}
PATHS |= {path: PATHS["working set, gradient first"] for path in NUDGED}
#: the exact path each level-of-detail (or nudged) path's accuracy is compared with
EXACT = {path: "working set, gradient first"
         for path in [f"working set + LOD {px} px, gradient first" for px in (1, 2, 3, 4)] + list(NUDGED)
         + ["working set, gradient first, plain renders"]}
EXACT["working set + LOD 2 px, gradient first, plain renders"] = "working set, gradient first, plain renders"
#: ``--maps split``: the split map's queries refined on the map before the split (its parents, as an ideal level of
#: detail would merge them back): how far the split map's own images are from its parents'
PARENTS = "the undensified map (the parents), gradient first"
PATHS[PARENTS] = PATHS["working set, gradient first"]
EXACT[PARENTS] = "working set, gradient first"
MAPS = ("split", "jitter", "snow_sharp")
DEFAULT_PATHS = ("whole map, search", "working set, search", "working set, gradient first")


def child(k: int, path: str, queries: int, noise: str, maps: str = "split") -> dict:
    import os
    import tempfile

    import hgsloc_plugin as hp
    from benchmarks.harness import case_errors, case_priors, load_dataset, stage_clock, worse_count
    from hgsloc_plugin.cli.demo.queries import degrade, query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify, densify_split, make_room_scene
    from hgsloc_plugin.evaluation.noise import apply_protocol
    from hgsloc_plugin.refine.plan import make_plan

    arch = hp.init()
    if maps == "snow_sharp":  # real photos on the good snow map split k times; priors 2 % of the depth / 1 deg
        cam, base, qs, _ = load_dataset(maps)
        qs = qs[:queries]
        scene = densify_split(base, k)
        priors = case_priors(maps, qs, 2.0, 1.0)
    else:
        room = make_room_scene()
        cam = QUERY_CAMERA
        gts = query_poses(queries, seed=1)
        scene = densify_split(room, k) if maps == "split" else densify(room, k)
        truth = scene if maps == "split" else room  # split maps render the room: the queries are their own images
        imgs = [degrade(im, np.random.default_rng(1000 + i)) for i, im in enumerate(hp.render(truth, cam, gts))]
        rng = np.random.default_rng(7)
        priors = [apply_protocol(g, noise, rng) for g in gts]
        qs = [(f"room{i}", g, im, 0.0) for i, (g, im) in enumerate(zip(gts, imgs))]  # metric: no depth needed
        if path == PARENTS:
            if maps != "split":
                raise SystemExit(f"{PARENTS!r} needs --maps split")
            scene = room  # the split map's queries, the map before the split
        del room, truth
    gts, imgs = [g for _, g, _, _ in qs], [im for _, _, im, _ in qs]
    case = maps if maps == "snow_sharp" else "room"  # errors in % of the depth, or cm (harness.case_errors)
    cfg = hp.RefineConfig.preset("default", working_set_min=0, **PATHS[path])  # a working set, when on, at every size
    if path in NUDGED:
        way = np.random.default_rng(11).normal(size=(len(priors), 3))
        way /= np.linalg.norm(way, axis=1, keepdims=True)
        priors = [hp.Pose.from_centre(p.R, p.centre() + NUDGED[path] * make_plan(cfg, scene, cam, p, hp.QueryPrior())
                                      .depth * w) for p, w in zip(priors, way)]
    refiner = hp.HGSLocPlugin(scene, cfg)
    build_s = hierarchy_mb = 0.0
    if cfg.tuning.lod_pixels is not None:
        with tempfile.TemporaryDirectory() as tmp:  # the hierarchy built here, not read from a cache
            os.environ["HGSLOC_LOD_CACHE_DIR"] = tmp
            t0 = time.perf_counter()
            hierarchy = refiner.hierarchy()
            build_s, hierarchy_mb = time.perf_counter() - t0, hierarchy.nbytes / 1e6
    # per-render cost at the scoring size, around the first prior, on the renderer the search would use
    plan = make_plan(cfg, scene, cam, priors[0], hp.QueryPrior())
    renderer = refiner.renderer_for(plan)
    poses = [apply_protocol(priors[0], "1cm,0.5deg", np.random.default_rng(s)) for s in range(14)]
    renderer.render_full(plan.cam_final, poses)  # warm-up: compile, workspaces
    t0 = time.perf_counter()
    reps = 3
    for _ in range(reps):
        renderer.render_full(plan.cam_final, poses)
    ms = 1000 * (time.perf_counter() - t0) / (reps * len(poses))
    t0 = time.perf_counter()
    refiner.refine(imgs[0], cam, priors[0])  # warm-up: compiles (or loads) every kernel the routes use, once
    warm = time.perf_counter() - t0
    ren, sec, wset, nsel, passes = [], [], [], [], []
    with stage_clock(refiner) as spent:
        results = [refiner.refine(img, cam, prior) for img, prior in zip(imgs, priors)]
    for r in results:
        ren.append(r.renders)
        sec.append(r.seconds)
        wset.append(r.working_set)
        nsel.append(r.working_set_selections)
        passes.append(r.derivative_passes)
    e0, e1 = case_errors(case, qs, priors), case_errors(case, qs, [r.pose for r in results])
    depths = [make_plan(cfg, scene, cam, p, hp.QueryPrior()).depth for p in priors]
    return {"k": k, "path": path, "arch": arch, "gaussians": scene.num_gaussians, "ms_per_render": ms,
            "errors_t": [r.pose.errors_to(g)[0] for r, g in zip(results, gts)], "errors_r": e1[:, 1].tolist(),
            "depths": depths,
            "accepted": sum(r.accepted for r in results),
            "worse": worse_count(e0, e1),
            "build_s": build_s, "hierarchy_mb": hierarchy_mb,
            "working_set": float(np.median(wset)),
            "selections": float(np.mean(nsel)), "renders": float(np.median(ren)),
            "passes": float(np.median(passes)), "warm_up_s": warm, "s_per_query": float(np.mean(sec)),
            "before": [float(np.median(e0[:, 0])), float(np.median(e0[:, 1]))],
            "after": [float(np.median(e1[:, 0])), float(np.median(e1[:, 1]))],
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "stages": {key: v / len(results) for key, v in spent.items()}}


def stages(k: int) -> str:
    """One Markdown row: a render's time split by kernel stage on the room densified ``k`` times."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify, make_room_scene
    from hgsloc_plugin.kernels.launch import timed_launches
    from hgsloc_plugin.kernels.layout import Rec
    from hgsloc_plugin.refine.plan import make_plan

    room = make_room_scene()
    scene = densify(room, k) if k > 1 else room
    prior = query_poses(1, seed=1)[0]
    refiner = hp.HGSLocPlugin(scene)
    plan = make_plan(refiner.config, scene, QUERY_CAMERA, prior, hp.QueryPrior())
    r = refiner.renderer_for(plan)
    r = r.covering([prior]) if hasattr(r, "covering") else r
    cam, bg = plan.cam_final, (0.0, 0.0, 0.0)

    def ms(fn) -> float:
        fn()
        times = []
        for _ in range(15):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return 1000 * float(np.median(times))

    wset = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("default", working_set_min=0)).renderer_for(plan)
    select = ms(lambda: wset.full.working_set(wset.cameras, prior, wset.radius_shift, wset.radius_rotation_deg))
    r.render_full(cam, [prior], bg)  # warm-up
    split = []  # (render, projection, tile sort, blending and read-back) ms of each render, the stages from its
    for _ in range(15):  # kernels' launches
        with timed_launches() as launches:
            t0 = time.perf_counter()
            r.render_full(cam, [prior], bg)
            wall = time.perf_counter() - t0
        t = launches.by_kernel
        proj, blend = t.get("project", 0.0), t.get("blend_images", 0.0) + t.get("readback", 0.0)
        split.append((wall, proj, launches.seconds - proj - blend - t.get("ext_arr_to_ndarray", 0.0), blend))
    full, proj, sort, blend = (1000 * float(np.median(col)) for col in zip(*split))
    rec = r.pool.records  # the last render's projection records
    ntiles = rec.ntiles.to_numpy()[0, :r.n]
    seen = ntiles > 0
    # each visible Gaussian's alpha ellipse sigma <= LIM, area 2 pi LIM / sqrt(ca cc - cb^2) (unclipped): the
    # pixels the splat blend visits at most (it stops at saturated pixels)
    packed = rec.packed.to_numpy()[0, :r.n][seen].astype(np.float64)
    det = packed[:, Rec.CA] * packed[:, Rec.CC] - packed[:, Rec.CB] ** 2
    footprint = float(np.sum(2.0 * np.pi * np.maximum(packed[:, Rec.LIM], 0.0) / np.sqrt(np.maximum(det, 1e-30))))
    return (f"| {scene.num_gaussians:,} | {r.n:,} | {int(seen.sum()):,} | {int(ntiles.sum()):,} | "
            f"{footprint / (cam.width * cam.height):.0f} | {full:.1f} | {proj:.1f} | {sort:.1f} | "
            f"{blend:.1f} | {select:.1f} |")


def footprints(k: int, queries: int) -> list[str]:
    """Markdown rows: on the room densified ``k`` times, at each scoring size (longer side 100, 200, 320 px), the
    Gaussians in view of the query poses (centres in front, within the image and 20 px around it) and the share
    whose largest standard deviation projects to under 0.5 and 1 px: what a level-of-detail cut at that size could
    merge (means over the queries)."""
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify, make_room_scene

    room = make_room_scene()
    scene = densify(room, k) if k > 1 else room
    smax = scene.scales.max(axis=1).astype(np.float64)
    rows = []
    for side in (100, 200, 320):
        cam = QUERY_CAMERA.with_max_side(side) if side < max(QUERY_CAMERA.width, QUERY_CAMERA.height) else QUERY_CAMERA
        seen, half, one = [], [], []
        for T in query_poses(queries, seed=1):
            p = scene.means.astype(np.float64) @ T.R.T + T.tvec
            z = np.maximum(p[:, 2], 1e-6)
            u, v = cam.fx * p[:, 0] / z + cam.cx, cam.fy * p[:, 1] / z + cam.cy
            vis = (p[:, 2] > 0.05) & (u > -20) & (u < cam.width + 20) & (v > -20) & (v < cam.height + 20)
            px = smax[vis] * cam.fx / z[vis]
            seen.append(int(vis.sum()))
            half.append(float(np.mean(px < 0.5)))
            one.append(float(np.mean(px < 1.0)))
        rows.append(f"| {scene.num_gaussians:,} | {cam.width}x{cam.height} | {np.mean(seen):,.0f} | "
                    f"{100 * np.mean(half):.0f} % | {100 * np.mean(one):.0f} % |")
    return rows


def cut_sizes(k: int) -> list[str]:
    """Markdown rows: on the room split ``k`` times (``densify_split``), at the first query's true pose and each
    scoring size of the default route, the Gaussians the exact working set draws and those cuts of the map's
    hierarchy at 1, 2 and 4 px draw (``CutSelection``; the working-set region of the default plan)."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify_split, make_room_scene
    from hgsloc_plugin.refine.plan import make_plan
    from hgsloc_plugin.render.hierarchy import CutSelection

    scene = densify_split(make_room_scene(), k)
    pose = query_poses(1, seed=1)[0]
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("default", working_set_min=0))
    plan = make_plan(refiner.config, scene, QUERY_CAMERA, pose, hp.QueryPrior())
    ws = refiner.renderer_for(plan)
    renderer, hierarchy = refiner.renderer, refiner.hierarchy()  # the hierarchy as a query gets it (cached)
    region = (pose, ws.radius_shift, ws.radius_rotation_deg)
    rows = []
    cams = {(c.width, c.height): c for c in (plan.cam_coarse, plan.cam_polish, plan.cam_final)}
    for _, cam in sorted(cams.items()):
        drawn = [renderer.working_set([cam], *region).n]
        drawn += [CutSelection(renderer, hierarchy, px)([cam], *region).n for px in (1.0, 2.0, 4.0)]
        rows.append(f"| {scene.num_gaussians:,} | {cam.width}x{cam.height} | " + " | ".join(f"{n:,}" for n in drawn)
                    + " |")
    return rows


def parents_psnr(k: int, queries: int) -> str:
    """One Markdown row: the PSNR (dB) of the room split ``k`` times against the room, rendered at the query poses
    (320x240): how far the split map's image is from its parents' (min, median, max over the queries)."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify_split, make_room_scene
    from hgsloc_plugin.render.lod import psnr

    room = make_room_scene()
    split = densify_split(room, k)
    poses = query_poses(queries, seed=1)
    db = [psnr(a, b) for a, b in zip(hp.render(room, QUERY_CAMERA, poses), hp.render(split, QUERY_CAMERA, poses))]
    return f"| {split.num_gaussians:,} | {min(db):.1f} / {np.median(db):.1f} / {max(db):.1f} |"


def _against_exact(r: dict, exact: dict | None) -> str:
    """Median and largest change of the translation error against the exact path's, per query, in % of the
    query's depth ("-" without an exact row)."""
    if exact is None:
        return "-"
    d = 100 * (np.array(r["errors_t"]) - np.array(exact["errors_t"])) / np.array(r["depths"])
    return f"{np.median(np.abs(d)):.4f} (max {d[np.argmax(np.abs(d))]:+.4f})"


def _build(r: dict) -> str:
    return f"{r['build_s']:.1f} / {r['hierarchy_mb']:.0f}" if r["build_s"] else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", nargs="+", type=int, default=[1, 4, 10, 20])
    ap.add_argument("--queries", type=int, default=9,
                    help="queries per map (9: a median of 3 moved with the queries drawn, 2026-12-07)")
    ap.add_argument("--noise", default="3cm,1deg")
    ap.add_argument("--maps", choices=MAPS, default="split",
                    help="split: densified by splitting, queries rendered from the map (the truth a minimum); "
                         "jitter: jittered copies, queries rendered from the room (every prior kept); snow_sharp: "
                         "the good snow map split, its real photos (--queries of 6), priors 2 %% of depth / 1 deg, "
                         "errors in %% of depth")
    ap.add_argument("--out", default=None)
    ap.add_argument("--paths", nargs="+", default=list(DEFAULT_PATHS), choices=list(PATHS), metavar="PATH",
                    help=f"paths to compare, the first is the speed-up reference (any of {list(PATHS)})")
    ap.add_argument("--stages", action="store_true", help="only split one render's time by stage at each --k")
    ap.add_argument("--footprints", action="store_true",
                    help="only the share of the Gaussians in view under 0.5 / 1 px at each scoring size, per --k")
    ap.add_argument("--cuts", action="store_true",
                    help="only the Gaussians drawn at each scoring size, exact and cut at 1 / 2 / 4 px, per --k")
    ap.add_argument("--child", nargs=2, metavar=("K", "PATH"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.footprints:
        print("| Gaussians | scoring size | in view | sigma < 0.5 px | < 1 px |\n|---|---|---|---|---|", flush=True)
        for k in a.k:
            print("\n".join(footprints(k, a.queries)), flush=True)
        return
    if a.cuts:
        print("| Gaussians | scoring size | exact working set | cut 1 px | 2 px | 4 px |\n|---|---|---|---|---|---|",
              flush=True)
        for k in a.k:
            print("\n".join(cut_sizes(k)), flush=True)
        print("\n| Gaussians | PSNR against the parents (dB: min / median / max over the queries) |\n|---|---|",
              flush=True)
        for k in a.k:
            print(parents_psnr(k, a.queries), flush=True)
        return
    if a.stages:
        print("| Gaussians | rendered (working set) | visible | tile-list entries | footprint pixels per pixel | "
              "render (ms) | projection | tile sort | blending (and read-back) | selection (ms) |\n"
              "|---|---|---|---|---|---|---|---|---|---|", flush=True)
        for k in a.k:
            print(stages(k), flush=True)
        return
    if a.child:
        print(json.dumps(child(int(a.child[0]), a.child[1], a.queries, a.noise, a.maps)))
        return
    lines = [f"Demo room densified ({a.maps}), {a.queries} queries, noise {a.noise}; 2 threads unless the machine has "
             "more.\n",
             "| Gaussians | path | ms / render | working set | selections | renders / query | derivative passes | "
             "s / query | speed-up | before t / R | after t / R | accepted | worse | vs exact (% of depth) | "
             "hierarchy build (s / MB) | peak RSS (MB) | warm-up (s) |", "|" + "---|" * 17]
    print("\n".join(lines), flush=True)
    t_all = time.time()
    split = []
    for k in a.k:
        rows = {}
        for path in a.paths:
            out = subprocess.run([*module_command(__file__), "--child", str(k), path, "--queries",
                                  str(a.queries), "--noise", a.noise, "--maps", a.maps], capture_output=True,
                                 text=True, cwd=ROOT)
            if out.returncode != 0:
                print(out.stderr[-2000:], file=sys.stderr)
                raise SystemExit(f"child k={k} {path} failed")
            rows[path] = json.loads(out.stdout.strip().splitlines()[-1])
        for path, r in rows.items():
            sp = rows[a.paths[0]]["s_per_query"] / r["s_per_query"]
            line = (f"| {r['gaussians']:,} | {path} | {r['ms_per_render']:.1f} | {r['working_set']:,.0f} | "
                    f"{r['selections']:.1f} | {r['renders']:.0f} | {r['passes']:.0f} | "
                    f"{r['s_per_query']:.2f} | {sp:.2f}x | {r['before'][0]:.2f} / "
                    f"{r['before'][1]:.2f} | {r['after'][0]:.2f} / {r['after'][1]:.3f} | "
                    f"{r['accepted']} / {len(r['depths'])} | {r['worse']} | "
                    f"{_against_exact(r, rows.get(EXACT.get(path)))} | "
                    f"{_build(r)} | {r['peak_rss_mb']:.0f} | {r['warm_up_s']:.1f} |")
            lines.append(line)
            print(line, flush=True)
            rest = r["s_per_query"] - sum(r["stages"].values())
            parts = sorted(r["stages"].items(), key=lambda kv: -kv[1]) + [("rest", rest)]
            split.append(f"| {r['gaussians']:,} | {path} | " + ", ".join(f"{n} {v:.2f}" for n, v in parts) + " |")
    lines += ["\nWhere a query's seconds go (per query, by stage and scoring size):\n",
              "| Gaussians | path | stages (s / query) |", "|---|---|---|", *split]
    print("\n".join(lines[-len(split) - 3:]), flush=True)
    lines.append(f"\nTotal {time.time() - t_all:.0f} s; Taichi backend: {rows[a.paths[0]]['arch']}.")
    print(lines[-1])
    if a.out:
        from benchmarks.harness import regenerate_line, write_keeping_notes

        head = ["# Map scale (`benchmarks/map_scale.py`)", "", regenerate_line(__file__), ""]
        write_keeping_notes(Path(a.out), head + lines, section="## ")  # its other runs' sections kept


if __name__ == "__main__":
    main()
