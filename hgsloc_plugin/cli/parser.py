"""The ``hgsloc`` command line: refine, check, evaluate, perturb, render, demo (``commands.py``). An error is one
line on stderr (and, with ``--json``, one JSON object on stdout); the exit codes are ``EXIT_CODES``."""

from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

from ..core.fileio import dumps_json
from ..core.units import count_arg, positive_count_arg
from ..refine.config import METRICS, PRESET_HELP
from .commands import cmd_check, cmd_demo, cmd_evaluate, cmd_perturb, cmd_refine, cmd_render

logger = logging.getLogger("hgsloc_plugin")

EXIT_CODES = """exit codes: 0 done; 1 check: the poses and the map disagree, or a sampled query could not be read;
2 bad input or usage (the message names the file, line or flag; nothing is written); 3 refine: some queries
failed (every other result is written; each failure is named on stderr and in the report); 130 interrupted
(rerun the same command to resume)"""


class UsageError(Exception):
    """A command line argparse refuses (exit code 2)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # raise instead of exiting, so that --json can still answer in JSON
        raise UsageError(f"{self.prog}: {message}", self.format_usage())


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="hgsloc", description="Heuristic 3DGS camera-pose refinement.", epilog=EXIT_CODES,
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arch", default=None, choices=["auto", "cpu", "cuda"], help="Taichi backend")
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("refine", help="refine a localizer's pose file (ACE, Marepo, HLoc, pGT, transforms.json, ...)",
                       epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("--scene", required=True, help="3DGS point_cloud.ply in the frame of the poses, or a trainer's "
                                                  "output folder (latest iteration, background from cfg_args)")
    r.add_argument("--poses", required=True, help="input pose file")
    r.add_argument("--images", required=True, help="folder with the query images")
    add_intrinsics_flags(r)
    r.add_argument("--out", required=True, help="refined pose file (same dialect as --poses)")
    r.add_argument("--config", default="default", help=PRESET_HELP)
    r.add_argument("--no-polish", action="store_true", help="skip the Levenberg-Marquardt polish: the lattice "
                   "search only (routes 'lattice')")
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
                        "ACE/GLACE pose files or of hloc's <results>_logs.pkl beside an hloc results file "
                        "(default: a confident pose gets a tight region, and the refined pose is fused with it "
                        "by the count's expected error)")
    r.add_argument("--lod-pixels", help="large maps (~500k Gaussians and more): render from the map's level-of-detail "
                   "hierarchy, merging cells of up to this many pixels (1 on real maps; built once, cached; "
                   "benchmarks/map_scale.md)")
    r.add_argument("--map-floor", help="the map's own error at a view, e.g. 0.6%%,0.2deg (camera centre in %% of the "
                   "median depth, rotation), as 'hgsloc check --measure-floor' measures it on views with known poses: "
                   "in every refined pose's sigma and in its fusion with the prior (default 0.3%%,0.1deg); with a "
                   "third item, e.g. 0.6%%,0.2deg,0.12cs, poses whose cs cost ends above it are refused")
    r.add_argument("--white-background", action="store_true", help="the map was trained on white")
    r.add_argument("--limit", type=count_arg, help="refine only the first N queries")
    r.add_argument("--gt-variant", help="recorded in the report (sfm, dslam, ...)")
    r.add_argument("--figures", help="write comparison figures here")
    r.add_argument("--workers", type=count_arg, default=0, help="refine on N local Ray worker processes")
    r.add_argument("--batch-size", type=positive_count_arg,
                   help="queries refined together, their renders sharing launches; the same poses "
                        "(default: 4 on the CPU, 32 on CUDA)")
    r.add_argument("--ray-address", help="run on an existing Ray cluster ('auto' or ray://host:port)")
    r.add_argument("--quiet", action="store_true")
    r.add_argument("--restart", action="store_true",
                   help="discard an earlier run's results in --out and start over (by default a rerun resumes: "
                        "results of unchanged queries are kept; a run of another map or settings is refused)")
    r.add_argument("--skip-check", action="store_true", help="do not check map/pose agreement first")
    r.add_argument("--json", action="store_true", help="print the totals as one JSON object (also on error)")
    r.set_defaults(func=cmd_refine)

    c = sub.add_parser("check", help="do the map and the poses agree? names a convention error if one fits",
                       epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("--scene", required=True, help="3DGS .ply or a trainer's output folder")
    c.add_argument("--poses", required=True, help="pose file (any dialect) or a trainer's cameras.json")
    c.add_argument("--images", required=True, help="folder with the query images")
    add_intrinsics_flags(c)
    c.add_argument("--white-background", action="store_true")
    c.add_argument("--sample", type=positive_count_arg, default=8, help="queries to render (evenly spaced)")
    c.add_argument("--figures", help="write query | rendering images here")
    c.add_argument("--measure-floor", action="store_true",
                   help="when they agree, also refine each sampled query from its own pose and report how far the "
                        "map's minima lie from the poses (the map's floor, for 'hgsloc refine --map-floor'): give "
                        "views whose poses are exact, e.g. the map's training views, and --sample 20 or more")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=cmd_check)

    e = sub.add_parser("evaluate", help="median errors and recalls against ground truth")
    e.add_argument("--poses", required=True, action="append", help="estimates (repeat per scene)")
    e.add_argument("--gt", required=True, action="append", help="ground truth (repeat per scene)")
    e.add_argument("--scale", type=float, help="metres per scene unit, for a map of arbitrary scale (default: the "
                                                "scene units are metres)")
    e.add_argument("--missing-as-failure", action="store_true",
                   help="score ground-truth images without an estimate as failures (a benchmark's protocol over "
                        "its whole test set; by default the images both files hold are scored)")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_evaluate)

    d = sub.add_parser("render", help="render a scene at one pose")
    d.add_argument("--scene", required=True)
    d.add_argument("--pose", required=True, help='"qw qx qy qz tx ty tz" (world-to-camera)')
    d.add_argument("--camera", required=True, help='"W H fx fy cx cy"')
    d.add_argument("--out", required=True)
    d.add_argument("--white-background", action="store_true")
    d.set_defaults(func=cmd_render)

    n = sub.add_parser("perturb", help="noisy priors from poses (e.g. ground truth), written in the input's dialect")
    n.add_argument("--poses", required=True, help="pose file (any dialect, transforms.json included)")
    n.add_argument("--noise", required=True,
                   help="'2%%,1deg': each centre moved exactly 2 %% of its query's median depth (needs --scene, "
                        "--images and the intrinsics: any map's scale) and each rotation exactly 1 deg, random "
                        "directions; '2cm,1deg': 0.02 scene units (metres only on a metric map); or the HGSLoc "
                        "paper's 'q2,t1' (raw quaternion and translation components; metric: 7-Scenes, Cambridge)")
    n.add_argument("--seed", type=int, default=0, help="random seed (same seed, same output)")
    n.add_argument("--out", required=True, help="the perturbed pose file")
    n.add_argument("--scene", help="3DGS map, for --noise P%%,Rdeg")
    n.add_argument("--images", help="folder with the query images, for --noise P%%,Rdeg")
    add_intrinsics_flags(n, "for --noise P%%,Rdeg: ")
    n.set_defaults(func=cmd_perturb)

    m = sub.add_parser("demo", help="run the whole chain on the embedded procedural room")
    m.add_argument("--out", default="demo_out")
    m.add_argument("--queries", type=positive_count_arg, default=6)
    m.add_argument("--noise", action="append", help="protocol, e.g. '3cm,1deg' or 'q2,t2' (repeatable)")
    m.add_argument("--config", default="default", help=PRESET_HELP)
    m.add_argument("--quiet", action="store_true")
    m.set_defaults(func=cmd_demo)
    return ap


def add_intrinsics_flags(p: argparse.ArgumentParser, use: str = "") -> None:
    """The flags naming where the queries' intrinsics come from (the user gives one), for every command that
    needs them: refine, check, perturb; ``use`` starts each help text."""
    p.add_argument("--focal", type=float, help=use + "one focal length, principal point at the centre")
    p.add_argument("--intrinsics", help=use + "HLoc queries_with_intrinsics.txt, a NeRF transforms.json, a trainer's "
                                              "cameras.json or a camera JSON (width height fx fy cx cy)")
    p.add_argument("--colmap", help=use + "COLMAP model folder")
    p.add_argument("--pgt-focal", help=use + "pGT file whose 9th column is the focal")
    p.add_argument("--allow-distortion", action="store_true",
                   help=use + "the photos are already undistorted: drop the intrinsics' distortion coefficients (by "
                              "default each photo with distortion is undistorted to a pinhole camera first)")


RENDERING_COMMANDS = (cmd_refine, cmd_render, cmd_demo, cmd_check)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    as_json = "--json" in argv
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        print(exc.args[1], end="", file=sys.stderr)
        return _fail(exc.args[0], as_json, usage=True)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    try:
        if args.func in RENDERING_COMMANDS:  # only commands that render start Taichi
            from ..core.backend import init

            init(args.arch)
        return args.func(args)
    except KeyboardInterrupt:
        return _fail("interrupted; rerun the same command to resume", as_json, code=130)
    except (ValueError, FileNotFoundError, KeyError, OSError, RuntimeError) as exc:
        # a KeyError's str() is the repr of its message; other messages may end in a quoted value: keep it
        if isinstance(exc, KeyError) and exc.args:
            msg = str(exc.args[0])
        elif isinstance(exc, OSError) and exc.filename and exc.strerror:  # "x: No such file", not "[Errno 2] ..."
            msg = f"{exc.filename}: {exc.strerror}"
        else:
            msg = str(exc) or type(exc).__name__
        return _fail(msg, as_json)


_WHERE = re.compile(r"^(?P<file>[^\s:][^:]*?)(?::(?P<line>\d+))?: ")


def error_record(message: str) -> dict:
    """The JSON form of an error: ``{"error", "file", "line"}``, the file and line read off a message that starts
    with ``FILE:LINE:`` or ``FILE:`` (a path with a suffix or a folder), else null."""
    m = _WHERE.match(message)
    file = line = None
    if m and (m.group("line") or Path(m.group("file")).suffix or Path(m.group("file")).exists()):
        file, line = m.group("file"), int(m.group("line")) if m.group("line") else None
    return {"error": message, "file": file, "line": line}


def _fail(message: str, as_json: bool, code: int = 2, usage: bool = False) -> int:
    """Report an error: one line on stderr, and with ``--json`` one JSON object on stdout."""
    print(message if usage else f"hgsloc: error: {message}", file=sys.stderr)
    if as_json:
        print(dumps_json(error_record(message)))
    return code


if __name__ == "__main__":
    sys.exit(main())
