"""The ``hgsloc`` commands, one function each (``cmd_*(args) -> exit code``); ``parser.py`` parses the command line."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from ..core.fileio import dumps_json
from ..core.units import parse_angle, parse_length, parse_map_floor, parse_pixels, prior_error_overrides

logger = logging.getLogger("hgsloc_plugin")
EXIT_FAILED_QUERIES = 3


def _intrinsics(args):
    from ..adapters import intrinsics as intr

    given = [x for x in (args.focal, args.intrinsics, args.colmap, args.pgt_focal) if x is not None]
    if len(given) != 1:
        raise ValueError("give exactly one of --focal, --intrinsics, --colmap, --pgt-focal")
    if args.focal is not None:
        return intr.from_focal(args.focal)
    if args.intrinsics is not None:
        return intr.from_query_list(args.intrinsics, allow_distortion=args.allow_distortion)
    if args.colmap is not None:
        return intr.from_colmap(args.colmap, allow_distortion=args.allow_distortion)
    return intr.from_pgt(args.pgt_focal)


def _white(args) -> bool:
    """--white-background, or what the trainer recorded in the --scene folder's cfg_args."""
    from ..core.scene import resolve_scene

    return bool(args.white_background or resolve_scene(args.scene)[1])


def cmd_refine(args) -> int:
    from ..refine import RefineConfig
    from ..run.pipeline import refine_pose_file, resumable
    from ..run.plugin import HGSLocPlugin

    overrides = {}
    if args.metric:
        overrides["metric"] = args.metric
    if _white(args):
        overrides["background"] = (1.0, 1.0, 1.0)
    if args.max_shift is not None:
        overrides["max_shift"] = parse_length(args.max_shift, "--max-shift")
    if args.max_rotation is not None:
        overrides["max_rotation_deg"] = parse_angle(args.max_rotation, "--max-rotation")
    overrides.update(prior_error_overrides(args.prior_error, args.prior_rotation_error))
    if args.no_polish:
        overrides["routes"] = "lattice"
    if args.lod_pixels is not None:
        overrides["lod_pixels"] = parse_pixels(args.lod_pixels)
    if args.map_floor is not None:
        overrides.update(parse_map_floor(args.map_floor))
    config = RefineConfig.preset(args.config, **overrides)
    if Path(args.out).resolve() == Path(args.poses).resolve():
        raise ValueError(f"{args.out}: refusing to overwrite the input pose file")
    _require_folder(args.images)
    scene, pf = inputs = _inputs(args)
    intrinsics = _intrinsics(args)  # read once (a COLMAP model, a query list) for the check and the refinement
    refiner = HGSLocPlugin(scene, config)
    previous = resumable(refiner, pf, Path(args.out), args.restart)  # other inputs: refused before any work
    if not args.skip_check:  # refining poses in another frame or convention would return nonsense
        rep = _check(args, 4, inputs=inputs, intrinsics=intrinsics)
        if not rep.agrees:
            raise ValueError(f"check failed: {rep.message()} (run 'hgsloc check' for details; --skip-check "
                             "refines anyway)")
    rep = refine_pose_file(refiner, pf, Path(args.images), intrinsics, Path(args.out), previous=previous,
                           limit=args.limit, gt_variant=args.gt_variant,
                           figures=Path(args.figures) if args.figures else None, progress=not args.quiet,
                           workers=args.workers, ray_address=args.ray_address, batch_size=args.batch_size,
                           inlier_region=not args.no_inlier_region, restart=args.restart)
    failed = {n: q["error"] for n, q in rep["queries"].items() if q.get("error")}
    for name, why in failed.items():
        print(f"hgsloc: failed: {name}: {why}", file=sys.stderr)
    if args.json:
        print(dumps_json({"output": str(args.out), "report": str(args.out) + ".json", "complete": rep["complete"],
                          "totals": rep["totals"],
                          "this_run": rep["this_run"], "resumed": rep["resumed"], "failed": failed}))
    else:
        if rep["resumed"]:
            print("this run: " + summary_line(rep["this_run"], args.out))
            print("in all:   " + summary_line(rep["totals"], args.out))
        else:
            print(summary_line(rep["totals"], args.out))
    return EXIT_FAILED_QUERIES if failed else 0


