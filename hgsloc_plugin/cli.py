"""The ``hgsloc`` command line: check, refine, evaluate, render, demo. User errors end in one line, exit code 2."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .refine.config import METRICS
from .units import count_arg, parse_angle, parse_length, positive_count_arg, prior_error_overrides

logger = logging.getLogger("hgsloc_plugin")


def _intrinsics(args):
    from .adapters import intrinsics as intr

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
    from .scene import resolve_scene

    return bool(args.white_background or resolve_scene(args.scene)[1])


def cmd_refine(args) -> int:
    from .pipeline import refine_pose_file
    from .refine import RefineConfig

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
        overrides["polish"] = False
    config = RefineConfig.preset(args.config, **overrides)
    if Path(args.out).resolve() == Path(args.poses).resolve():
        raise ValueError(f"{args.out}: refusing to overwrite the input pose file")
    scene, pf = inputs = _inputs(args)
    if not args.skip_check:  # refining poses in another frame or convention would return nonsense
        rep = _check(args, 4, inputs=inputs)
        if not rep.ok:
            raise ValueError(f"check failed: {rep.message()} (run 'hgsloc check' for details; --skip-check "
                             "refines anyway)")
    rep = refine_pose_file(scene, pf, Path(args.images), _intrinsics(args), Path(args.out),
                           config=config, limit=args.limit, gt_variant=args.gt_variant,
                           figures=Path(args.figures) if args.figures else None, progress=not args.quiet,
                           workers=args.workers, ray_address=args.ray_address,
                           inlier_region=not args.no_inlier_region)
    print(summary_line(rep["totals"], args.out))
    return 0


def summary_line(t: dict, out) -> str:
    """One line: refined (fused with the prior), kept (per reason), failed, median confidence, effort (renders,
    queries that needed the lattice search, seconds)."""
    kept = sum(t.get("rejected", {}).values())
    why = ", ".join(f"{k} {v}" for k, v in t.get("rejected", {}).items())
    conf, st, sr = t.get("median_confidence"), t.get("median_sigma_t"), t.get("median_sigma_r_deg")
    sig = f", median sigma {st:.3g} / {sr:.3g} deg" if st is not None and sr is not None else ""
    fused = f" ({t['fused']} fused with the prior's expected error)" if t.get("fused") else ""
    return (f"refined {t['accepted']} / {t['queries']} queries{fused}, kept the prior for {kept}"
            + (f" ({why})" if why else "") + f", {t['failed']} failed; median confidence "
            + (f"{conf:.2f}" if conf is not None else "-") + sig
            + f"; {t['renders']} renders, {t.get('searched', 0)} searched, {t['seconds']:.1f} s -> {out}")


def _inputs(args):
    """The command's scene and pose file, each read once: (GaussianScene, PoseFile)."""
    from .adapters import read_poses
    from .scene import GaussianScene

    return GaussianScene.from_ply(args.scene), read_poses(args.poses)


def _check(args, sample: int, figures=None, inputs=None):
    from .adapters.names import resolve_image
    from .check import check_poses

    scene, pf = inputs or _inputs(args)
    images = Path(args.images)
    return check_poses(scene, {n: pf[n] for n in pf}, lambda n: resolve_image(n, images), _intrinsics(args),
                       sample=sample, background=(1.0, 1.0, 1.0) if _white(args) else (0.0, 0.0, 0.0),
                       figures=figures)


def cmd_check(args) -> int:
    from .fileio import dumps_json

    rep = _check(args, args.sample, Path(args.figures) if args.figures else None)
    if args.json:
        print(dumps_json(rep.to_dict()))
    else:
        for k, n in enumerate(rep.names):
            alt = min((h for h in rep.costs if h != "as given"), key=lambda h: rep.costs[h][k])
            moved = f", aligned {rep.aligned['as given'][k]:.3f}" if "as given" in rep.aligned else ""
            print(f"{n}: cs cost {rep.costs['as given'][k]:.3f}{moved} (best other reading '{alt}' "
                  f"{rep.costs[alt][k]:.3f}), PSNR {rep.psnr[k]:.1f} dB, SSIM {rep.ssim[k]:.3f}")
        print(f"{rep.verdict}: {rep.message()}")
    return 0 if rep.ok else 1


