"""Localization accuracy: camera-centre and rotation errors, medians and recalls (CONVENTIONS §7)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from .pose import Pose, rotation_angle_deg

THRESHOLDS = (("5cm5deg", 0.05, 5.0), ("2cm2deg", 0.02, 2.0), ("1cm1deg", 0.01, 1.0))


def pose_errors(est: Pose | None, gt: Pose) -> tuple[float, float]:
    """(centre distance in scene units, rotation error in degrees); a missing estimate is (inf, 180)."""
    if est is None:
        return math.inf, 180.0
    return float(np.linalg.norm(est.centre() - gt.centre())), rotation_angle_deg(gt.R, est.R)


def unmatched(estimates: Mapping[str, object], gt: Mapping[str, object]) -> tuple[list[str], list[str]]:
    """(ground-truth names with no estimate, estimate names with no ground truth), matched across name styles."""
    from .adapters.names import canonical_name

    est_keys, gt_keys = {canonical_name(n): n for n in estimates}, {canonical_name(n): n for n in gt}
    return ([n for k, n in gt_keys.items() if k not in est_keys], [n for k, n in est_keys.items() if k not in gt_keys])


def evaluate(estimates: Mapping[str, Pose | None], gt: Mapping[str, Pose], *, scale_to_m: float = 1.0) -> dict:
    """Errors of ``estimates`` against ``gt``; names are matched across styles (canonical keys).

    Missing queries (and failed priors) count as failures: e_t = inf, e_R = 180.

    Returns:
        dict with n, missing, median_translation_cm, median_rotation_deg, recall {"5cm5deg", "2cm2deg",
        "1cm1deg"} as fractions, and per-query errors ``errors`` {name: [t_cm, r_deg]}.
    """
    from .adapters.names import canonical_name

    est_by_key = {canonical_name(k): v for k, v in estimates.items()}
    et, er, per = [], [], {}
    missing = 0
    for name, g in gt.items():
        key = canonical_name(name)
        if key not in est_by_key:
            missing += 1
        t, r = pose_errors(est_by_key.get(key), g)
        t *= scale_to_m
        et.append(t)
        er.append(r)
        per[name] = [t * 100, r]
    et, er = np.array(et), np.array(er)
    n = len(et)
    recall = {k: float(np.mean((et < tt) & (er < rr))) if n else 0.0 for k, tt, rr in THRESHOLDS}
    return {
        "n": n,
        "missing": missing,
        "median_translation_cm": float(np.median(et) * 100) if n else math.nan,
        "median_rotation_deg": float(np.median(er)) if n else math.nan,
        "recall": recall,
        "errors": per,
    }


def mean_over_scenes(results: list[dict]) -> dict:
    """The dataset figure: mean over scenes of the per-scene medians and recalls."""
    return {
        "scenes": len(results),
        "median_translation_cm": float(np.mean([r["median_translation_cm"] for r in results])),
        "median_rotation_deg": float(np.mean([r["median_rotation_deg"] for r in results])),
        "recall": {k: float(np.mean([r["recall"][k] for r in results])) for k, _, _ in THRESHOLDS},
    }