def summary_line(t: dict, out) -> str:
    """One line: refined (fused with the prior), kept (per reason), failed, median confidence, effort (renders,
    queries that needed the lattice search, wall-clock seconds and their share per query)."""
    kept = sum(t.get("rejected", {}).values())
    why = ", ".join(f"{k} {v}" for k, v in t.get("rejected", {}).items())
    conf, st, sr = t.get("median_confidence"), t.get("median_sigma_t"), t.get("median_sigma_r_deg")
    sig = f", median sigma {st:.3g} / {sr:.3g} deg" if st is not None and sr is not None else ""
    fused = f" ({t['fused']} fused with the prior's expected error)" if t.get("fused") else ""
    per = f", {t['seconds_per_query']:.2f} s/query" if t.get("queries") else ""
    return (f"refined {t['accepted']} / {t['queries']} queries{fused}, kept the prior for {kept}"
            + (f" ({why})" if why else "") + f", {t['failed']} failed; median confidence "
            + (f"{conf:.2f}" if conf is not None else "-") + sig
            + f"; {t['renders']} renders, {t.get('searched', 0)} searched, {t['wall_seconds']:.1f} s wall{per} "
            f"-> {out}")


def _require_folder(path) -> None:
    """A FileNotFoundError naming ``path`` when it is not a folder (``--images``)."""
    if not Path(path).is_dir():
        raise FileNotFoundError(f"{path}: image folder not found (--images)")


def _inputs(args):
    """The command's scene and pose file, each read once: (GaussianScene, PoseFile)."""
    from ..adapters import read_poses
    from ..core.scene import GaussianScene

    return GaussianScene.from_ply(args.scene), read_poses(args.poses)


def _check(args, sample: int, figures=None, inputs=None, intrinsics=None):
    from ..adapters.names import resolve_image
    from .check import check_poses

    scene, pf = inputs or _inputs(args)
    images = Path(args.images)
    return check_poses(scene, {n: pf[n] for n in pf}, lambda n: resolve_image(n, images),
                       intrinsics or _intrinsics(args),
                       sample=sample, background=(1.0, 1.0, 1.0) if _white(args) else (0.0, 0.0, 0.0),
                       figures=figures)


def _measure_floor(args, names: list[str], inputs, intrinsics):
    """The map's floor (``evaluation.floor.MapFloor``) over the queries ``names``, each refined from its own pose
    with the default settings."""
    from ..adapters.names import resolve_image
    from ..core.image import load_image
    from ..evaluation.floor import map_floor
    from ..refine import RefineConfig
    from ..run.plugin import HGSLocPlugin

    scene, pf = inputs
    background = (1.0, 1.0, 1.0) if _white(args) else (0.0, 0.0, 0.0)
    refiner = HGSLocPlugin(scene, RefineConfig(background=background))
    views = []
    for n in names:
        img = load_image(resolve_image(n, Path(args.images)), name=n, background=background)
        views.append((img, intrinsics(n, img.shape[1], img.shape[0]), pf[n], n))
    return map_floor(refiner, views)