def cmd_evaluate(args) -> int:
    from .adapters import read_poses
    from .evaluate import evaluate, mean_over_scenes, unmatched
    from .fileio import dumps_json

    if len(args.poses) != len(args.gt):
        raise ValueError("give one --gt per --poses (one pair per scene)")
    results = []
    for p, g in zip(args.poses, args.gt):
        est, gt = read_poses(p), read_poses(g)
        missing, extra = unmatched(est, gt)
        if len(missing) == len(gt):  # wrong pair of files, or a name style the matcher misses
            raise ValueError(f"{p}: none of its {len(est)} estimates names an image of {g} (e.g. "
                             f"{next(iter(est))!r} vs {next(iter(gt))!r}): not the ground truth of these poses?")
        if missing:
            logger.warning("%s: %d of the %d images of %s have no estimate (counted as failed), e.g. %r", p,
                           len(missing), len(gt), g, missing[0])
        if extra:
            logger.warning("%s: %d estimates name no image of %s (not counted), e.g. %r", p, len(extra), g, extra[0])
        r = evaluate(est, gt)
        r.pop("errors")
        r["poses"], r["gt"] = p, g
        results.append(r)
    if args.json:
        out = results[0] if len(results) == 1 else {"scenes": results, "mean": mean_over_scenes(results)}
        print(dumps_json(out))
        return 0
    for r in results:
        rc = r["recall"]
        print(f"{r['poses']}: n={r['n']} missing={r['missing']} median {r['median_translation_cm']:.2f} cm / "
              f"{r['median_rotation_deg']:.3f} deg, recall 5cm5deg {100 * rc['5cm5deg']:.1f}% "
              f"2cm2deg {100 * rc['2cm2deg']:.1f}% 1cm1deg {100 * rc['1cm1deg']:.1f}%")
    if len(results) > 1:
        m = mean_over_scenes(results)
        rc = m["recall"]
        print(f"mean over {m['scenes']} scenes: {m['median_translation_cm']:.2f} cm / {m['median_rotation_deg']:.3f} "
              f"deg, {100 * rc['5cm5deg']:.1f} / {100 * rc['2cm2deg']:.1f} / {100 * rc['1cm1deg']:.1f} %")
    return 0


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.replace(",", " ").split()]
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from exc
    if len(v) != n:
        raise ValueError(f"{what}: expected {n} numbers, got {len(v)}")
    return v


def cmd_render(args) -> int:
    from . import Camera, GaussianScene, Pose, render
    from .viz import save_png

    p = _floats(args.pose, 7, "--pose 'qw qx qy qz tx ty tz'")
    c = _floats(args.camera, 6, "--camera 'W H fx fy cx cy'")
    cam = Camera(int(c[0]), int(c[1]), *c[2:])
    img = render(GaussianScene.from_ply(args.scene), cam, Pose(p[:4], p[4:]),
                 background=(1.0, 1.0, 1.0) if _white(args) else (0.0, 0.0, 0.0))
    save_png(img, args.out)
    print(f"wrote {args.out} ({cam.width}x{cam.height})")
    return 0


