"""The refinement step for hloc pipelines, in hloc's style (a module with ``main``).

Run it after ``localize_sfm.main(...)`` and before ``evaluate(...)`` in a pipeline such as
``hloc/pipelines/7Scenes/pipeline.py::run_scene``::

    from hgsloc_plugin import hloc_step
    results_refined = hloc_step.main(scene_ply, query_list, results, images, results.with_name("results_refined.txt"))

or from the shell: ``python -m hgsloc_plugin.hloc_step --scene S.ply --queries Q.txt --results R.txt
--image_dir DIR --output OUT.txt``.

hloc's results file carries no per-pose confidence, but ``localize_sfm`` writes each query's PnP inlier count to a
log beside it (``<results>_logs.pkl``): the step reads it and sets each query's trust region and expected error from
the count (``adapters/confidence.hloc_trust``), so each refined pose is fused with its prior (``refine/trust.py``),
which keeps a precise prior where the map's cost minimum drifts off the truth. Without the log (one warning), or with
``--no_inlier_region``, give the localizer's typical (median) error when known (``RefineConfig(prior_error=...,
prior_error_deg=...)``, or ``--prior_error 2cm --prior_rotation_error 1deg``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from .adapters.intrinsics import from_query_list
from .run.pipeline import refine_pose_file

logger = logging.getLogger("hgsloc_plugin")


def main(scene: Path, queries: Path, results: Path, image_dir: Path, output: Path, config=None,
         limit: int | None = None, gt_variant: str | None = None, allow_distortion: bool = False,
         batch_size: int | None = None, inlier_region: bool = True, restart: bool = False,
         flags: dict[str, str] | None = None) -> Path:
    """Refine hloc's ``results`` with the 3DGS ``scene``; intrinsics from ``queries`` (with intrinsics).

    Returns the path of the refined results (HLoc dialect), written when every query has its result, with a JSON
    report beside it (``pipeline.refine_pose_file``: a rerun resumes; ``restart`` starts over). ``results`` is read
    as hloc writes it (``name qw qx qy qz tx ty tz`` per line): any other line is an error naming it.
    ``batch_size``: queries refined together (``batch.run_batch``; None: the backend's default).
    ``inlier_region``: read hloc's PnP inlier counts from ``<results>_logs.pkl`` (one warning when missing).
    ``allow_distortion``: the photos are already undistorted (by default a camera with distortion has its photo
    undistorted first). ``flags``: how messages name the options (the command line passes its own).
    """
    logger.info("Refining %s with %s", results, scene)
    flags = flags or {"restart": "restart=True", "allow_distortion": "allow_distortion=True"}
    refine_pose_file(scene, Path(results), Path(image_dir),
                     from_query_list(queries, allow_distortion=allow_distortion), Path(output),
                     config=config, limit=limit, gt_variant=gt_variant, dialect="hloc", batch_size=batch_size,
                     inlier_region=inlier_region, expect_hloc_log=inlier_region, restart=restart, flags=flags)
    return Path(output)


def build_parser() -> argparse.ArgumentParser:
    """The step's command line (hloc's flag style)."""
    from .core.units import count_arg, positive_count_arg
    from .refine.config import PRESET_HELP

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--queries", type=Path, required=True, help="queries_with_intrinsics.txt")
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--image_dir", type=Path, required=True)
    ap.add_argument("--output", type=Path, required=True)
    ap.add_argument("--config", default="default", help=PRESET_HELP)
    ap.add_argument("--limit", type=count_arg)
    ap.add_argument("--allow_distortion", action="store_true",
                    help="the photos are already undistorted: drop the query list's distortion coefficients (by "
                         "default each photo with distortion is undistorted to a pinhole camera first)")
    ap.add_argument("--restart", action="store_true",
                    help="discard an earlier run's results in --output and start over (by default a rerun resumes)")
    ap.add_argument("--batch_size", type=positive_count_arg, help="queries refined together (default: 4 on the "
                                                                  "CPU, 32 on CUDA)")
    ap.add_argument("--no_inlier_region", action="store_true",
                    help="do not read hloc's PnP inlier counts from <results>_logs.pkl (each query's trust region "
                         "and expected error)")
    ap.add_argument("--prior_error", help="the localizer's typical (median) camera-centre error, e.g. 2cm: each "
                                          "refined pose is fused with its prior (default: unknown)")
    ap.add_argument("--prior_rotation_error", help="its typical rotation error, e.g. 1deg")
    ap.add_argument("--lod_pixels", help="large maps (~500k Gaussians and more): render from the map's level-of-detail "
                                         "hierarchy, merging cells of up to this many pixels (1 on real maps)")
    ap.add_argument("--map_floor", help="the map's own error at a view, e.g. 0.6%%,0.2deg, and optionally its cost "
                                        "bound (0.6%%,0.2deg,0.12cs), as 'hgsloc check --measure-floor' measures them "
                                        "on views with known poses (default 0.3%%,0.1deg, no bound)")
    return ap


def cli(argv=None) -> int:
    """The shell entry point; user errors end in one line on stderr and exit code 2; failed queries are named on
    stderr, exit code 3 (every other result is written); an interrupt exits 130 (rerun to resume)."""
    from .core.units import parse_map_floor, parse_pixels, prior_error_overrides
    from .refine import RefineConfig
    from .run.pipeline import read_report

    a = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    try:
        overrides = prior_error_overrides(a.prior_error, a.prior_rotation_error,
                                          ("--prior_error", "--prior_rotation_error"))
        if a.lod_pixels is not None:
            overrides["lod_pixels"] = parse_pixels(a.lod_pixels, "--lod_pixels")
        if a.map_floor is not None:
            overrides.update(parse_map_floor(a.map_floor, "--map_floor"))
        main(a.scene, a.queries, a.results, a.image_dir, a.output, RefineConfig.preset(a.config, **overrides),
             a.limit, allow_distortion=a.allow_distortion, batch_size=a.batch_size,
             inlier_region=not a.no_inlier_region, restart=a.restart,
             flags={"restart": "--restart", "allow_distortion": "--allow_distortion"})
    except KeyboardInterrupt:
        print("hloc step: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, KeyError, OSError) as exc:
        print(f"hloc step: error: {exc}", file=sys.stderr)
        return 2
    failed = {n: q["error"] for n, q in read_report(a.output)["queries"].items() if q.get("error")}
    for name, why in failed.items():
        print(f"hloc step: failed: {name}: {why}", file=sys.stderr)
    return 3 if failed else 0


if __name__ == "__main__":
    sys.exit(cli())
