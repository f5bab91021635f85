"""Refine a localizer's pose file end to end: read, refine every query, write the same dialect + a JSON report.

This is the code path of ``hgsloc refine``, the HLoc step and ``hgsloc demo``. Outputs are written atomically
and regularly, so an interrupted run leaves a valid file; a rerun resumes (queries refined or rejected in the
report are skipped, failed ones are retried, no line is duplicated).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path

from .adapters.confidence import hloc_trust, inlier_trust, record_inliers
from .adapters.dialects import read_poses, write_poses
from .adapters.names import resolve_image
from .adapters.posefile import PoseFile
from .batch import Query, run_batch
from .camera import Camera
from .fileio import write_json
from .image import load_image
from .plugin import HGSLocPlugin
from .pose import Pose
from .prior import QueryPrior
from .refine import RefineConfig, RefineResult
from .scene import GaussianScene

logger = logging.getLogger("hgsloc_plugin")


def report_path(output: Path) -> Path:
    return Path(str(output) + ".json")


class _Run:
    """The state of one pose-file run: refined poses, per-query report entries, and how to save them."""

    def __init__(self, pf: PoseFile, output: Path, report: dict, refined: dict[str, Pose]):
        self.pf, self.output, self.report, self.refined = pf, output, report, refined
        self.this_run: set[str] = set()  # the queries recorded by this run (not an earlier, resumed one)

    def record(self, name: str, res: RefineResult | None = None, error: str | None = None) -> None:
        if res is not None and res.error:
            error = res.error
        if error is not None:
            entry = {"accepted": False, "error": error, "renders": 0,
                     "seconds": round(res.seconds, 4) if res is not None else 0.0}
        else:
            entry = res.to_dict()
            entry.pop("name", None)
            if res.accepted:
                self.refined[name] = res.pose
        self.report["queries"][name] = entry
        self.this_run.add(name)

    def save(self) -> None:
        write_poses(self.output, self.refined, like=self.pf)
        queries = self.report["queries"]
        self.report["totals"] = totals(queries.values())
        self.report["this_run"] = totals(v for k, v in queries.items() if k in self.this_run)
        write_json(report_path(self.output), self.report)


def totals(entries) -> dict:
    """Counts and medians over report entries: queries, accepted, fused, failed, rejected per reason, median
    confidence and sigmas of the accepted ones, renders, queries that searched, seconds."""
    q = list(entries)
    return {
        "queries": len(q), "accepted": sum(1 for v in q if v.get("accepted")),
        "fused": sum(1 for v in q if v.get("accepted") and v.get("fused")),
        "failed": sum(1 for v in q if v.get("error")), "rejected": rejected_counts(q),
        "median_confidence": median_confidence(q),
        "median_sigma_t": median_accepted(q, "sigma_t"), "median_sigma_r_deg": median_accepted(q, "sigma_r_deg"),
        "renders": sum(v.get("renders", 0) for v in q),
        "searched": sum(1 for v in q if v.get("route") in ("search", "wide search")),
        "seconds": round(sum(v.get("seconds", 0.0) for v in q), 3),
    }


def rejected_counts(entries) -> dict[str, int]:
    """Queries whose search pose was not returned, per reason (report entries)."""
    out: dict[str, int] = {}
    for v in entries:
        if v.get("rejected") and not v.get("error"):
            out[v["rejected"]] = out.get(v["rejected"], 0) + 1
    return dict(sorted(out.items()))


def median_confidence(entries) -> float | None:
    """Median confidence of the accepted queries (None if none was accepted)."""
    return median_accepted(entries, "confidence")


def median_accepted(entries, key: str) -> float | None:
    """Median of a finite field (``confidence``, ``sigma_t``, ...) over the accepted queries (None if none)."""
    c = sorted(v[key] for v in entries if v.get("accepted") and isinstance(v.get(key), (int, float))
               and math.isfinite(v[key]))
    return round(c[len(c) // 2], 6) if c else None


def _resume(pf: PoseFile, output: Path) -> tuple[dict[str, dict], dict[str, Pose], int]:
    """Report entries and refined poses of an earlier run of the same output (empty if none), and how many of its
    queries failed (they are retried)."""
    done: dict[str, dict] = {}
    refined: dict[str, Pose] = {}
    failed = 0
    rep_path = report_path(output)
    if output.exists() and rep_path.exists():
        old = json.loads(rep_path.read_text())
        prev = read_poses(output, pf.dialect)
        for name, q in old.get("queries", {}).items():
            if q.get("error"):  # failed queries are retried (the user may have fixed the input)
                continue
            if name in pf and name in prev:
                done[name] = q
                if prev[name] is not None:
                    refined[name] = prev[name]
        failed = sum(1 for q in old.get("queries", {}).values() if q.get("error"))
    return done, refined, failed


def _queries(run: _Run, names: list[str], images: Path, intrinsics: Callable[[str, int, int], Camera],
             region_of: Callable[[str], QueryPrior]) -> list[Query]:
    """Queries to refine: name, image path, intrinsics, prior and its own settings (``region_of``). Unusable ones
    are recorded as failed at once."""
    from PIL import Image

    out = []
    for name in names:
        coarse = run.pf[name]
        if coarse is None:
            run.record(name, error="failed prior (non-finite or zero pose)")
            continue
        try:
            img_path = resolve_image(name, images)
            with Image.open(img_path) as im:
                w, h = im.size
            out.append(Query(len(out), name, str(img_path), intrinsics(name, w, h), coarse, region_of(name)))
        except Exception as exc:  # one bad query never stops the run
            logger.warning("%s: %s", name, exc)
            run.record(name, error=f"{type(exc).__name__}: {exc}")
    return out


def _region_of(pf: PoseFile, cfg: RefineConfig, hloc_counts: dict[str, float] | None = None
               ) -> Callable[[str], QueryPrior]:
    """name -> the query's settings from its inlier count: the record's own (ACE, GLACE:
    ``adapters/confidence.inlier_trust``) or hloc's log's (``hloc_counts``: ``confidence.hloc_trust``); none
    without one; less those the refiner's config fixes (``QueryPrior.deferring_to``)."""

    def region_of(name: str) -> QueryPrior:
        if hloc_counts is not None:
            n = hloc_counts.get(name)
            return QueryPrior() if n is None else hloc_trust(n).deferring_to(cfg)
        inliers = record_inliers(pf.dialect, pf.record(name).tokens)
        return QueryPrior() if inliers is None else inlier_trust(inliers).deferring_to(cfg)

    return region_of