def cmd_demo(args) -> int:
    from .demo.run import DEFAULT_NOISE, format_table, run_demo

    noise = args.noise or list(DEFAULT_NOISE)
    summary = run_demo(Path(args.out), queries=args.queries, noise=noise, preset=args.config,
                       progress=not args.quiet)
    print(format_table(summary))
    print(f"outputs in {args.out}: refined pose files (+ .json reports), figures/")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hgsloc", description="Heuristic 3DGS camera-pose refinement.")
    ap.add_argument("--arch", default=None, choices=["auto", "cpu", "cuda"], help="Taichi backend")
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("refine", help="refine a localizer's pose file (ACE, Marepo, HLoc, pGT, generic)")
    r.add_argument("--scene", required=True, help="3DGS point_cloud.ply in the frame of the poses, or a trainer's "
                                                  "output folder (latest iteration, background from cfg_args)")
    r.add_argument("--poses", required=True, help="input pose file")
    r.add_argument("--images", required=True, help="folder with the query images")
    r.add_argument("--focal", type=float, help="one focal length, principal point at the centre")
    r.add_argument("--intrinsics", help="HLoc queries_with_intrinsics.txt or a trainer's cameras.json")
    r.add_argument("--colmap", help="COLMAP model folder")
    r.add_argument("--pgt-focal", help="pGT file whose 9th column is the focal")
    r.add_argument("--allow-distortion", action="store_true", help="images are undistorted: ignore k, p")
    r.add_argument("--out", required=True, help="refined pose file (same dialect as --poses)")
    r.add_argument("--config", default="default", help="preset: default (gradient first, the search when it is "
                                                       "refused), search (always search), fast, accurate, gradient, "
                                                       "paper")
    r.add_argument("--no-polish", action="store_true", help="skip the Levenberg-Marquardt polish after the search")
    r.add_argument("--metric", choices=list(METRICS), help="heuristic (default cs: local structure)")
    r.add_argument("--max-shift", help="trust region: camera shift from the prior, e.g. 0.25m or 25cm "
                                       "(scene units; default: 8 coarsest steps)")
    r.add_argument("--max-rotation", help="trust region: rotation from the prior, e.g. 5deg "
                                          "(default: 8 coarsest steps)")
    r.add_argument("--prior-error", help="the priors' typical (median) camera-centre error, e.g. 2cm (scene "
                                         "units): each refined pose is fused with its prior, weighted by the two "
                                         "uncertainties (default: unknown)")
    r.add_argument("--prior-rotation-error", help="the priors' typical rotation error, e.g. 1deg (see --prior-error)")
    r.add_argument("--no-inlier-region", action="store_true",
                   help="do not set each query's trust region and expected error from the inlier count of "
                        "ACE/GLACE pose files (default: a confident pose gets a tight region, and the refined "
                        "pose is fused with it by the count's expected error)")
    r.add_argument("--white-background", action="store_true", help="the map was trained on white")
    r.add_argument("--limit", type=count_arg, help="refine only the first N queries")
    r.add_argument("--gt-variant", help="recorded in the report (sfm, dslam, ...)")
    r.add_argument("--figures", help="write comparison figures here")
    r.add_argument("--workers", type=count_arg, default=0, help="refine on N local Ray worker processes")
    r.add_argument("--ray-address", help="run on an existing Ray cluster ('auto' or ray://host:port)")
    r.add_argument("--quiet", action="store_true")
    r.add_argument("--skip-check", action="store_true", help="do not check map/pose agreement first")
    r.set_defaults(func=cmd_refine)

    c = sub.add_parser("check", help="do the map and the poses agree? names a convention error if one fits")
    c.add_argument("--scene", required=True, help="3DGS .ply or a trainer's output folder")
    c.add_argument("--poses", required=True, help="pose file (any dialect) or a trainer's cameras.json")
    c.add_argument("--images", required=True, help="folder with the query images")
    c.add_argument("--focal", type=float)
    c.add_argument("--intrinsics", help="HLoc queries_with_intrinsics.txt or a trainer's cameras.json")
    c.add_argument("--colmap", help="COLMAP model folder")
    c.add_argument("--pgt-focal", help="pGT file whose 9th column is the focal")
    c.add_argument("--allow-distortion", action="store_true")
    c.add_argument("--white-background", action="store_true")
    c.add_argument("--sample", type=positive_count_arg, default=8, help="queries to render (evenly spaced)")
    c.add_argument("--figures", help="write query | rendering images here")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=cmd_check)

    e = sub.add_parser("evaluate", help="median errors and recalls against ground truth")
    e.add_argument("--poses", required=True, action="append", help="estimates (repeat per scene)")
    e.add_argument("--gt", required=True, action="append", help="ground truth (repeat per scene)")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_evaluate)

    d = sub.add_parser("render", help="render a scene at one pose")
    d.add_argument("--scene", required=True)
    d.add_argument("--pose", required=True, help='"qw qx qy qz tx ty tz" (world-to-camera)')
    d.add_argument("--camera", required=True, help='"W H fx fy cx cy"')
    d.add_argument("--out", required=True)
    d.add_argument("--white-background", action="store_true")
    d.set_defaults(func=cmd_render)

    m = sub.add_parser("demo", help="run the whole chain on the embedded procedural room")
    m.add_argument("--out", default="demo_out")
    m.add_argument("--queries", type=positive_count_arg, default=6)
    m.add_argument("--noise", action="append", help="protocol, e.g. '3cm,1deg' or 'q2,t2' (repeatable)")
    m.add_argument("--config", default="default")
    m.add_argument("--quiet", action="store_true")
    m.set_defaults(func=cmd_demo)
    return ap


RENDERING_COMMANDS = (cmd_refine, cmd_render, cmd_demo, cmd_check)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    try:
        if args.func in RENDERING_COMMANDS:  # only commands that render start Taichi
            from .backend import init

            init(args.arch)
        return args.func(args)
    except KeyboardInterrupt:
        print("hgsloc: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, KeyError, OSError, RuntimeError) as exc:
        # a KeyError's str() is the repr of its message; other messages may end in a quoted value: keep it
        msg = (str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)) or type(exc).__name__
        print(f"hgsloc: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
