"""Localization accuracy: camera-centre and rotation errors, medians and recalls (CONVENTIONS §7)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ..core.pose import Pose, rotation_angle_deg

THRESHOLDS = (("5cm5deg", 0.05, 5.0), ("2cm2deg", 0.02, 2.0), ("1cm1deg", 0.01, 1.0))


def pose_errors(est: Pose | None, gt: Pose) -> tuple[float, float]:
    """(centre distance in scene units, rotation error in degrees); a missing estimate is (inf, 180)."""
    if est is None:
        return math.inf, 180.0
    return float(np.linalg.norm(est.centre() - gt.centre())), rotation_angle_deg(gt.R, est.R)


def unmatched(estimates: Mapping[str, object], gt: Mapping[str, object]) -> tuple[list[str], list[str]]:
    """(ground-truth names with no estimate, estimate names with no ground truth), matched across name styles."""
    from ..adapters.names import canonical_name

    est_keys, gt_keys = {canonical_name(n): n for n in estimates}, {canonical_name(n): n for n in gt}
    return ([n for k, n in gt_keys.items() if k not in est_keys], [n for k, n in est_keys.items() if k not in gt_keys])


def units_note(scale_to_m: float | None) -> str:
    """What the evaluation's "cm" mean: metres per scene unit given, or the scene units taken as metres."""
    if scale_to_m is None:
        return ("cm = scene units / 100: the map is taken as metric (give --scale S, metres per scene unit, for an "
                "SfM map of arbitrary scale)")
    return f"cm with 1 scene unit = {scale_to_m:g} m"


def evaluate(estimates: Mapping[str, Pose | None], gt: Mapping[str, Pose], *, scale_to_m: float | None = None,
             missing_as_failure: bool = False) -> dict:
    """Errors of ``estimates`` against ``gt``; names are matched across styles (canonical keys).

    The images both hold are scored (a failed prior counts as a failure: e_t = inf, e_R = 180); ground-truth images
    without an estimate are counted in ``missing`` and, with ``missing_as_failure``, scored as failures too (a
    benchmark's protocol over its whole test set). ``scale_to_m``: metres per scene unit (None: the scene units are
    taken as metres, as in 7-Scenes and Cambridge).

    Returns:
        dict with n (images scored), missing, median_translation_cm, median_rotation_deg, recall {"5cm5deg",
        "2cm2deg", "1cm1deg"} as fractions, per-query errors ``errors`` {name: [t_cm, r_deg]}, and ``units``
        {"scale_to_m", "assumed_metric", "note"}.
    """
    if scale_to_m is not None and not (math.isfinite(scale_to_m) and scale_to_m > 0):
        raise ValueError(f"scale_to_m must be a positive number of metres per scene unit, got {scale_to_m}")
    units = {"scale_to_m": 1.0 if scale_to_m is None else float(scale_to_m), "assumed_metric": scale_to_m is None,
             "note": units_note(scale_to_m)}
    scale = units["scale_to_m"]
    from ..adapters.names import canonical_name

    est_by_key = {canonical_name(k): v for k, v in estimates.items()}
    et, er, per = [], [], {}
    missing = 0
    for name, g in gt.items():
        key = canonical_name(name)
        if key not in est_by_key:
            missing += 1
            if not missing_as_failure:
                continue
        t, r = pose_errors(est_by_key.get(key), g)
        t *= scale
        et.append(t)
        er.append(r)
        per[name] = [t * 100, r]
    et, er = np.array(et), np.array(er)
    n = len(et)
    recall = {k: float(np.mean((et < tt) & (er < rr))) if n else 0.0 for k, tt, rr in THRESHOLDS}
    return {
        "n": n,
        "missing": missing,
        "missing_as_failure": missing_as_failure,
        "median_translation_cm": float(np.median(et) * 100) if n else math.nan,
        "median_rotation_deg": float(np.median(er)) if n else math.nan,
        "recall": recall,
        "errors": per,
        "units": units,
    }


def mean_over_scenes(results: list[dict]) -> dict:
    """The dataset figure: mean over scenes of the per-scene medians and recalls."""
    return {
        "scenes": len(results),
        "median_translation_cm": float(np.mean([r["median_translation_cm"] for r in results])),
        "median_rotation_deg": float(np.mean([r["median_rotation_deg"] for r in results])),
        "recall": {k: float(np.mean([r["recall"][k] for r in results])) for k, _, _ in THRESHOLDS},
    }