def cmd_check(args) -> int:
    _require_folder(args.images)
    inputs, intrinsics = _inputs(args), _intrinsics(args)
    rep = _check(args, args.sample, Path(args.figures) if args.figures else None, inputs=inputs,
                 intrinsics=intrinsics)
    floor = _measure_floor(args, rep.names, inputs, intrinsics) if args.measure_floor and rep.agrees else None
    if args.json:
        out = rep.to_dict()
        if floor is not None:
            out["map_floor"] = {"depth": floor.depth, "deg": floor.deg, "views": floor.n, "flag": floor.flag(),
                                "offsets": {n: list(map(float, o)) for n, o in zip(floor.names, floor.offsets)},
                                "cost_bound": floor.cost_bound,
                                "costs": {n: float(c) for n, c in zip(floor.names, floor.costs)}}
        print(dumps_json(out))
    else:
        for k, n in enumerate(rep.names):
            alt = min((h for h in rep.costs if h != "as given"), key=lambda h: rep.costs[h][k])
            moved = f", aligned {rep.aligned['as given'][k]:.3f}" if "as given" in rep.aligned else ""
            print(f"{n}: cs cost {rep.costs['as given'][k]:.3f}{moved} (best other reading '{alt}' "
                  f"{rep.costs[alt][k]:.3f}), PSNR {rep.psnr[k]:.1f} dB, SSIM {rep.ssim[k]:.3f}")
        print(f"{rep.verdict}: {rep.message()}")
        print(f"median depth {rep.median_depth:.4g} scene units at the sampled poses: 'hgsloc evaluate --scale "
              f"{rep.scale_for_2m:.3g}' gives errors in cm as if it were 2 m (a 7-Scenes room), comparable across "
              "maps (its cm-eq)")
        if floor is not None:
            worst = floor.offsets.max(axis=0)
            bound = ("" if floor.cost_bound is None else f"; cs cost at their minima {floor.costs.min():.3g}-"
                     f"{floor.costs.max():.3g}, refused above {floor.cost_bound:.3g}")
            print(f"map floor over {floor.n} views (their poses taken as exact): {100 * floor.depth:.3g} % of the "
                  f"depth / {floor.deg:.3g} deg (root mean square; largest {100 * worst[0]:.3g} % / {worst[1]:.3g} "
                  f"deg{bound}): refine with --map-floor {floor.flag()}")
        elif args.measure_floor:
            print("map floor not measured: the map and the poses do not agree")
    return 0 if rep.ok else 1


def cmd_evaluate(args) -> int:
    from ..adapters import read_poses
    from ..evaluation.evaluate import evaluate, mean_over_scenes, units_note, unmatched

    if len(args.poses) != len(args.gt):
        raise ValueError("give one --gt per --poses (one pair per scene)")
    results = []
    for p, g in zip(args.poses, args.gt):
        _require_complete(p)
        est, gt = read_poses(p), read_poses(g)
        missing, extra = unmatched(est, gt)
        if len(missing) == len(gt):  # wrong pair of files, or a name style the matcher misses
            raise ValueError(f"{p}: none of its {len(est)} estimates names an image of {g} (e.g. "
                             f"{next(iter(est))!r} vs {next(iter(gt))!r}): not the ground truth of these poses?")
        if extra:  # e.g. a transforms.json of every frame against the held-out frames' ground truth
            print(f"hgsloc: error: {len(extra)} of the {len(est)} estimates in {p} name no image of {g} (e.g. "
                  f"{extra[0]!r}): not scored", file=sys.stderr)
        if missing:
            how = "counted as failed" if args.missing_as_failure else "not scored; --missing-as-failure counts them"
            logger.warning("%s: %d of the %d images of %s have no estimate (%s), e.g. %r", p, len(missing), len(gt),
                           g, how, missing[0])
        r = evaluate(est, gt, scale_to_m=args.scale, missing_as_failure=args.missing_as_failure)
        r["without_ground_truth"] = len(extra)
        r.pop("errors")
        r["poses"], r["gt"] = p, g
        results.append(r)
    if args.json:
        out = results[0] if len(results) == 1 else {"scenes": results, "mean": mean_over_scenes(results),
                                                    "units": results[0]["units"]}
        print(dumps_json(out))
        return 0
    print(f"units: {units_note(args.scale)}")
    for r in results:
        rc = r["recall"]
        print(f"{r['poses']}: n={r['n']} (ground truth without estimate {r['missing']}, estimates without ground "
              f"truth {r['without_ground_truth']}) median {r['median_translation_cm']:.2f} cm / "
              f"{r['median_rotation_deg']:.3f} deg, recall 5cm5deg {100 * rc['5cm5deg']:.1f}% "
              f"2cm2deg {100 * rc['2cm2deg']:.1f}% 1cm1deg {100 * rc['1cm1deg']:.1f}%")
    if len(results) > 1:
        m = mean_over_scenes(results)
        rc = m["recall"]
        print(f"mean over {m['scenes']} scenes: {m['median_translation_cm']:.2f} cm / {m['median_rotation_deg']:.3f} "
              f"deg, {100 * rc['5cm5deg']:.1f} / {100 * rc['2cm2deg']:.1f} / {100 * rc['1cm1deg']:.1f} %")
    return 0


