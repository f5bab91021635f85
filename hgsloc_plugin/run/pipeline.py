"""Refine a localizer's pose file end to end: read, refine every query, write the same dialect + a JSON report.

This is the code path of ``hgsloc refine``, the HLoc step and ``hgsloc demo``. While a run goes on only its report
is written (``OUT.json``, regularly, with ``"complete": false`` and each query's result); the pose file ``OUT`` is
written when every query has its result, then the report with ``"complete": true``. An interrupted run therefore
leaves no pose file to mistake for a result, and a rerun of the same command resumes: the report's fingerprint
(the map's content and the settings) must match, and each query's result is reused only when its inputs (prior
record, intrinsics, photo bytes, trust region) are the ones it was computed from; failed queries are retried.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..adapters.confidence import hloc_trust, inlier_trust, record_inliers
from ..adapters.dialects import read_poses, write_poses
from ..adapters.names import resolve_image
from ..adapters.posefile import PoseFile
from ..core.camera import Camera
from ..core.fileio import dumps_json, write_json
from ..core.image import distortion_notice, load_image, undistort
from ..core.pose import Pose
from ..core.prior import QueryPrior
from ..core.scene import GaussianScene
from ..refine import RefineConfig, RefineResult
from .batch import Query, run_batch
from .plugin import HGSLocPlugin

logger = logging.getLogger("hgsloc_plugin")


def report_path(output: Path) -> Path:
    return Path(str(output) + ".json")


def read_report(output: Path) -> dict | None:
    """The report beside a pose file ``output`` (None when there is none); a ValueError naming it when it is not
    readable JSON."""
    path = report_path(Path(output))
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable report ({exc})") from exc


class _Run:
    """The state of one pose-file run: refined poses, per-query report entries, and how to save them."""

    def __init__(self, pf: PoseFile, output: Path, report: dict, wall_before: float):
        self.pf, self.output, self.report = pf, output, report
        self.refined: dict[str, Pose] = {}
        self.digests: dict[str, str] = {}  # name -> the digest of the inputs its result is computed from
        self.this_run: set[str] = set()  # the queries recorded by this run (not an earlier, resumed one)
        self.t0, self.wall_before = time.perf_counter(), wall_before

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
        if name in self.digests:
            entry["input_digest"] = self.digests[name]
        self.report["queries"][name] = entry
        self.this_run.add(name)

    def reuse(self, name: str, entry: dict) -> None:
        """An earlier run's result of the same inputs, kept as it is."""
        self.report["queries"][name] = entry
        if entry.get("accepted"):
            self.refined[name] = Pose.from_stored(entry["qvec"], entry["tvec"])

    def save(self, complete: bool = False) -> None:
        """The report (``complete`` False: partial state for a resume), and with ``complete`` the pose file first."""
        wall = time.perf_counter() - self.t0
        queries = self.report["queries"]
        self.report["totals"] = totals(queries.values(), self.wall_before + wall)
        self.report["this_run"] = totals((v for k, v in queries.items() if k in self.this_run), wall)
        if complete:
            write_poses(self.output, self.refined, like=self.pf)
        self.report["complete"] = complete
        write_json(report_path(self.output), self.report)