def _hloc_counts(pf: PoseFile, expect_log: bool) -> dict[str, float] | None:
    """hloc's PnP inlier counts for an hloc-dialect file from the log beside it (``adapters.hloc.read_inlier_log``);
    None, with one warning, when it is unreadable, or missing where ``expect_log`` (the hloc step) says it should be
    there."""
    from .adapters.hloc import inlier_log_path, read_inlier_log

    if pf.dialect != "hloc" or pf.path is None:
        return None
    try:
        counts = read_inlier_log(pf.path)
    except ValueError as exc:
        logger.warning("%s; refining without hloc's inlier counts", exc)
        return None
    if counts is None:
        if expect_log:
            logger.warning("%s not found: refining without hloc's inlier counts", inlier_log_path(pf.path))
        return None
    logger.info("read hloc's PnP inlier counts of %d queries from %s", len(counts), inlier_log_path(pf.path))
    return counts


def refine_pose_file(scene: GaussianScene | str | Path | HGSLocPlugin, poses: Path | PoseFile, images: Path,
                     intrinsics: Callable[[str, int, int], Camera], output: Path, *,
                     config: RefineConfig | None = None, limit: int | None = None, dialect: str = "auto",
                     gt_variant: str | None = None, figures: Path | None = None, progress: bool = True,
                     save_every: int = 10, settings: dict | None = None, workers: int = 0,
                     ray_address: str | None = None, inlier_region: bool = True,
                     batch_size: int | None = None, expect_hloc_log: bool = False) -> dict:
    """Refine the poses in ``poses`` and write ``output`` (same dialect) and ``output + '.json'``.

    Args:
        scene: the 3DGS map (object, .ply path, or a ready HGSLocPlugin), in the frame of the poses.
        poses: the localizer's pose file (a path, or one read already). images: folder holding the query images
            (any name style).
        intrinsics: (name, width, height) -> Camera. output: refined pose file (must differ from ``poses``).
        limit: refine only the first N queries (the rest keep their input pose).
        gt_variant: recorded in the report ("sfm", "dslam", ...).
        figures: folder for comparison figures of each refined query.
        workers / ray_address: refine on N local Ray worker processes, or on an existing Ray cluster
            (see :mod:`hgsloc_plugin.batch`); by default everything runs in this process.
        batch_size: queries advanced together (``batch.run_batch``; None: the backend's default). Same poses.
        inlier_region: where each pose's inlier count is known, set each query's trust region and expected prior
            error from it (``adapters/confidence.py``): the RANSAC count in ACE and GLACE files, the PnP count in
            hloc's log beside an hloc results file (``<results>_logs.pkl``); values set in ``config`` win.
        expect_hloc_log: warn (once) when an hloc results file has no log beside it (the hloc step).

    Returns:
        The report dict (also written as JSON).
    """
    pf = poses if isinstance(poses, PoseFile) else None
    poses, images, output = Path(pf.path if pf is not None else poses), Path(images), Path(output)
    if limit is not None and limit < 0:  # a negative slice would refine all but the last -limit queries
        raise ValueError(f"limit must be >= 0 (the first N queries), got {limit}")
    if output.exists() and output.resolve() == poses.resolve():
        raise ValueError(f"{output}: refusing to overwrite the input pose file")
    pf = pf if pf is not None else read_poses(poses, dialect)
    refiner = scene if isinstance(scene, HGSLocPlugin) else HGSLocPlugin(scene, config)
    done, refined, failed_before = _resume(pf, output)
    names = list(pf)[: limit if limit is not None else None]
    report = {
        "input": str(poses), "output": str(output), "dialect": pf.dialect,
        "scene": str(getattr(refiner.scene, "source", None)), "gt_variant": gt_variant,
        "config": refiner.config.to_dict(), "settings": settings or {}, "queries": done,
        "resumed": {"done": sum(1 for n in names if n in done), "of": len(names), "retried": failed_before}
        if done or failed_before else None,
    }
    if report["resumed"]:
        r = report["resumed"]
        logger.warning("resuming: %d of %d queries already done in %s, retrying %d failed", r["done"], r["of"],
                       output, r["retried"])
    run = _Run(pf, output, report, refined)
    queries = _queries(run, [n for n in names if n not in done], images, intrinsics,
                       _region_of(pf, refiner.config, _hloc_counts(pf, expect_hloc_log))
                       if inlier_region else lambda _: QueryPrior())
    count = 0

    def on_result(q: Query, res: RefineResult) -> None:
        nonlocal count
        run.record(q.name, res)
        if figures is not None and res.accepted:
            from .viz import comparison_figure

            comparison_figure(refiner.scene, q.camera, load_image(q.image), q.coarse_pose, res.pose,
                              Path(figures) / (q.name.replace("/", "_") + ".png"),
                              background=refiner.config.background)
        count += 1
        if save_every and count % save_every == 0:
            run.save()

    try:
        run_batch(refiner, queries, workers=workers, ray_address=ray_address, progress=progress,
                  on_result=on_result, batch_size=batch_size)
    finally:
        run.save()
    return report