def _require_complete(path) -> None:
    """A ValueError when ``path``'s report (``refine``'s ``PATH.json``) says its run did not complete."""
    from ..run.pipeline import read_report, report_path

    rep = read_report(Path(path))
    if rep is not None and rep.get("complete") is False:
        done = (rep.get("totals") or {}).get("queries", 0)
        raise ValueError(f"{path}: the run that writes it has not completed ({report_path(Path(path))}: "
                         f"\"complete\": false, {done} queries done); rerun its refine command to finish it")


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.replace(",", " ").split()]
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from exc
    if len(v) != n:
        raise ValueError(f"{what}: expected {n} numbers, got {len(v)}")
    return v


def cmd_render(args) -> int:
    from .. import Camera, GaussianScene, Pose, render
    from ..evaluation.viz import save_png

    p = _floats(args.pose, 7, "--pose 'qw qx qy qz tx ty tz'")
    c = _floats(args.camera, 6, "--camera 'W H fx fy cx cy'")
    cam = Camera(int(c[0]), int(c[1]), *c[2:])
    img = render(GaussianScene.from_ply(args.scene), cam, Pose(p[:4], p[4:]),
                 background=(1.0, 1.0, 1.0) if _white(args) else (0.0, 0.0, 0.0))
    save_png(img, args.out)
    print(f"wrote {args.out} ({cam.width}x{cam.height})")
    return 0


def cmd_perturb(args) -> int:
    import numpy as np

    from ..adapters import read_poses, write_poses
    from ..evaluation.noise import apply_protocol, parse_protocol

    kind, a, b = parse_protocol(args.noise)  # a bad spec is an error before anything is read
    if Path(args.out).resolve() == Path(args.poses).resolve():
        raise ValueError(f"{args.out}: refusing to overwrite the input pose file")
    pf = read_poses(args.poses)
    depth_of = _depths(args, pf) if kind == "depth" else {}
    rng = np.random.default_rng(args.seed)
    poses = {n: apply_protocol(p, args.noise, rng, depth_of.get(n)) for n, p in pf.items() if p is not None}
    write_poses(args.out, poses, like=pf)
    if kind == "se3":
        what = f"each camera centre moved exactly {a:g} scene units and rotated exactly {b:g} deg, random directions"
    elif kind == "depth":
        d = float(np.median(list(depth_of.values())))
        what = (f"each camera centre moved exactly {100 * a:g} % of its median depth (median depth {d:.3g} scene "
                f"units: {a * d:.3g}) and rotated exactly {b:g} deg, random directions")
    else:
        what = f"the paper's q{int(a)},t{int(b)} noise on the raw components (metric: 10^-{int(b)} m per step)"
    kept = len(pf) - len(poses)
    print(f"wrote {args.out}: {len(poses)} poses ({what}; seed {args.seed})"
          + (f"; {kept} failed priors copied as they are" if kept else ""))
    return 0


def _depths(args, pf) -> dict:
    """name -> the median depth (scene units) of the map at each usable pose, for ``perturb --noise P%,Rdeg``."""
    from PIL import Image

    from ..adapters.names import resolve_image
    from ..core.scene import GaussianScene
    from ..refine.plan import median_depth

    sources = [args.focal, args.intrinsics, args.colmap, args.pgt_focal]
    if args.scene is None or args.images is None or all(x is None for x in sources):
        raise ValueError(f"--noise {args.noise}: a share of each query's median depth needs the map and the "
                         "cameras: give --scene, --images and one of --focal, --intrinsics, --colmap, --pgt-focal "
                         "(as for refine)")
    _require_folder(args.images)
    scene, intrinsics = GaussianScene.from_ply(args.scene), _intrinsics(args)
    out = {}
    for n, p in pf.items():
        if p is None:
            continue
        with Image.open(resolve_image(n, args.images)) as im:
            w, h = im.size
        out[n] = median_depth(scene, intrinsics(n, w, h), p)
    return out


def cmd_demo(args) -> int:
    from .demo.run import DEFAULT_NOISE, format_table, run_demo

    noise = args.noise or list(DEFAULT_NOISE)
    summary = run_demo(Path(args.out), queries=args.queries, noise=noise, preset=args.config,
                       progress=not args.quiet)
    print(format_table(summary))
    print(f"outputs in {args.out}: refined pose files (+ .json reports), figures/")
    return 0