def totals(entries, wall_seconds: float) -> dict:
    """Counts and medians over report entries: queries, accepted, fused, failed, rejected per reason, median
    confidence and sigmas of the accepted ones, renders, queries that searched; ``wall_seconds`` (the runs' wall
    clock), ``seconds_per_query`` (its share per query) and ``query_seconds`` (the sum of each query's own elapsed
    time, which overlap when queries are refined together in batches)."""
    q = list(entries)
    return {
        "queries": len(q), "accepted": sum(1 for v in q if v.get("accepted")),
        "fused": sum(1 for v in q if v.get("accepted") and v.get("fused")),
        "failed": sum(1 for v in q if v.get("error")), "rejected": rejected_counts(q),
        "median_confidence": median_confidence(q),
        "median_sigma_t": median_accepted(q, "sigma_t"), "median_sigma_r_deg": median_accepted(q, "sigma_r_deg"),
        "renders": sum(v.get("renders", 0) for v in q),
        "searched": sum(1 for v in q if v.get("route") in ("search", "wide search")),
        "wall_seconds": round(wall_seconds, 3),
        "seconds_per_query": round(wall_seconds / len(q), 4) if q else None,
        "query_seconds": round(sum(v.get("seconds", 0.0) for v in q), 3),
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


def _digest(value) -> str:
    return hashlib.sha256(dumps_json(value, indent=None).encode()).hexdigest()[:32]


def fingerprint(refiner: HGSLocPlugin, pf: PoseFile) -> dict[str, str]:
    """What every result of a run depends on: the map's content (``GaussianScene.digest``), the refinement and
    raster settings, the pose file's dialect. A resume must match it."""
    import dataclasses

    return {"scene": refiner.scene.digest()[:32], "config": _digest(refiner.config.to_dict()),
            "raster": _digest(dataclasses.asdict(refiner.raster)), "dialect": pf.dialect}


_FINGERPRINT_WORDS = {"scene": "the map's content (--scene)", "config": "the refinement settings (--config and "
                      "its flags)", "raster": "the renderer's settings", "dialect": "the pose file's format"}


@dataclass(frozen=True)
class Previous:
    """What a run resumes: its inputs' ``fingerprint``, the earlier run's ``entries`` (name -> report entry; empty
    when there is none or on a restart) and the earlier runs' ``wall_seconds``."""

    fingerprint: dict[str, str]
    entries: dict[str, dict]
    wall_seconds: float


def resumable(refiner: HGSLocPlugin, pf: PoseFile, output: Path, restart: bool = False,
              restart_flag: str = "--restart") -> Previous:
    """The earlier run in ``output`` that this one resumes (see :class:`Previous`; ``restart``: none); a report of
    other inputs is a ValueError naming what differs and ``restart_flag`` (nothing is touched). A command calls it
    to refuse before any other work and passes the result to ``refine_pose_file``."""
    output = Path(output)
    fp = fingerprint(refiner, pf)
    old = None if restart else read_report(output)
    if old is None:
        return Previous(fp, {}, 0.0)
    before = old.get("fingerprint")
    changed = [k for k in fp if not isinstance(before, dict) or before.get(k) != fp[k]]
    if changed:
        what = ("it has no fingerprint (an older hgsloc wrote it)" if not isinstance(before, dict)
                else "other " + ", ".join(_FINGERPRINT_WORDS[k] for k in changed))
        raise ValueError(f"{report_path(output)}: an earlier run into {output} used {what}; its results are not "
                         f"these inputs': rerun with {restart_flag} to start over, or give another output")
    return Previous(fp, dict(old.get("queries", {})), float((old.get("totals") or {}).get("wall_seconds") or 0.0))


def _prepare(pf: PoseFile, name: str, images: Path, intrinsics: Callable[[str, int, int], Camera],
             region_of: Callable[[str], QueryPrior]) -> tuple[Query | None, str | None, str | None]:
    """(query, the digest of its inputs, None), or (None, None, why it cannot be refined)."""
    from PIL import Image

    coarse = pf[name]
    if coarse is None:
        return None, None, "failed prior (non-finite or zero pose)"
    try:
        img_path = resolve_image(name, images)
        data = img_path.read_bytes()
        with Image.open(io.BytesIO(data)) as im:  # the bytes read once: the size and the digest
            w, h = im.size
        cam, prior = intrinsics(name, w, h), region_of(name)
    except Exception as exc:  # one bad query never stops the run
        msg = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
        return None, None, f"{type(exc).__name__}: {msg}"
    digest = _digest({"record": pf.record(name).tokens, "camera": repr(cam), "prior": prior.as_dict(),
                      "image": hashlib.sha256(data).hexdigest()})
    return Query(0, name, str(img_path), cam, coarse, prior), digest, None


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
    from ..adapters.hloc import inlier_log_path, read_inlier_log

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
                     batch_size: int | None = None, expect_hloc_log: bool = False, restart: bool = False,
                     flags: dict[str, str] | None = None, previous: Previous | None = None) -> dict:
    """Refine the poses in ``poses`` and write ``output`` (same dialect) and ``output + '.json'``.

    Args:
        scene: the 3DGS map (object, .ply path, or a ready HGSLocPlugin), in the frame of the poses.
        poses: the localizer's pose file (a path, or one read already). images: folder holding the query images
            (any name style).
        intrinsics: (name, width, height) -> Camera (with distortion: each photo is undistorted, said once).
        output: refined pose file (must differ from ``poses``), written when every query has its result.
        limit: refine only the first N queries (the rest keep their input pose).
        gt_variant: recorded in the report ("sfm", "dslam", ...).
        figures: folder for comparison figures of each refined query.
        workers / ray_address: refine on N local Ray worker processes, or on an existing Ray cluster
            (see :mod:`hgsloc_plugin.run.batch`); by default everything runs in this process.
        batch_size: queries advanced together (``batch.run_batch``; None: the backend's default). Same poses.
        inlier_region: where each pose's inlier count is known, set each query's trust region and expected prior
            error from it (``adapters/confidence.py``): the RANSAC count in ACE and GLACE files, the PnP count in
            hloc's log beside an hloc results file (``<results>_logs.pkl``); values set in ``config`` win.
        expect_hloc_log: warn (once) when an hloc results file has no log beside it (the hloc step).
        restart: discard an earlier run's results in ``output`` instead of resuming (a resume of other inputs is
            refused).
        flags: how the caller spells its options in messages: ``{"restart": "--restart", "allow_distortion":
            "--allow-distortion"}`` (``hgsloc refine``'s, the default).
        previous: what :func:`resumable` returned for this ``scene`` (a ready refiner), ``poses`` and ``output``
            when the caller checked it already (None: checked here).

    Returns:
        The report dict (also written as JSON; ``"complete"`` says whether the pose file was written).
    """
    flags = {"restart": "--restart", "allow_distortion": "--allow-distortion", **(flags or {})}
    pf = poses if isinstance(poses, PoseFile) else None
    poses, images, output = Path(pf.path if pf is not None else poses), Path(images), Path(output)
    if limit is not None and limit < 0:  # a negative slice would refine all but the last -limit queries
        raise ValueError(f"limit must be >= 0 (the first N queries), got {limit}")
    if output.exists() and output.resolve() == poses.resolve():
        raise ValueError(f"{output}: refusing to overwrite the input pose file")
    if not images.is_dir():
        raise FileNotFoundError(f"{images}: image folder not found")
    pf = pf if pf is not None else read_poses(poses, dialect)
    refiner = scene if isinstance(scene, HGSLocPlugin) else HGSLocPlugin(scene, config)
    if previous is None:
        previous = resumable(refiner, pf, output, restart, flags["restart"])
    fp, wall_before, previous = previous.fingerprint, previous.wall_seconds, previous.entries
    names = list(pf)[: limit if limit is not None else None]
    report = {
        "complete": False, "input": str(poses), "output": str(output), "dialect": pf.dialect,
        "scene": str(getattr(refiner.scene, "source", None)), "gt_variant": gt_variant, "fingerprint": fp,
        "config": refiner.config.to_dict(), "settings": settings or {}, "queries": {}, "resumed": None,
    }
    run = _Run(pf, output, report, wall_before)
    region_of = (_region_of(pf, refiner.config, _hloc_counts(pf, expect_hloc_log)) if inlier_region
                 else lambda _: QueryPrior())
    queries, reused, changed = [], 0, 0
    wanted = set(names)
    for name in [*names, *(n for n in previous if n in pf and n not in wanted)]:  # earlier results beyond the limit
        old = previous.get(name)
        query, digest, why = _prepare(pf, name, images, intrinsics, region_of)
        if old is not None and not old.get("error") and digest is not None and old.get("input_digest") == digest:
            run.reuse(name, old)
            reused += name in wanted
            continue
        if name not in wanted:
            continue
        changed += old is not None and not old.get("error")
        if why is not None:  # the command names each failure once, at the end (exit code 3)
            logger.info("%s: %s", name, why)
            run.record(name, error=why)
            continue
        if query.camera.distortion is not None:
            distortion_notice(query.camera, flags["allow_distortion"])
        run.digests[name] = digest
        query.index = len(queries)
        queries.append(query)
    failed_before = sum(1 for n in names if (previous.get(n) or {}).get("error"))
    if previous:
        report["resumed"] = {"done": reused, "of": len(names), "recomputed": changed, "retried": failed_before}
        logger.warning("resuming: %d of %d queries already done in %s%s, retrying %d failed", reused, len(names),
                       output, f", recomputing {changed} whose inputs changed" if changed else "", failed_before)
    if output.exists():  # an earlier result is superseded: none is on disk until this run completes
        output.unlink()
    run.save()
    count = 0

    def on_result(q: Query, res: RefineResult) -> None:
        nonlocal count
        run.record(q.name, res)
        if figures is not None and res.accepted:
            from ..evaluation.viz import comparison_figure

            img, cam = undistort(load_image(q.image, background=refiner.config.background), q.camera)
            comparison_figure(refiner.scene, cam, img, q.coarse_pose, res.pose,
                              Path(figures) / (Path(q.name.replace("/", "_")).stem + ".png"),
                              background=refiner.config.background)
        count += 1
        if save_every and count % save_every == 0:
            run.save()

    complete = False
    try:
        run_batch(refiner, queries, workers=workers, ray_address=ray_address, progress=progress,
                  on_result=on_result, batch_size=batch_size)
        complete = True
    finally:
        run.save(complete)
    return report
